"""Sequence windows over the store: robomimic padding at episode ends, mixtures, episode subsets,
lazy bounded reads and the policies' batch contract."""

import pickle

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import small_net
from nostra.data import CollectionError, SequenceDataset, Store, make_loader, split_episodes
import fixtures as F
from nostra.policies.modules import NostraPolicy

KEYS = list(F.PAPER_KEYS)


@pytest.fixture
def store(tmp_path):
    s = Store(tmp_path / "store.zarr")
    s.ingest(F.write_robomimic(tmp_path / "a.hdf5", lengths=[5, 3, 6], image_size=8), progress=False)
    s.ingest(F.write_robomimic(tmp_path / "b.hdf5", lengths=[4, 9], seed=1, image_size=8), progress=False)
    return s


def expected(store, coll, ep, t0, T, key):
    """robomimic's SequenceDataset(pad_seq_length=True): steps past the end repeat the last one."""
    x = store.episode(coll, ep, [key])[key]
    return x[np.minimum(t0 + np.arange(T), len(x) - 1)]


def test_windows_at_episode_boundaries(store):
    ds = SequenceDataset(store, ["a"], KEYS, seq_len=4)
    assert len(ds) == 5 + 3 + 6  # a window may start at every step
    assert [ds.locate(i) for i in (0, 4, 5, 7, 8, 13)] == [
        ("a", 0, 0), ("a", 0, 4), ("a", 1, 0), ("a", 1, 2), ("a", 2, 0), ("a", 2, 5)]
    actions = store.episode("a", 0, ["actions"])["actions"]
    w = ds[3]  # episode 0 (5 steps), from step 3: steps 3, 4, 4, 4
    np.testing.assert_array_equal(w["actions"].numpy(), actions[[3, 4, 4, 4]])
    assert w["pad_mask"].tolist() == [True, True, False, False]
    w = ds[7]  # episode 1 (3 steps), from its last step: all four are step 2
    assert w["pad_mask"].tolist() == [True, False, False, False]
    np.testing.assert_array_equal(w["obs"]["agentview_image"].numpy(), expected(store, "a", 1, 2, 4, "agentview_image"))
    for i in range(len(ds)):
        c, e, t0 = ds.locate(i)
        w = ds[i]
        for k in KEYS:
            np.testing.assert_array_equal(w["obs"][k].numpy(), expected(store, c, e, t0, 4, k), err_msg=f"{i} {k}")
        np.testing.assert_array_equal(w["actions"].numpy(), expected(store, c, e, t0, 4, "actions"))


def test_windows_without_padding(store):
    ds = SequenceDataset(store, ["a"], ["robot0_eef_pos"], seq_len=4, pad=False)
    assert [ds.locate(i) for i in range(len(ds))] == [("a", 0, 0), ("a", 0, 1), ("a", 2, 0), ("a", 2, 1), ("a", 2, 2)]
    assert all(ds[i]["pad_mask"].all() for i in range(len(ds)))
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_many_collections_and_an_episode_subset(store):
    ds = SequenceDataset(store, ["a", "b"], ["robot0_eef_pos"], seq_len=2)
    assert len(ds) == 5 + 3 + 6 + 4 + 9 and ds.locate(14) == ("b", 0, 0)
    sub = SequenceDataset(store, None, ["robot0_eef_pos"], seq_len=2, episodes=[("b", 1), ("a", 2)])
    assert sub.collections == ["b", "a"] and len(sub) == 9 + 6
    assert {sub.locate(i)[:2] for i in range(len(sub))} == {("b", 1), ("a", 2)}
    manifest = pd.DataFrame({"collection": ["a"], "episode": [1], "weight": [1.0]})
    assert len(SequenceDataset(store, None, ["robot0_eef_pos"], episodes=manifest)) == 3
    with pytest.raises(CollectionError, match="episodes 0..1, not 7"):
        SequenceDataset(store, ["b"], ["robot0_eef_pos"], episodes=[("b", 7)])
    with pytest.raises(CollectionError, match=r"\['b'\], which are not among"):
        SequenceDataset(store, ["a"], ["robot0_eef_pos"], episodes=[("b", 0)])


def test_mixture_weights(store):
    loader = make_loader(store, {"a": 3.0, "b": 1.0}, ["robot0_eef_pos"], seq_len=2, batch_size=50,
                         num_workers=0, num_samples=4000)
    ds = loader.dataset
    idx = torch.tensor(list(loader.sampler))
    from_a = ((idx >= ds.ranges["a"][0]) & (idx < ds.ranges["a"][1])).float().mean().item()
    assert abs(from_a - 0.75) < 0.03  # a has fewer windows (14 vs 13+) but three times the weight
    assert idx.min() >= 0 and idx.max() < len(ds)
    b = idx[idx >= ds.ranges["b"][0]] - ds.ranges["b"][0]
    assert len(torch.unique(b)) == ds.ranges["b"][1] - ds.ranges["b"][0]  # every window of b is drawn
    with pytest.raises(CollectionError, match="weights given for"):
        make_loader(store, ["a"], ["robot0_eef_pos"], weights={"c": 1.0}, num_workers=0)


def test_missing_image_key_names_the_key_and_the_collection(tmp_path, store):
    store.ingest(F.write_dp_zarr(tmp_path / "nodepth.zarr", n=2, image_size=8), progress=False)
    with pytest.raises(CollectionError, match="collection 'nodepth' has no key 'robot0_eye_in_hand_image' "
                                              r"\(missing \['robot0_eye_in_hand_image', 'agentview_depth'\]"):
        SequenceDataset(store, ["a", "nodepth"], KEYS)


