"""`nostra retrieve retrieval.target=<collection> retrieval.budget=N retrieval.mode=obj_skill|all`:
a manifest of co-training episodes (JSON) whose hash identifies the set everywhere."""

from __future__ import annotations

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.data.store import Store
    from retrieval.select import select, write_manifest

    r = cfg.retrieval
    manifest = select(Store(cfg.data.store), r.index_dir, r.target, r.budget, r.mode, r.candidates)
    digest = write_manifest(manifest, r.manifest)
    by = {}
    for e in manifest["episodes"]:
        by[e["collection"]] = by.get(e["collection"], 0) + 1
    print(f"{len(manifest['episodes'])} episodes by {r.mode} for {r.target} ({by}); manifest {r.manifest}, "
          f"hash {digest}")


def main(argv: list[str]) -> int:
    return run("retrieve", argv, _app)
