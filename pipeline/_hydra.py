"""Running a stage as a Hydra app from `nostra <stage> [overrides]`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import hydra
from omegaconf import OmegaConf

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def _if_gpus(gpus, with_gpus, without):
    """${nostra.if_gpus:<gpus>,<value with GPUs>,<value without>} (conf/launcher/slurm.yaml)."""
    return with_gpus if int(gpus or 0) > 0 else without


def _gpus_per_node(gpus, gres):
    """--gpus-per-node: none for a CPU job, nor when a gpu --gres already asks for the GPUs."""
    return None if int(gpus or 0) <= 0 or "gpu" in str(gres or "") else int(gpus)


OmegaConf.register_new_resolver("nostra.if_gpus", _if_gpus, replace=True)
OmegaConf.register_new_resolver("nostra.gpus_per_node", _gpus_per_node, replace=True)


def run(stage: str, argv: list[str], fn: Callable, config_name: str = "config") -> int:
    """Hydra reads sys.argv, so the stage's own arguments are put there (this keeps --cfg job,
    --help and --multirun working exactly as for any Hydra app)."""
    saved = sys.argv
    sys.argv = [f"nostra {stage}", *argv]
    try:
        hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)(fn)()
    finally:
        sys.argv = saved
    return 0
