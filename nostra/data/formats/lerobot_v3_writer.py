"""Write episodes as a LeRobot v3.0 dataset laid out as lerobot (0.4.x) writes it, so LeRobot's
training reads it:

    meta/info.json                              codebase_version v3.0, fps, features, path templates
    meta/stats.json                             per feature min/max/mean/std/count/q01..q99
    meta/tasks.parquet                          pandas DataFrame: the task strings as the index
                                                (named ``task``), one column ``task_index``
    meta/episodes/chunk-000/file-000.parquet    one row per episode: tasks, length, row range,
                                                data and video chunk/file, from/to timestamps,
                                                stats/<feature>/<stat>
    data/chunk-CCC/file-FFF.parquet             frames of many episodes (a new file past 100 MB)
    videos/<key>/chunk-CCC/file-FFF.mp4         one mp4 per chunk and camera (a new file past 500 MB),
                                                AV1 (libsvtav1, yuv420p, g=2, crf=30) as lerobot encodes

Our keys become LeRobot features: ``actions`` -> ``action``; the lowdim obs keys, concatenated,
-> ``observation.state`` with ``names`` ``<key>.<i>`` (our reader splits them back); rgb
``<cam>_image`` -> ``observation.images.<cam>`` (video); depth ``<key>`` -> ``observation.<key>``
(float, in the parquet); ``rewards``/``dones``/``states`` -> ``next.reward``/``next.done``/``states``.
Dtypes are kept. The task string of an episode is its ``language``, else its ``task``."""

from __future__ import annotations

import json
import os
import shutil
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import av
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from nostra.data.episode import Episode
from nostra.modality import kind_of_key

DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
CHUNKS_SIZE, DATA_MB, VIDEO_MB = 1000, 100, 500
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
EXTRA_FEATURES = {"rewards": "next.reward", "dones": "next.done", "states": "states"}
BOOKKEEPING = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
               "task_index": "int64"}


def features_of(ep: Episode) -> tuple[dict, dict]:
    """LeRobot features for the keys of an episode, and {feature: how to get it from an episode}."""
    lows = [k for k in ep.obs if kind_of_key(k) == "lowdim"]
    features = {"action": _spec(ep.actions)}
    how: dict = {"action": ("actions",)}
    if lows:
        state = np.concatenate([ep.obs[k].reshape(len(ep), -1) for k in lows], 1)
        features["observation.state"] = _spec(state, [f"{k}.{i}" for k in lows for i in range(ep.obs[k].shape[1])])
        how["observation.state"] = ("state", lows)
    for k, v in ep.obs.items():
        if kind_of_key(k) == "rgb":
            features[f"observation.images.{k.removesuffix('_image')}"] = {
                "dtype": "video", "shape": list(v.shape[1:]), "names": ["height", "width", "channels"]}
            how[f"observation.images.{k.removesuffix('_image')}"] = ("obs", k)
        elif kind_of_key(k) == "depth":
            features[f"observation.{k}"] = _spec(v, ["height", "width", "channels"])
            how[f"observation.{k}"] = ("obs", k)
    for k, f in EXTRA_FEATURES.items():
        if k in ep.extras:
            v = ep.extras[k]
            features[f] = _spec(v.reshape(len(v), -1))
            how[f] = ("extra", k)
    return features, how


def _spec(a: np.ndarray, names=None) -> dict:
    return {"dtype": "bool" if a.dtype == np.bool_ else str(a.dtype), "shape": list(a.shape[1:]), "names": names}


def _arrays(ep: Episode, how: dict) -> dict[str, np.ndarray]:
    out = {}
    for f, h in how.items():
        if h[0] == "actions":
            out[f] = ep.actions
        elif h[0] == "state":
            out[f] = np.concatenate([ep.obs[k].reshape(len(ep), -1) for k in h[1]], 1)
        elif h[0] == "obs":
            out[f] = ep.obs[h[1]]
        else:
            out[f] = ep.extras[h[1]].reshape(len(ep), -1)
    return out


class _Files:
    """chunk/file indices as lerobot advances them: file_index up to chunks_size, then a new chunk."""

    def __init__(self):
        self.chunk, self.file, self.bytes = 0, 0, 0

    def next(self) -> None:
        self.file += 1
        if self.file >= CHUNKS_SIZE:
            self.chunk, self.file = self.chunk + 1, 0
        self.bytes = 0


