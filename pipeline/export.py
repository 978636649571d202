"""`nostra export`: a store collection -> a robomimic HDF5 file that peers' tools read, or a
LeRobot v3.0 dataset that LeRobot's training reads.

    nostra export export.collection=lift export.path=lift_export.hdf5
    nostra export export.collection=lift export.format=lerobot
"""

from __future__ import annotations

import sys

from omegaconf import OmegaConf

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.data.errors import CollectionError, DataError
    from nostra.data.store import Store

    c = cfg.export
    if OmegaConf.is_missing(c, "collection"):
        have = Store(c.store).collections()
        print(f"nostra export: say which collection, export.collection=<name>; {c.store} has {have or 'none'}",
              file=sys.stderr)
        raise SystemExit(2)
    if c.format not in ("robomimic", "lerobot"):
        print(f"nostra export: export.format={c.format!r}; valid: robomimic, lerobot", file=sys.stderr)
        raise SystemExit(2)
    path = c.path or (f"{cfg.paths.data}/export/{c.collection}.hdf5" if c.format == "robomimic"
                      else f"{cfg.paths.data}/export/{c.collection}_lerobot")
    try:
        path = Store(c.store).export(c.collection, path, next_obs=c.next_obs, progress=c.progress, format=c.format,
                                     fps=c.fps)
    except (CollectionError, DataError) as e:
        print(f"nostra export: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    print(f"{c.collection} -> {path}")


def main(argv: list[str]) -> int:
    return run("export", argv, _app)
