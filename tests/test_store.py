"""The zarr store: layout, metadata table, statistics, atomic and idempotent ingest, export round trip."""

import json
import os
import signal
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
import zarr

from nostra.data import CollectionError, DataError, Store
import fixtures as F
from nostra.data import store as store_mod


@pytest.fixture
def lift(tmp_path):
    return F.write_robomimic(tmp_path / "lift.hdf5", lengths=[18, 7, 12], image_size=16)


def listing(path):
    return sorted(str(p.relative_to(path.parent)) for p in path.parent.rglob("*") if "store" in str(p))


def test_ingest_layout_and_arrays(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    assert s.ingest(lift, progress=False) == "lift"
    assert s.collections() == ["lift"]
    ref = F.make_episodes(3, [18, 7, 12], image_size=16)
    np.testing.assert_array_equal(s.episode_ends("lift"), [18, 25, 37])
    for i, ep in enumerate(ref):
        got = s.episode("lift", i)
        for k, v in {**ep.obs, "actions": ep.actions, **ep.extras}.items():
            np.testing.assert_array_equal(got[k], v, err_msg=k)
    img = s.array("lift", "agentview_image")
    assert img.dtype == np.uint8 and img.shape == (37, 16, 16, 3)
    assert img.chunks == (store_mod.chunk_len((16, 16, 3), np.uint8), 16, 16, 3)  # time-chunked
    assert store_mod.chunk_len((84, 84, 3), np.uint8) == 16 and store_mod.chunk_len((7,), np.float32) == 8192
    codec = img.metadata.codecs[-1]
    assert type(codec).__name__ == "BloscCodec" and codec.cname.value == "zstd"
    g = zarr.open_group(tmp_path / "store.zarr" / "lift", mode="r")  # diffusion_policy layout
    assert "episode_ends" in g["meta"] and "actions" in g["data"]


def test_episode_table_has_the_metadata_contract(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    df = s.episodes("lift")
    assert list(df["demo_id"]) == ["demo_0", "demo_1", "demo_2"]
    assert list(df["length"]) == [18, 7, 12] and list(df["start"]) == [0, 18, 25]
    row = df.iloc[1]
    assert row["task"] == "Lift" and row["skill"] == "pick" and row["language"] == "lift the red cube"
    assert row["objects"] == ["cube"] and row["camera_pose"]["agentview"]["pos"] == [0.51, 0.0, 1.35]
    assert set(row["object_placements"]) == {"cube"} and row["variation"] == {"cube_size": 0.021}
    assert bool(row["success"]) is False and row["seed"] == 101
    assert row["source"] == str(lift) and row["source_format"] == "robomimic"
    assert list(df["masks"]) == [["valid"], ["train"], ["train"]]


def test_stats_per_collection_and_combined(tmp_path, lift):
    other = F.write_robomimic(tmp_path / "other.hdf5", lengths=[9, 30], seed=5, image_size=16)
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    s.ingest(other, progress=False)
    a, b = (np.concatenate([s.array(n, "robot0_eef_pos")[:] for n in names]) for names in (["lift"], ["lift", "other"]))
    one = s.stats(["lift"])["robot0_eef_pos"]
    both = s.stats(["lift", "other"])["robot0_eef_pos"]
    for st, x in ((one, a), (both, b)):
        np.testing.assert_allclose(st["mean"], x.mean(0), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(st["std"], x.std(0), rtol=1e-5, atol=1e-7)
        np.testing.assert_array_equal(st["min"], x.min(0))
        np.testing.assert_array_equal(st["max"], x.max(0))
    assert set(s.stats("lift")) == {"actions", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}
    with pytest.raises(CollectionError, match="agentview_image"):
        s.stats(["lift"], ["agentview_image"])


def test_second_ingest_is_a_noop(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "store.zarr").rglob("*")}
    assert s.ingest(lift, name="again", progress=False) == "lift"  # same content hash, under any name
    assert s.collections() == ["lift"]
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "store.zarr").rglob("*")} == before


