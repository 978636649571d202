import faiss
import numpy as np
import pytest

from retrieval.embed import EmbeddingError, Embeddings, vectors_for
from retrieval.index import (EpisodeIndex, IndexConfig, IndexMismatchError, build_index, rerank,
                             update_index)

faiss.omp_set_num_threads(1)
DIM = 32


def unit(n, seed, dim=DIM):
    x = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def emb(n, seed, model="minilm", kind="obj_skill", dim=DIM):
    return Embeddings(kind, model, unit(n, seed, dim), np.arange(n))


def true_topk(x, q, k):
    return np.argsort(-(q @ x.T), axis=1)[:, :k]


def test_exact_index_returns_true_top_k():
    x, q = unit(500, 0), unit(20, 1)
    index = EpisodeIndex("minilm", "obj_skill", DIM)
    index.add("c", np.arange(500) + 1000, x)
    ids, scores = index.search(q, 10)
    assert index.index_type == "flat"
    np.testing.assert_array_equal(ids, true_topk(x, q, 10))
    np.testing.assert_allclose(scores, np.take_along_axis(q @ x.T, ids, axis=1), atol=1e-5)
    table = index.lookup(ids, scores)
    assert table.episode.iloc[0] == ids[0, 0] + 1000 and set(table.collection) == {"c"} and len(table) == 200
    # more than it holds: padded with -1 / -inf
    ids, scores = index.search(q[:1], 600)
    assert (ids[0, :500] >= 0).all() and (ids[0, 500:] == -1).all() and np.isneginf(scores[0, 500:]).all()


def test_l2_index_scores_are_negative_squared_distances():
    x, q = unit(300, 2) * 3, unit(5, 3) * 3  # scene vectors need not be unit length
    index = EpisodeIndex("scene-v1", "scene", DIM, metric="l2")
    index.add("c", np.arange(300), x)
    ids, scores = index.search(q, 5)
    d2 = ((q[:, None] - x[None]) ** 2).sum(-1)
    np.testing.assert_array_equal(ids, np.argsort(d2, axis=1)[:, :5])
    np.testing.assert_allclose(scores, -np.take_along_axis(d2, ids, axis=1), rtol=1e-4)


def test_duplicates_are_stored_once_and_expand_to_all_their_episodes():
    tasks = unit(3, 4)
    x = tasks[np.repeat([0, 1, 2], [50, 30, 20])]  # 100 episodes, 3 instructions
    index = EpisodeIndex("minilm", "obj_skill", DIM)
    index.add("mimiclabs", np.arange(100), x)
    assert index.n_unique == 3 and len(index) == 100
    ids, scores = index.search(tasks[1], 40)
    assert sorted(ids[0, :30]) == list(range(50, 80))  # all 30 episodes of task 1 first
    np.testing.assert_allclose(scores[0, :30], 1, atol=1e-5)
    assert (scores[0, 30:] < 0.99).all() and (ids[0] >= 0).all()


def test_auto_index_switches_to_hnsw_above_threshold():
    cfg = IndexConfig(threshold=400, hnsw_m=16, ef_construction=64, ef_search=128)
    x1, x2, q = unit(400, 5), unit(100, 6), unit(10, 7)
    index = EpisodeIndex("minilm", "obj_skill", DIM, config=cfg)
    index.add("a", np.arange(400), x1)
    assert index.index_type == "flat"  # at the threshold: still exact
    index.add("b", np.arange(100), x2)
    assert index.index_type == "hnsw" and isinstance(index.index, faiss.IndexHNSWFlat) and index.n_unique == 500
    ids, _ = index.search(q, 10)
    truth = true_topk(np.concatenate([x1, x2]), q, 10)
    assert np.mean([len(set(a) & set(b)) / 10 for a, b in zip(ids, truth)]) > 0.9
    with pytest.raises(ValueError, match="valid: auto, flat, hnsw, ivf"):
        IndexConfig(index_type="lsh")


@pytest.mark.parametrize("index_type", ["flat", "hnsw", "ivf"])
def test_persistence_round_trip(tmp_path, index_type):
    embs = {"a": emb(800, 8), "b": emb(300, 9)}
    index = build_index(embs, {"a": "fa", "b": "fb"}, IndexConfig(index_type=index_type, ivf_nprobe=64))
    q = unit(5, 10)
    ids, scores = index.search(q, 8)
    index.save(tmp_path / "idx")
    loaded = EpisodeIndex.load(tmp_path / "idx", model="minilm", kind="obj_skill")
    assert loaded.index_type == index_type and len(loaded) == 1100 and loaded.collections["b"]["fingerprint"] == "fb"
    ids2, scores2 = loaded.search(q, 8)
    np.testing.assert_array_equal(ids, ids2)
    np.testing.assert_allclose(scores, scores2)
    assert loaded.entries(ids2[:, 0]).equals(index.entries(ids[:, 0]))


