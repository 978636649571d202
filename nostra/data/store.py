"""The zarr store: one zarr v3 group per collection, diffusion_policy-compatible at group level.

    <store>/zarr.json                       root group (attrs: nostra_store format)
    <store>/<collection>/data/<key>         every step of every episode concatenated along time;
                                            obs keys, ``actions`` and (if the source has them)
                                            ``states``/``rewards``/``dones``; time-chunked, Blosc-zstd
    <store>/<collection>/meta/episode_ends  int64, exclusive end of each episode
    <store>/<collection>/meta/episodes      the per-episode table: parquet bytes in a uint8 array
    <store>/<collection>/next_obs/<key>     (if the source has next_obs) one row per episode: the
                                            observation after its last step (the other steps of
                                            next_obs are obs shifted by one)
    <store>/<collection>/zarr.json          attrs: source, format, content hash, env_args, obs keys,
                                            normalisation stats (count/mean/std/min/max per lowdim
                                            key and actions), mask names (empty ones too), next_obs

Dtypes are kept as the source has them (float64 stays float64) unless ``float32=True``.

An ingest writes a temporary group beside the store and renames it in at the end, so a crash or
Ctrl-C leaves the store as it was; ingesting content already held (same content hash) is a no-op.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import shutil
import uuid
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import zarr
from tqdm import tqdm
from zarr.codecs import BloscCodec

from nostra.data.episode import EXTRA_KEYS, META_DEFAULTS, NESTED, Episode, as_float32, check_episode
from nostra.data.errors import CollectionError, DataError
from nostra.data.formats import lerobot_v3_writer, open_source, robomimic_hdf5
from nostra.data.stats import RunningStats, combine
from nostra.modality import kind_of_key

log = logging.getLogger(__name__)
STORE_FORMAT = 1
CHUNK_BYTES = 1 << 19  # ~0.5 MiB per chunk: a 16-step window of 84x84 images touches one or two
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
TABLE_SCHEMA = pa.schema([
    ("episode", pa.int64()), ("demo_id", pa.string()), ("source", pa.string()), ("source_format", pa.string()),
    ("start", pa.int64()), ("length", pa.int64()), ("task", pa.string()), ("language", pa.string()),
    ("skill", pa.string()), ("objects", pa.string()), ("camera_pose", pa.string()),
    ("object_placements", pa.string()), ("variation", pa.string()), ("success", pa.bool_()),
    ("seed", pa.int64()), ("masks", pa.string()), ("model_file", pa.string()), ("robots", pa.string()),
    ("controller", pa.string()),
])


def chunk_len(step_shape: tuple, dtype) -> int:
    """Steps per chunk: a power of two near CHUNK_BYTES, 4..8192."""
    step = max(1, int(np.prod(step_shape)) * np.dtype(dtype).itemsize)
    return int(np.clip(2 ** int(np.log2(max(1, CHUNK_BYTES // step))), 4, 8192))


def compressor() -> BloscCodec:
    return BloscCodec(cname="zstd", clevel=3, shuffle="shuffle")


class Store:
    def __init__(self, path):
        self.path = Path(path)

    # ---- reading ---------------------------------------------------------------------------
    def collections(self) -> list[str]:
        if not self.path.is_dir():
            return []
        return sorted(d.name for d in self.path.iterdir()
                      if d.is_dir() and NAME.match(d.name) and (d / "zarr.json").is_file())

    def group(self, name: str) -> zarr.Group:
        if name not in self.collections():
            raise CollectionError(f"store {self.path} has no collection {name!r}; "
                                  f"it has {self.collections() or 'none'}")
        return zarr.open_group(self.path / name, mode="r")

    def info(self, name: str) -> dict:
        return dict(self.group(name).attrs)

    def keys(self, name: str) -> list[str]:
        """Obs keys and ``actions`` (and extras such as ``rewards``) held by a collection."""
        return sorted(self.group(name)["data"].keys())

    def array(self, name: str, key: str) -> zarr.Array:
        data = self.group(name)["data"]
        if key not in data:
            raise CollectionError(f"collection {name!r} in {self.path} has no key {key!r}; "
                                  f"it has {sorted(data.keys())}")
        return data[key]

    def episode_ends(self, name: str) -> np.ndarray:
        return np.asarray(self.group(name)["meta/episode_ends"][:], dtype=np.int64)

    def episodes(self, name: str) -> pd.DataFrame:
        """The per-episode table: one row per episode, nested values decoded from JSON."""
        raw = self.group(name)["meta/episodes"][:].tobytes()
        df = pq.read_table(io.BytesIO(raw)).to_pandas(
            types_mapper={pa.int64(): pd.Int64Dtype(), pa.bool_(): pd.BooleanDtype()}.get)
        for c in NESTED:
            if c not in df:  # collections ingested before the column existed
                df[c] = "[]" if c == "robots" else "{}"
            df[c] = df[c].map(json.loads)
        df.insert(0, "collection", name)
        return df

    def episode(self, name: str, index: int, keys: list[str] | None = None) -> dict[str, np.ndarray]:
        ends = self.episode_ends(name)
        if not 0 <= index < len(ends):
            raise CollectionError(f"collection {name!r} has episodes 0..{len(ends) - 1}, not {index}")
        a, b = (ends[index - 1] if index else 0), ends[index]
        return {k: self.array(name, k)[a:b] for k in (keys or self.keys(name))}

    def stats(self, names: list[str] | str, keys: list[str] | None = None) -> dict[str, dict]:
        """{key: {"mean", "std", "min", "max"} float32 arrays (and "count")}, combined over ``names``.
        Default keys: the lowdim keys and actions that every collection holds."""
        names = [names] if isinstance(names, str) else list(names)
        per = {n: self.info(n)["stats"] for n in names}
        if keys is None:
            keys = sorted(set.intersection(*(set(s) for s in per.values())))
        for n, s in per.items():
            missing = [k for k in keys if k not in s]
            if missing:
                raise CollectionError(f"collection {n!r} has no statistics for {missing} (lowdim keys and "
                                      f"actions only); it has {sorted(s)}")
        return {k: combine([per[n][k] for n in names]) for k in keys}

    # ---- writing ---------------------------------------------------------------------------
    def ingest(self, source, name: str | None = None, fmt: str = "auto", key_map: dict | None = None,
               keys: list[str] | None = None, defaults: dict | None = None, progress: bool = True,
               float32: bool = False, next_obs: bool = True, render: bool = False, render_size: int = 84) -> str:
        """Read one source (or a list, concatenated) into a new collection; returns its name. A
        source whose content the store already holds (whatever its file name) is not read again:
        that collection's name is returned. ``float32``: store float lowdim obs and actions as
        float32 (default: as the source has them). ``next_obs=False``: ignore a robomimic source's
        next_obs (export then derives it). ``render``: robosuite raw demos get their six modalities
        rendered from the recorded states at ``render_size`` (nostra.sim.raw_demos)."""
        paths = [Path(source)] if isinstance(source, (str, os.PathLike)) else [Path(s) for s in source]
        if not paths:
            raise DataError(self.path, "nothing to ingest: no source paths given")
        defaults = {k: v for k, v in (defaults or {}).items() if v is not None} or None
        readers = [open_source(p, fmt, key_map or None, keys, defaults, next_obs=next_obs, render=render,
                               render_size=render_size) for p in paths]
        opts = {"key_map": key_map or None, "keys": keys, "defaults": defaults}
        opts |= {"float32": True} if float32 else {}
        opts |= {} if next_obs else {"next_obs": False}
        opts |= {"render_size": int(render_size)} if render else {}
        digest = content_hash(readers, opts)
        for c in self.collections():
            if self.info(c).get("content_hash") == digest:
                log.info("%s is already in %s as collection %r", paths[0], self.path, c)
                return c
        name = name or default_name(paths[0])
        if not NAME.match(name):
            raise DataError(paths[0], f"collection name {name!r} is invalid; use letters, digits, '_' and '-', "
                                      "starting with a letter or digit")
        if name in self.collections():
            raise DataError(paths[0], f"collection {name!r} already exists in {self.path} with other content "
                                      f"(from {self.info(name).get('sources')}); remove it or choose another name")
        self._clean_stale()
        tmp = self.path.parent / f".{self.path.name}.ingest-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            _write_collection(tmp, readers, digest, progress, float32)
            self._open_root()
            try:
                os.rename(tmp, self.path / name)
            except OSError as e:
                raise DataError(paths[0], f"cannot create collection {name!r} in {self.path} ({e})") from None
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return name

    def remove(self, name: str) -> None:
        self.group(name)
        trash = self.path.parent / f".{self.path.name}.trash-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.rename(self.path / name, trash)  # atomic: the collection is gone or intact, never half
        shutil.rmtree(trash, ignore_errors=True)

    def export(self, name: str, path, next_obs: bool = True, progress: bool = True, format: str = "robomimic",
               fps: float | None = None) -> Path:
        """Write a collection as a robomimic HDF5 file that peers' tools read (next_obs from the
        source where it had one, else derived and said so in ``data.attrs``; every mask, empty ones
        too), or with ``format="lerobot"`` as a LeRobot v3.0 dataset directory (``fps``: default the
        source's LeRobot fps, else env_args' control_freq)."""
        if format == "lerobot":
            return self._export_lerobot(name, path, fps, progress)
        if format != "robomimic":
            raise DataError(path, f"unknown export format {format!r}; valid: robomimic, lerobot", key="format")
        attrs = self.info(name)
        return robomimic_hdf5.write(path, self._stored_episodes(name, demo_ids=True), attrs.get("env_args", {}),
                                    total=attrs["num_episodes"], next_obs=next_obs, progress=progress,
                                    mask_names=attrs.get("masks", []))

    def _export_lerobot(self, name: str, path, fps: float | None, progress: bool) -> Path:
        attrs = self.info(name)
        env_args = attrs.get("env_args") or {}
        kwargs = env_args.get("env_kwargs") or {}
        fps = fps or (attrs.get("source_attrs", {}).get("lerobot_info") or {}).get("fps") or kwargs.get("control_freq")
        if not fps:
            raise DataError(path, f"collection {name!r} does not say its frame rate; pass fps (export.fps=<hz>)",
                            key="fps")
        robots = kwargs.get("robots")
        robot = (robots[0] if isinstance(robots, list) and robots else robots) or \
            (attrs.get("source_attrs", {}).get("lerobot_info") or {}).get("robot_type")
        return lerobot_v3_writer.write(path, self._stored_episodes(name), fps=int(round(float(fps))),
                                       robot_type=str(robot).lower() if robot else None,
                                       total=attrs["num_episodes"], progress=progress)

    def _stored_episodes(self, name: str, demo_ids: bool = False):
        """The collection's episodes as readers yield them (next_obs as its last step)."""
        table = self.episodes(name)
        ids = list(table["demo_id"])
        if demo_ids and (len(set(ids)) != len(ids) or not all(re.fullmatch(r"demo_\d+", i) for i in ids)):
            ids = [f"demo_{i}" for i in range(len(table))]
        obs_keys = self.info(name)["obs_keys"]
        extra_keys = [k for k in EXTRA_KEYS if k in self.keys(name)]
        arrays = {k: self.array(name, k) for k in ["actions", *obs_keys, *extra_keys]}
        last = self.next_obs_last(name)
        for i, (demo, row) in enumerate(zip(ids, table.itertuples(index=False))):
            a, b = int(row.start), int(row.start + row.length)
            meta = {k: _plain(getattr(row, k)) for k in (*META_DEFAULTS, "masks", "model_file")}
            yield Episode(demo, arrays["actions"][a:b], {k: arrays[k][a:b] for k in obs_keys},
                          {k: arrays[k][a:b] for k in extra_keys}, meta, {k: v[i:i + 1] for k, v in last.items()})

    def next_obs_last(self, name: str) -> dict[str, zarr.Array]:
        """{obs key: (episodes, ...) array} of the source's next observation after each episode's
        last step; empty when the source had no next_obs."""
        g = self.group(name)
        return {k: g["next_obs"][k] for k in g["next_obs"].keys()} if "next_obs" in g else {}

    def _open_root(self) -> None:
        root = zarr.open_group(self.path, mode="a", zarr_format=3)
        if root.attrs.get("nostra_store") is None:
            root.attrs["nostra_store"] = STORE_FORMAT

    def _clean_stale(self) -> None:
        """Temporary groups of ingests whose process is gone (killed mid-way)."""
        for d in self.path.parent.glob(f".{self.path.name}.*-*-*"):
            kind, pid = (d.name.rsplit(".", 1)[-1].split("-") + [""])[:2]
            if kind in ("ingest", "trash") and pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(d, ignore_errors=True)