class _Video:
    """One camera's current mp4: episodes appended, each at the time the file had reached."""

    def __init__(self, root: Path, key: str, fps: int, codec: str, crf: int, gop: int):
        self.root, self.key, self.fps, self.codec, self.crf, self.gop = root, key, fps, codec, crf, gop
        self.at, self.c, self.s, self.frames = _Files(), None, None, 0

    def path(self) -> Path:
        return self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=self.at.chunk, file_index=self.at.file)

    def add(self, frames: np.ndarray) -> dict:
        if self.c is not None and self.at.bytes >= VIDEO_MB * 2 ** 20:
            self.close()
            self.at.next()
        if self.c is None:
            os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only, not its banner per file
            self.path().parent.mkdir(parents=True, exist_ok=True)
            self.c = av.open(str(self.path()), "w")
            opts = {"g": str(self.gop), "crf": str(self.crf)}
            self.s = self.c.add_stream(self.codec, rate=self.fps, options=opts)
            self.s.pix_fmt, self.s.width, self.s.height = "yuv420p", frames.shape[2], frames.shape[1]
            self.s.time_base = Fraction(1, self.fps)
            self.frames = 0
        start = self.frames
        for img in frames:
            fr = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            fr.pts = self.frames
            self.frames += 1
            self._mux(self.s.encode(fr))
        return {f"videos/{self.key}/chunk_index": self.at.chunk, f"videos/{self.key}/file_index": self.at.file,
                f"videos/{self.key}/from_timestamp": start / self.fps,
                f"videos/{self.key}/to_timestamp": self.frames / self.fps}

    def _mux(self, packets) -> None:
        for p in packets:
            self.at.bytes += p.size
            self.c.mux(p)

    def close(self) -> None:
        if self.c is not None:
            self._mux(self.s.encode())
            self.c.close()
            self.c = None

    def info(self) -> dict:
        first = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=0, file_index=0)
        with av.open(str(first)) as c:
            s = c.streams.video[0]
            return {"video.height": s.height, "video.width": s.width,
                    "video.codec": s.codec_context.codec.canonical_name, "video.pix_fmt": s.pix_fmt,
                    "video.is_depth_map": False, "video.fps": int(self.fps), "video.channels": 3, "has_audio": False}


