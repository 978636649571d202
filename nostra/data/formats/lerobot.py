"""LeRobot datasets, v3 and v2.x.

v3: ``meta/info.json`` (features, fps, path templates), ``meta/tasks.parquet`` (as lerobot writes
it, the task strings are the pandas index; a ``task`` column reads too), ``meta/episodes/chunk-XXX/
file-XXX.parquet`` (one row per episode: length, ``tasks``, where its rows and video segments are),
frames in ``data/chunk-XXX/file-XXX.parquet`` (many episodes per file) and camera streams either
as mp4s shared by the episodes of a chunk, ``videos/<key>/chunk-XXX/file-XXX.mp4``, each
episode decoded (PyAV) from ``videos/<key>/from_timestamp`` on, or as PNG bytes inside the parquet
("image" features). An episode's task string is its ``tasks`` entry, else its frames'
``task_index`` looked up in the tasks table.

v2.0/v2.1: ``meta/episodes.jsonl``, ``meta/tasks.jsonl``, one parquet per episode
(``data/chunk-XXX/episode_XXXXXX.parquet``) and one mp4 per episode and camera.

LeRobot keys map to ours by a key map ``{our_key: "feature"}`` where a feature may be sliced,
``"observation.state[0:3]"``. Without one: ``action`` -> ``actions``, ``observation.images.<cam>``
-> ``<cam>_image``, ``observation.image`` -> the front image (``nostra.modality.FRONT_IMAGE``),
``observation.<x>`` -> ``<x>``, a vector whose ``names`` are ``<key>.<i>`` (our export's
``observation.state``) -> those keys, ``next.reward``/``next.done`` -> rewards/dones."""

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
from nostra.data.formats.keys import select_keys
from nostra.modality import FRONT_IMAGE, kind_of_key

FMT = "lerobot"
BOOKKEEPING = {"timestamp", "frame_index", "episode_index", "index", "task_index"}
EXTRAS = {"next.reward": "rewards", "next.done": "dones", "states": "states"}
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
V2_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
V2_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
_SLICE = re.compile(r"^(?P<feat>.+?)(?:\[(?P<a>-?\d*):(?P<b>-?\d*)\])?$")


def sniff(path: Path) -> bool:
    return path.is_dir() and (path / "meta" / "info.json").is_file()


def default_key(feature: str, spec: dict) -> str | None:
    """Our key for a LeRobot feature, or None for bookkeeping and non-numeric columns."""
    if feature == "action":
        return "actions"
    if feature in BOOKKEEPING or feature in EXTRAS or feature.startswith("next.") or spec.get("dtype") == "string":
        return None
    name = feature.removeprefix("observation.")
    if spec.get("dtype") in ("video", "image"):
        name = name.removeprefix("images.")
        if name == "image":
            return FRONT_IMAGE
        return name.replace(".", "_") if name.endswith(("_image", "_depth")) else f"{name.replace('.', '_')}_image"
    return name.replace(".", "_")


