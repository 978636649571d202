"""MLflow tracking that never loses results: every metric also goes to a local JSONL file, and if
the tracking backend fails mid-run the run goes on and says so at its end.

Tracking URI: ``MLFLOW_TRACKING_URI`` when set (a server), else an embedded sqlite file
``mlflow.db`` in the working directory."""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping

from lightning.pytorch.loggers import Logger
from lightning.pytorch.utilities import rank_zero_only

log = logging.getLogger(__name__)


def tracking_uri() -> str:
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{Path.cwd() / 'mlflow.db'}"


def _flat(params: Mapping, prefix: str = "") -> dict[str, str]:
    out = {}
    for k, v in params.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flat(v, f"{key}."))
        else:
            out[key] = str(v)[:6000]  # MLflow's param value limit
    return out


def global_rank() -> int:
    """This process's rank in a distributed run: torch.distributed's once its process group
    exists, else Lightning's (set from the launch environment, and by a Trainer when it is built)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank()
    return int(rank_zero_only.rank or 0)


class Tracker:
    """One MLflow run plus a local copy of everything logged to it.

    In a distributed run only global rank 0 tracks: on any other rank (``rank``, by default
    ``global_rank()``) the tracker is inert: no MLflow run, no local file, every call a no-op."""

    def __init__(self, experiment: str, run_name: str, local_dir: str | os.PathLike, params: Mapping | None = None,
                 tags: Mapping | None = None, parent_run_id: str | None = None, uri: str | None = None,
                 rank: int | None = None):
        self.local_dir = Path(local_dir)
        self.local_file = self.local_dir / "metrics.jsonl"
        self.uri, self.failure, self.run_id, self.client = uri or tracking_uri(), None, None, None
        self.rank = global_rank() if rank is None else int(rank)
        if not self.active:
            return
        self.local_dir.mkdir(parents=True, exist_ok=True)
        self._guard(self._start, experiment, run_name, dict(tags or {}), parent_run_id)
        self.log_params(params or {})

    @property
    def active(self) -> bool:
        return self.rank == 0

    def _start(self, experiment, run_name, tags, parent_run_id):
        from mlflow.tracking import MlflowClient

        self.client = MlflowClient(self.uri)
        exp = self.client.get_experiment_by_name(experiment)
        exp_id = exp.experiment_id if exp else self.client.create_experiment(experiment)
        if parent_run_id:
            tags["mlflow.parentRunId"] = parent_run_id
        self.run_id = self.client.create_run(exp_id, run_name=run_name, tags=tags).info.run_id

    def _guard(self, fn, *args) -> None:
        if self.failure is not None or not self.active:
            return
        try:
            fn(*args)
        except Exception as e:  # any backend error: keep training, keep the local copy
            self.failure = f"{type(e).__name__}: {e}"
            log.warning("MLflow tracking at %s failed (%s); metrics continue in %s", self.uri, self.failure,
                        self.local_file)

    def _local(self, record: dict) -> None:
        if not self.active:
            return
        with open(self.local_file, "a") as f:
            f.write(json.dumps(record, default=str) + "\n")

    def log_params(self, params: Mapping) -> None:
        flat = _flat(params)
        if not flat:
            return
        self._local({"params": flat})
        self._guard(lambda: self.client.log_batch(
            self.run_id, params=[_param(k, v) for k, v in flat.items()]))

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        metrics = {k: float(v) for k, v in metrics.items()}
        self._local({"step": step, "metrics": metrics})
        ts = int(time.time() * 1000)
        self._guard(lambda: self.client.log_batch(
            self.run_id, metrics=[_metric(k, v, ts, step or 0) for k, v in metrics.items()]))

    def log_artifact(self, path: str | os.PathLike) -> None:
        self._guard(lambda: self.client.log_artifact(self.run_id, str(path)))

    def finish(self, status: str = "FINISHED") -> str:
        if not self.active:
            return f"rank {self.rank}: rank 0 tracks this run"
        self._guard(lambda: self.client.set_terminated(self.run_id, status))
        if self.failure is None:
            return f"tracked in MLflow run {self.run_id} at {self.uri}"
        return (f"WARNING: MLflow tracking failed ({self.failure}); nothing is lost: all metrics are in "
                f"{self.local_file}")


def _param(k, v):
    from mlflow.entities import Param

    return Param(k, v)


def _metric(k, v, ts, step):
    from mlflow.entities import Metric

    return Metric(k, v, ts, step)


class TrackingLogger(Logger):
    """Lightning logger over a Tracker."""

    def __init__(self, tracker: Tracker | None = None):
        super().__init__()
        self.tracker = tracker  # may be set after the Trainer is built (its global rank picks the tracker)

    @property
    def name(self) -> str:
        return "mlflow"

    @property
    def version(self) -> str:
        return (self.tracker and self.tracker.run_id) or "local"

    @rank_zero_only
    def log_hyperparams(self, params: Any, *args, **kwargs) -> None:
        if self.tracker is not None:
            self.tracker.log_params({f"hparams.{k}": v for k, v in dict(params).items()})

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        if self.tracker is not None:
            self.tracker.log_metrics({k: v for k, v in metrics.items() if k != "epoch"}, step)


def search_runs(experiment: str, uri: str | None = None):
    """All runs of an experiment as a pandas DataFrame (empty when there is none)."""
    import mlflow
    import pandas as pd

    mlflow.set_tracking_uri(uri or tracking_uri())
    exp = mlflow.get_experiment_by_name(experiment)
    if exp is None:
        return pd.DataFrame()
    return mlflow.search_runs([exp.experiment_id])
