"""Running a stage as a Hydra app from `nostra <stage> [overrides]`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import hydra

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


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
