"""Format readers: robomimic HDF5 (ours and others'), LeRobot v3 (video and image frames, key maps)
and diffusion_policy zarr ReplayBuffers (format 2 and 3, directory and zip)."""

import h5py
import numpy as np
import pandas as pd
import pytest

from nostra.data import DataError, Store, detect
import fixtures as F

LENGTHS = [12, 7, 9]


@pytest.fixture
def ref():
    return F.make_episodes(3, LENGTHS, image_size=16)


def test_detect(tmp_path):
    assert detect(F.write_robomimic(tmp_path / "a.hdf5", lengths=[4], image_size=8)) == "robomimic"
    assert detect(F.write_lerobot(tmp_path / "lr", n=1, image_size=8, video=False)) == "lerobot"
    assert detect(F.write_dp_zarr(tmp_path / "dp.zarr", n=1, image_size=8)) == "dp_zarr"
    assert detect(F.write_dp_zarr(tmp_path / "dp.zarr.zip", n=1, image_size=8)) == "dp_zarr"


def test_robomimic_without_images_and_with_extra_keys(tmp_path, ref):
    """Someone else's file: lowdim only, an extra obs key, extra datasets, no metadata attrs, no masks."""
    path = tmp_path / "theirs.hdf5"
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = '{"env_name": "PickPlaceCan", "type": 1, "env_kwargs": {}}'
        for i, ep in enumerate(ref[:2]):
            g = data.create_group(f"demo_{i}")
            g["actions"] = ep.actions.astype(np.float64)
            g["obs/robot0_eef_pos"] = ep.obs["robot0_eef_pos"].astype(np.float64)
            g["obs/robot0_joint_pos"] = np.zeros((len(ep), 7))
            g["datagen_info/eef_pose"] = np.zeros((len(ep), 4, 4))  # MimicGen-style extra group: ignored
        data["demo_1"].attrs["objects"] = np.array([b"can", b"bin"])  # a list attribute, not JSON
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(path, progress=False)
    assert s.keys(name) == ["actions", "robot0_eef_pos", "robot0_joint_pos"]
    np.testing.assert_array_equal(s.episode(name, 1)["robot0_eef_pos"], ref[1].obs["robot0_eef_pos"])
    assert s.array(name, "actions").dtype == np.float64  # the source's dtype is kept
    f32 = s.ingest(path, name="as_f32", float32=True, progress=False)  # unless asked for float32
    assert s.array(f32, "actions").dtype == np.float32 and s.array(f32, "robot0_eef_pos").dtype == np.float32
    s.remove(f32)
    row = s.episodes(name).iloc[0]
    assert row["task"] == "PickPlaceCan"  # from env_args when the demo has no task attribute
    assert row["objects"] == [] and row["camera_pose"] == {} and row["masks"] == []
    assert pd.isna(row["success"]) and pd.isna(row["seed"])
    assert s.episodes(name).iloc[1]["objects"] == ["can", "bin"]
    # picking keys: one that is missing is named
    with pytest.raises(DataError, match="obs/agentview_image"):
        s.ingest(path, name="picked", keys=["agentview_image"], progress=False)
    assert s.keys(s.ingest(path, name="picked", keys=["robot0_eef_pos"], progress=False)) == ["actions", "robot0_eef_pos"]


@pytest.mark.parametrize("video", [True, False])
def test_lerobot_v3(tmp_path, ref, video):
    root = F.write_lerobot(tmp_path / "lr", n=3, lengths=LENGTHS, image_size=16, video=video)
    assert (root / "meta/episodes/chunk-000/file-000.parquet").exists()
    assert (root / "videos/observation.images.agentview/chunk-000/file-000.mp4").exists() == video
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(root, key_map=F.LEROBOT_KEY_MAP, defaults={"task": "Lift"}, progress=False)
    assert sorted(s.keys(name)) == sorted(["actions", *F.RGB_KEYS, *F.LOWDIM])
    np.testing.assert_array_equal(s.episode_ends(name), np.cumsum(LENGTHS))
    for i, ep in enumerate(ref):
        got = s.episode(name, i)
        np.testing.assert_array_equal(got["actions"], ep.actions)
        for k in F.LOWDIM:  # sliced out of observation.state
            np.testing.assert_array_equal(got[k], ep.obs[k])
        for k in F.RGB_KEYS:
            err = np.abs(got[k].astype(float) - ep.obs[k]).mean()
            assert err < (4.0 if video else 1e-9), (k, err)  # mp4 is lossy, png is not
    row = s.episodes(name).iloc[2]
    assert row["language"] == "lift the red cube" and row["task"] == "Lift" and row["demo_id"] == "episode_2"
    assert row["source_format"] == "lerobot"