def test_name_clash_with_other_content_is_refused(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    other = F.write_robomimic(tmp_path / "x" / "lift.hdf5", lengths=[5], seed=9, image_size=16)
    with pytest.raises(DataError, match="'lift' already exists"):
        s.ingest(other, progress=False)
    with pytest.raises(DataError, match="invalid"):
        s.ingest(other, name="bad name!", progress=False)


@pytest.mark.parametrize("exc", [RuntimeError("disk on fire"), KeyboardInterrupt()])
def test_failure_mid_ingest_leaves_store_as_it_was(tmp_path, lift, monkeypatch, exc):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    other = F.write_robomimic(tmp_path / "other.hdf5", lengths=[9, 9, 9], seed=3, image_size=16)
    before = listing(tmp_path / "store.zarr")
    real, calls = store_mod.check_episode, []

    def failing(ep, file, shapes):
        calls.append(ep.demo_id)
        if len(calls) == 3:  # two episodes were written into the temporary group
            raise exc
        return real(ep, file, shapes)

    monkeypatch.setattr(store_mod, "check_episode", failing)
    with pytest.raises(type(exc)):
        s.ingest(other, progress=False)
    assert len(calls) == 3
    assert listing(tmp_path / "store.zarr") == before and s.collections() == ["lift"]


KILLED = textwrap.dedent("""
    import sys, time
    from nostra.data import Store, store as m
    real = m.check_episode
    def slow(ep, file, shapes):
        if ep.demo_id == "demo_2":
            print("HALFWAY", flush=True)
            time.sleep(60)
        return real(ep, file, shapes)
    m.check_episode = slow
    Store(sys.argv[1]).ingest(sys.argv[2], progress=False)
""")


def test_kill_mid_ingest_leaves_store_as_it_was(tmp_path, lift):
    store = tmp_path / "store.zarr"
    Store(store).ingest(lift, progress=False)
    other = F.write_robomimic(tmp_path / "other.hdf5", lengths=[9, 9, 9, 9], seed=3, image_size=16)
    proc = subprocess.Popen([sys.executable, "-c", KILLED, str(store), str(other)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "HALFWAY"
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    stale = list(tmp_path.glob(".store.zarr.ingest-*"))
    assert len(stale) == 1  # the killed ingest's temporary group, outside the store
    assert Store(store).collections() == ["lift"]
    assert Store(store).ingest(other, progress=False) == "other"
    assert not list(tmp_path.glob(".store.zarr.ingest-*"))  # cleaned up by the next ingest
    assert len(Store(store).episodes("other")) == 4


def test_remove(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    s.remove("lift")
    assert s.collections() == []
    with pytest.raises(CollectionError, match="no collection 'lift'"):
        s.remove("lift")


def test_export_then_ingest_round_trips(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    out = s.export("lift", tmp_path / "out" / "lift_export.hdf5", progress=False)
    with h5py.File(out, "r") as f:  # the layout peers' robomimic tools read
        assert f["data"].attrs["total"] == 37
        assert json.loads(f["data"].attrs["env_args"])["env_name"] == "Lift"
        d = f["data/demo_1"]
        assert d.attrs["num_samples"] == 7 and d.attrs["model_file"] == "<mujoco model='lift'/>"
        assert json.loads(d.attrs["objects"]) == ["cube"]
        np.testing.assert_array_equal(d["next_obs/robot0_eef_pos"][:-1], d["obs/robot0_eef_pos"][1:])
        assert [x.decode() for x in f["mask/valid"][:]] == ["demo_0"]
    assert s.ingest(out, progress=False) == "lift_export"
    for k in s.keys("lift"):
        a, b = s.array("lift", k), s.array("lift_export", k)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a[:], b[:], err_msg=k)
    drop = ["collection", "source"]
    assert s.episodes("lift").drop(columns=drop).equals(s.episodes("lift_export").drop(columns=drop))
    assert s.info("lift_export")["env_args"] == s.info("lift")["env_args"]


def test_unknown_collection_and_key_errors_list_choices(tmp_path, lift):
    s = Store(tmp_path / "store.zarr")
    s.ingest(lift, progress=False)
    with pytest.raises(CollectionError, match=r"no collection 'nope'; it has \['lift'\]"):
        s.episodes("nope")
    with pytest.raises(CollectionError, match="no key 'robot0_joint_pos'.*agentview_image"):
        s.array("lift", "robot0_joint_pos")
