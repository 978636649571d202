"""Data-parallel training (DDP) for ``nostra.workflows.training.train``, on CPUs (gloo) or GPUs (NCCL).

``train.trainer={accelerator: cpu, devices: 2, strategy: ddp}`` (or ``gpu`` with N devices) runs
N processes, one per device. Each builds the same model and loader; the loader's sampler shards
itself by rank (``nostra.data.dataset.ShardedSampler``), gradients are averaged across ranks, so
N ranks with batch B train like one process with batch N*B. Only global rank 0 tracks (one MLflow
run), writes ``metrics.jsonl``, ``run.json``, checkpoints and runs the in-training rollouts.

Lightning's own launcher for ``strategy: ddp`` starts the other ranks by re-running the command
line (``sys.argv``). That fails for ``nostra train`` (a Hydra app behind a console script), for
``python -m pipeline.cli train``, pytest and notebooks, so a DDP strategy named by a string is
built here with a launcher that starts each other rank as ``python -m nostra.workflows.ddp <spec.json>``:
the same ``train()`` call, whatever started rank 0. Where processes are created outside (Slurm's
``srun`` with one task per device, ``torchrun``), nothing is launched and Lightning's cluster
environment gives the ranks.

The process group gets a long timeout (``train.dist_timeout_minutes``): while rank 0 runs
the in-training rollouts (minutes), the other ranks wait in a barrier, and the default 30 minutes
would kill them on a long check.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.strategies import DDPStrategy, StrategyRegistry
from lightning.pytorch.strategies.launchers.subprocess_script import _SubprocessScriptLauncher
from lightning.pytorch.utilities import rank_zero_warn

# the directory holding the nostra package: children import the same code as rank 0
_CODE_ROOT = str(Path(__file__).resolve().parents[2])
_ENV_KEYS = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE")


class _SpecLauncher(_SubprocessScriptLauncher):
    """Lightning's subprocess launcher, starting ranks 1.. as ``python -m nostra.workflows.ddp <spec.json>``
    instead of re-running sys.argv (environment, process observer and the rest as Lightning's)."""

    def __init__(self, cluster_environment, num_processes: int, num_nodes: int, spec: dict, spec_file: Path):
        super().__init__(cluster_environment, num_processes, num_nodes)
        self.spec, self.spec_file = spec, Path(spec_file)

    def _call_children_scripts(self) -> None:
        self._check_can_spawn_children()
        self.procs = []
        os.environ["MASTER_ADDR"] = self.cluster_environment.main_address
        os.environ["MASTER_PORT"] = str(self.cluster_environment.main_port)
        os.environ["NODE_RANK"] = str(self.cluster_environment.node_rank())
        os.environ["LOCAL_RANK"] = str(self.cluster_environment.local_rank())
        os.environ["WORLD_SIZE"] = f"{self.num_processes * self.num_nodes}"
        if self.num_processes > 1:  # what the other ranks run: train() on this spec
            self.spec_file.parent.mkdir(parents=True, exist_ok=True)
            self.spec_file.write_text(json.dumps(self.spec, indent=2))
        env = os.environ.copy()
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_CODE_ROOT, env.get("PYTHONPATH")) if p)
        if os.environ.get("PL_GLOBAL_SEED") is None:
            env.pop("PL_GLOBAL_SEED", None)
        for local_rank in range(1, self.num_processes):
            env["LOCAL_RANK"] = str(local_rank)
            cmd = [sys.executable, "-m", "nostra.workflows.ddp", str(self.spec_file.resolve())]
            self.procs.append(subprocess.Popen(cmd, env=dict(env)))


class NostraDDP(DDPStrategy):
    """DDPStrategy whose local launcher starts the other ranks through ``nostra.workflows.ddp``."""

    def __init__(self, spec: dict, spec_file: Path, **kwargs):
        super().__init__(**kwargs)
        self._spec, self._spec_file = spec, spec_file

    def _configure_launcher(self) -> None:
        super()._configure_launcher()
        if type(self._launcher) is _SubprocessScriptLauncher:
            self._launcher = _SpecLauncher(self.cluster_environment, self.num_processes, self.num_nodes,
                                           self._spec, self._spec_file)


