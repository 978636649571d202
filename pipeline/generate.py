"""`nostra generate task=lift [generate.episodes=50 generate.workers=2 generate.variation.occluded=1.0 ...]`:
scripted-expert demos into a robomimic HDF5 collection (conf/generate/default.yaml)."""

from __future__ import annotations

import json
import sys

from omegaconf import OmegaConf

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.sim.generate import GenerateConfig, generate

    c = OmegaConf.to_container(cfg.generate, resolve=True)
    progress = bool(c.pop("progress", True))
    c.pop("collection", None)  # only used to build `out`
    try:
        gen_cfg = GenerateConfig(task=cfg.task.name, **c)
    except (TypeError, ValueError) as e:
        print(f"nostra generate: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    summary = generate(gen_cfg, progress=progress)
    if summary["failed"]:
        print(f"nostra generate: dropped {summary['failed']} failed expert episodes of {summary['attempts']}",
              file=sys.stderr)
    if summary["demos"] < gen_cfg.episodes:
        print(f"nostra generate: only {summary['demos']} of {gen_cfg.episodes} demos succeeded within "
              f"{summary['attempts']} attempts", file=sys.stderr)
    print(json.dumps(summary))


def main(argv: list[str]) -> int:
    return run("generate", argv, _app)
