"""Rollouts during training (robomimic's habit): every ``every`` steps the policy as it stands is
saved as ``checkpoints/step=<n>.ckpt`` and rolled out in the simulator on fixed seeds that no demo
used, through the evaluation code (``nostra.workflows.evaluation.run_jobs``: the same episode loop, worker
processes and noise schedules as ``nostra evaluate``), at the image size the policy trains on (the
checkpoint's modalities say it; no config repeats it). Success goes to MLflow as
``rollout/<task>/<noise>/<variant>`` at that step; the checkpoint with the best success on the
first noise and variant (clean, closed loop by default) is copied to ``checkpoints/best.ckpt``.
Early checks use few episodes, the one at the end of training ``final_episodes``, so rollouts stay
a small share of the wall time; ``rollouts.json`` lists every check with its cost and horizon.
A run resumed at another horizon (``train.rollout.horizon``) keeps the earlier checks in the log,
but picks its best, and skips a step already checked, only among the checks at its own horizon:
success at 200 steps and at 400 are not one score (rows from before horizons were logged count as
the current horizon's, as they did then).

Under DDP every rank saves the checkpoint (a collective call; rank 0 writes it), rank 0 alone
runs the rollouts, logs and writes, and the other ranks wait in a barrier, for at most the
process group's timeout (``train.dist_timeout_minutes``, 6 h by default; Lightning's 30 min
would be too short for a long final check), then take rank 0's row of results.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import lightning as L

from nostra.configs import RolloutConfig
from nostra.workflows.variants import MODES

# variant id suffix of each imagination mode, as in the evaluation tables (nostra_mli, rssm_li, ...)
SUFFIX = {"closed": "", "oracle": "_mli", "adaptive": "_adamli"}


@dataclass
class RolloutEnv:
    """Where the rollouts run, as `nostra evaluate` runs them: the task, the noise windows per task
    (the task's own when absent) and the noise parameters; images render at the checkpoint's size."""
    task: str
    windows: dict = field(default_factory=dict)
    noise_params: dict = field(default_factory=dict)


def _check(cfg: RolloutConfig, env: RolloutEnv, policy: str, can_imagine: bool) -> None:
    from nostra.noise import check_noise
    from nostra.sim.tasks import get_task

    get_task(env.task)
    for n in cfg.noises:
        check_noise(n)
    bad = [m for m in cfg.modes if m not in MODES]
    if bad:
        raise ValueError(f"train.rollout.modes: unknown {bad}; valid: {', '.join(MODES)}")
    if not can_imagine and set(cfg.modes) - {"closed"}:
        raise ValueError(f"train.rollout.modes={cfg.modes}: a '{policy}' policy cannot imagine; use [closed]")
    if cfg.every < 0 or cfg.episodes < 1 or cfg.final_episodes < 0:
        raise ValueError(f"train.rollout needs every >= 0, episodes >= 1, final_episodes >= 0; got {asdict(cfg)}")


def variant_id(policy: str, mode: str) -> str:
    suffix = "_li" if (policy, mode) == ("rssm", "oracle") else SUFFIX[mode]
    return policy + suffix


class RolloutCallback(L.Callback):
    def __init__(self, cfg: RolloutConfig, env: RolloutEnv, policy: str, out_dir: str | Path, can_imagine: bool):
        from nostra.sim.tasks import get_task

        _check(cfg, env, policy, can_imagine)
        self.cfg, self.env, self.policy, self.out = cfg, env, policy, Path(out_dir)
        self.task = get_task(env.task)
        self.log_path = self.out / "rollouts.json"
        self.history: list[dict] = json.loads(self.log_path.read_text()) if self.log_path.is_file() else []
        self.horizon = cfg.horizon or self.task.horizon
        self.best = max((h["score"] for h in self._comparable()), default=-1.0)
        self.started = time.time()

    # ---- hooks -----------------------------------------------------------------------------
    def on_fit_start(self, trainer, pl_module):
        from nostra.workflows.evaluation import check_renderable

        try:  # before any training, not at the first check
            check_renderable(pl_module.net.modalities)
        except ValueError as e:
            raise ValueError(f"train.rollout: the simulator cannot feed this policy: {e}") from None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        step = trainer.global_step
        if self.cfg.every and step % self.cfg.every == 0 and not self._done(step):
            self.check(trainer, self.cfg.episodes)

    def on_train_end(self, trainer, pl_module):
        if self.cfg.final_episodes and not self._done(trainer.global_step, self.cfg.final_episodes):
            self.check(trainer, self.cfg.final_episodes)

    # ---- one check -------------------------------------------------------------------------
    def check(self, trainer, episodes: int) -> dict:
        from nostra.workflows.evaluation import run_jobs, task_windows, wilson
        from nostra.sim.rollout import EpisodeJob

        step, start = trainer.global_step, time.time()
        path = self.out / "checkpoints" / f"step={step}.ckpt"
        trainer.save_checkpoint(path)  # collective under DDP: every rank calls it, rank 0 writes
        row = {"step": step, "episodes": episodes, "horizon": self.horizon, "checkpoint": path.name, "success": {}}
        if trainer.is_global_zero:
            cells = [(n, m) for n in self.cfg.noises for m in self.cfg.modes]
            windows = task_windows(self.env.windows, self.task.name, self.task)
            jobs = [EpisodeJob(self.task.name, n, variant_id(self.policy, m), str(path), m, self.cfg.seed + i,
                               self.horizon, windows, dict(self.env.noise_params))
                    for n, m in cells for i in range(episodes)]
            results = run_jobs(jobs, self.cfg.workers, progress=False)
            metrics = {}
            for n, m in cells:
                v = variant_id(self.policy, m)
                ok = [r.success for r in results if (r.job.noise, r.job.variant) == (n, v)]
                rate = sum(ok) / len(ok)
                metrics[f"rollout/{self.task.name}/{n}/{v}"] = rate
                row["success"][f"{n}/{v}"] = {"rate": rate, "ci": list(wilson(sum(ok), len(ok))),
                                              "errors": sum(bool(r.reason) for r in results
                                                            if (r.job.noise, r.job.variant) == (n, v))}
            row["score"] = metrics[f"rollout/{self.task.name}/{cells[0][0]}/{variant_id(self.policy, cells[0][1])}"]
            row["seconds"] = round(time.time() - start, 1)
            row["wall_seconds"] = round(time.time() - self.started, 1)
            if row["score"] >= self.best:  # ties go to the later, longer-trained checkpoint
                shutil.copyfile(path, self.out / "checkpoints" / "best.ckpt")
                row["best"] = True
            for logger in trainer.loggers:
                logger.log_metrics({**metrics, "rollout/seconds": row["seconds"]}, step=step)
            self.log_path.write_text(json.dumps(self.history + [row], indent=2))
            print(f"rollouts at step {step}: " + ", ".join(f"{k} {v['rate']:.0%}" for k, v in row["success"].items())
                  + f" ({episodes} episodes, {row['seconds']:.0f} s)" + (" best" if row.get("best") else ""))
        # under DDP the other ranks wait here for rank 0's rollouts (the process group's timeout is
        # train.dist_timeout_minutes), then take its row: every rank keeps the same history, so
        # all of them make the same decisions in _done() and enter the collective calls together
        trainer.strategy.barrier("rollouts")
        row = trainer.strategy.broadcast(row, src=0)
        self.history.append(row)
        self.best = max(self.best, row["score"])
        return row

    def _done(self, step: int, episodes: int | None = None) -> bool:
        """Already checked at this step (a resumed run), with at least this many episodes."""
        return any(h["step"] == step and h["episodes"] >= (episodes or 0) for h in self._comparable())

    def _comparable(self) -> list[dict]:
        """The checks at this run's horizon (a row without one predates the key: taken as this horizon's)."""
        return [h for h in self.history if h.get("horizon", self.horizon) == self.horizon]

    def summary(self) -> dict:
        """Rollout cost against the wall time of the run, and the best and last checks."""
        spent = sum(h.get("seconds", 0) for h in self.history)
        best = max(self._comparable(), key=lambda h: (h["score"], h["step"]), default=None)
        return {"rollout_seconds": round(spent, 1), "checks": len(self.history), "horizon": self.horizon,
                "best": best and {"step": best["step"], "score": best["score"], "episodes": best["episodes"]},
                "last": self.history[-1] if self.history else None}