def trainer_kwargs(kwargs: dict, spec: dict, spec_file: Path, timeout_minutes: float) -> dict:
    """``train.trainer`` for lightning.Trainer: a DDP strategy named by a string ('ddp',
    'ddp_find_unused_parameters_true', 'ddp_spawn', ...) becomes a DDPStrategy with the long
    process-group timeout ('ddp' and its popen variants with nostra's launcher); Lightning must
    not swap our rank-aware samplers for its DistributedSampler (use_distributed_sampler=False)."""
    kwargs = dict(kwargs)
    kwargs.setdefault("use_distributed_sampler", False)
    name = kwargs.get("strategy")
    if isinstance(name, str) and name in StrategyRegistry and StrategyRegistry[name]["strategy"] is DDPStrategy:
        params = {**StrategyRegistry[name]["init_params"], "timeout": timedelta(minutes=timeout_minutes)}
        if params.get("start_method", "popen") == "popen":
            kwargs["strategy"] = NostraDDP(spec, spec_file, **params)
        else:
            kwargs["strategy"] = DDPStrategy(**params)
    return kwargs


def make_trainer(kwargs: dict, spec: dict, spec_file: Path, timeout_minutes: float) -> L.Trainer:
    """lightning.Trainer(**kwargs) through trainer_kwargs; when Lightning itself picks DDP for
    several devices (strategy 'auto'), the same as strategy='ddp' (nostra's launcher and timeout)."""
    trainer = L.Trainer(**trainer_kwargs(kwargs, spec, spec_file, timeout_minutes))
    if (kwargs.get("strategy", "auto") == "auto" and type(trainer.strategy) is DDPStrategy
            and type(trainer.strategy.launcher) is _SubprocessScriptLauncher):
        trainer = L.Trainer(**trainer_kwargs({**kwargs, "strategy": "ddp"}, spec, spec_file, timeout_minutes))
    return trainer


@contextmanager
def session():
    """Leaves the calling process as it found it: the DDP environment variables the launcher sets
    and a process group created meanwhile are undone (a later train() in the same process, a test
    session or a sweep's local jobs, starts clean)."""
    saved = {k: os.environ.get(k) for k in _ENV_KEYS}
    had_group = torch.distributed.is_available() and torch.distributed.is_initialized()
    try:
        yield
    finally:
        if not had_group and torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _digest(tensors) -> int:
    h = hashlib.blake2b(digest_size=8)
    for t in tensors:
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return int.from_bytes(h.digest(), "little", signed=True)


class ReplicaCheck(L.Callback):
    """Under DDP, what training relies on, checked on every rank and reported by rank 0 (in
    run.json): the ranks' first batches differ (the samplers shard), and at the end every rank
    holds the same weights and buffers (Diffusion Policy's EMA copy included). A mismatch warns."""

    def __init__(self):
        self.report: dict = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if "distinct_first_batches" in self.report or trainer.world_size < 2:
            return
        mine = _digest([batch["actions"], *(batch["obs"][k] for k in sorted(batch["obs"]))])
        every = trainer.strategy.all_gather(torch.tensor([mine], device=pl_module.device)).flatten().tolist()
        self.report["distinct_first_batches"] = len(set(every)) == len(every)
        if not self.report["distinct_first_batches"]:
            rank_zero_warn("DDP: some ranks drew the same first batch; the loader's sampler does not shard by rank")

    def on_train_end(self, trainer, pl_module) -> None:
        if trainer.world_size < 2:
            return
        state = pl_module.state_dict()
        names = sorted(state)
        mine = torch.tensor([_digest([state[n]]) for n in names], device=pl_module.device)
        every = trainer.strategy.all_gather(mine).reshape(trainer.world_size, len(names))
        differ = [n for i, n in enumerate(names) if not bool((every[:, i] == every[0, i]).all())]
        self.report.update(world_size=trainer.world_size, replicas_identical=not differ,
                           compared=sorted({n.split('.')[0] for n in names}))  # net, ema_net, ...
        if differ:
            self.report["differing"] = differ[:20]
            rank_zero_warn(f"DDP: the ranks' weights differ at the end of training: {differ[:20]}")


def main(argv: list[str] | None = None) -> None:
    """A rank started by _SpecLauncher: ``python -m nostra.workflows.ddp <spec.json>``."""
    from nostra.workflows.training import TrainSpec, train

    argv = sys.argv[1:] if argv is None else argv
    train(TrainSpec.from_dict(json.loads(Path(argv[0]).read_text())))


if __name__ == "__main__":
    main()
