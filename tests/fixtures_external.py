"""Tiny datasets laid out as other tools write them, not as this project's writers do, so the
readers are tested against the real layouts. No third-party writer is imported (lerobot cannot be
installed here); each function says which tool and version it mimics and what it reproduces.

- ``write_lerobot_v30``: lerobot 0.4.1 (codebase v3.0), ``LeRobotDataset.save_episode``.
- ``write_lerobot_v21``: lerobot 0.3.3 (codebase v2.1).
- ``write_robosuite_raw``: robosuite 1.5.2, its own DataCollectionWrapper and gather_demonstrations_as_hdf5.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import av
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from nostra.data.episode import Episode
from nostra.modality import kind_of_key, sim_observations

QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
TASK_LAYOUTS = ("lerobot", "named_index", "episodes_only", "frames_only")
LOWDIM_OBS = sim_observations().lowdim_keys


def lerobot_frames(eps: list[Episode], state_keys: list[str]) -> tuple[list[dict], dict]:
    """Per-episode feature arrays in LeRobot names (``action``, ``observation.state``,
    ``observation.images.<cam>``) and the ``features`` of info.json for them."""
    out = []
    for e in eps:
        f = {"action": e.actions}
        if state_keys:
            f["observation.state"] = np.concatenate([e.obs[k] for k in state_keys], 1)
        for k, v in e.obs.items():
            if kind_of_key(k) == "rgb":
                f[f"observation.images.{k.removesuffix('_image')}"] = v
        out.append(f)
    features = {}
    for name, a in out[0].items():
        if a.dtype == np.uint8:
            features[name] = {"dtype": "video", "shape": list(a.shape[1:]), "names": ["height", "width", "channels"]}
        else:
            features[name] = {"dtype": str(a.dtype), "shape": list(a.shape[1:]), "names": None}
    return out, features


def _stats(a: np.ndarray, image: bool) -> dict:
    """lerobot's per-feature statistics: images per channel in [0, 1] with shape (3, 1, 1)."""
    if image:  # (T, H, W, C) -> (C, T*H*W): per channel
        x = (a.astype(np.float64) / 255.0).transpose(3, 0, 1, 2).reshape(a.shape[-1], -1).T
        shape = (a.shape[-1], 1, 1)
    else:
        x, shape = a.astype(np.float64).reshape(len(a), -1), a.shape[1:]
    s = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0)}
    s |= {q: np.quantile(x, v, axis=0) for q, v in QUANTILES.items()}
    return {**{k: v.reshape(shape) for k, v in s.items()}, "count": np.array([len(a)])}


