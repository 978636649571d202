"""`nostra <stage> [hydra overrides]`: one console script dispatching to the pipeline stages."""

from __future__ import annotations

import importlib
import importlib.util
import sys

# stage -> (what it does, issue that delivers it)
STAGES = {
    "generate": ("collect scripted-expert demos in robosuite into robomimic HDF5", 3),
    "ingest": ("read robomimic HDF5 / LeRobot v3 / diffusion_policy zarr into the zarr store", 3),
    "export": ("write a store collection back to robomimic HDF5", 3),
    "index": ("embed episodes and build faiss indices", 5),
    "retrieve": ("select a co-training subset into a manifest", 5),
    "train": ("pretrain / finetune / cotrain a policy with Lightning", 5),
    "evaluate": ("rollouts under the noise suite and offline KL / detection analyses", 4),
    "report": ("the paper's tables and figures from MLflow", 6),
    "compare": ("Table 4 / 5 analogues from MLflow", 5),
    "sweep": ("Hydra multirun through submitit (local or Slurm)", 6),
}


def usage() -> str:
    width = max(map(len, STAGES))
    lines = ["usage: nostra <stage> [hydra overrides]   (nostra <stage> --help for a stage's options)", "", "stages:"]
    for name, (what, _) in STAGES.items():
        note = "" if _implemented(name) else "  [not implemented yet]"
        lines.append(f"  {name:<{width}}  {what}{note}")
    return "\n".join(lines)


def _implemented(stage: str) -> bool:
    return importlib.util.find_spec(f"pipeline.{stage}") is not None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    stage, rest = argv[0], argv[1:]
    if stage not in STAGES:
        print(f"nostra: unknown stage {stage!r}; valid stages: {', '.join(STAGES)}", file=sys.stderr)
        return 2
    if not _implemented(stage):
        print(f"nostra {stage}: not implemented yet (tracked in issue {STAGES[stage][1]})", file=sys.stderr)
        return 2
    return importlib.import_module(f"pipeline.{stage}").main(rest) or 0


if __name__ == "__main__":
    sys.exit(main())