class LeRobotSource:
    fmt = FMT

    def __init__(self, path, key_map: dict | None = None, keys: list[str] | None = None, defaults: dict | None = None):
        self.root = self.path = Path(path)
        self.defaults = defaults or {}
        self.info = self._info()
        self.v2 = str(self.info["codebase_version"]).startswith("v2")
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
        if not isinstance(info, dict):
            raise DataError(p, "is not a JSON object")
        version = str(info.get("codebase_version", ""))
        if not version.startswith(("v2", "v3")):
            raise DataError(p, f"LeRobot codebase_version {version!r} is not supported; valid: v2.0, v2.1, v3.x "
                               "(convert older datasets with lerobot's conversion scripts)", key="codebase_version")
        if not isinstance(info.get("features"), dict):
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
            out = {}
            for f, s in self.features.items():
                out |= split_by_names(f, s) or ({k: (f, None)} if (k := default_key(f, s)) else {})
        if "actions" not in out:
            raise DataError(self.root / "meta/info.json", "no action feature (map one to 'actions')", key="actions")
        return select_keys(out, keys, self.root, "feature")

    def _episodes(self) -> list[dict]:
        if self.v2:
            rows = _read_jsonl(self.root / "meta" / "episodes.jsonl")
            where = self.root / "meta" / "episodes.jsonl"
        else:
            where = self.root / "meta" / "episodes"
            files = sorted(where.glob("chunk-*/file-*.parquet"))
            if not files:
                raise DataError(where, "no episode metadata (chunk-XXX/file-XXX.parquet)")
            rows = []
            for f in files:
                rows += _read_parquet(f).to_pylist()
        for i, r in enumerate(rows):
            if not isinstance(r, dict) or not isinstance(r.get("episode_index"), int):
                raise DataError(where, f"row {i} has no integer episode_index", key="episode_index")
        return sorted(rows, key=lambda r: r["episode_index"])

    def _tasks(self) -> dict[int, str]:
        """task_index -> task string, from meta/tasks.parquet (v3) or meta/tasks.jsonl (v2)."""
        if self.v2:
            p = self.root / "meta" / "tasks.jsonl"
            rows = _read_jsonl(p) if p.exists() else []
            try:
                return {int(r["task_index"]): str(r["task"]) for r in rows}
            except (KeyError, TypeError, ValueError) as e:
                raise DataError(p, f"each line needs task_index and task ({type(e).__name__}: {e})",
                                key="task") from None
        p = self.root / "meta" / "tasks.parquet"
        return read_tasks_parquet(p) if p.exists() else {}

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
            demo = f"episode_{row['episode_index']}"
            try:
                yield self._episode(row, demo)
            except DataError:
                raise
            except (KeyError, IndexError, TypeError, ValueError, OSError, pa.ArrowException) as e:
                raise DataError(self.root, f"cannot be read ({type(e).__name__}: {e})", demo) from None

    def _episode(self, row: dict, demo: str) -> Episode:
        table = self._rows(row, demo)
        cols: dict[str, np.ndarray] = {}
        out: dict[str, np.ndarray] = {}
        for ours, (feat, sl) in self.map.items():
            if feat not in cols:
                cols[feat] = self._feature(feat, table, row, demo)
            out[ours] = cols[feat] if sl is None else cols[feat][:, sl]
        extras = {ours: _column(table, f, self.root, demo) for f, ours in EXTRAS.items() if f in table.column_names}
        extras = {k: v.reshape(len(v)) if v.ndim == 2 and v.shape[1] == 1 else v for k, v in extras.items()}
        raw = {"language": self._language(row, table, demo), "task": self.defaults.get("task", "")}
        actions = out.pop("actions")
        return Episode(demo, actions, out, extras, normalize_meta(raw, self.root, demo, self.defaults))

    def _language(self, row: dict, table: pa.Table, demo: str) -> str:
        """The episode's task string: the episodes table's ``tasks`` list, else the first frame's
        ``task_index`` looked up in the tasks table."""
        tasks = row.get("tasks")
        if isinstance(tasks, str):
            return tasks
        if tasks:
            return str(tasks[0])
        if "task_index" not in table.column_names:
            return ""
        i = int(table["task_index"][0].as_py())
        if i not in self.tasks:
            where = "meta/tasks.jsonl" if self.v2 else "meta/tasks.parquet"
            raise DataError(self.root / where, f"has no task_index {i} (used by the episode's frames); it has "
                                               f"{sorted(self.tasks)}", demo, "task_index")
        return self.tasks[i]

    def _data_path(self, row: dict) -> str:
        ep = row["episode_index"]
        if self.v2:
            return self.info.get("data_path", V2_DATA_PATH).format(
                episode_chunk=ep // int(self.info.get("chunks_size") or 1000), episode_index=ep)
        return self.info.get("data_path", DATA_PATH).format(
            chunk_index=row.get("data/chunk_index", 0), file_index=row.get("data/file_index", 0))

    def _rows(self, row: dict, demo: str) -> pa.Table:
        rel = self._data_path(row)
        if self._table_key != rel:  # many episodes share one file: keep the last one read
            self._table, self._table_key = _read_parquet(self.root / rel), rel
        t = self._table
        if "episode_index" in t.column_names:
            t = t.filter(pc.equal(t["episode_index"], row["episode_index"]))
        elif not self.v2:
            raise DataError(self.root / rel, "no episode_index column", demo, "episode_index")
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
            raise DataError(self.root / self._data_path(row), "feature listed in info.json has no data column",
                            demo, feat)
        if spec.get("dtype") == "image":
            return _images(table[feat], self.root, demo, feat)
        return _column(table, feat, self.root, demo, spec.get("shape"))

    def _video_path(self, feat: str, row: dict) -> Path:
        ep = row["episode_index"]
        if self.v2:
            rel = self.info.get("video_path") or V2_VIDEO_PATH
            return self.root / rel.format(episode_chunk=ep // int(self.info.get("chunks_size") or 1000),
                                          video_key=feat, episode_index=ep)
        return self.root / (self.info.get("video_path") or VIDEO_PATH).format(
            video_key=feat, chunk_index=row.get(f"videos/{feat}/chunk_index", 0),
            file_index=row.get(f"videos/{feat}/file_index", 0))

    def _video(self, feat: str, spec: dict, table: pa.Table, row: dict, demo: str) -> np.ndarray:
        """Frames of the episode: its frame timestamps, offset by where the episode starts in a
        shared (v3) file, ``videos/<key>/from_timestamp``."""
        if spec.get("info", {}).get("video.is_depth_map"):
            raise DataError(self.root, "depth-map videos are not supported; store depth as a float feature", demo, feat)
        path = self._video_path(feat, row)
        start = 0.0 if self.v2 else row.get(f"videos/{feat}/from_timestamp")
        if start is None:
            raise DataError(self.root / "meta/episodes", "no from_timestamp for the video", demo,
                            f"videos/{feat}/from_timestamp")
        ts = table["timestamp"].to_numpy().astype(np.float64) if "timestamp" in table.column_names else \
            np.arange(table.num_rows) / self.fps
        return decode_frames(path, float(start) + ts, self.fps, demo, feat)


def read_tasks_parquet(path: Path) -> dict[int, str]:
    """lerobot writes ``meta/tasks.parquet`` with pandas from ``DataFrame({"task_index": ...},
    index=tasks)``: the strings are the index, a column named ``task`` (index named) or
    ``__index_level_0__`` (unnamed), named in the pandas metadata. A plain ``task`` column reads too."""
    t = _read_parquet(path)
    names = t.column_names
    meta = json.loads((t.schema.metadata or {}).get(b"pandas", b"{}") or b"{}")
    index_cols = [c for c in meta.get("index_columns", []) if isinstance(c, str)]
    col = next((c for c in ["task", *index_cols, "__index_level_0__"] if c in names and c != "task_index"), None)
    if col is None or "task_index" not in names:
        raise DataError(path, f"needs task strings (a 'task' column or the pandas index) and 'task_index'; it has "
                              f"columns {names}", key="task" if col is None else "task_index")
    try:
        return {int(i): str(s) for i, s in zip(t["task_index"].to_pylist(), t[col].to_pylist())}
    except (TypeError, ValueError) as e:
        raise DataError(path, f"task_index is not an integer ({e})", key="task_index") from None


def split_by_names(feature: str, spec: dict) -> dict[str, tuple[str, slice]]:
    """A vector feature whose ``names`` are ``<key>.<i>`` (as our LeRobot export writes
    ``observation.state``) splits back into those keys."""
    names = spec.get("names")
    if spec.get("dtype") in ("video", "image", "string") or not isinstance(names, list) or not names:
        return {}
    parts = [str(n).rsplit(".", 1) for n in names]
    if not all(len(p) == 2 and p[1].isdigit() for p in parts):
        return {}
    out, start = {}, 0
    for i in range(1, len(parts) + 1):
        if i == len(parts) or parts[i][0] != parts[start][0]:
            key = parts[start][0]
            if key in out or [int(p[1]) for p in parts[start:i]] != list(range(i - start)):
                return {}
            out[key] = (feature, slice(start, i))
            start = i
    return out


def _read_jsonl(path: Path) -> list:
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise DataError(path, f"cannot be read ({e})") from None
    out = []
    for i, line in enumerate(lines):
        if line.strip():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError as e:
                raise DataError(path, f"line {i + 1} is not JSON ({e})") from None
    return out


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