class _Appender:
    """Buffers steps and writes whole chunks, so every chunk is written once."""

    def __init__(self, arr: zarr.Array):
        self.arr, self.buf, self.n, self.done = arr, [], 0, 0

    def add(self, x: np.ndarray) -> None:
        self.buf.append(x)
        self.n += len(x)
        if self.n >= self.arr.chunks[0]:
            self.flush(final=False)

    def flush(self, final: bool = True) -> None:
        if not self.buf:
            return
        data = np.concatenate(self.buf)
        k = len(data) if final else len(data) // self.arr.chunks[0] * self.arr.chunks[0]
        if k:
            self.arr.resize((self.done + k, *self.arr.shape[1:]))
            self.arr[self.done:self.done + k] = data[:k]
            self.done += k
        self.buf, self.n = ([data[k:]] if k < len(data) else []), len(data) - k


def _write_collection(tmp: Path, readers, digest: str, progress: bool, float32: bool = False) -> None:
    g = zarr.open_group(tmp, mode="w", zarr_format=3)
    writers: dict[str, _Appender] = {}
    nexts: dict[str, _Appender] = {}
    stats: dict[str, RunningStats] = {}
    shapes: dict = {}
    rows, total = [], 0
    for r in readers:
        for ep in tqdm(r, total=len(r), desc=f"ingest {r.path.name}", disable=not progress):
            ep = check_episode(ep, r.path, shapes)
            ep = as_float32(ep) if float32 else ep
            arrays = {"actions": ep.actions, **ep.obs, **ep.extras}
            if not writers:
                writers = {k: _Appender(_create(g, k, v)) for k, v in arrays.items()}
                nexts = {k: _Appender(_create(g, k, v, "next_obs")) for k, v in ep.next_obs.items()}
                stats = {k: RunningStats() for k in arrays if k == "actions" or (k in ep.obs and kind_of_key(k) == "lowdim")}
                obs_keys = list(ep.obs)
            _same_keys(arrays, writers, r.path, ep.demo_id)
            _same_keys(ep.next_obs, nexts, r.path, ep.demo_id, "next_obs/")
            for k, v in arrays.items():
                writers[k].add(_cast(v, writers[k].arr.dtype, r.path, ep.demo_id, k))
            for k, v in ep.next_obs.items():
                nexts[k].add(_cast(v, nexts[k].arr.dtype, r.path, ep.demo_id, f"next_obs/{k}"))
            for k, s in stats.items():
                s.update(arrays[k])
            rows.append(_row(len(rows), ep, r, total))
            total += len(ep)
    for w in [*writers.values(), *nexts.values()]:
        w.flush()
    meta = g.require_group("meta")
    meta.create_array("episode_ends", data=np.cumsum([row["length"] for row in rows]).astype(np.int64))
    meta.create_array("episodes", data=np.frombuffer(_table_bytes(rows), dtype=np.uint8))
    g.attrs.update({
        "nostra_collection": STORE_FORMAT, "content_hash": digest,
        "sources": [str(r.path) for r in readers], "source_format": readers[0].fmt,
        "env_args": readers[0].attrs.get("env_args", {}), "obs_keys": obs_keys,
        "num_episodes": len(rows), "num_steps": total, "stats": {k: s.to_dict() for k, s in stats.items()},
        "source_attrs": {k: v for k, v in readers[0].attrs.items() if k != "env_args"},
        "masks": sorted({m for r in readers for m in getattr(r, "mask_names", [])}),
        "next_obs": "source" if nexts else "none",
    })


