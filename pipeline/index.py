"""`nostra index [retrieval.collections=[...]]`: embed every collection of the store (or those
listed: the pool retrieval draws from; cached beside the store) and update the faiss indices; new
collections are added, changed ones rebuilt, unchanged ones left alone."""

from __future__ import annotations

import json

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.data.store import Store
    from retrieval.select import index_store

    store = Store(cfg.data.store)
    if not store.collections():
        raise SystemExit(f"nostra index: the store {store.path} holds no collection; run `nostra ingest` first")
    collections = cfg.retrieval.collections
    summary = index_store(store, cfg.retrieval.index_dir, cfg.retrieval.progress,
                          list(collections) if collections is not None else None)
    print(json.dumps({"index_dir": cfg.retrieval.index_dir, **summary}))


def main(argv: list[str]) -> int:
    return run("index", argv, _app)
