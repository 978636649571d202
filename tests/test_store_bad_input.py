"""Bad input fails with an error naming the file, demo and key, and the store is left untouched.
One test per case."""

import json

import h5py
import numpy as np
import pytest

from nostra.data import DataError, Store
import fixtures as F


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "store.zarr")
    s.ingest(F.write_robomimic(tmp_path / "good.hdf5", lengths=[6, 6], image_size=8), progress=False)
    return s


def snapshot(s: Store):
    root = s.path.parent
    return sorted((str(p.relative_to(root)), p.stat().st_size) for p in root.rglob("*")
                  if p.name.startswith(".store") or "store.zarr" in str(p))


def bad_file(tmp_path, edit, lengths=(6, 6, 6)):
    path = F.write_robomimic(tmp_path / "bad.hdf5", lengths=list(lengths), seed=1, image_size=8)
    with h5py.File(path, "a") as f:
        edit(f)
    return path


def replace(f, name, data):
    del f[name]
    f[name] = data


def fails(store, path, *parts, **kw):
    before = snapshot(store)
    with pytest.raises(DataError) as e:
        store.ingest(path, progress=False, **kw)
    msg = str(e.value)
    for p in (str(path), *parts):
        assert p in msg, (p, msg)
    assert snapshot(store) == before and store.collections() == ["good"]
    return msg


def test_truncated_file(tmp_path, store):
    path = F.write_robomimic(tmp_path / "bad.hdf5", lengths=[6, 6], seed=1, image_size=8)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    fails(store, path, "truncated")


def test_missing_actions(tmp_path, store):
    fails(store, bad_file(tmp_path, lambda f: f.__delitem__("data/demo_1/actions")), "demo_1", "'actions'", "missing")


def test_lengths_disagree(tmp_path, store):
    edit = lambda f: replace(f, "data/demo_2/obs/robot0_eef_pos", np.zeros((5, 3), np.float32))
    fails(store, bad_file(tmp_path, edit), "demo_2", "'robot0_eef_pos'", "5 steps but actions has 6")


def test_nan(tmp_path, store):
    def edit(f):
        a = f["data/demo_1/actions"][:]
        a[3, 2] = np.nan
        replace(f, "data/demo_1/actions", a)
    fails(store, bad_file(tmp_path, edit), "demo_1", "'actions'", "NaN or Inf (first at step 3)")


def test_inf(tmp_path, store):
    def edit(f):
        a = f["data/demo_0/obs/agentview_depth"][:]
        a[4, 0, 0, 0] = np.inf
        replace(f, "data/demo_0/obs/agentview_depth", a)
    fails(store, bad_file(tmp_path, edit), "demo_0", "'agentview_depth'", "NaN or Inf")


def test_wrong_dtype_image(tmp_path, store):
    edit = lambda f: replace(f, "data/demo_1/obs/agentview_image", f["data/demo_1/obs/agentview_image"][:].astype(np.float32))
    fails(store, bad_file(tmp_path, edit), "demo_1", "'agentview_image'", "must be uint8")


def test_wrong_dtype_strings(tmp_path, store):
    edit = lambda f: replace(f, "data/demo_0/obs/robot0_eef_pos", np.array([b"x"] * 6))
    fails(store, bad_file(tmp_path, edit), "demo_0", "'robot0_eef_pos'", "not numeric")


def test_wrong_shape_channels_first(tmp_path, store):
    edit = lambda f: replace(f, "data/demo_0/obs/robot0_eye_in_hand_image", np.zeros((6, 3, 8, 8), np.uint8))
    fails(store, bad_file(tmp_path, edit), "demo_0", "'robot0_eye_in_hand_image'", "(steps, H, W, 3)")


def test_shape_differs_between_demos(tmp_path, store):
    edit = lambda f: replace(f, "data/demo_2/obs/robot0_eef_quat", np.zeros((6, 3), np.float32))
    fails(store, bad_file(tmp_path, edit), "demo_2", "'robot0_eef_quat'", "differs from (4,)")


def test_key_missing_in_a_later_demo(tmp_path, store):
    fails(store, bad_file(tmp_path, lambda f: f.__delitem__("data/demo_2/obs/agentview_depth")),
          "demo_2", "'agentview_depth'", "present in earlier demos")


def test_empty_episode(tmp_path, store):
    def edit(f):
        for k in list(f["data/demo_1/obs"]):
            replace(f, f"data/demo_1/obs/{k}", f[f"data/demo_1/obs/{k}"][:0])
        for k in ("actions", "states", "rewards", "dones"):
            replace(f, f"data/demo_1/{k}", f[f"data/demo_1/{k}"][:0])
    fails(store, bad_file(tmp_path, edit), "demo_1", "empty episode")


