"""`nostra sweep [launcher=local|slurm] <train overrides with comma-separated values>`: a Hydra
multirun of `nostra train` through the submitit launcher, every job's MLflow run grouped under
one parent run, e.g.

    nostra sweep train.stage=finetune train.init_from=... train.num_demos=10,20,50 model=nostra,rssm,lstm
"""

from __future__ import annotations

import os
import time

from pipeline import train as train_stage
from pipeline._hydra import run


def main(argv: list[str]) -> int:
    from nostra.workflows.tracking import Tracker

    if any(a in ("-h", "--help") for a in argv):
        print(__doc__)
        return run("sweep", ["--help"], train_stage._app)
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    folder = f"data/runs/sweeps/{stamp}"  # one folder per job inside: 0, 1, ... (multirun.yaml lists them)
    parent = Tracker("nostra", f"sweep-{stamp}", folder, {"overrides": " ".join(argv)}, tags={"sweep": "true"})
    overrides = [f"train.parent_run_id={parent.run_id}" if parent.run_id else "train.parent_run_id=null",
                 f"hydra.sweep.dir={folder}", "train.out_dir=${hydra:sweep.dir}/${hydra:sweep.subdir}",
                 "train.run_name=sweep-${model.policy}-${hydra:job.num}", "train.progress=false"]
    # the jobs (Slurm: other processes, maybe other nodes and working dirs) track to the parent's store
    saved = os.environ.get("MLFLOW_TRACKING_URI")
    os.environ["MLFLOW_TRACKING_URI"] = parent.uri
    status = "FAILED"
    try:
        run("sweep", ["--multirun", *overrides, *argv], train_stage._app)
        status = "FINISHED"
    finally:
        print(parent.finish(status))
        if saved is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = saved
    return 0