def test_shapes_must_agree_across_collections(tmp_path, store):
    store.ingest(F.write_robomimic(tmp_path / "big.hdf5", lengths=[4], image_size=16), progress=False)
    with pytest.raises(CollectionError, match="'agentview_image' has per-step shape .16, 16, 3. in collection 'big'"):
        SequenceDataset(store, ["a", "big"], ["agentview_image"])


def test_loader_yields_the_policy_batch_contract(store):
    loader = make_loader(store, ["a", "b"], KEYS, seq_len=4, batch_size=6, num_workers=2, shuffle=False)
    ds = loader.dataset
    batches = list(loader)
    assert sum(len(b["actions"]) for b in batches) == len(ds)
    b = batches[1]
    assert set(b) == {"obs", "actions", "pad_mask"} and list(b["obs"]) == KEYS
    assert b["obs"]["agentview_image"].dtype == torch.uint8 and b["obs"]["agentview_image"].shape == (6, 4, 8, 8, 3)
    assert b["obs"]["agentview_depth"].dtype == torch.float32 and b["obs"]["agentview_depth"].shape == (6, 4, 8, 8, 1)
    assert b["obs"]["robot0_eef_quat"].shape == (6, 4, 4) and b["actions"].shape == (6, 4, 7)
    for j in range(6):  # raw values, window by window (sequential sampler: batch 1 holds windows 6..11)
        c, e, t0 = ds.locate(6 + j)
        np.testing.assert_array_equal(b["obs"]["agentview_depth"][j].numpy(), expected(store, c, e, t0, 4, "agentview_depth"))
        np.testing.assert_array_equal(b["actions"][j].numpy(), expected(store, c, e, t0, 4, "actions"))
    assert [m.name for m in ds.modalities()] == KEYS and ds.action_dim == 7
    assert set(ds.stats()) == {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "actions"}


def test_a_policy_trains_on_a_batch(tmp_path):
    torch.manual_seed(0)
    store = Store(tmp_path / "store.zarr")  # images large enough for the light conv encoder
    store.ingest(F.write_robomimic(tmp_path / "a.hdf5", lengths=[5, 6], image_size=40), progress=False)
    loader = make_loader(store, ["a"], KEYS, seq_len=4, batch_size=4, num_workers=0)
    ds = loader.dataset
    module = NostraPolicy([m.to_dict() for m in ds.modalities()], ds.action_dim, net=small_net("nostra"))
    module.set_normalization(ds.stats())
    out = module.net.loss(next(iter(loader)), **module.loss_cfg)
    out["loss"].backward()
    assert torch.isfinite(out["loss"])


def test_validation_holdout(tmp_path, store):
    train, val = split_episodes(store, ["a"])
    assert val == [("a", 0)] and train == [("a", 1), ("a", 2)]  # the file's robomimic "valid" mask
    store.ingest(F.write_dp_zarr(tmp_path / "nomask.zarr", n=10, image_size=8), progress=False)
    train, val = split_episodes(store, ["nomask"], val_fraction=0.2, seed=3)
    assert len(val) == 2 and len(train) == 8 and not set(train) & set(val)
    assert split_episodes(store, ["nomask"], val_fraction=0.2, seed=3) == (train, val)  # seeded
    v = make_loader(store, None, ["robot0_eef_pos"], episodes=val, shuffle=False, num_workers=0)
    assert {v.dataset.locate(i)[:2] for i in range(len(v.dataset))} == set(val)


def test_reads_are_lazy_and_memory_bounded(tmp_path):
    s = Store(tmp_path / "store.zarr")
    s.ingest(F.write_robomimic(tmp_path / "a.hdf5", lengths=[60] * 6, image_size=32), progress=False)
    ds = SequenceDataset(s, ["a"], ["agentview_image", "robot0_eef_pos"], seq_len=8, cache_mb=0.5)
    assert len(pickle.dumps(ds)) < 20_000  # what goes to each worker: an index per episode, no arrays
    for i in range(0, len(ds), 3):
        ds[i]
    cache = ds._cache
    assert cache.bytes <= 0.5 * 2 ** 20 < s.array("a", "agentview_image").nbytes
    assert 1 < len(cache.items)


def test_direct_chunk_reads_match_zarr(tmp_path):
    import zarr

    from nostra.data.dataset import chunk_reader
    from nostra.data.store import compressor

    g = zarr.open_group(tmp_path / "g.zarr", mode="w", zarr_format=3)
    img = g.create_array("img", shape=(37, 5, 5, 3), chunks=(8, 5, 5, 3), dtype="uint8", compressors=compressor())
    img[:] = np.random.default_rng(0).integers(0, 255, (37, 5, 5, 3), dtype=np.uint8)
    zeros = g.create_array("zeros", shape=(20, 2), chunks=(8, 2), dtype="float32", compressors=compressor())
    zeros[:] = 0  # all fill value: zarr writes no chunk files
    v2 = zarr.open_group(tmp_path / "v2.zarr", mode="w", zarr_format=2).create_array("x", data=np.arange(30.0), chunks=(8,))
    for arr in (img, zeros, v2):
        read = chunk_reader(arr)
        for i in range(-(-arr.shape[0] // 8)):
            want = arr[i * 8:(i + 1) * 8]
            np.testing.assert_array_equal(read(i)[:len(want)], want)