def test_bad_metadata_json(tmp_path, store):
    fails(store, bad_file(tmp_path, lambda f: f["data/demo_1"].attrs.__setitem__("camera_pose", "{not json")),
          "demo_1", "'camera_pose'", "not valid JSON")


def test_not_robomimic_layout(tmp_path, store):
    path = tmp_path / "bad.hdf5"
    with h5py.File(path, "w") as f:
        f["foo"] = np.zeros(3)
    fails(store, path, "no 'data' group")


def test_unknown_format(tmp_path, store):
    path = tmp_path / "bad.csv"
    path.write_text("a,b\n1,2\n")
    msg = fails(store, path, "unknown format")
    assert "robomimic" in msg and "lerobot" in msg and "dp_zarr" in msg
    fails(store, path, "unknown format 'hdf6'", "valid: auto, robomimic, lerobot, dp_zarr", fmt="hdf6")


def test_missing_source(tmp_path, store):
    fails(store, tmp_path / "nope.hdf5", "no such file")


def test_lerobot_old_version(tmp_path, store):
    root = F.write_lerobot(tmp_path / "bad_lr", n=1, image_size=8, video=False)
    info = json.loads((root / "meta/info.json").read_text())
    (root / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v1.6"}))
    fails(store, root, "'codebase_version'", "v1.6", "valid: v2.0, v2.1, v3")


def test_lerobot_corrupt_parquet(tmp_path, store):
    root = F.write_lerobot(tmp_path / "bad_lr", n=2, image_size=8, video=False)
    data = root / "data/chunk-000/file-000.parquet"
    data.write_bytes(data.read_bytes()[:100])
    before = snapshot(store)
    with pytest.raises(DataError, match="file-000.parquet: cannot be read as parquet"):
        store.ingest(root, progress=False)
    assert snapshot(store) == before


def test_dp_zarr_bad_episode_ends(tmp_path, store):
    import zarr
    path = F.write_dp_zarr(tmp_path / "bad.zarr", n=2, image_size=8)
    g = zarr.open_group(path, mode="a")
    g["meta/episode_ends"][:] = [5, 3]
    fails(store, path, "'meta/episode_ends'", "increase strictly")


def test_demo_is_a_dataset(tmp_path, store):
    fails(store, bad_file(tmp_path, lambda f: f["data"].create_dataset("demo_9", data=np.zeros(3))),
          "demo_9", "'data/demo_9'", "expected a demo group")


def test_seed_not_an_integer(tmp_path, store):
    fails(store, bad_file(tmp_path, lambda f: f["data/demo_1"].attrs.__setitem__("seed", "abc")),
          "demo_1", "'seed'", "not an integer")


def test_lerobot_tasks_without_strings(tmp_path, store):
    import pandas as pd
    root = F.write_lerobot(tmp_path / "bad_lr", n=1, image_size=8, video=False)
    pd.DataFrame({"task_index": [0]}).to_parquet(root / "meta/tasks.parquet", index=False)
    fails(store, root, "tasks.parquet", "'task'", "needs task strings")


def test_lerobot_episodes_without_episode_index(tmp_path, store):
    import pyarrow.parquet as pq
    root = F.write_lerobot(tmp_path / "bad_lr", n=2, image_size=8, video=False)
    p = root / "meta/episodes/chunk-000/file-000.parquet"
    pq.write_table(pq.read_table(p).drop_columns(["episode_index"]), p)
    fails(store, root, "meta/episodes", "'episode_index'", "row 0 has no integer episode_index")


def test_lerobot_feature_without_data_column(tmp_path, store):
    import pyarrow.parquet as pq
    root = F.write_lerobot(tmp_path / "bad_lr", n=2, image_size=8, video=False)
    p = root / "data/chunk-000/file-000.parquet"
    pq.write_table(pq.read_table(p).drop_columns(["action"]), p)
    fails(store, root, "file-000.parquet", "episode_0", "'action'", "has no data column")


def test_lerobot_missing_video(tmp_path, store):
    root = F.write_lerobot(tmp_path / "bad_lr", n=2, image_size=8, video=True)
    (root / "videos/observation.images.agentview/chunk-000/file-000.mp4").unlink()
    fails(store, root, "episode_0", "'observation.images.agentview'", "cannot decode video")
