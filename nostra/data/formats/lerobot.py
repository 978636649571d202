"""LeRobot v3 datasets: ``meta/info.json`` (features, fps, path templates), ``meta/tasks.parquet``,
``meta/episodes/chunk-XXX/file-XXX.parquet`` (one row per episode: length, tasks, where its rows and
video segments are), frames in ``data/chunk-XXX/file-XXX.parquet`` (many episodes per file) and
camera streams either as mp4 segments in ``videos/<key>/chunk-XXX/file-XXX.mp4`` (decoded with
PyAV) or as PNG bytes inside the parquet ("image" features).

LeRobot keys map to ours by a key map ``{our_key: "feature"}`` where a feature may be sliced,
``"observation.state[0:3]"``. Without one: ``action`` -> ``actions``, ``observation.images.<cam>``
-> ``<cam>_image``, ``observation.image`` -> ``agentview_image``, ``observation.<x>`` -> ``<x>``,
``next.reward``/``next.done`` -> rewards/dones."""

from __future__ import annotations

import io
import json
import re
from fractions import Fraction
from pathlib import Path
from typing import Iterable

import av
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from PIL import Image

from nostra.data.episode import Episode, normalize_meta
from nostra.data.errors import DataError
from nostra.modality import kind_of_key

FMT = "lerobot"
BOOKKEEPING = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
EXTRAS = {"next.reward": "rewards", "next.done": "dones"}
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
_SLICE = re.compile(r"^(?P<feat>.+?)(?:\[(?P<a>-?\d*):(?P<b>-?\d*)\])?$")


def sniff(path: Path) -> bool:
    return path.is_dir() and (path / "meta" / "info.json").is_file()


def default_key(feature: str, spec: dict) -> str | None:
    """Our key for a LeRobot feature, or None for bookkeeping and non-numeric columns."""
    if feature == "action":
        return "actions"
    if feature in BOOKKEEPING or feature.startswith("next.") or spec.get("dtype") == "string":
        return None
    name = feature.removeprefix("observation.")
    if spec.get("dtype") in ("video", "image"):
        name = name.removeprefix("images.")
        if name == "image":
            return "agentview_image"
        return name.replace(".", "_") if name.endswith(("_image", "_depth")) else f"{name.replace('.', '_')}_image"
    return name.replace(".", "_")


