"""Files as other tools write them (tests/fixtures_external.py says which tool and version each
mimics): LeRobot v3.0 task layouts and shared mp4s, LeRobot v2.1, round trips."""

import numpy as np
import pytest

from nostra.data import DataError, Store
import fixtures as F
import fixtures_external as X

LENGTHS = [12, 7, 9]
VIDEO_TOL = 4.0  # mean absolute error (0..255) of AV1 (crf 30) frames against the originals


@pytest.fixture(scope="module")
def eps():
    out = F.make_episodes(3, LENGTHS, image_size=16, keys=(*F.RGB_KEYS, *F.LOWDIM))
    out[1].meta["language"] = "push the red cube"  # two tasks: index 0 and 1
    return out


def check_lerobot_collection(s, name, eps):
    np.testing.assert_array_equal(s.episode_ends(name), np.cumsum(LENGTHS))
    for i, ep in enumerate(eps):
        got = s.episode(name, i)
        np.testing.assert_array_equal(got["actions"], ep.actions)
        for k in F.LOWDIM:
            np.testing.assert_array_equal(got[k], ep.obs[k])
        for k in F.RGB_KEYS:  # each episode's own frames out of the shared file
            err = np.abs(got[k].astype(float) - ep.obs[k]).mean()
            assert err < VIDEO_TOL, (i, k, err)
    assert s.episodes(name)["language"].tolist() == [e.meta["language"] for e in eps]


@pytest.mark.parametrize("layout", X.TASK_LAYOUTS)
def test_lerobot_v30_task_layouts_and_shared_mp4(tmp_path, eps, layout):
    root = X.write_lerobot_v30(tmp_path / "lr", eps, state_keys=list(F.LOWDIM), task_layout=layout)
    assert sorted(p.name for p in (root / "videos/observation.images.agentview").rglob("*.mp4")) == ["file-000.mp4"]
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(root, key_map=F.LEROBOT_KEY_MAP, progress=False)
    check_lerobot_collection(s, name, eps)


def test_lerobot_v30_task_index_missing_from_tasks(tmp_path, eps):
    import pandas as pd
    root = X.write_lerobot_v30(tmp_path / "lr", eps, state_keys=list(F.LOWDIM), task_layout="frames_only")
    pd.DataFrame({"task_index": [0]}, index=["lift the red cube"]).to_parquet(root / "meta/tasks.parquet")
    with pytest.raises(DataError, match=r"tasks.parquet: episode_1: key 'task_index': has no task_index 1"):
        Store(tmp_path / "store.zarr").ingest(root, key_map=F.LEROBOT_KEY_MAP, progress=False)


def theirs_robomimic(path, eps, next_obs=True, empty_valid=True):
    """A robomimic file as robomimic's dataset_states_to_obs writes it: float64 lowdim obs and
    actions, next_obs whose last step is the observation after the last action (not a repeat),
    and masks where ``mask/valid`` may be empty."""
    import h5py
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = '{"env_name": "Lift", "type": 1, "env_kwargs": {"control_freq": 20}}'
        total = 0
        for i, ep in enumerate(eps):
            g = data.create_group(f"demo_{i}")
            g.attrs["num_samples"] = len(ep)
            g["actions"] = ep.actions.astype(np.float64)
            g["states"], g["rewards"], g["dones"] = ep.extras["states"], ep.extras["rewards"], ep.extras["dones"]
            for k, v in ep.obs.items():
                v = v.astype(np.float64) if v.dtype == np.float32 and v.ndim == 2 else v
                g[f"obs/{k}"] = v
                if next_obs:
                    after = v[-1:] + (1 if v.dtype != np.uint8 else 0)  # the observation after the last action
                    g[f"next_obs/{k}"] = np.concatenate([v[1:], after.astype(v.dtype)])
            total += len(ep)
        data.attrs["total"] = total
        f["mask/train"] = np.array([f"demo_{i}" for i in range(len(eps))], dtype="S")
        f["mask/valid"] = np.zeros(0, "S1") if empty_valid else np.array([b"demo_0"])
    return path


def h5_tree(path):
    import h5py
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda k, v: out.__setitem__(k, v[()]) if hasattr(v, "shape") else None)
    return out


def test_robomimic_round_trip_keeps_dtypes_next_obs_and_empty_masks(tmp_path):
    eps = F.make_episodes(2, [6, 5], image_size=8)
    src = theirs_robomimic(tmp_path / "theirs.hdf5", eps)
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(src, progress=False)
    assert s.array(name, "actions").dtype == np.float64 and s.array(name, "robot0_eef_pos").dtype == np.float64
    assert s.info(name)["masks"] == ["train", "valid"] and s.info(name)["next_obs"] == "source"
    out = s.export(name, tmp_path / "back.hdf5", progress=False)
    a, b = h5_tree(src), h5_tree(out)
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    import h5py
    with h5py.File(out, "r") as f:
        assert not f["data"].attrs["next_obs_derived"] and "next_obs_note" not in f["data"].attrs
        assert f["mask/valid"].shape == (0,)


