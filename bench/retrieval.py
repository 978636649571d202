"""Retrieval index benchmark: build time, single-query top-100 latency and recall@100 of the
automatic approximate index (HNSW above the threshold) against exact inner-product search.

Data: synthetic 384-d L2-normalised embeddings from a structured Gaussian mixture, not uniform
noise: 50 topics, 1000 clusters (20 per topic, centres = topic + offset), each cluster spread in
its own random 32-d subspace (``--rank``) plus small isotropic noise, so that the data has the low
intrinsic dimension and the cluster/sub-cluster structure of sentence embeddings. ``--rank 384``
spreads clusters in every direction: a much harder stress case (noise-like neighbourhoods). Queries are fresh draws
from the same mixture. Latency is one query per call (a retrieval stage asks per target task),
timed with ``--query-threads`` faiss threads. ``--n`` runs smaller. Last line: JSON.

    .venv/bin/python bench/retrieval.py            # 1M, several minutes (the HNSW build)
    .venv/bin/python bench/retrieval.py --n 100000
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

# This script is named like the package it measures: keep bench/ off the path so that `retrieval`
# is the package (installed, or the repository root).
_here = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _here] + [str(_here.parent)]

import faiss
import numpy as np
from tqdm import tqdm

from retrieval.index import EpisodeIndex, IndexConfig

DIM, TOPICS, CLUSTERS = 384, 50, 1000


def mixture(n: int, seed: int, rank: int = 32, centres: tuple | None = None) -> tuple[np.ndarray, tuple]:
    """n points of the mixture; the mixture itself (centres, bases) is drawn from seed 0."""
    if centres is None:
        g = np.random.default_rng(0)
        topics = g.standard_normal((TOPICS, DIM)).astype(np.float32) / np.sqrt(DIM)
        offsets = g.standard_normal((CLUSTERS, DIM)).astype(np.float32) / np.sqrt(DIM)
        c = topics[np.arange(CLUSTERS) % TOPICS] + 0.7 * offsets
        c /= np.linalg.norm(c, axis=1, keepdims=True)
        bases = g.standard_normal((CLUSTERS, rank, DIM)).astype(np.float32) / np.sqrt(DIM)
        centres = (c, bases)
    c, bases = centres
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, CLUSTERS, n)
    x = np.empty((n, DIM), np.float32)
    for j in range(CLUSTERS):
        rows = np.flatnonzero(labels == j)
        # spread ~0.6 within the cluster's subspace, ~0.1 isotropic, around a unit centre
        z = rng.standard_normal((len(rows), rank)).astype(np.float32) * (0.6 / np.sqrt(rank))
        iso = rng.standard_normal((len(rows), DIM)).astype(np.float32) * (0.1 / np.sqrt(DIM))
        x[rows] = c[j] + z @ bases[j] + iso
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x, centres


def latency_ms(index: EpisodeIndex, q: np.ndarray, k: int) -> tuple[np.ndarray, dict]:
    ids, times = [], []
    for row in q:
        t = time.perf_counter()
        i, _ = index.search(row[None], k)
        times.append(time.perf_counter() - t)
        ids.append(i[0])
    ms = np.array(times) * 1e3
    return np.stack(ids), {"mean_ms": round(float(ms.mean()), 3), "p50_ms": round(float(np.median(ms)), 3),
                           "p95_ms": round(float(np.percentile(ms, 95)), 3)}


def recall(found: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean([len(np.intersect1d(f[f >= 0], t)) / len(t) for f, t in zip(found, truth)]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--rank", type=int, default=32, help="dimension of each cluster's spread")
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--threshold", type=int, default=None,
                    help=f"auto index threshold (default: the config's {IndexConfig.threshold}, or n/2 if "
                         f"that is not below n, so the approximate index is measured)")
    ap.add_argument("--m", type=int, default=IndexConfig.hnsw_m)
    ap.add_argument("--ef-construction", type=int, default=IndexConfig.ef_construction)
    ap.add_argument("--ef-search", type=int, nargs="+", default=[128, IndexConfig.ef_search, 512],
                    help="efSearch values to measure (the default config's value is among them)")
    ap.add_argument("--build-threads", type=int, default=os.cpu_count())
    ap.add_argument("--query-threads", type=int, default=1)
    ap.add_argument("--keep", type=Path, default=None,
                    help="save the approximate index here, or load it if one built with the same settings is there "
                         "(re-measures queries without the long build)")
    args = ap.parse_args()
    if args.threshold is None:
        args.threshold = IndexConfig.threshold if IndexConfig.threshold < args.n else args.n // 2

    print(f"data: {args.n} x {DIM} Gaussian mixture, clusters of rank {args.rank}", flush=True)
    x, centres = mixture(args.n, seed=1, rank=args.rank)
    q, _ = mixture(args.queries, seed=2, rank=args.rank, centres=centres)
    episodes = np.arange(args.n)
    out = {"n": args.n, "dim": DIM, "k": args.k, "queries": args.queries, "data": f"gaussian_mixture_rank{args.rank}",
           "cpus": os.cpu_count(), "loadavg_start": os.getloadavg()[0]}

    faiss.omp_set_num_threads(args.build_threads)
    t = time.perf_counter()
    exact = EpisodeIndex("synthetic", "bench", DIM, "ip", IndexConfig(index_type="flat"))
    exact.add("synthetic", episodes, x)
    out["exact_build_s"] = round(time.perf_counter() - t, 2)
    truth, _ = exact.search(q, args.k)  # batched: the ground truth
    faiss.omp_set_num_threads(args.query_threads)
    _, out["exact_query"] = latency_ms(exact, q[:50], args.k)
    del exact

    faiss.omp_set_num_threads(args.build_threads)
    cfg = IndexConfig(index_type="auto", threshold=args.threshold, hnsw_m=args.m, ef_construction=args.ef_construction)
    print(f"building auto index (threshold {args.threshold}, M {args.m}, efConstruction {args.ef_construction}) "
          f"on {args.build_threads} threads", flush=True)
    t = time.perf_counter()
    tag = f"n{args.n}-rank{args.rank}-t{args.threshold}-m{args.m}-efc{args.ef_construction}"
    if args.keep and (args.keep / "meta.json").is_file() and json.loads((args.keep / "meta.json").read_text()).get(
            "model") == tag:
        approx = EpisodeIndex.load(args.keep, model=tag)
        out["approx_build_s"] = json.loads((args.keep / "build.json").read_text())["build_s"]
        out["approx_loaded_from"] = str(args.keep)
    else:
        approx = EpisodeIndex(tag, "bench", DIM, "ip", cfg)
        approx.add("synthetic", episodes, x)
        out["approx_build_s"] = round(time.perf_counter() - t, 2)
        if args.keep:
            approx.save(args.keep)
            (args.keep / "build.json").write_text(json.dumps({"build_s": out["approx_build_s"]}))
    out["approx_type"] = approx.index_type
    out["approx"] = []
    faiss.omp_set_num_threads(args.query_threads)
    for ef in tqdm(args.ef_search, desc="efSearch"):
        approx.config.ef_search = ef
        approx._apply_search_params()
        found, lat = latency_ms(approx, q, args.k)
        row = {"ef_search": ef, "recall_at_k": round(recall(found, truth), 4), **lat}
        out["approx"].append(row)
        print(row, flush=True)
    out["loadavg_end"] = os.getloadavg()[0]
    print("| index | build s | recall@%d | mean ms | p95 ms |\n|---|---|---|---|---|" % args.k)
    ex = out["exact_query"]
    print(f"| exact flat | {out['exact_build_s']} | 1.0 | {ex['mean_ms']} | {ex['p95_ms']} |")
    for r in out["approx"]:
        print(f"| {out['approx_type']} ef={r['ef_search']} | {out['approx_build_s']} | {r['recall_at_k']} "
              f"| {r['mean_ms']} | {r['p95_ms']} |")
    print(json.dumps({"retrieval": out}))


if __name__ == "__main__":
    main()
