"""`nostra ingest`: robomimic HDF5 / LeRobot v2.x, v3 / diffusion_policy zarr -> collections of the zarr store.

    nostra ingest ingest.sources=[data/raw/lift.hdf5]
    nostra ingest ingest.sources=[path/to/lerobot_ds] ingest.name=so100 ingest.metadata.task=Lift
"""

from __future__ import annotations

import sys

from omegaconf import OmegaConf

from pipeline._hydra import run


def _container(node):
    return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node


def _app(cfg) -> None:
    from nostra.data.errors import DataError
    from nostra.data.store import Store

    c = cfg.ingest
    sources = [c.sources] if isinstance(c.sources, str) else list(c.sources or [])
    if not sources:
        print("nostra ingest: no sources given; pass ingest.sources=[path,...]", file=sys.stderr)
        raise SystemExit(2)
    store = Store(c.store)
    batches = [sources] if c.name else [[s] for s in sources]
    try:
        for batch in batches:
            name = store.ingest(batch, name=c.name, fmt=c.format, key_map=_container(c.key_map),
                                keys=_container(c["keys"]), defaults=_container(c.metadata), progress=c.progress,
                                float32=bool(c.float32), next_obs=bool(c.next_obs), render=bool(c.render),
                                render_size=int(c.render_size))
            info = store.info(name)
            print(f"{name}: {info['num_episodes']} episodes, {info['num_steps']} steps, keys "
                  f"{store.keys(name)} in {store.path}")
            for demo, err in (info.get("source_attrs", {}).get("replay_divergence") or {}).items():
                print(f"  {demo}: replaying its actions diverges from the recorded states by {err:.4g} at most")
    except DataError as e:
        print(f"nostra ingest: {e}", file=sys.stderr)
        raise SystemExit(1) from None


def main(argv: list[str]) -> int:
    return run("ingest", argv, _app)
