"""robomimic HDF5: ``data`` (attrs ``total``, ``env_args`` JSON) holding ``demo_N`` groups (attrs
``num_samples``, ``model_file`` and our per-episode metadata, nested values as JSON strings) with
``actions``, ``states``, ``rewards``, ``dones``, ``obs/<key>``, ``next_obs/<key>``; ``mask/<name>``
lists demo names as byte strings. Any file in this layout reads, not only ours: image keys may be
missing and extra keys are kept. A source's next_obs is kept (it must be obs shifted by one step;
the step after the last is what the store keeps); every mask name is kept, empty ones too."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Callable, Iterable

import h5py
import numpy as np
from tqdm import tqdm

from nostra.data.episode import EXTRA_KEYS, NESTED, Episode, META_DEFAULTS, normalize_meta
from nostra.data.errors import DataError

FMT = "robomimic"


def sniff(path: Path) -> bool:
    return path.is_file() and h5py.is_hdf5(path)


def _natural(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _open(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as e:  # truncated / corrupt / not HDF5
        raise DataError(path, f"cannot be read as HDF5 (truncated or corrupt?): {e}") from None


class RobomimicSource:
    fmt = FMT

    def __init__(self, path, keys: list[str] | None = None, defaults: dict | None = None, next_obs: bool = True):
        self.path, self.keys, self.defaults, self.next_obs = Path(path), keys, defaults or {}, next_obs
        with _open(self.path) as f:
            if "data" not in f or not isinstance(f["data"], h5py.Group):
                raise DataError(self.path, "no 'data' group: not a robomimic file", key="data")
            self.demos = sorted(f["data"].keys(), key=_natural)
            if not self.demos:
                raise DataError(self.path, "the 'data' group holds no demos", key="data")
            for demo in self.demos:
                if not isinstance(f["data"][demo], h5py.Group):
                    raise DataError(self.path, "is a dataset, expected a demo group (actions, obs/...)", demo,
                                    f"data/{demo}")
            first = f["data"][self.demos[0]]
            if "obs" not in first:
                if "states" in first:
                    raise raw_refusal(self.path)
                raise DataError(self.path, "has no observations (obs/<key>)", self.demos[0], "obs")
            self.env_args = _env_args(f["data"].attrs.get("env_args"), self.path)
            self.masks = _masks(f, self.path)

    @property
    def files(self) -> list[Path]:
        return [self.path]

    @property
    def attrs(self) -> dict:
        return {"env_args": self.env_args}

    @property
    def mask_names(self) -> list[str]:
        return sorted(self.masks)

    def __len__(self) -> int:
        return len(self.demos)

    def __iter__(self):
        with _open(self.path) as f:
            for demo in self.demos:
                try:
                    yield self._episode(f["data"][demo], demo)
                except DataError:
                    raise
                except (KeyError, IndexError, TypeError, ValueError, OSError, AttributeError) as e:
                    raise DataError(self.path, f"cannot be read ({type(e).__name__}: {e})", demo) from None

    def _episode(self, g, demo: str) -> Episode:
        read = lambda grp, k: _read(grp, k, self.path, demo)  # noqa: E731
        actions = read(g, "actions") if "actions" in g else None
        obs_g = g.get("obs")
        names = list(obs_g.keys()) if obs_g is not None else []
        keys = self.keys if self.keys is not None else names
        missing = [k for k in keys if k not in names]
        if missing:
            raise DataError(self.path, f"obs has no such key; it has {names}", demo, f"obs/{missing[0]}")
        obs = {k: read(obs_g, k) for k in keys}
        nxt = self._next_obs(g, obs, demo) if self.next_obs else {}
        extras = {k: read(g, k) for k in EXTRA_KEYS if k in g}
        raw = {k: g.attrs[k] for k in (*META_DEFAULTS, "model_file") if k in g.attrs}
        raw["masks"] = [m for m, members in self.masks.items() if demo in members]
        if not raw.get("task") and self.env_args.get("env_name"):
            raw["task"] = self.env_args["env_name"]
        return Episode(demo, actions, obs, extras, normalize_meta(raw, self.path, demo, self.defaults), nxt)

    def _next_obs(self, g, obs: dict, demo: str) -> dict:
        nxt = g.get("next_obs")
        if nxt is None or not obs:
            return {}
        missing = [k for k in obs if k not in nxt]
        if missing:
            raise DataError(self.path, f"next_obs lacks obs keys {missing} (it has {sorted(nxt)}); ingest with "
                                       "next_obs=false (ingest.next_obs=false) to drop next_obs", demo,
                            f"next_obs/{missing[0]}")
        return {k: _read(nxt, k, self.path, demo) for k in obs}


def is_raw(path: Path) -> bool:
    """robosuite raw demos (collect_human_demonstrations): demos with states and actions, no obs."""
    try:
        with h5py.File(path, "r") as f:
            data = f.get("data")
            if not isinstance(data, h5py.Group) or not len(data):
                return False
            first = data[sorted(data.keys(), key=_natural)[0]]
            return isinstance(first, h5py.Group) and "obs" not in first and "states" in first
    except OSError:
        return False


def raw_refusal(path: Path) -> DataError:
    return DataError(path, "robosuite raw demos (states, actions and model_file; no observations): render the "
                           f"observations while ingesting: nostra ingest 'ingest.sources=[{path}]' ingest.render=true "
                           "(ingest.render_size=84 sets the image size)", key="obs")


def _read(g, key: str, path, demo: str) -> np.ndarray:
    if not isinstance(g[key], h5py.Dataset):
        raise DataError(path, "is a group, expected a dataset", demo, key)
    try:
        return g[key][()]
    except (OSError, TypeError, ValueError) as e:
        raise DataError(path, f"cannot be read ({e})", demo, key) from None


def _env_args(raw, path) -> dict:
    if raw is None:
        return {}
    try:
        return json.loads(raw.decode() if isinstance(raw, bytes) else raw)
    except json.JSONDecodeError as e:
        raise DataError(path, f"data.attrs['env_args'] is not JSON ({e})", key="env_args") from None


def _masks(f, path) -> dict[str, set[str]]:
    if "mask" not in f:
        return {}
    out = {}
    for name, ds in f["mask"].items():
        if not isinstance(ds, h5py.Dataset):
            raise DataError(path, "is a group, expected a dataset of demo names", key=f"mask/{name}")
        try:
            out[name] = {x.decode() if isinstance(x, bytes) else str(x) for x in np.asarray(ds[()]).ravel()}
        except (OSError, TypeError, ValueError, UnicodeDecodeError) as e:
            raise DataError(path, f"cannot be read as demo names ({e})", key=f"mask/{name}") from None
    return out


NEXT_OBS_DERIVED = "next_obs/<key> derived by nostra: obs shifted by one step, the last step repeated (the source had no next_obs)"


def write(path, episodes: Iterable[Episode], env_args: dict, total: int | None = None,
          next_obs: bool = True, progress: bool = True, mask_names: Iterable[str] = (),
          split: Callable[[list[str]], dict[str, list[str]]] | None = None) -> Path:
    """Write episodes as a robomimic file (the one writer: `nostra generate` and `nostra export`).
    Written beside the target and renamed at the end, so a failure (an exception from the
    ``episodes`` iterator included) never leaves a half-written file; no creation times (the same
    episodes, the same bytes). ``next_obs`` is each obs shifted by one step, then the episode's
    ``next_obs`` last step where it has one, else the last step repeated; ``data.attrs``
    ``next_obs_derived`` says which (and ``next_obs_note`` how). Masks: each episode's
    ``meta["masks"]``, plus ``split(demo names)`` computed once every demo is written (e.g. a seeded
    train/valid split); ``mask_names`` are written even when no demo is in them."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    masks: dict[str, list[str]] = {m: [] for m in mask_names}
    derived = False
    try:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            steps = 0
            for ep in tqdm(episodes, total=total, desc=f"export {path.name}", disable=not progress):
                derived |= _write_demo(data.create_group(ep.demo_id), ep, next_obs)
                steps += len(ep)
                for m in ep.meta.get("masks", []):
                    masks.setdefault(m, []).append(ep.demo_id)
            for name, demos in (split(sorted(data, key=_natural)) if split else {}).items():
                masks.setdefault(name, []).extend(demos)
            data.attrs["total"] = steps
            data.attrs["env_args"] = json.dumps(env_args)
            if next_obs:
                data.attrs["next_obs_derived"] = derived
                if derived:
                    data.attrs["next_obs_note"] = NEXT_OBS_DERIVED
            for name, demos in masks.items():
                f.create_dataset(f"mask/{name}", data=np.array(demos, dtype="S") if demos else np.zeros(0, "S1"),
                                 track_times=False)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _write_demo(g, ep: Episode, next_obs: bool) -> bool:
    """Write one demo; True when some next_obs had to be derived."""
    n = len(ep)
    g.attrs["num_samples"] = n
    for k, v in ep.meta.items():
        if k == "masks" or v is None:
            continue
        g.attrs[k] = json.dumps(v) if k in NESTED else v
    g.attrs.setdefault("model_file", "")
    g.create_dataset("actions", data=ep.actions, track_times=False)
    extras = dict(ep.extras)
    extras.setdefault("rewards", np.zeros(n, np.float32))
    extras.setdefault("dones", (np.arange(n) == n - 1).astype(np.int64))
    for k, v in extras.items():
        g.create_dataset(k, data=v, track_times=False)
    derived = False
    for k, v in ep.obs.items():
        _obs(g, f"obs/{k}", v)
        if next_obs:
            last = ep.next_obs.get(k)
            derived |= last is None
            last = v[-1:] if last is None else np.asarray(last)[-1:]
            _obs(g, f"next_obs/{k}", np.concatenate([v[1:], last]))
    return derived


def _obs(g, key: str, v: np.ndarray) -> None:
    """Images gzip-compressed, one chunk per frame (a reader can fetch one step); others plain."""
    if v.dtype == np.uint8 and v.ndim >= 3:
        g.create_dataset(key, data=v, chunks=(1, *v.shape[1:]), compression="gzip", compression_opts=4,
                         track_times=False)
    else:
        g.create_dataset(key, data=v, track_times=False)
