"""`nostra export`: a store collection -> a robomimic HDF5 file that peers' tools read.

    nostra export export.collection=lift export.path=lift_export.hdf5
"""

from __future__ import annotations

import sys

from omegaconf import OmegaConf

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.data.errors import CollectionError
    from nostra.data.store import Store

    c = cfg.export
    if OmegaConf.is_missing(c, "collection"):
        have = Store(c.store).collections()
        print(f"nostra export: say which collection, export.collection=<name>; {c.store} has {have or 'none'}",
              file=sys.stderr)
        raise SystemExit(2)
    try:
        path = Store(c.store).export(c.collection, c.path, next_obs=c.next_obs, progress=c.progress)
    except CollectionError as e:
        print(f"nostra export: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    print(f"{c.collection} -> {path}")


def main(argv: list[str]) -> int:
    return run("export", argv, _app)