def _create(g: zarr.Group, key: str, v: np.ndarray, group: str = "data") -> zarr.Array:
    c = chunk_len(v.shape[1:], v.dtype)
    return g.require_group(group).create_array(key, shape=(0, *v.shape[1:]), chunks=(c, *v.shape[1:]),
                                               dtype=v.dtype, compressors=compressor())


def _same_keys(arrays: dict, writers: dict, file, demo: str, prefix: str = "") -> None:
    for k in writers:
        if k not in arrays:
            raise DataError(file, "missing here but present in earlier demos", demo, prefix + k)
    for k in arrays:
        if k not in writers:
            raise DataError(file, "present here but missing in earlier demos", demo, prefix + k)


def _cast(v: np.ndarray, dtype, file, demo: str, key: str) -> np.ndarray:
    if v.dtype == dtype:
        return v
    if not np.can_cast(v.dtype, dtype, casting="same_kind"):
        raise DataError(file, f"dtype {v.dtype} cannot be stored as {dtype} (the dtype of earlier demos)", demo, key)
    return v.astype(dtype)


def _row(index: int, ep: Episode, reader, start: int) -> dict:
    meta = {k: (json.dumps(v) if k in NESTED else v) for k, v in ep.meta.items()}
    return {"episode": index, "demo_id": ep.demo_id, "source": str(reader.path), "source_format": reader.fmt,
            "start": start, "length": len(ep), **{k: meta.get(k) for k in TABLE_SCHEMA.names if k in meta}}