def write(root, episodes: Iterable[Episode], fps: int, robot_type: str | None = None, total: int | None = None,
          progress: bool = True, codec: str = "libsvtav1", crf: int = 30, gop: int = 2) -> Path:
    """Write episodes as a LeRobot v3.0 dataset at ``root``: written in a temporary directory
    beside it and renamed in at the end (replacing an earlier export), so a failure leaves nothing
    half-written."""
    root = Path(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.with_name(f".{root.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _write(tmp, episodes, int(fps), robot_type, total, progress, codec, crf, gop)
        if root.exists():
            old = root.with_name(f".{root.name}.old-{os.getpid()}")
            os.rename(root, old)
            shutil.rmtree(old, ignore_errors=True)
        os.rename(tmp, root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


def _write(root: Path, episodes, fps, robot_type, total, progress, codec, crf, gop) -> None:
    features = how = None
    tasks: dict[str, int] = {}
    rows, stats, videos, offset = [], {}, {}, 0
    data_at, writer = _Files(), None
    try:
        for i, ep in enumerate(tqdm(episodes, total=total, desc=f"export {root.name}", disable=not progress)):
            if features is None:
                features, how = features_of(ep)
                videos = {f: _Video(root, f, fps, codec, crf, gop) for f, s in features.items() if s["dtype"] == "video"}
            task = str(ep.meta.get("language") or ep.meta.get("task") or "")
            tasks.setdefault(task, len(tasks))
            arrays = _arrays(ep, how)
            table = _frames(arrays, features, i, offset, tasks[task], fps)
            if writer is not None and data_at.bytes >= DATA_MB * 2 ** 20:
                writer.close()
                writer = None
                data_at.next()
            if writer is None:
                path = root / DATA_PATH.format(chunk_index=data_at.chunk, file_index=data_at.file)
                path.parent.mkdir(parents=True, exist_ok=True)
                writer = pq.ParquetWriter(path, table.schema, compression="snappy", use_dictionary=True)
            writer.write_table(table)  # one row group per episode
            data_at.bytes += table.nbytes
            row = {"episode_index": i, "tasks": [task], "length": len(ep), "data/chunk_index": data_at.chunk,
                   "data/file_index": data_at.file, "dataset_from_index": offset, "dataset_to_index": offset + len(ep)}
            for f, v in videos.items():
                row |= v.add(arrays[f])
            row |= {"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0}
            ep_stats = {f: episode_stats(a, features[f]["dtype"] == "video") for f, a in arrays.items()}
            ep_stats |= {k: episode_stats(table[k].to_numpy()[:, None], False) for k in BOOKKEEPING}
            for f, st in ep_stats.items():
                row |= {f"stats/{f}/{k}": v.tolist() for k, v in st.items()}
                stats.setdefault(f, []).append(st)
            rows.append(row)
            offset += len(ep)
    finally:
        if writer is not None:
            writer.close()
        for v in videos.values():
            v.close()
    if not rows:
        raise ValueError("no episodes to export")
    for f, v in videos.items():
        features[f]["info"] = v.info()
    _parquet(root / "meta/episodes/chunk-000/file-000.parquet", pa.Table.from_pylist(rows))
    (root / "meta/tasks.parquet").parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame({"task_index": list(tasks.values())}, index=pd.Index(list(tasks), name="task")).to_parquet(
        root / "meta/tasks.parquet")
    (root / "meta/stats.json").write_text(json.dumps(
        {f: {k: v.tolist() for k, v in aggregate(s).items()} for f, s in stats.items()}, indent=4))
    info = {"codebase_version": "v3.0", "robot_type": robot_type, "total_episodes": len(rows), "total_frames": offset,
            "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": DATA_MB,
            "video_files_size_in_mb": VIDEO_MB, "fps": fps, "splits": {"train": f"0:{len(rows)}"},
            "data_path": DATA_PATH, "video_path": VIDEO_PATH if videos else None,
            "features": {**features, **{k: {"dtype": d, "shape": [1], "names": None} for k, d in BOOKKEEPING.items()}}}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))


def _frames(arrays: dict, features: dict, ep_index: int, offset: int, task_index: int, fps: int) -> pa.Table:
    """One episode's rows with the arrow types of lerobot's HF features: shape-(1,) features as
    scalars, vectors as fixed-size lists, images (depth) as nested lists; videos stay out."""
    n = len(arrays["action"])
    cols = {}
    for f, a in arrays.items():
        if features[f]["dtype"] == "video":
            continue
        flat = pa.array(a.reshape(-1))
        if a.shape[1:] == (1,):
            cols[f] = flat
        elif a.ndim == 2:
            cols[f] = pa.FixedSizeListArray.from_arrays(flat, a.shape[1])
        else:
            for dim in reversed(a.shape[1:]):
                flat = pa.ListArray.from_arrays(pa.array(np.arange(0, len(flat) + 1, dim, dtype=np.int32)), flat)
            cols[f] = flat
    cols["timestamp"] = pa.array(np.arange(n, dtype=np.float32) / np.float32(fps))
    cols["frame_index"] = pa.array(np.arange(n, dtype=np.int64))
    cols["episode_index"] = pa.array(np.full(n, ep_index, np.int64))
    cols["index"] = pa.array(np.arange(offset, offset + n, dtype=np.int64))
    cols["task_index"] = pa.array(np.full(n, task_index, np.int64))
    return pa.table(cols)


def episode_stats(a: np.ndarray, image: bool) -> dict[str, np.ndarray]:
    """lerobot's statistics of one episode: per dimension, images per channel in [0, 1] (shape (3, 1, 1))."""
    if image:
        x, shape = (a.astype(np.float64) / 255.0).reshape(-1, a.shape[-1]), (a.shape[-1], 1, 1)
    else:
        x, shape = a.astype(np.float64).reshape(len(a), -1), a.shape[1:]
    s = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0)}
    s |= {q: np.quantile(x, v, axis=0) for q, v in QUANTILES.items()}
    return {**{k: v.reshape(shape) for k, v in s.items()}, "count": np.array([len(a)])}


def aggregate(parts: list[dict]) -> dict[str, np.ndarray]:
    """Episodes' statistics combined as lerobot's aggregate_stats does: exact min/max/mean/std,
    quantiles as count-weighted means."""
    n = np.array([p["count"][0] for p in parts], dtype=np.float64)
    w = (n / n.sum()).reshape(-1, *[1] * parts[0]["mean"].ndim)
    means = np.stack([p["mean"] for p in parts])
    mean = (w * means).sum(0)
    var = (w * (np.stack([p["std"] for p in parts]) ** 2 + (means - mean) ** 2)).sum(0)
    out = {"min": np.min([p["min"] for p in parts], 0), "max": np.max([p["max"] for p in parts], 0),
           "mean": mean, "std": np.sqrt(var), "count": np.array([int(n.sum())])}
    out |= {q: (w * np.stack([p[q] for p in parts])).sum(0) for q in QUANTILES}
    return out


def _parquet(path: Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy")
