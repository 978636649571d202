"""One evaluation episode: a policy runner in a task, under a noise schedule, recording what
happened at every step (the episode engine of ``nostra.episode`` with the simulator as its
observation source). Also the worker-process side of parallel evaluation (one env and the
runners it needs, cached per process)."""

from __future__ import annotations

import os
import traceback
from dataclasses import dataclass, field

import numpy as np

from nostra import episode
from nostra.modality import FRONT_IMAGE, render_size
from nostra.noise import NoiseSchedule


@dataclass
class EpisodeJob:
    task: str
    noise: str
    variant: str
    checkpoint: str
    mode: str
    seed: int
    horizon: int
    windows: list
    noise_params: dict = field(default_factory=dict)
    image_size: int | None = None   # None: the checkpoint's (a value that disagrees with it fails the episode)
    video_path: str | None = None
    rnn_horizon: int | None = None  # the runner's state reset period (None: the checkpoint's)
    adamli: tuple = ()              # mode=adaptive: AdaMLI's thresholds as sorted (name, value) pairs


@dataclass
class EpisodeResult:
    job: EpisodeJob
    success: bool
    steps: int
    reason: str = ""          # why a failed episode failed when it was not the policy (crash, instability)
    record: dict = field(default_factory=dict)   # per-step arrays


def run_episode(env, runner, job: EpisodeJob) -> EpisodeResult:
    """Roll out until success or the horizon (robomimic's convention: stop at success)."""
    schedule = NoiseSchedule(job.noise, job.windows, job.noise_params)
    rng = np.random.default_rng([job.seed, 7])  # noise draws: the same for every variant
    if hasattr(runner, "seed"):  # a sampling policy (Diffusion Policy): its noise fixed by the episode, so
        runner.seed = job.seed   # a cell and an in-training check of one checkpoint roll out alike
    ep = episode.run(SimSource(env, job.seed), runner, schedule, job.mode, job.horizon, rng,
                     frame_key=FRONT_IMAGE if job.video_path else None)
    if ep.reason:
        return EpisodeResult(job, False, ep.steps, reason=ep.reason, record=ep.record())
    if ep.frames and ep.frames[0] is not None:
        _write_video(job.video_path, ep.frames)
    return EpisodeResult(job, ep.success, ep.steps, record=ep.record())


class SimSource:
    """The simulator as the episode engine's observation source (``nostra.episode``): scene noise is
    set up before the simulator step that renders the observation it affects."""

    def __init__(self, env, seed: int):
        self.env, self.seed = env, seed

    def reset(self, schedule, rng) -> dict:
        return self.env.reset(seed=self.seed)

    def unusable(self, obs: dict) -> str:
        if not all(np.isfinite(v).all() for v in obs.values() if v.dtype.kind == "f"):
            return "simulation became unstable (non-finite observation)"
        return ""

    def step(self, action, schedule, t: int, rng):
        schedule.prepare(self.env, t, rng)
        obs, _, _, info = self.env.step(np.clip(action, -1.0, 1.0))
        if _unstable(self.env):
            return obs, False, "MuJoCo instability (bad QACC: the simulation diverged)"
        return obs, bool(info["success"]), ""

    def close(self, schedule, t: int) -> None:
        schedule.close(self.env, t)

    def objects(self) -> dict:
        """Where the task's objects are now (recorded each step: a missed grasp or a drop shows); none from
        an env that does not say."""
        return self.env.object_positions() if hasattr(self.env, "object_positions") else {}


def _unstable(env) -> bool:
    import mujoco

    return env.data.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0


def _write_video(path: str, frames: list) -> None:
    import imageio.v3 as iio

    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    iio.imwrite(path, np.stack(frames), plugin="pyav", codec="libx264", fps=20)


# ---- worker process side -------------------------------------------------------------------
_ENVS: dict = {}
_RUNNERS: dict = {}


def init_worker(threads: int, render_threads: int | None = None) -> None:
    import torch

    torch.set_num_threads(max(1, threads))
    if render_threads:  # Mesa's llvmpipe renders with one thread per core unless told otherwise
        os.environ["LP_NUM_THREADS"] = str(render_threads)


def work(job: EpisodeJob) -> EpisodeResult:
    """Run one job in this process; any error becomes a failed episode with its reason."""
    size = None
    try:
        runner = _runner(job.checkpoint, job.mode, job.rnn_horizon, job.adamli)
        size = render_size(runner.net.modalities, job.image_size)
        env = _env(job.task, size)
        return run_episode(env, runner, job)
    except Exception as e:  # the evaluation goes on: this episode failed, with why
        _ENVS.pop((job.task, size), None)  # the env may be in a broken state
        reason = f"{type(e).__name__}: {e}"
        return EpisodeResult(job, False, 0, reason=reason, record={"traceback": traceback.format_exc()})


def _env(task: str, image_size: int):
    from nostra.sim.env import make_env

    key = (task, image_size)
    if key not in _ENVS:
        _ENVS[key] = make_env(task, image_size=image_size)
    return _ENVS[key]


def _runner(checkpoint: str, mode: str, rnn_horizon: int | None = None, adamli: tuple = ()):
    from nostra.policies.checkpoint import load_runner

    key = (checkpoint, mode, rnn_horizon, adamli)
    if key not in _RUNNERS:
        kwargs = {"adaptive": True, "adamli": dict(adamli)} if mode == "adaptive" else {}
        if rnn_horizon is not None:
            kwargs["rnn_horizon"] = rnn_horizon
        _RUNNERS[key] = load_runner(checkpoint, **kwargs)
    return _RUNNERS[key]