def _encode_episode_video(path: Path, frames: np.ndarray, fps: int) -> None:
    """lerobot's encode_video_frames defaults: libsvtav1, yuv420p, g=2, crf=30; frames get no pts."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream("libsvtav1", fps, options={"g": "2", "crf": "30"})
        s.pix_fmt, s.width, s.height = "yuv420p", frames.shape[2], frames.shape[1]
        for img in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)


def _concatenate(inputs: list[Path], output: Path) -> None:
    """Stream copy through ffmpeg's concat demuxer, as lerobot's concatenate_video_files does."""
    with tempfile.TemporaryDirectory() as tmp:
        lst = Path(tmp) / "list.ffconcat"
        lst.write_text("ffconcat version 1.0\n" + "".join(f"file '{p.resolve()}'\n" for p in inputs))
        out = Path(tmp) / "out.mp4"
        with av.open(str(lst), "r", format="concat", options={"safe": "0"}) as src, \
                av.open(str(out), "w", options={"movflags": "faststart"}) as dst:
            streams = {}
            for s in src.streams:
                if s.type == "video":
                    streams[s.index] = dst.add_stream_from_template(template=s, opaque=True)
                    streams[s.index].time_base = s.time_base
            for packet in src.demux():
                if packet.stream.index not in streams or packet.dts is None:
                    continue
                packet.stream = streams[packet.stream.index]
                dst.mux(packet)
        output.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(out, output)


def _duration(path: Path) -> float:
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        return float(s.duration * s.time_base) if s.duration is not None else float(c.duration / av.time_base)


def _video_info(path: Path) -> dict:
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        return {"video.height": s.height, "video.width": s.width, "video.codec": s.codec_context.codec.canonical_name,
                "video.pix_fmt": s.pix_fmt, "video.is_depth_map": False, "video.fps": int(s.base_rate),
                "video.channels": 3, "has_audio": False}


def _frame_table(f: dict, features: dict, ep_index: int, offset: int, task_index: int, fps: int) -> pa.Table:
    """One episode's rows as lerobot's HF features store them: shape-(1,) features as scalars,
    vectors as fixed-size lists; videos are not in the parquet."""
    n = len(f["action"])
    cols = {}
    for name, a in f.items():
        if features[name]["dtype"] == "video":
            continue
        flat = pa.array(a.reshape(-1))
        cols[name] = flat if a.shape[1:] == (1,) else pa.FixedSizeListArray.from_arrays(flat, a.shape[1])
    cols["timestamp"] = pa.array(np.arange(n, dtype=np.float32) / fps)
    cols["frame_index"] = pa.array(np.arange(n, dtype=np.int64))
    cols["episode_index"] = pa.array(np.full(n, ep_index, np.int64))
    cols["index"] = pa.array(np.arange(offset, offset + n, dtype=np.int64))
    cols["task_index"] = pa.array(np.full(n, task_index, np.int64))
    return pa.table(cols)


def write_lerobot_v30(root, eps: list[Episode], fps: int = 10, state_keys=(), task_layout: str = "lerobot") -> Path:
    """A LeRobot v3.0 dataset as lerobot 0.4.1 writes it: all frames in
    ``data/chunk-000/file-000.parquet``; each episode's video encoded alone (libsvtav1) and
    appended to ``videos/<key>/chunk-000/file-000.mp4`` by stream copy, its place in the shared
    file kept as ``videos/<key>/from_timestamp``/``to_timestamp`` (the durations of the files
    before it); ``meta/episodes/chunk-000/file-000.parquet`` with ``tasks`` (a list), lengths, row
    ranges and flattened ``stats/<feature>/<stat>``; ``meta/tasks.parquet`` written by pandas from
    ``DataFrame({"task_index": ...}, index=tasks)`` (the strings in the index, stored as
    ``__index_level_0__``); ``meta/stats.json`` and ``meta/info.json``.

    ``task_layout`` mimics the other layouts seen in official v3 datasets: ``named_index`` (the
    index named ``task``, as newer lerobot writes it), ``episodes_only`` (no tasks.parquet, the
    strings only in the episodes' ``tasks`` column), ``frames_only`` (no ``tasks`` column in the
    episodes table: only the per-frame ``task_index``)."""
    if task_layout not in TASK_LAYOUTS:
        raise ValueError(f"task_layout {task_layout!r}; valid: {TASK_LAYOUTS}")
    root = Path(root)
    frames, features = lerobot_frames(eps, list(state_keys))
    tasks = list(dict.fromkeys(e.meta.get("language", "") for e in eps))
    cams = [k for k, v in features.items() if v["dtype"] == "video"]
    tables, rows, offset, elapsed = [], [], 0, {c: 0.0 for c in cams}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (e, f) in enumerate(zip(eps, frames)):
            n, task = len(e), e.meta.get("language", "")
            tables.append(_frame_table(f, features, i, offset, tasks.index(task), fps))
            row = {"episode_index": i, "tasks": [task], "length": n, "data/chunk_index": 0, "data/file_index": 0,
                   "dataset_from_index": offset, "dataset_to_index": offset + n}
            for cam in cams:
                ep_path = Path(tmp) / cam / f"episode_{i}.mp4"
                _encode_episode_video(ep_path, f[cam], fps)
                dur = _duration(ep_path)
                shared = root / f"videos/{cam}/chunk-000/file-000.mp4"
                if i == 0:
                    shared.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy(ep_path, shared)
                    features[cam]["info"] = _video_info(shared)
                else:
                    _concatenate([shared, ep_path], shared)
                row |= {f"videos/{cam}/chunk_index": 0, f"videos/{cam}/file_index": 0,
                        f"videos/{cam}/from_timestamp": elapsed[cam], f"videos/{cam}/to_timestamp": elapsed[cam] + dur}
                elapsed[cam] += dur
            row |= {"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0}
            for name, a in f.items():
                for k, v in _stats(a, features[name]["dtype"] == "video").items():
                    row[f"stats/{name}/{k}"] = v.tolist()
            if task_layout == "frames_only":
                del row["tasks"]
            rows.append(row)
            offset += n
    data = pa.concat_tables(tables)
    pq.write_table(data, _mkparent(root / "data/chunk-000/file-000.parquet"), compression="snappy")
    pq.write_table(pa.Table.from_pylist(rows), _mkparent(root / "meta/episodes/chunk-000/file-000.parquet"),
                   compression="snappy")
    if task_layout != "episodes_only":
        index = pd.Index(tasks, name="task") if task_layout == "named_index" else tasks
        pd.DataFrame({"task_index": range(len(tasks))}, index=index).to_parquet(root / "meta/tasks.parquet")
    default = {k: {"dtype": "float32" if k == "timestamp" else "int64", "shape": [1], "names": None}
               for k in ("timestamp", "frame_index", "episode_index", "index", "task_index")}
    stats = {name: {k: v.tolist() for k, v in _stats(np.concatenate([f[name] for f in frames]),
                                                      features[name]["dtype"] == "video").items()}
             for name in features}
    (root / "meta/stats.json").write_text(json.dumps(stats, indent=4))
    info = {"codebase_version": "v3.0", "robot_type": "panda", "total_episodes": len(eps), "total_frames": offset,
            "total_tasks": len(tasks), "chunks_size": 1000, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500, "fps": fps, "splits": {"train": f"0:{len(eps)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4" if cams else None,
            "features": {**features, **default}}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    return root


def write_lerobot_v21(root, eps: list[Episode], fps: int = 10, state_keys=()) -> Path:
    """A LeRobot v2.1 dataset as lerobot 0.3.3 writes it: one parquet per episode
    (``data/chunk-000/episode_000000.parquet``), one mp4 per episode and camera
    (``videos/chunk-000/<key>/episode_000000.mp4``, libsvtav1, each starting at 0 s),
    ``meta/episodes.jsonl`` (episode_index, tasks, length), ``meta/tasks.jsonl``
    (task_index, task), ``meta/episodes_stats.jsonl`` and ``meta/info.json``."""
    root = Path(root)
    frames, features = lerobot_frames(eps, list(state_keys))
    tasks = list(dict.fromkeys(e.meta.get("language", "") for e in eps))
    cams = [k for k, v in features.items() if v["dtype"] == "video"]
    episodes, ep_stats, offset = [], [], 0
    for i, (e, f) in enumerate(zip(eps, frames)):
        task = e.meta.get("language", "")
        pq.write_table(_frame_table(f, features, i, offset, tasks.index(task), fps),
                       _mkparent(root / f"data/chunk-000/episode_{i:06d}.parquet"), compression="snappy")
        for cam in cams:
            path = root / f"videos/chunk-000/{cam}/episode_{i:06d}.mp4"
            _encode_episode_video(path, f[cam], fps)
            features[cam]["info"] = _video_info(path)
        episodes.append({"episode_index": i, "tasks": [task], "length": len(e)})
        ep_stats.append({"episode_index": i, "stats": {
            name: {k: v.tolist() for k, v in _stats(a, features[name]["dtype"] == "video").items()}
            for name, a in f.items()}})
        offset += len(e)
    _jsonl(root / "meta/episodes.jsonl", episodes)
    _jsonl(root / "meta/tasks.jsonl", [{"task_index": i, "task": t} for i, t in enumerate(tasks)])
    _jsonl(root / "meta/episodes_stats.jsonl", ep_stats)
    default = {k: {"dtype": "float32" if k == "timestamp" else "int64", "shape": [1], "names": None}
               for k in ("timestamp", "frame_index", "episode_index", "index", "task_index")}
    info = {"codebase_version": "v2.1", "robot_type": "panda", "total_episodes": len(eps), "total_frames": offset,
            "total_tasks": len(tasks), "total_videos": len(eps) * len(cams), "total_chunks": 1, "chunks_size": 1000,
            "fps": fps, "splits": {"train": f"0:{len(eps)}"},
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
            "features": {**features, **default}}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    return root


def _jsonl(path: Path, items: list[dict]) -> None:
    _mkparent(path).write_text("".join(json.dumps(x) + "\n" for x in items))


def _mkparent(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def write_robosuite_raw(out_dir, episodes: int = 2, steps: int = 12, seed: int = 0) -> tuple[Path, list[dict]]:
    """Raw demos written by robosuite 1.5.2's own code, as ``collect_human_demonstrations`` does:
    ``Lift`` with a Panda and the BASIC controller, wrapped in ``DataCollectionWrapper`` (which
    writes ``state_*.npz`` and ``model.xml`` per episode), then ``gather_demonstrations_as_hdf5``
    imported from ``robosuite.scripts.collect_human_demonstrations`` with the script's
    ``env_info``. Small random actions stand in for the human; ``_check_success`` is patched to
    True because the script keeps successful demos only.

    Returns the ``demo.hdf5`` path and, per episode, what was seen while collecting: ``states``
    (after each step) and the proprioception of that state (``sim.forward()`` then robosuite's
    observables: ``env.step``'s own observations lag the state by one physics substep)."""
    import contextlib
    import gc
    import io

    from nostra.sim.env import import_robosuite

    suite = import_robosuite()
    from robosuite.controllers import load_composite_controller_config
    from robosuite.scripts.collect_human_demonstrations import gather_demonstrations_as_hdf5
    from robosuite.wrappers import DataCollectionWrapper

    out_dir = Path(out_dir)
    raw_dir = out_dir / "raw"
    config = {"env_name": "Lift", "robots": ["Panda"],
              "controller_configs": load_composite_controller_config(controller="BASIC", robot="Panda")}
    env = suite.make(**config, has_renderer=False, has_offscreen_renderer=False, ignore_done=True,
                     use_camera_obs=False, reward_shaping=True, control_freq=20)
    env._check_success = lambda: True
    env = DataCollectionWrapper(env, str(raw_dir))
    rng = np.random.default_rng(seed)
    seen = []
    with contextlib.redirect_stdout(io.StringIO()):  # the wrapper and the script print per episode
        for _ in range(episodes):
            env.reset()
            ep = {k: [] for k in ("states", *LOWDIM_OBS)}
            for _ in range(steps):
                action = np.concatenate([rng.uniform(-0.3, 0.3, 6), [rng.choice([-1.0, 1.0])]])
                env.step(action)
                ep["states"].append(env.env.sim.get_state().flatten())
                env.env.sim.forward()
                obs = env.env._get_observations(force_update=True)
                for k in LOWDIM_OBS:
                    ep[k].append(np.asarray(obs[k]))
            seen.append({k: np.stack(v) for k, v in ep.items()})
        env.close()
        gather_demonstrations_as_hdf5(str(raw_dir), str(out_dir), json.dumps(config))
    gc.collect()  # the script rebinds its h5py file's name; collecting closes the file
    return out_dir / "demo.hdf5", seen