def test_export_says_next_obs_was_derived(tmp_path):
    import h5py
    src = theirs_robomimic(tmp_path / "no_next.hdf5", F.make_episodes(2, [6, 5], image_size=8), next_obs=False)
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(src, progress=False)
    assert s.info(name)["next_obs"] == "none"
    with h5py.File(s.export(name, tmp_path / "back.hdf5", progress=False), "r") as f:
        assert f["data"].attrs["next_obs_derived"] and "derived" in f["data"].attrs["next_obs_note"]
        np.testing.assert_array_equal(f["data/demo_0/next_obs/robot0_eef_pos"][-1], f["data/demo_0/obs/robot0_eef_pos"][-1])


def test_next_obs_that_is_not_a_shift_is_refused_with_the_way_out(tmp_path):
    import h5py
    src = theirs_robomimic(tmp_path / "odd.hdf5", F.make_episodes(1, [6], image_size=8))
    with h5py.File(src, "a") as f:
        f["data/demo_0/next_obs/robot0_eef_pos"][2] += 1
    s = Store(tmp_path / "store.zarr")
    with pytest.raises(DataError, match=r"demo_0: key 'next_obs/robot0_eef_pos': next_obs is not obs shifted.*"
                                        r"step 2.*ingest.next_obs=false"):
        s.ingest(src, progress=False)
    assert s.info(s.ingest(src, next_obs=False, progress=False))["next_obs"] == "none"


def test_same_content_under_another_name_is_not_ingested_again(tmp_path):
    import shutil
    src = F.write_robomimic(tmp_path / "lift.hdf5", lengths=[5, 4], image_size=8)
    copy = shutil.copy(src, tmp_path / "renamed_copy.hdf5")
    s = Store(tmp_path / "store.zarr")
    assert s.ingest(src, progress=False) == "lift"
    assert s.ingest(copy, progress=False) == "lift" and s.collections() == ["lift"]


def test_loader_gives_float32_batches_from_float64_collections(tmp_path):
    from nostra.data import make_loader
    src = theirs_robomimic(tmp_path / "theirs.hdf5", F.make_episodes(2, [6, 5], image_size=8))
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(src, progress=False)
    loader = make_loader(s, [name], keys=["robot0_eef_pos"], seq_len=4, batch_size=2, num_workers=0)
    batch = next(iter(loader))
    assert batch["actions"].dtype.is_floating_point and str(batch["actions"].dtype) == "torch.float32"
    assert str(batch["obs"]["robot0_eef_pos"].dtype) == "torch.float32"


def test_lerobot_v21(tmp_path, eps):
    root = X.write_lerobot_v21(tmp_path / "lr21", eps, state_keys=list(F.LOWDIM))
    assert (root / "videos/chunk-000/observation.images.agentview/episode_000002.mp4").exists()
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(root, key_map=F.LEROBOT_KEY_MAP, progress=False)
    check_lerobot_collection(s, name, eps)
    assert s.info(name)["source_attrs"]["lerobot_info"]["codebase_version"] == "v2.1"


def test_export_lerobot_v30_layout_and_round_trip(tmp_path):
    """robomimic -> store -> LeRobot v3.0 -> store: lowdim, depth and extras exact with their
    dtypes, video within VIDEO_TOL."""
    import json

    import pandas as pd
    import pyarrow.parquet as pq
    src = F.write_robomimic(tmp_path / "lift.hdf5", lengths=[9, 6], image_size=16)
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(src, progress=False)
    out = s.export(name, tmp_path / "lift_lerobot", format="lerobot", progress=False)
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert files == ["data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet",
                     "meta/info.json", "meta/stats.json", "meta/tasks.parquet",
                     "videos/observation.images.agentview/chunk-000/file-000.mp4",
                     "videos/observation.images.robot0_eye_in_hand/chunk-000/file-000.mp4"]
    info = json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 20 and info["robot_type"] == "panda"
    assert info["features"]["observation.state"]["names"][:4] == ["robot0_eef_pos.0", "robot0_eef_pos.1",
                                                                  "robot0_eef_pos.2", "robot0_eef_quat.0"]
    assert info["features"]["observation.images.agentview"]["info"]["video.codec"] == "av1"
    tasks = pd.read_parquet(out / "meta/tasks.parquet")  # lerobot's load_tasks: the strings are the index
    assert tasks.index.tolist() == ["lift the red cube"] and tasks.columns.tolist() == ["task_index"]
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["videos/observation.images.agentview/from_timestamp"] for e in eps] == [0.0, 9 / 20]
    assert eps[1]["dataset_from_index"] == 9 and eps[0]["tasks"] == ["lift the red cube"]
    stats = json.loads((out / "meta/stats.json").read_text())
    assert np.array(stats["observation.images.agentview"]["mean"]).shape == (3, 1, 1)
    assert stats["action"]["count"] == [15]

    back = s.ingest(out, progress=False)  # no key map: observation.state splits back by its names
    assert s.keys(back) == s.keys(name)
    for k in s.keys(name):
        a, b = s.array(name, k), s.array(back, k)
        assert a.dtype == b.dtype, k
        if k.endswith("_image"):
            assert np.abs(a[:].astype(float) - b[:]).mean() < VIDEO_TOL, k
        else:
            np.testing.assert_array_equal(a[:], b[:], err_msg=k)


