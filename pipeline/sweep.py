"""`nostra sweep [launcher=local|serial|slurm] <train overrides with comma-separated values>`: a Hydra
multirun of `nostra train` (launcher=local: submitit processes in parallel; serial: one job after
the other in this process, e.g. for time-budgeted runs on one machine; slurm: a job array), every
job's MLflow run grouped under one parent run, e.g.

    nostra sweep train.stage=finetune train.init_from=... train.num_demos=10,20,50 model=nostra,rssm,lstm

Settings that are not a grid: sweep over a node's values, each merged into it, e.g.
`model.loss={beta:1e-5},{beta:1e-2},{gamma:0.5}` (one setting varied at a time).

Resumable: by default the jobs land in data/runs/sweeps/<time stamp>/<job number>; with
`hydra.sweep.dir=<folder>` the same command continues in that folder, and with
`train.out_dir=...` / `train.run_name=...` (interpolations of the job's config, e.g.
`sweep-${model.loss.beta}`) wherever those say. A job that finished (its run.json) is kept
(train.skip_finished), one that was cut short resumes from its last.ckpt.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from pipeline import train as train_stage
from pipeline._hydra import run

DIR = "hydra.sweep.dir="


def main(argv: list[str]) -> int:
    from nostra.workflows.tracking import Tracker

    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        return run("sweep", ["--help"], train_stage._app)
    named = [a[len(DIR):] for a in argv if a.startswith(DIR)]
    # one folder per job inside: 0, 1, ... (multirun.yaml lists them)
    folder = named[-1] if named else f"data/runs/sweeps/{time.strftime('%Y-%m-%d_%H-%M-%S')}"
    argv = [a for a in argv if not a.startswith(DIR)]
    parent = Tracker("nostra", f"sweep-{Path(folder).name}", folder, {"overrides": " ".join(argv)},
                     tags={"sweep": "true"})
    overrides = [f"train.parent_run_id={parent.run_id}" if parent.run_id else "train.parent_run_id=null",
                 f"{DIR}{folder}", "train.out_dir=${hydra:sweep.dir}/${hydra:sweep.subdir}",
                 "train.run_name=sweep-${model.policy}-${hydra:job.num}", "train.progress=false",
                 "train.skip_finished=true"]
    # the jobs (Slurm: other processes, maybe other nodes and working dirs) track to the parent's store
    saved = os.environ.get("MLFLOW_TRACKING_URI")
    os.environ["MLFLOW_TRACKING_URI"] = parent.uri
    status = "FAILED"
    try:
        run("sweep", ["--multirun", *overrides, *argv], train_stage._app)  # the user's overrides win
        status = "FINISHED"
    finally:
        print(parent.finish(status))
        if saved is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = saved
    return 0
