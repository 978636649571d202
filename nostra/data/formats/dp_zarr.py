"""diffusion_policy ReplayBuffer zarr: ``data/<key>`` concatenated along time and
``meta/episode_ends`` (exclusive end of each episode), as a directory or a ``.zip``; zarr format 2
(as diffusion_policy writes it) or 3. No per-episode metadata: the contract's defaults are used.

Keys map by ``{our_key: "source_key"}`` (sliceable, ``"state[0:2]"``); without a map ``action`` ->
``actions``, ``img``/``image`` -> the front image (``nostra.modality.FRONT_IMAGE``) and other keys
keep their names. Float images holding whole numbers in 0..255 (as in diffusion_policy's push-T)
become uint8."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Iterable

import numpy as np
import zarr
from zarr.storage import ZipStore

from nostra.data.episode import Episode, normalize_meta
from nostra.data.errors import DataError
from nostra.data.formats.keys import select_keys
from nostra.modality import FRONT_IMAGE, kind_of_key

FMT = "dp_zarr"
DEFAULT_MAP = {"action": "actions", "img": FRONT_IMAGE, "image": FRONT_IMAGE}
_SLICE = re.compile(r"^(?P<key>.+?)(?:\[(?P<a>-?\d*):(?P<b>-?\d*)\])?$")


def _open(path: Path, mode: str = "r"):
    try:
        store = ZipStore(path, mode=mode) if path.suffix == ".zip" else path
        return zarr.open_group(store, mode=mode)
    except Exception as e:  # zarr raises many types for unreadable groups
        raise DataError(path, f"cannot be opened as a zarr group ({type(e).__name__}: {e})") from None


def sniff(path: Path) -> bool:
    if not (path.is_dir() or path.suffix == ".zip"):
        return False
    try:
        g = zarr.open_group(ZipStore(path, mode="r") if path.suffix == ".zip" else path, mode="r")
        return "data" in g and "meta" in g and "episode_ends" in g["meta"]
    except Exception:
        return False


class DPZarrSource:
    fmt = FMT

    def __init__(self, path, key_map: dict | None = None, keys: list[str] | None = None, defaults: dict | None = None):
        self.path, self.defaults = Path(path), defaults or {}
        g = _open(self.path)
        if "data" not in g or "meta" not in g or "episode_ends" not in g["meta"]:
            raise DataError(self.path, "not a ReplayBuffer: needs data/<key> and meta/episode_ends", key="meta/episode_ends")
        self.group = g
        ends = np.asarray(g["meta/episode_ends"][:], dtype=np.int64)
        if ends.ndim != 1 or (np.diff(ends, prepend=0) <= 0).any():
            raise DataError(self.path, f"episode_ends must increase strictly, got {ends[:10]}...", key="meta/episode_ends")
        self.ends = ends
        self.map = self._mapping(key_map, keys)
        for ours, (src, _) in self.map.items():
            if g["data"][src].shape[0] < ends[-1]:
                raise DataError(self.path, f"has {g['data'][src].shape[0]} steps, episode_ends says {ends[-1]}",
                                key=f"data/{src}")

    def _mapping(self, key_map, keys) -> dict[str, tuple[str, slice | None]]:
        names = sorted(self.group["data"].keys())
        if key_map:
            out = {}
            for ours, spec in key_map.items():
                m = _SLICE.match(str(spec))
                if m["key"] not in names:
                    raise DataError(self.path, f"key map entry {ours!r} -> {spec!r}: no such array; valid: {names}",
                                    key=f"data/{m['key']}")
                sl = slice(int(m["a"]) if m["a"] else None, int(m["b"]) if m["b"] else None) if m["b"] is not None else None
                out[ours] = (m["key"], sl)
        else:
            out = {DEFAULT_MAP.get(n, n): (n, None) for n in names}
        if "actions" not in out:
            raise DataError(self.path, f"no action array (map one to 'actions'); arrays: {names}", key="data/action")
        return select_keys(out, keys, self.path, "array")

    @property
    def files(self) -> list[Path]:
        return [self.path] if self.path.is_file() else sorted(p for p in self.path.rglob("*") if p.is_file())

    @property
    def attrs(self) -> dict:
        return {"env_args": {"env_name": self.defaults.get("task", ""), "type": 1, "env_kwargs": {}}}

    def __len__(self) -> int:
        return len(self.ends)

    def __iter__(self):
        starts = np.concatenate([[0], self.ends[:-1]])
        for i, (a, b) in enumerate(zip(starts, self.ends)):
            demo = f"episode_{i}"
            arrays = {ours: self._read(src, sl, a, b, demo, ours) for ours, (src, sl) in self.map.items()}
            actions = arrays.pop("actions")
            yield Episode(demo, actions, arrays, {}, normalize_meta({}, self.path, demo, self.defaults))

    def _read(self, src, sl, a, b, demo, ours) -> np.ndarray:
        try:
            x = self.group["data"][src][int(a):int(b)]
        except Exception as e:  # missing chunks, unknown codecs (e.g. imagecodecs' jpeg2k)
            raise DataError(self.path, f"cannot be read ({type(e).__name__}: {e})", demo, f"data/{src}") from None
        if sl is not None:
            x = x[:, sl]
        if kind_of_key(ours) == "rgb" and x.dtype.kind == "f" and _whole_bytes(x):
            x = x.astype(np.uint8)
        return x


def _whole_bytes(x: np.ndarray) -> bool:
    return bool(np.isfinite(x).all() and x.min() >= 0 and x.max() <= 255 and (x == np.round(x)).all())


def write(path, episodes: Iterable[Episode], zarr_format: int = 2, key_map: dict | None = None) -> Path:
    """Write episodes as a ReplayBuffer (zarr format 2 by default, as diffusion_policy does);
    ``key_map`` renames our keys to the file's (default ``actions`` -> ``action``)."""
    path = Path(path)
    names = {"actions": "action", **(key_map or {})}
    eps = list(episodes)
    g = zarr.open_group(ZipStore(path, mode="w") if path.suffix == ".zip" else path, mode="w", zarr_format=zarr_format)
    arrays = {"actions": [e.actions for e in eps], **{k: [e.obs[k] for e in eps] for k in eps[0].obs}}
    for k, parts in arrays.items():
        a = np.concatenate(parts)
        g.require_group("data").create_array(names.get(k, k), data=a, chunks=(min(len(a), 100), *a.shape[1:]))
    g.require_group("meta").create_array("episode_ends", data=np.cumsum([len(e) for e in eps]).astype(np.int64))
    if isinstance(g.store, ZipStore):
        g.store.close()
    return path
