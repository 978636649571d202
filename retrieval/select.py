"""Co-training subsets: given a target collection (a few demos) and a budget, a manifest of
retrieved episodes by object/skill (`obj_skill`) or by object/skill then camera pose and placement
(`all`, paper Table 5). Target episodes are never retrieved; each episode appears once.

A manifest is JSON: {"target", "mode", "budget", "query", "embedding_model", "episodes":
[{"collection", "episode", "score", "weight", "mode"}]}; its hash (of the episode list and mode)
identifies the co-training set everywhere (MLflow param `manifest_hash`)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd

from retrieval.embed import embed_store, vectors_for
from retrieval.index import EpisodeIndex, rerank, update_index

MODES = ("obj_skill", "all")
KINDS = ("obj_skill", "scene")


def index_store(store, index_dir: str | os.PathLike, progress: bool = True,
                collections: list[str] | None = None) -> dict:
    """Embed ``collections`` (default: every collection; cached beside the store) and bring one index
    per kind up to date: the pool that ``select`` draws from."""
    missing = sorted(set(collections or ()) - set(store.collections()))
    if missing:
        raise ValueError(f"retrieval.collections {missing} are not in the store {store.path}; "
                         f"it has {store.collections()}")
    summary = {}
    for kind in KINDS:
        emb = embed_store(store, kind, collections, progress=progress)
        spaces = {(e.kind, e.model) for e in emb.values()}
        if len(spaces) > 1:  # collections without camera metadata are embedded visually
            by = {s: [n for n, e in emb.items() if (e.kind, e.model) == s] for s in spaces}
            emb = {n: emb[n] for n in max(by.values(), key=len)}
        _, changes = update_index(Path(index_dir) / kind, emb)
        summary[kind] = {k: changes[k] for k in ("added", "rebuilt", "unchanged")}
    return summary


def select(store, index_dir: str | os.PathLike, target: str, budget: int, mode: str = "obj_skill",
           candidates: int = 5) -> dict:
    """The manifest of ``budget`` episodes for ``target`` (see the module doc)."""
    if mode not in MODES:
        raise ValueError(f"unknown retrieval mode {mode!r}; valid: {', '.join(MODES)}")
    if target not in store.collections():
        raise ValueError(f"target collection {target!r} is not in the store {store.path}; "
                         f"it has {store.collections()}")
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    obj = embed_store(store, "obj_skill", progress=False)
    index = EpisodeIndex.load(Path(index_dir) / "obj_skill", model=obj[target].model, kind="obj_skill")
    query = obj[target].vectors.mean(0, keepdims=True)
    query /= max(float(np.linalg.norm(query)), 1e-12)
    pool = budget * (candidates if mode == "all" else 1)
    hits = _search_excluding(index, query, pool, target)
    if mode == "all" and len(hits):
        scene = embed_store(store, "scene", progress=False)
        target_scene = scene[target].vectors.mean(0, keepdims=True)
        order, sim = rerank(target_scene, vectors_for(scene, hits), scene[target].metric, budget)
        hits = hits.iloc[order].assign(score=sim)
    hits = hits.head(budget)
    episodes = [{"collection": str(c), "episode": int(e), "score": float(s), "weight": 1.0, "mode": mode}
                for c, e, s in zip(hits["collection"], hits["episode"], hits["score"])]
    return {"target": target, "mode": mode, "budget": budget, "embedding_model": obj[target].model,
            "query": {"kind": "obj_skill", "from": f"mean of {len(obj[target])} target episodes",
                      "rerank": "scene (camera pose + placements) of the target" if mode == "all" else None},
            "episodes": episodes}


def _search_excluding(index: EpisodeIndex, query: np.ndarray, k: int, target: str) -> pd.DataFrame:
    """Top-k distinct non-target episodes (searching deeper until k are found or all are seen)."""
    depth = k
    while True:
        ids, scores = index.search(query, min(depth, len(index)))
        table = index.lookup(ids, scores)
        table = table[table["collection"] != target].drop_duplicates(["collection", "episode"])
        if len(table) >= k or depth >= len(index):
            return table.head(k)[["collection", "episode", "score"]].reset_index(drop=True)
        depth *= 4


def manifest_hash(manifest: dict) -> str:
    core = {"mode": manifest["mode"], "episodes": [(e["collection"], e["episode"]) for e in manifest["episodes"]]}
    return hashlib.sha256(json.dumps(core, sort_keys=True).encode()).hexdigest()[:16]


def write_manifest(manifest: dict, path: str | os.PathLike) -> str:
    """Write atomically; returns the manifest's hash (also stored in it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    manifest = {**manifest, "hash": manifest_hash(manifest)}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, path)
    return manifest["hash"]

