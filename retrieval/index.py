"""faiss indices over episode embeddings of one space (one embedding model and kind).

- Exact search (IndexFlatIP / IndexFlatL2) up to ``threshold`` unique vectors; above it the
  ``auto`` type moves once to HNSW (IndexHNSWFlat), after which collections are added
  incrementally. ``ivf`` (IndexIVFFlat) is available explicitly: it is trained on the first batch
  and later batches reuse the trained quantizer.
- Identical vectors are stored once and map to all their episodes (every episode of a task shares
  its obj/skill text, so a collection is mostly duplicates; duplicates also degrade an HNSW graph).
  ``search`` expands them back to episodes, so it still returns the true top-k episodes.
- Scores are "higher is more similar": inner products for ``ip`` spaces, minus squared L2
  distance for ``l2`` spaces (the metadata scene embedding).
- ``save(dir)`` writes ``index.faiss``, ``entries.npz`` (collection, episode, vector id) and
  ``meta.json`` (model, kind, dim, metric, index type, parameters, per-collection fingerprints);
  ``load(dir, model=, kind=)`` refuses an index of another space, naming both.

Retrieval by obj/skill is ``search``; "all" (obj/skill, then aligned by camera pose and placement)
is ``search`` for candidates and ``rerank`` of those by their scene vectors.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import faiss
import numpy as np
import pandas as pd
from tqdm import tqdm

log = logging.getLogger(__name__)

INDEX_TYPES = ("auto", "flat", "hnsw", "ivf")
METRICS = {"ip": faiss.METRIC_INNER_PRODUCT, "l2": faiss.METRIC_L2}
FORMAT = 1


class IndexMismatchError(ValueError):
    """An index and embeddings (or a query) from different embedding spaces."""


@dataclass
class IndexConfig:
    index_type: str = "auto"  # auto: flat up to `threshold` unique vectors, hnsw above
    threshold: int = 100_000
    hnsw_m: int = 32  # graph degree; bench/retrieval.py shows recall vs latency at 1M
    ef_construction: int = 128
    ef_search: int = 256
    ivf_nlist: int = 0  # 0: 4 * sqrt(n) at training time
    ivf_nprobe: int = 32
    dedupe: bool = True

    def __post_init__(self):
        if self.index_type not in INDEX_TYPES:
            raise ValueError(f"unknown index_type {self.index_type!r}; valid: {', '.join(INDEX_TYPES)}")
        if self.threshold < 1:
            raise ValueError(f"threshold must be >= 1, got {self.threshold}")


def _hashes(vectors: np.ndarray) -> list[bytes]:
    return [hashlib.blake2b(v.tobytes(), digest_size=16).digest() for v in vectors]


class EpisodeIndex:
    def __init__(self, model: str, kind: str, dim: int, metric: str = "ip", config: IndexConfig | None = None):
        if metric not in METRICS:
            raise ValueError(f"unknown metric {metric!r}; valid: {', '.join(METRICS)}")
        self.model, self.kind, self.dim, self.metric = model, kind, int(dim), metric
        self.config = config or IndexConfig()
        self.index = None  # faiss index of unique vectors, created on the first add
        self.index_type = None  # flat | hnsw | ivf once created
        self.collections: dict[str, dict] = {}  # name -> {"code", "n", "fingerprint"}
        self._col = np.zeros(0, np.int32)  # per entry (episode): collection code,
        self._ep = np.zeros(0, np.int64)  # episode index,
        self._vid = np.zeros(0, np.int64)  # id of its vector in the faiss index
        self._hash: list[bytes] = []  # per unique vector
        self._vid_of: dict[bytes, int] = {}
        self._groups = None  # (order, starts) of entries by vector id, built on search

    # ---- identity -------------------------------------------------------------------------
    @classmethod
    def for_embeddings(cls, emb, config: IndexConfig | None = None) -> "EpisodeIndex":
        return cls(emb.model, emb.kind, emb.dim, emb.metric, config)

    def space(self) -> str:
        return f"model {self.model!r}, kind {self.kind!r}, dim {self.dim}"

    def check_space(self, model: str | None = None, kind: str | None = None, dim: int | None = None,
                    what: str = "embeddings") -> None:
        if (model is not None and model != self.model) or (kind is not None and kind != self.kind) \
                or (dim is not None and int(dim) != self.dim):
            raise IndexMismatchError(
                f"the index was built with {self.space()} but the {what} have model {model!r}, "
                f"kind {kind!r}, dim {dim}; rebuild the index for the new embeddings")

    def __len__(self) -> int:
        return len(self._ep)

    @property
    def n_unique(self) -> int:
        return 0 if self.index is None else int(self.index.ntotal)

    # ---- adding ---------------------------------------------------------------------------
    def add_embeddings(self, collection: str, emb, fingerprint: str | None = None) -> None:
        """Add an ``embed.Embeddings`` of one collection, checking that it is in this index's space."""
        self.check_space(emb.model, emb.kind, emb.dim, what=f"embeddings of collection {collection!r}")
        self.add(collection, emb.episodes, emb.vectors, fingerprint)

    def add(self, collection: str, episodes, vectors, fingerprint: str | None = None) -> None:
        if collection in self.collections:
            raise ValueError(f"collection {collection!r} is already in the index; a changed collection "
                             f"needs a rebuild (update_index does it)")
        x = np.ascontiguousarray(vectors, dtype=np.float32)
        episodes = np.asarray(episodes, dtype=np.int64).ravel()
        if x.ndim != 2 or x.shape[1] != self.dim or len(x) != len(episodes):
            raise ValueError(f"collection {collection!r}: vectors must be ({len(episodes)}, {self.dim}), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"collection {collection!r}: vectors contain NaN or inf")
        if self.metric == "ip":  # inner product ranks by cosine only for unit (or zero) vectors
            norms = np.linalg.norm(x, axis=1)
            bad = np.flatnonzero((np.abs(norms - 1) > 1e-3) & (norms > 1e-6))
            if len(bad):
                raise ValueError(f"collection {collection!r}: inner-product index needs L2-normalised vectors; "
                                 f"episode {int(episodes[bad[0]])} has norm {norms[bad[0]]:.4f}")
        vid = np.empty(len(x), np.int64)
        new_rows = []
        if self.config.dedupe:
            pending: dict[bytes, int] = {}  # committed to _vid_of only once faiss took the vectors
            for i, h in enumerate(_hashes(x)):
                j = self._vid_of.get(h, pending.get(h))
                if j is None:
                    j = pending[h] = len(self._hash) + len(new_rows)
                    new_rows.append(i)
                vid[i] = j
            new_hashes = list(pending)
        else:
            new_rows = list(range(len(x)))
            vid[:] = np.arange(len(x)) + len(self._hash)
            new_hashes = [b""] * len(x)
        self._add_unique(x if len(new_rows) == len(x) else x[new_rows])
        self._hash += new_hashes
        if self.config.dedupe:
            self._vid_of.update(pending)
        code = len(self.collections)
        self.collections[collection] = {"code": code, "n": int(len(x)), "fingerprint": fingerprint}
        self._col = np.concatenate([self._col, np.full(len(x), code, np.int32)])
        self._ep = np.concatenate([self._ep, episodes])
        self._vid = np.concatenate([self._vid, vid])
        self._groups = None

    def _target_type(self, n: int) -> str:
        t = self.config.index_type
        return t if t != "auto" else ("flat" if n <= self.config.threshold else "hnsw")

    def _add_unique(self, x: np.ndarray) -> None:
        if not len(x) and self.index is not None:
            return
        target = self._target_type(self.n_unique + len(x))
        if self.index is not None and target != self.index_type:
            # auto crossed the threshold: move the vectors held so far (once) into the new index.
            log.info("index of %d vectors passes threshold %d: moving from %s to %s",
                     self.n_unique + len(x), self.config.threshold, self.index_type, target)
            x = np.concatenate([self.index.reconstruct_n(0, self.n_unique), x])
            self.index = None
        if self.index is None:
            self.index, self.index_type = self._new_index(target, x), target
        self._apply_search_params()
        step = 50_000  # in chunks, for a progress bar on big adds (HNSW inserts are slow)
        for a in tqdm(range(0, len(x), step), desc=f"{self.index_type} add", disable=len(x) <= 2 * step):
            self.index.add(x[a:a + step])

    def _new_index(self, kind: str, x: np.ndarray):
        metric, c = METRICS[self.metric], self.config
        if kind == "flat":
            return faiss.IndexFlatIP(self.dim) if self.metric == "ip" else faiss.IndexFlatL2(self.dim)
        if kind == "hnsw":
            index = faiss.IndexHNSWFlat(self.dim, c.hnsw_m, metric)
            index.hnsw.efConstruction = c.ef_construction
            return index
        # ivf: at least ~39 training points per list, as faiss's k-means wants
        nlist = max(1, min(c.ivf_nlist or int(4 * math.sqrt(max(len(x), 1))), len(x) // 39))
        quantizer = faiss.IndexFlatIP(self.dim) if self.metric == "ip" else faiss.IndexFlatL2(self.dim)
        index = faiss.IndexIVFFlat(quantizer, self.dim, nlist, metric)
        if not len(x):
            raise ValueError("an ivf index needs vectors to train on in its first add")
        sample = x if len(x) <= nlist * 256 else x[np.random.default_rng(0).choice(len(x), nlist * 256, replace=False)]
        index.train(sample)  # faiss's wrapper keeps a reference to the quantizer
        return index

    def _apply_search_params(self) -> None:
        if self.index_type == "hnsw":
            self.index.hnsw.efSearch = self.config.ef_search
        elif self.index_type == "ivf":
            self.index.nprobe = min(self.config.ivf_nprobe, self.index.nlist)

    # ---- searching ------------------------------------------------------------------------
    def search(self, queries, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-k episodes per query: (ids [nq, k] int64 entry ids, -1 where fewer exist;
        scores [nq, k] float32, higher is more similar, -inf where no entry). ``entries(ids)``
        names the episodes."""
        q = np.ascontiguousarray(np.atleast_2d(np.asarray(queries, dtype=np.float32)))
        if q.shape[1] != self.dim:
            raise IndexMismatchError(f"queries have dim {q.shape[1]} but the index holds {self.space()}")
        ids = np.full((len(q), k), -1, np.int64)
        scores = np.full((len(q), k), -np.inf, np.float32)
        if self.index is None or k < 1:
            return ids, scores
        # k unique vectors always cover the top-k episodes (each vector has >= 1 episode)
        dist, vids = self.index.search(q, min(k, self.n_unique))
        if self.metric == "l2":
            dist = -dist
        order, starts = self._group_table()
        for r in range(len(q)):
            filled = 0
            for v, s in zip(vids[r], dist[r]):
                if v < 0 or filled == k:
                    break
                members = order[starts[v]:starts[v + 1]][:k - filled]
                ids[r, filled:filled + len(members)] = members
                scores[r, filled:filled + len(members)] = s
                filled += len(members)
        return ids, scores

    def _group_table(self):
        if self._groups is None:
            order = np.argsort(self._vid, kind="stable")
            starts = np.searchsorted(self._vid[order], np.arange(self.n_unique + 1))
            self._groups = (order, starts)
        return self._groups

    def entries(self, ids) -> pd.DataFrame:
        """The (collection, episode) of entry ids from ``search`` (flattened, -1 dropped)."""
        ids = np.asarray(ids, dtype=np.int64).ravel()
        ids = ids[ids >= 0]
        names = np.array(list(self.collections), dtype=object)
        return pd.DataFrame({"collection": names[self._col[ids]] if len(names) else [], "episode": self._ep[ids]})

    def lookup(self, ids, scores) -> pd.DataFrame:
        """Search results as a table: query, rank, collection, episode, score."""
        ids, scores = np.atleast_2d(ids), np.atleast_2d(scores)
        q, rank = np.nonzero(ids >= 0)
        out = self.entries(ids[q, rank])
        out.insert(0, "rank", rank)
        out.insert(0, "query", q)
        out["score"] = scores[q, rank]
        return out

    # ---- persistence ----------------------------------------------------------------------
    def meta(self) -> dict:
        return {"format": FORMAT, "model": self.model, "kind": self.kind, "dim": self.dim, "metric": self.metric,
                "index_type": self.index_type, "config": asdict(self.config), "n_entries": len(self),
                "n_unique": self.n_unique, "collections": self.collections, "faiss": faiss.__version__}

    def save(self, path) -> Path:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        tmp = {name: path / f".{name}.tmp" for name in ("index.faiss", "entries.npz", "meta.json")}
        if self.index is not None:
            faiss.write_index(self.index, str(tmp["index.faiss"]))
        hashes = np.frombuffer(b"".join(self._hash), np.uint8).reshape(-1, 16) if self.config.dedupe \
            else np.zeros((0, 16), np.uint8)
        with open(tmp["entries.npz"], "wb") as f:
            np.savez(f, collection=self._col, episode=self._ep, vector=self._vid, hashes=hashes)
        tmp["meta.json"].write_text(json.dumps(self.meta(), indent=1))
        for name, t in tmp.items():  # meta.json last: it is what load checks first
            if t.exists():
                os.replace(t, path / name)
        return path

    @classmethod
    def load(cls, path, model: str | None = None, kind: str | None = None) -> "EpisodeIndex":
        """Load an index saved by ``save``; with ``model``/``kind``, refuse one of another space."""
        path = Path(path)
        meta_file = path / "meta.json"
        if not meta_file.is_file():
            raise FileNotFoundError(f"{path} holds no episode index (no meta.json)")
        meta = json.loads(meta_file.read_text())
        if meta.get("format") != FORMAT:
            raise ValueError(f"{meta_file}: index format {meta.get('format')!r}, this code reads {FORMAT}")
        if (model is not None and model != meta["model"]) or (kind is not None and kind != meta["kind"]):
            raise IndexMismatchError(
                f"{path} was built with embedding model {meta['model']!r}, kind {meta['kind']!r}, but "
                f"model {model!r}, kind {kind!r} was asked for; rebuild the index for these embeddings")
        self = cls(meta["model"], meta["kind"], meta["dim"], meta["metric"], IndexConfig(**meta["config"]))
        self.collections = meta["collections"]
        with np.load(path / "entries.npz") as z:
            self._col, self._ep, self._vid = z["collection"], z["episode"], z["vector"]
            hashes = z["hashes"]
        self._hash = [h.tobytes() for h in hashes]
        self._vid_of = {h: i for i, h in enumerate(self._hash)}
        if meta["index_type"] is not None:
            self.index, self.index_type = faiss.read_index(str(path / "index.faiss")), meta["index_type"]
            self._apply_search_params()
        if not self.config.dedupe:
            self._hash = [b""] * self.n_unique
        return self


# ---- building and updating -------------------------------------------------------------------

def _fingerprints(embeddings: dict, given: dict | None) -> dict:
    """Given fingerprints, else those the embedding cache recorded in each Embeddings' meta."""
    return {n: (given or {}).get(n, getattr(e, "meta", {}).get("fingerprint")) for n, e in embeddings.items()}


def build_index(embeddings: dict, fingerprints: dict | None = None, config: IndexConfig | None = None) -> EpisodeIndex:
    """One index over {collection: Embeddings}, all of one space."""
    if not embeddings:
        raise ValueError("no embeddings to index")
    first = next(iter(embeddings.values()))
    index = EpisodeIndex.for_embeddings(first, config)
    fingerprints = _fingerprints(embeddings, fingerprints)
    for name, emb in tqdm(embeddings.items(), desc="indexing collections", disable=len(embeddings) < 10):
        index.add_embeddings(name, emb, fingerprints[name])
    return index


def update_index(path, embeddings: dict, fingerprints: dict | None = None, config: IndexConfig | None = None,
                 rebuild: bool = False) -> tuple[EpisodeIndex, dict]:
    """Bring the index at ``path`` to exactly the collections of ``embeddings``: new collections
    are added to the loaded index; a changed (fingerprint differs) or removed collection, or
    ``rebuild``, rebuilds it. Saves it and returns (index, {"added", "rebuilt", "unchanged"}).
    Fingerprints default to those the embedding cache recorded."""
    if not embeddings:
        raise ValueError("no embeddings to index")
    fingerprints = _fingerprints(embeddings, fingerprints)
    first = next(iter(embeddings.values()))
    path = Path(path)
    if rebuild or not (path / "meta.json").is_file():
        index = build_index(embeddings, fingerprints, config)
        return index, {"added": list(embeddings), "rebuilt": True, "unchanged": [], "path": str(index.save(path))}
    try:
        index = EpisodeIndex.load(path, model=first.model, kind=first.kind)
    except IndexMismatchError as e:
        raise IndexMismatchError(f"{e} (update_index(..., rebuild=True) replaces it)") from None
    stale = [n for n, c in index.collections.items()
             if n not in embeddings or c.get("fingerprint") != fingerprints.get(n)]
    if stale:
        log.info("rebuilding %s: collections changed or removed: %s", path, stale)
        return update_index(path, embeddings, fingerprints, config or index.config, rebuild=True)
    new = [n for n in embeddings if n not in index.collections]
    for name in new:
        index.add_embeddings(name, embeddings[name], fingerprints.get(name))
    if new:
        index.save(path)
    return index, {"added": new, "rebuilt": False, "unchanged": [n for n in embeddings if n not in new],
                   "path": str(path)}


# ---- re-ranking ------------------------------------------------------------------------------

def similarity(query, vectors, metric: str) -> np.ndarray:
    """Higher-is-closer similarity of one query vector to each row of ``vectors``."""
    q, v = np.asarray(query, np.float32).ravel(), np.atleast_2d(np.asarray(vectors, np.float32))
    if metric == "ip":
        return v @ q
    if metric == "l2":
        return -((v - q) ** 2).sum(axis=1)
    raise ValueError(f"unknown metric {metric!r}; valid: {', '.join(METRICS)}")


def rerank(query, candidates, metric: str, top: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Order candidate rows by similarity to ``query`` (e.g. obj/skill hits by camera/scene):
    (positions into candidates, best first, at most ``top``; their similarities)."""
    sim = similarity(query, candidates, metric)
    order = np.argsort(-sim, kind="stable")[:top]
    return order, sim[order]