def _table_bytes(rows: list[dict]) -> bytes:
    buf = io.BytesIO()
    pq.write_table(pa.Table.from_pylist(rows, schema=TABLE_SCHEMA), buf, compression="zstd")
    return buf.getvalue()


def _plain(v):
    """pandas' nullable scalars back to plain Python (None for missing)."""
    if v is pd.NA or v is None:
        return None
    return v.item() if isinstance(v, np.generic) else v


def content_hash(readers, options: dict) -> str:
    h = hashlib.sha256(json.dumps(options, sort_keys=True, default=str).encode())
    for r in readers:  # the bytes, not the name: a copy under another name is the same content
        h.update(r.fmt.encode())
        for f in r.files:
            if r.path.is_dir():  # inside a dataset directory, where a file lies is content
                h.update(str(f.relative_to(r.path)).encode())
            with open(f, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 22), b""):
                    h.update(block)
    return h.hexdigest()


def default_name(path: Path) -> str:
    """A collection name from a source path: ``lift.hdf5`` -> ``lift``, ``pusht.zarr.zip`` -> ``pusht``."""
    name = path.name
    for suffix in (".zip", ".zarr", ".hdf5", ".h5"):
        name = name.removesuffix(suffix)
    return re.sub(r"[^A-Za-z0-9_-]", "_", name).lstrip("_-") or "collection"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