def test_lerobot_default_key_names(tmp_path):
    root = F.write_lerobot(tmp_path / "lr", n=2, image_size=8, video=False)
    s = Store(tmp_path / "store.zarr")
    assert s.keys(s.ingest(root, progress=False)) == ["actions", "agentview_image", "robot0_eye_in_hand_image", "state"]
    with pytest.raises(DataError, match="observation.stat'.*no such feature"):
        s.ingest(root, name="x", key_map={"actions": "action", "s": "observation.stat[0:3]"}, progress=False)


@pytest.mark.parametrize("name,fmt", [("dp.zarr", 2), ("dp3.zarr", 3), ("dp.zarr.zip", 2)])
def test_dp_zarr(tmp_path, ref, name, fmt):
    from nostra.data.formats import dp_zarr
    keys = (F.RGB_KEYS[0], *F.LOWDIM)
    eps = F.make_episodes(3, LENGTHS, image_size=16, keys=keys)
    path = dp_zarr.write(tmp_path / name, eps, zarr_format=fmt, key_map={"agentview_image": "img"})
    s = Store(tmp_path / "store.zarr")
    coll = s.ingest(path, progress=False)
    assert coll == name.split(".")[0]
    assert s.keys(coll) == sorted(["actions", "agentview_image", *F.LOWDIM])  # img -> agentview_image
    for i, ep in enumerate(eps):
        got = s.episode(coll, i)
        np.testing.assert_array_equal(got["agentview_image"], ep.obs["agentview_image"])
        np.testing.assert_array_equal(got["actions"], ep.actions)
    assert s.episodes(coll)["task"].tolist() == ["", "", ""]


def test_dp_zarr_float_images_and_key_map(tmp_path):
    """diffusion_policy's push-T keeps images as float32 0..255 and the agent position in 'state'."""
    import zarr
    eps = F.make_episodes(2, [5, 6], image_size=8, keys=(F.RGB_KEYS[0], "robot0_eef_pos"))
    path = tmp_path / "pusht.zarr"
    g = zarr.open_group(path, mode="w", zarr_format=2)
    g["data/img"] = np.concatenate([e.obs["agentview_image"] for e in eps]).astype(np.float32)
    g["data/state"] = np.concatenate([e.obs["robot0_eef_pos"] for e in eps])
    g["data/action"] = np.concatenate([e.actions for e in eps])
    g["meta/episode_ends"] = np.array([5, 11])
    s = Store(tmp_path / "store.zarr")
    coll = s.ingest(path, key_map={"actions": "action", "agentview_image": "img", "agent_pos": "state[0:2]"},
                    defaults={"task": "PushT"}, progress=False)
    assert s.array(coll, "agentview_image").dtype == np.uint8
    np.testing.assert_array_equal(s.episode(coll, 1)["agent_pos"], eps[1].obs["robot0_eef_pos"][:, :2])
    assert s.episodes(coll)["task"].tolist() == ["PushT", "PushT"]


def test_keys_select_and_name_what_is_missing(tmp_path):
    """``keys`` keeps only the asked keys (and actions); a key no array or feature maps to is named,
    with the keys that do map, and the store is left without the collection."""
    from nostra.data.formats import dp_zarr
    eps = F.make_episodes(2, [5, 6], image_size=8, keys=(F.RGB_KEYS[0], *F.LOWDIM))
    zpath = dp_zarr.write(tmp_path / "dp.zarr", eps, zarr_format=2)
    lpath = F.write_lerobot(tmp_path / "lr", n=2, image_size=8, video=False)
    s = Store(tmp_path / "store.zarr")
    lowdim = next(iter(F.LOWDIM))
    coll = s.ingest(zpath, keys=[lowdim], progress=False)
    assert s.keys(coll) == sorted(["actions", lowdim])
    for path, what in [(zpath, "array"), (lpath, "feature")]:
        with pytest.raises(DataError, match=rf"no {what} maps to \['gripper_cam'\]; mapped keys: \[.*'actions'"):
            s.ingest(path, name=f"x-{what}", keys=["gripper_cam"], progress=False)
    assert s.collections() == [coll]