def test_lerobot_round_trip_through_the_store(tmp_path, eps):
    """LeRobot v3.0 (as lerobot writes it) -> store -> LeRobot v3.0: the same frames and tasks."""
    import pyarrow.parquet as pq
    src = X.write_lerobot_v30(tmp_path / "theirs", eps, state_keys=list(F.LOWDIM))
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(src, key_map=F.LEROBOT_KEY_MAP, progress=False)
    out = s.export(name, tmp_path / "ours", format="lerobot", progress=False)
    a = pq.read_table(src / "data/chunk-000/file-000.parquet")
    b = pq.read_table(out / "data/chunk-000/file-000.parquet")
    for col in ("action", "observation.state", "timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert a[col].type == b[col].type, col
        assert a[col].to_pylist() == b[col].to_pylist(), col
    again = s.ingest(out, key_map=F.LEROBOT_KEY_MAP, progress=False)
    assert s.episodes(again)["language"].tolist() == [e.meta["language"] for e in eps]
    for k in F.RGB_KEYS:  # encoded twice
        err = np.abs(s.array(again, k)[:].astype(float) - s.array(name, k)[:]).mean()
        assert err < VIDEO_TOL, (k, err)


@pytest.fixture(scope="module")
def raw_demo(tmp_path_factory):
    return X.write_robosuite_raw(tmp_path_factory.mktemp("raw"), episodes=2, steps=12)


def test_robosuite_raw_demo_without_render_is_refused_with_the_way(tmp_path, raw_demo):
    path, _ = raw_demo
    s = Store(tmp_path / "store.zarr")
    with pytest.raises(DataError, match=r"demo.hdf5: key 'obs': robosuite raw demos.*ingest.render=true"):
        s.ingest(path, progress=False)
    assert s.collections() == []


def test_robosuite_raw_demo_rendered(tmp_path, raw_demo, monkeypatch, capsys):
    from pipeline.cli import main
    path, seen = raw_demo
    monkeypatch.chdir(tmp_path)
    assert main(["ingest", f"ingest.sources=[{path}]", "ingest.render=true", "ingest.render_size=32",
                 "ingest.name=raw", "ingest.progress=false", "paths.data=d"]) == 0
    out = capsys.readouterr().out
    assert "raw: 2 episodes, 24 steps" in out
    assert "demo_1: replaying its actions diverges from the recorded states by" in out and "demo_2: " in out
    s = Store(tmp_path / "d/store.zarr")
    assert s.keys("raw") == sorted(["actions", "states", *F.PAPER_KEYS])
    info = s.info("raw")
    assert set(info["source_attrs"]["replay_divergence"]) == {"demo_1", "demo_2"}
    assert info["env_args"]["env_name"] == "Lift"
    row = s.episodes("raw").iloc[0]
    assert row["task"] == "Lift" and row["robots"] == ["Panda"] and row["controller"]["type"] == "BASIC"
    assert row["model_file"].startswith("<mujoco")
    for i in range(2):
        ep = s.episode("raw", i)
        for k in F.RGB_KEYS:
            assert ep[k].shape == (12, 32, 32, 3) and ep[k].dtype == np.uint8
            assert (ep[k].reshape(12, -1).max(1) > 30).all(), f"an all-black {k} frame"
        depth = ep["agentview_depth"]
        assert depth.shape == (12, 32, 32, 1) and 0.1 < depth.min() and depth.max() < 10  # metres
        # the rendered state t+1 is the state reached by action t while collecting
        match = [e for e in seen if np.allclose(e["states"][0], ep["states"][1])]
        assert len(match) == 1
        for k in X.LOWDIM_OBS:
            np.testing.assert_allclose(ep[k][1:], match[0][k][:-1], atol=1e-6, err_msg=k)