class LeRobotSource:
    fmt = FMT

    def __init__(self, path, key_map: dict | None = None, keys: list[str] | None = None, defaults: dict | None = None):
        self.root = self.path = Path(path)
        self.defaults = defaults or {}
        self.info = self._info()
        self.features: dict = self.info["features"]
        self.fps = float(self.info.get("fps") or 0) or None
        self.map = self._mapping(key_map, keys)
        self.episodes = self._episodes()
        self.tasks = self._tasks()
        self._table_key, self._table = None, None

    # ---- metadata -------------------------------------------------------------------------
    def _info(self) -> dict:
        p = self.root / "meta" / "info.json"
        try:
            info = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise DataError(p, f"cannot read LeRobot info ({e})") from None
        version = str(info.get("codebase_version", ""))
        if not version.startswith("v3"):
            raise DataError(p, f"LeRobot codebase_version {version!r} is not supported; valid: v3.x "
                               "(convert older datasets with lerobot's convert_dataset_v21_to_v30)",
                            key="codebase_version")
        if "features" not in info:
            raise DataError(p, "no 'features'", key="features")
        return info

    def _mapping(self, key_map: dict | None, keys: list[str] | None) -> dict[str, tuple[str, slice | None]]:
        if key_map:
            out = {}
            for ours, spec in key_map.items():
                m = _SLICE.match(str(spec))
                feat, a, b = m["feat"], m["a"], m["b"]
                if feat not in self.features:
                    raise DataError(self.root / "meta/info.json", f"key map entry {ours!r} -> {spec!r}: no such "
                                    f"feature; valid: {sorted(self.features)}", key=feat)
                sl = slice(int(a) if a else None, int(b) if b else None) if m["b"] is not None else None
                out[ours] = (feat, sl)
        else:
            out = {k: (f, None) for f, s in self.features.items() if (k := default_key(f, s))}
        if "actions" not in out:
            raise DataError(self.root / "meta/info.json", "no action feature (map one to 'actions')", key="actions")
        if keys is not None:
            missing = [k for k in keys if k not in out]
            if missing:
                raise DataError(self.root, f"no feature maps to {missing}; mapped keys: {sorted(out)}", key=missing[0])
            out = {k: v for k, v in out.items() if k in keys or k == "actions"}
        return out

    def _episodes(self) -> list[dict]:
        files = sorted((self.root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
        if not files:
            raise DataError(self.root / "meta/episodes", "no episode metadata (chunk-XXX/file-XXX.parquet)")
        rows = []
        for f in files:
            rows += _read_parquet(f).to_pylist()
        return sorted(rows, key=lambda r: r["episode_index"])

    def _tasks(self) -> dict[int, str]:
        p = self.root / "meta" / "tasks.parquet"
        if not p.exists():
            return {}
        df = _read_parquet(p).to_pandas()
        if "task" not in df.columns:
            df = df.reset_index()
        return {int(i): str(t) for i, t in zip(df["task_index"], df["task"])}

    @property
    def files(self) -> list[Path]:
        return sorted(p for p in self.root.rglob("*") if p.is_file())

    @property
    def attrs(self) -> dict:
        return {"env_args": {"env_name": self.defaults.get("task", ""), "type": 1, "env_kwargs": {}},
                "lerobot_info": {k: v for k, v in self.info.items() if k != "features"}}

    def __len__(self) -> int:
        return len(self.episodes)

    # ---- episodes -------------------------------------------------------------------------
    def __iter__(self):
        for row in self.episodes:
            yield self._episode(row)

    def _episode(self, row: dict) -> Episode:
        demo = f"episode_{row['episode_index']}"
        table = self._rows(row, demo)
        cols: dict[str, np.ndarray] = {}
        out: dict[str, np.ndarray] = {}
        for ours, (feat, sl) in self.map.items():
            if feat not in cols:
                cols[feat] = self._feature(feat, table, row, demo)
            out[ours] = cols[feat] if sl is None else cols[feat][:, sl]
        extras = {ours: _column(table, f, self.root, demo) for f, ours in EXTRAS.items() if f in table.column_names}
        extras = {k: v.reshape(len(v)) for k, v in extras.items()}
        tasks = row.get("tasks") or []
        raw = {"language": tasks[0] if tasks else "", "task": self.defaults.get("task", "")}
        actions = out.pop("actions")
        return Episode(demo, actions, out, extras, normalize_meta(raw, self.root, demo, self.defaults))

    def _rows(self, row: dict, demo: str) -> pa.Table:
        rel = self.info.get("data_path", DATA_PATH).format(
            chunk_index=row.get("data/chunk_index", 0), file_index=row.get("data/file_index", 0))
        if self._table_key != rel:  # many episodes share one file: keep the last one read
            self._table, self._table_key = _read_parquet(self.root / rel), rel
        t = self._table.filter(pc.equal(self._table["episode_index"], row["episode_index"]))
        if "frame_index" in t.column_names:
            t = t.sort_by("frame_index")
        if t.num_rows != row.get("length", t.num_rows) or t.num_rows == 0:
            raise DataError(self.root / rel, f"has {t.num_rows} rows for the episode, episode metadata says "
                                             f"{row.get('length')}", demo, "length")
        return t

    def _feature(self, feat: str, table: pa.Table, row: dict, demo: str) -> np.ndarray:
        spec = self.features[feat]
        if spec.get("dtype") == "video":
            return self._video(feat, spec, table, row, demo)
        if feat not in table.column_names:
            raise DataError(self.root, "feature listed in info.json has no data column", demo, feat)
        if spec.get("dtype") == "image":
            return _images(table[feat], self.root, demo, feat)
        return _column(table, feat, self.root, demo, spec.get("shape"))

    def _video(self, feat: str, spec: dict, table: pa.Table, row: dict, demo: str) -> np.ndarray:
        if spec.get("info", {}).get("video.is_depth_map"):
            raise DataError(self.root, "depth-map videos are not supported; store depth as a float feature", demo, feat)
        rel = self.info.get("video_path", VIDEO_PATH).format(
            video_key=feat, chunk_index=row.get(f"videos/{feat}/chunk_index", 0),
            file_index=row.get(f"videos/{feat}/file_index", 0))
        start = float(row.get(f"videos/{feat}/from_timestamp", 0.0))
        ts = table["timestamp"].to_numpy().astype(np.float64) if "timestamp" in table.column_names else \
            np.arange(table.num_rows) / self.fps
        return decode_frames(self.root / rel, start + ts, self.fps, demo, feat)


def _read_parquet(path: Path) -> pa.Table:
    try:
        return pq.read_table(path)
    except (OSError, pa.ArrowException) as e:
        raise DataError(path, f"cannot be read as parquet (truncated or corrupt?): {e}") from None


def _column(table: pa.Table, name: str, root, demo: str, shape=None) -> np.ndarray:
    col = table[name].combine_chunks()
    n = len(col)
    while pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
        col = col.flatten()
    try:
        flat = col.to_numpy(zero_copy_only=False)
    except (pa.ArrowException, ValueError) as e:
        raise DataError(root, f"cannot convert column to numbers ({e})", demo, name) from None
    if flat.dtype == object:
        raise DataError(root, f"column holds {col.type}, not numbers", demo, name)
    if n and flat.size % n:
        raise DataError(root, f"ragged column: {flat.size} values for {n} rows", demo, name)
    want = tuple(shape or ())
    if want and int(np.prod(want)) * n == flat.size and want != (1,):
        return flat.reshape(n, *want)
    return flat.reshape(n, -1)


def _images(col: pa.ChunkedArray, root, demo: str, name: str) -> np.ndarray:
    """'image' features: a struct of PNG/JPEG bytes and a path (used when bytes are absent)."""
    frames = []
    for item in col.to_pylist():
        data = item.get("bytes") if isinstance(item, dict) else item
        try:
            src = io.BytesIO(data) if data else Path(root) / item["path"]
            frames.append(np.asarray(Image.open(src).convert("RGB")))
        except (OSError, KeyError, TypeError) as e:
            raise DataError(root, f"cannot decode image ({e})", demo, name) from None
    return np.stack(frames)


def decode_frames(path: Path, times: np.ndarray, fps: float | None, demo: str, key: str) -> np.ndarray:
    """Frames at the given times (seconds) of an mp4, matched to the nearest decoded frame within
    half a frame period."""
    tol = 0.5 / fps if fps else 1e-3
    try:
        with av.open(str(path)) as c:
            s = c.streams.video[0]
            c.seek(max(0, int((times[0] - tol) / s.time_base)), stream=s, backward=True)
            got_t, got = [], []
            for fr in c.decode(s):
                t = float(fr.pts * s.time_base)
                if t < times[0] - tol:
                    continue
                if t > times[-1] + tol:
                    break
                got_t.append(t)
                got.append(fr.to_ndarray(format="rgb24"))
    except (OSError, av.FFmpegError) as e:
        raise DataError(path, f"cannot decode video ({e})", demo, key) from None
    if not got:
        raise DataError(path, f"no frames between {times[0]:.3f}s and {times[-1]:.3f}s", demo, key)
    got_t = np.asarray(got_t)
    idx = np.abs(got_t[None, :] - times[:, None]).argmin(1)
    err = np.abs(got_t[idx] - times)
    if (err > tol).any():
        i = int(err.argmax())
        raise DataError(path, f"no frame at {times[i]:.3f}s (nearest {got_t[idx[i]]:.3f}s)", demo, key)
    return np.stack([got[i] for i in idx])


# ---- writer (fixtures and conversions) ------------------------------------------------------

def write(root, episodes: Iterable[Episode], fps: int = 10, video: bool = True,
          state_keys: list[str] | None = None) -> Path:
    """Write episodes as a LeRobot v3 dataset (one data file, one video file per camera).
    ``state_keys`` are concatenated into ``observation.state``; other lowdim keys become
    ``observation.<key>``; rgb keys ``observation.images.<cam>``; ``language`` becomes the task."""
    root = Path(root)
    eps = list(episodes)
    state_keys = list(state_keys or [])
    cams = [k for k in eps[0].obs if kind_of_key(k) == "rgb"]
    lows = [k for k in eps[0].obs if kind_of_key(k) == "lowdim" and k not in state_keys]
    tasks = sorted({e.meta.get("language", "") for e in eps})
    cols: dict[str, list] = {c: [] for c in ("index", "episode_index", "frame_index", "timestamp", "task_index")}
    feats: dict[str, np.ndarray | list] = {}
    ep_rows, offset = [], 0
    for i, e in enumerate(eps):
        n = len(e)
        cols["index"] += list(range(offset, offset + n))
        cols["episode_index"] += [i] * n
        cols["frame_index"] += list(range(n))
        cols["timestamp"] += list(np.arange(n, dtype=np.float32) / fps)
        cols["task_index"] += [tasks.index(e.meta.get("language", ""))] * n
        arrays = {"action": e.actions, **{f"observation.{k}": e.obs[k] for k in lows}}
        if state_keys:
            arrays["observation.state"] = np.concatenate([e.obs[k] for k in state_keys], 1)
        for cam in cams:
            arrays[_cam_feature(cam)] = e.obs[cam]
        for f, a in arrays.items():
            feats.setdefault(f, []).append(a)
        row = {"episode_index": i, "tasks": [e.meta.get("language", "")], "length": n,
               "dataset_from_index": offset, "dataset_to_index": offset + n,
               "data/chunk_index": 0, "data/file_index": 0,
               "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0}
        for cam in cams if video else []:
            f = _cam_feature(cam)
            row |= {f"videos/{f}/chunk_index": 0, f"videos/{f}/file_index": 0,
                    f"videos/{f}/from_timestamp": offset / fps, f"videos/{f}/to_timestamp": (offset + n) / fps}
        ep_rows.append(row)
        offset += n
    feats = {f: np.concatenate(v) for f, v in feats.items()}
    table = {k: pa.array(v) for k, v in cols.items()}
    features = {k: {"dtype": "int64" if k != "timestamp" else "float32", "shape": [1], "names": None} for k in cols}
    for f, a in feats.items():
        if a.dtype == np.uint8:  # a camera
            features[f] = {"dtype": "video" if video else "image", "shape": list(a.shape[1:]),
                           "names": ["height", "width", "channels"]}
            if video:
                features[f]["info"] = {"video.fps": fps, "video.codec": "h264", "video.pix_fmt": "yuv420p",
                                       "video.is_depth_map": False, "has_audio": False}
                _encode_mp4(root / VIDEO_PATH.format(video_key=f, chunk_index=0, file_index=0), a, fps)
            else:
                table[f] = pa.array([{"bytes": _png(img), "path": None} for img in a],
                                    pa.struct([("bytes", pa.binary()), ("path", pa.string())]))
        else:
            features[f] = {"dtype": str(a.dtype), "shape": list(a.shape[1:]), "names": None}
            table[f] = pa.FixedSizeListArray.from_arrays(pa.array(a.reshape(-1)), a.shape[1])
    _write_parquet(root / DATA_PATH.format(chunk_index=0, file_index=0), pa.table(table))
    _write_parquet(root / "meta/episodes/chunk-000/file-000.parquet", pa.Table.from_pylist(ep_rows))
    _write_parquet(root / "meta/tasks.parquet", pa.table({"task_index": list(range(len(tasks))), "task": tasks}))
    info = {"codebase_version": "v3.0", "robot_type": "panda", "total_episodes": len(eps), "total_frames": offset,
            "total_tasks": len(tasks), "chunks_size": 1000, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200, "fps": fps, "splits": {"train": f"0:{len(eps)}"},
            "data_path": DATA_PATH, "video_path": VIDEO_PATH if video else None, "features": features}
    (root / "meta/info.json").write_text(json.dumps(info, indent=2))
    return root


def _cam_feature(key: str) -> str:
    return f"observation.images.{key.removesuffix('_image')}"


def _write_parquet(path: Path, table: pa.Table) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path)


def _png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def _encode_mp4(path: Path, frames: np.ndarray, fps: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libx264", rate=fps, options={"crf": "10", "g": "10"})
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        s.time_base = Fraction(1, fps)
        for i, img in enumerate(frames):
            fr = av.VideoFrame.from_ndarray(img, format="rgb24")
            fr.pts = i
            c.mux(s.encode(fr))
        c.mux(s.encode())
