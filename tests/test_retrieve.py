"""Index and retrieve on a small store: obj/skill retrieval prefers the same task, `all` re-ranks
by camera pose, target episodes are never returned, the manifest's hash identifies the set, and
bad input (unknown target, mode, another embedding model) fails clearly."""

import json

import pytest

from fixtures import make_episodes
from nostra.data.formats import robomimic_hdf5
from fixtures import ENV_ARGS
from nostra.data.store import Store
from retrieval.index import EpisodeIndex, IndexMismatchError
from retrieval.select import index_store, manifest_hash, select, write_manifest


def _collection(root, store, name, task, language, cam_x, n=4, seed=0):
    eps = make_episodes(n, [6] * n, 8, seed, task=task)
    for i, ep in enumerate(eps):
        ep.meta = {**ep.meta, "language": language, "skill": "pick" if task == "Lift" else "open",
                   "camera_pose": {"agentview": {"pos": [cam_x, 0.0, 1.35], "quat": [0.65, 0.27, 0.27, 0.65]}}}
    path = robomimic_hdf5.write(root / f"{name}.hdf5", eps, ENV_ARGS, total=n, progress=False)
    store.ingest(path, name=name, progress=False)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("retr")
    s = Store(root / "store.zarr")
    _collection(root, s, "target", "Lift", "lift the red cube", 0.5, seed=0)
    _collection(root, s, "lift_near", "Lift", "lift the red cube", 0.52, seed=1)
    _collection(root, s, "lift_far", "Lift", "pick up the red block", 1.2, seed=2)
    _collection(root, s, "door", "Door", "open the door", 0.5, seed=3)
    index_store(s, root / "index", progress=False)
    return s, root / "index"


def test_obj_skill_prefers_the_same_task(store):
    s, index = store
    m = select(s, index, "target", budget=8, mode="obj_skill")
    cols = [e["collection"] for e in m["episodes"]]
    assert "target" not in cols and "door" not in cols
    assert len({(e["collection"], e["episode"]) for e in m["episodes"]}) == 8


def test_all_reranks_by_camera(store):
    s, index = store
    m = select(s, index, "target", budget=4, mode="all", candidates=2)  # 8 obj/skill hits: the two lifts
    assert {e["collection"] for e in m["episodes"]} == {"lift_near"}
    assert all(e["mode"] == "all" for e in m["episodes"])


def test_manifest_hash_and_file(store, tmp_path):
    s, index = store
    m = select(s, index, "target", budget=4, mode="obj_skill")
    digest = write_manifest(m, tmp_path / "m.json")
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["hash"] == digest == manifest_hash(m)
    other = select(s, index, "target", budget=4, mode="all")
    assert manifest_hash(other) != digest


def test_reindex_is_incremental(store):
    s, index = store
    assert index_store(s, index, progress=False)["obj_skill"]["added"] == []


def test_bad_input(store):
    s, index = store
    with pytest.raises(ValueError, match="target collection 'nope'"):
        select(s, index, "nope", 4)
    with pytest.raises(ValueError, match="unknown retrieval mode 'camera'"):
        select(s, index, "target", 4, mode="camera")
    with pytest.raises(IndexMismatchError, match="built with embedding model"):
        EpisodeIndex.load(index / "obj_skill", model="another-model", kind="obj_skill")


def test_index_only_the_listed_collections(store, tmp_path):
    s, _ = store  # a pool without lift_near: retrieval for the target can only draw from lift_far and door
    index_store(s, tmp_path / "pool", progress=False, collections=["target", "lift_far", "door"])
    m = select(s, tmp_path / "pool", "target", budget=8, mode="obj_skill")
    assert {e["collection"] for e in m["episodes"]} <= {"lift_far", "door"}
    assert "lift_far" in {e["collection"] for e in m["episodes"]}
    with pytest.raises(ValueError, match=r"retrieval.collections \['nope'\] are not in the store"):
        index_store(s, tmp_path / "bad", progress=False, collections=["target", "nope"])