def test_incremental_add_after_load(tmp_path):
    index = build_index({"a": emb(200, 11)}, {"a": "fa"})
    index.save(tmp_path / "idx")
    new = emb(50, 12)
    loaded, report = update_index(tmp_path / "idx", {"a": emb(200, 11), "b": new}, {"a": "fa", "b": "fb"})
    assert report["added"] == ["b"] and not report["rebuilt"] and len(loaded) == 250
    ids, scores = EpisodeIndex.load(tmp_path / "idx").search(new.vectors[7], 1)
    hit = loaded.entries(ids)
    assert hit.collection[0] == "b" and hit.episode[0] == 7 and scores[0, 0] == pytest.approx(1, abs=1e-5)
    # nothing new: nothing added; a changed collection: rebuilt
    _, report = update_index(tmp_path / "idx", {"a": emb(200, 11), "b": new}, {"a": "fa", "b": "fb"})
    assert report["added"] == [] and not report["rebuilt"]
    _, report = update_index(tmp_path / "idx", {"a": emb(200, 13), "b": new}, {"a": "fa2", "b": "fb"})
    assert report["rebuilt"] and len(EpisodeIndex.load(tmp_path / "idx")) == 250
    with pytest.raises(ValueError, match="'a' is already in the index"):
        loaded.add_embeddings("a", emb(5, 14))


def test_ivf_keeps_its_trained_quantizer_on_add():
    index = build_index({"a": emb(2000, 15)}, config=IndexConfig(index_type="ivf", ivf_nprobe=1000))
    nlist, centroids = index.index.nlist, index.index.quantizer.reconstruct_n(0, index.index.nlist)
    new = emb(100, 16)
    index.add_embeddings("b", new)
    assert index.index.nlist == nlist and index.index.ntotal == 2100
    np.testing.assert_array_equal(index.index.quantizer.reconstruct_n(0, nlist), centroids)
    ids, _ = index.search(new.vectors[:3], 1)
    assert index.entries(ids).collection.tolist() == ["b"] * 3


def test_mismatched_embedding_model_or_kind_is_a_clear_error(tmp_path):
    build_index({"a": emb(50, 17)}).save(tmp_path / "idx")
    with pytest.raises(IndexMismatchError, match="'minilm'.*'other-model'"):
        EpisodeIndex.load(tmp_path / "idx", model="other-model", kind="obj_skill")
    with pytest.raises(IndexMismatchError, match="kind 'obj_skill'.*kind 'scene'"):
        EpisodeIndex.load(tmp_path / "idx", model="minilm", kind="scene")
    index = EpisodeIndex.load(tmp_path / "idx")
    with pytest.raises(IndexMismatchError, match="'minilm'.*'other-model'"):
        index.add_embeddings("b", emb(5, 18, model="other-model"))
    with pytest.raises(IndexMismatchError, match="dim 16"):
        index.search(unit(1, 19, dim=16), 3)
    with pytest.raises(IndexMismatchError, match="'minilm'.*'other-model'"):
        update_index(tmp_path / "idx", {"b": emb(5, 18, model="other-model")})
    with pytest.raises(FileNotFoundError, match="no episode index"):
        EpisodeIndex.load(tmp_path / "nothing")


def test_inner_product_index_rejects_unnormalised_vectors():
    index = EpisodeIndex("minilm", "obj_skill", DIM)
    with pytest.raises(ValueError, match="collection 'raw'.*L2-normalised.*episode 0"):
        index.add("raw", np.arange(3), unit(3, 20) * 2)


def test_rerank_orders_obj_skill_hits_by_scene_distance():
    # "all" retrieval: candidates from the obj/skill search, re-ranked by their scene vectors.
    target = np.zeros(8, np.float32)
    cands = np.stack([np.full(8, d, np.float32) for d in (0.5, 0.1, 2.0, 0.0)])
    order, sims = rerank(target, cands, "l2", top=3)
    assert order.tolist() == [3, 1, 0] and np.all(np.diff(sims) <= 0)
    order, _ = rerank(unit(1, 0)[0], unit(1, 0), "ip")
    assert order.tolist() == [0]


def test_all_selection_recipe_obj_skill_then_scene():
    # Two collections with the same task text; their episodes differ in scene. Search by obj/skill,
    # fetch the hits' scene vectors, re-rank by distance to the target scene.
    text = unit(1, 21)[0]
    obj = {c: Embeddings("obj_skill", "minilm", np.tile(text, (n, 1)), np.arange(n)) for c, n in (("a", 4), ("b", 3))}
    offsets = {"a": [3.0, 0.2, 5.0, 1.0], "b": [0.1, 9.0, 2.0]}
    scene = {c: Embeddings("scene", "scene-v1", np.array([[d] + [0.0] * 7 for d in offs], np.float32),
                           np.arange(len(offs))) for c, offs in offsets.items()}
    hits = build_index(obj).search(text, 7)[0]
    cands = build_index(obj).entries(hits)
    order, _ = rerank(np.zeros(8, np.float32), vectors_for(scene, cands), "l2", top=3)
    assert list(map(tuple, cands.iloc[order][["collection", "episode"]].values)) == [("b", 0), ("a", 1), ("a", 3)]
    with pytest.raises(EmbeddingError, match="collection 'c' episode 0"):
        vectors_for(scene, cands.assign(collection="c"))


def test_update_index_reads_fingerprints_recorded_by_the_cache(tmp_path):
    a = emb(30, 22)
    a.meta["fingerprint"] = "fa"
    index, _ = update_index(tmp_path / "idx", {"a": a})
    assert index.collections["a"]["fingerprint"] == "fa"
    changed = emb(30, 23)
    changed.meta["fingerprint"] = "fa2"
    _, report = update_index(tmp_path / "idx", {"a": changed})
    assert report["rebuilt"]
    _, report = update_index(tmp_path / "idx", {"a": changed})
    assert not report["rebuilt"] and report["unchanged"] == ["a"]
