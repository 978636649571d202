"""Scripted-expert demonstrations in robomimic's HDF5 layout, collected by parallel workers.

Layout written (robomimic's, plus the episode metadata of the contract as demo attributes)::

    data                attrs: total, env_args (JSON: env_name, env_version, type=1, env_kwargs)
    data/demo_N         attrs: num_samples, model_file (MJCF), task, language, skill, objects,
                               camera_pose, object_placements, variation (JSON strings), success, seed
      states (N, D)     flattened MuJoCo state before each action
      actions (N, 7)    rewards (N,)    dones (N,)
      obs/<key>         observation before each action;  next_obs/<key>: after it
    mask/train, mask/valid   demo names (byte strings)

Noise-injected demonstrations (``action_noise`` > 0): Gaussian noise is added to the action the
robot executes (clipped to [-1, 1]), so demos visit states slightly off the expert's path
(``action_noise_phases``: only while the expert's script is in one of those phases, e.g. ``[approach]``);
``record="executed"`` stores the noisy executed action (MimicGen), ``record="expert"`` the expert's
clean action at those states, i.e. its correction (DART). Episodes whose expert fails are dropped
and counted. The file is written under a temporary name
and renamed when complete, so an interrupted run leaves no partial file behind.

The file is bit-reproducible: the same config, code and machine write the same bytes. It holds no
creation times (h5py's ``track_times=False``), no wall-clock values, and ``model_file`` names the
robosuite assets relative to the package (``robosuite/models/assets/...``, which robosuite's
``edit_model_xml`` resolves against the local install, as it does for robomimic's files) rather than
by the absolute path of the installation that generated it.
"""

from __future__ import annotations

import os
import re
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Callable, Iterator, Mapping

import numpy as np
from tqdm import tqdm

from nostra.data.episode import Episode
from nostra.data.formats import robomimic_hdf5
from nostra.sim.env import make_env, robomimic_env_args, robosuite_kwargs
from nostra.sim.experts import PHASES, make_expert
from nostra.sim.tasks import get_task
from nostra.sim.variations import Variation, sample_variation

RECORDS = ("executed", "expert")  # which action a noise-injected demo stores


@dataclass
class GenerateConfig:
    task: str
    out: str
    episodes: int = 20  # successful demos wanted
    workers: int = 2
    image_size: int = 84
    depth: bool = True
    tuned_render: bool = True
    seed_offset: int = 0
    max_steps: int | None = None  # None: the task's horizon
    steps_after_success: int = 10
    max_attempts_factor: float = 2.0  # give up after episodes * factor attempts
    valid_fraction: float = 0.1
    variation: Mapping = field(default_factory=dict)  # ranges, see variations.RANGE_KEYS
    action_noise: float = 0.0  # std of the Gaussian noise on the executed action
    record: str = "executed"  # which action the demo stores: executed | expert
    action_noise_phases: list[str] = field(default_factory=list)  # the expert's phases noised; empty: every step

    def __post_init__(self):
        get_task(self.task)  # unknown task -> ValueError listing the valid ones
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not 0.0 <= self.valid_fraction < 1.0:
            raise ValueError(f"valid_fraction must be in [0, 1), got {self.valid_fraction}")
        sample_variation(self.variation, np.random.default_rng(0))  # bad ranges fail before any work
        if self.record not in RECORDS:
            raise ValueError(f"generate.record={self.record!r} unknown; valid: {', '.join(RECORDS)}")
        if not self.action_noise >= 0:
            raise ValueError(f"generate.action_noise must be >= 0, got {self.action_noise}")
        unknown = [p for p in self.action_noise_phases if p not in PHASES]
        if unknown:
            raise ValueError(f"generate.action_noise_phases: unknown phase(s) {unknown}; the experts' phases: "
                             f"{', '.join(PHASES)}")


# ---- one episode -------------------------------------------------------------------------------

def run_episode(env, expert, seed: int, variation: Variation | None = None, max_steps: int | None = None,
                steps_after_success: int = 10, action_noise: float = 0.0, record: str = "executed",
                noise_phases: tuple[str, ...] = ()) -> dict:
    """Roll the expert out; stop `steps_after_success` steps after the task first succeeds.
    With `action_noise`, the executed action is perturbed (seeded by the episode's seed), with
    `noise_phases` only while the expert is in one of them (the draws stay those of every step)."""
    obs = env.reset(seed=seed, variation=variation)
    expert.reset()
    rng = np.random.default_rng([seed, 11])
    max_steps = max_steps or env.spec.horizon
    frames, states, actions, rewards = [obs], [], [], []
    succeeded_at = None
    for t in range(max_steps):
        states.append(env.sim_state())
        action = np.asarray(expert.act(obs), dtype=np.float64)
        executed = action
        if action_noise > 0:
            noise = rng.normal(0.0, action_noise, action.shape)
            if not noise_phases or expert.phase in noise_phases:
                executed = np.clip(action + noise, -1.0, 1.0)
        obs, reward, done, info = env.step(executed)
        frames.append(obs)
        actions.append(executed if record == "executed" else action)
        rewards.append(reward)
        if info["success"] and succeeded_at is None:
            succeeded_at = t
        if done or (succeeded_at is not None and t >= succeeded_at + steps_after_success):
            break
    meta = env.metadata()
    meta["success"] = bool(succeeded_at is not None and meta["success"])
    n = len(actions)
    return {
        "meta": meta, "model_file": portable_model_xml(env.model_xml()),
        "obs": {k: np.stack([f[k] for f in frames]) for k in frames[0]},
        "states": np.stack(states), "actions": np.stack(actions).astype(np.float32),
        "rewards": np.asarray(rewards, dtype=np.float32), "dones": (np.arange(n) == n - 1).astype(np.uint8),
    }


def portable_model_xml(xml: str) -> str:
    """The MJCF with robosuite's asset files named from the package directory on
    (``file="robosuite/models/assets/..."``) instead of this installation's absolute path, so the
    demos do not depend on where the environment was installed."""
    import robosuite

    root = os.path.dirname(os.path.abspath(robosuite.__file__))
    return re.sub(r'(\bfile=")' + re.escape(root) + "/", r"\1robosuite/", xml)


# ---- workers -------------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(cfg: GenerateConfig) -> None:
    env = make_env(cfg.task, image_size=cfg.image_size, depth=cfg.depth, tuned_render=cfg.tuned_render,
                   seed=cfg.seed_offset)
    _WORKER.update(env=env, expert=make_expert(env), cfg=cfg)


def _episode_job(job: tuple[int, dict]) -> dict:
    seed, variation = job
    cfg = _WORKER["cfg"]
    return run_episode(_WORKER["env"], _WORKER["expert"], seed, Variation.from_dict(variation), cfg.max_steps,
                       cfg.steps_after_success, cfg.action_noise, cfg.record, tuple(cfg.action_noise_phases))


def _jobs(cfg: GenerateConfig) -> Iterator[tuple[int, dict]]:
    """(seed, variation) per attempt; the variation is drawn from the seed, so reruns match."""
    attempts = int(np.ceil(cfg.episodes * max(1.0, cfg.max_attempts_factor)))
    for seed in range(cfg.seed_offset, cfg.seed_offset + attempts):
        yield seed, sample_variation(cfg.variation, np.random.default_rng([seed, 7])).to_dict()


def _episodes(cfg: GenerateConfig, wanted: Callable[[], int]) -> Iterator[dict]:
    """Episodes in seed order; workers run ahead, one env per process, but never on more episodes
    than `wanted()` (demos still missing) so none are thrown away at the end."""
    if cfg.workers <= 1:
        _init_worker(cfg)
        try:
            yield from map(_episode_job, _jobs(cfg))
        finally:
            _WORKER.pop("env").close()
        return
    ctx = get_context("spawn")  # fresh interpreters: no GL context or MuJoCo state inherited
    with ProcessPoolExecutor(cfg.workers, mp_context=ctx, initializer=_init_worker, initargs=(cfg,)) as pool:
        pending, jobs = [], _jobs(cfg)
        try:
            while True:
                while len(pending) < min(2 * cfg.workers, wanted()):
                    job = next(jobs, None)
                    if job is None:
                        break
                    pending.append(pool.submit(_episode_job, job))
                if not pending:
                    return
                yield pending.pop(0).result()
        finally:
            for f in pending:
                f.cancel()


# ---- the HDF5 file ----------------------------------------------------------------------------

def split_names(names: list[str], valid_fraction: float, seed: int = 0) -> tuple[list[str], list[str]]:
    """A seeded train/valid split (at least one valid demo when there are two or more)."""
    order = np.random.default_rng(seed).permutation(len(names))
    n_valid = int(round(len(names) * valid_fraction))
    if valid_fraction > 0 and len(names) >= 2:
        n_valid = max(1, n_valid)
    valid = sorted((names[i] for i in order[:n_valid]), key=lambda s: int(s.split("_")[1]))
    return [n for n in names if n not in valid], valid


def generate(cfg: GenerateConfig, progress: bool = True) -> dict:
    """Collect `cfg.episodes` successful expert demos into `cfg.out` (robomimic's layout, written by
    the one robomimic writer, which leaves nothing behind on failure); returns a summary."""
    start = time.time()
    count = {"kept": 0, "failed": 0, "samples": 0}
    bar = tqdm(total=cfg.episodes, desc=f"generate {cfg.task}", unit="demo", disable=not progress)

    def kept() -> Iterator[Episode]:
        for episode in _episodes(cfg, wanted=lambda: cfg.episodes - count["kept"]):
            if not episode["meta"]["success"]:
                count["failed"] += 1
                bar.set_postfix(failed=count["failed"])
                continue
            yield as_episode(f"demo_{count['kept']}", episode)
            count["kept"] += 1
            count["samples"] += len(episode["actions"])
            bar.update(1)
            if count["kept"] >= cfg.episodes:
                return
        if count["kept"] == 0:
            raise RuntimeError(f"the {cfg.task} expert failed all {count['failed']} episodes; nothing written to {cfg.out}")

    def split(names: list[str]) -> dict[str, list[str]]:
        train, valid = split_names(names, cfg.valid_fraction, cfg.seed_offset)
        return {"train": train, "valid": valid}

    try:
        path = robomimic_hdf5.write(cfg.out, kept(), _env_args(cfg), progress=False, split=split)
    finally:
        bar.close()
    kept_n, failed = count["kept"], count["failed"]
    return {"path": str(path), "task": get_task(cfg.task).name, "demos": kept_n, "failed": failed,
            "attempts": kept_n + failed, "expert_success_rate": round(kept_n / (kept_n + failed), 4),
            "samples": count["samples"], "seconds": round(time.time() - start, 1)}


def as_episode(demo_id: str, episode: dict) -> Episode:
    """A rolled-out episode (N actions, N + 1 observation frames) as the writer's Episode."""
    frames = episode["obs"]
    return Episode(demo_id=demo_id, actions=episode["actions"], obs={k: v[:-1] for k, v in frames.items()},
                   extras={k: episode[k] for k in ("states", "rewards", "dones")},
                   meta={**episode["meta"], "model_file": episode["model_file"]},
                   next_obs={k: v[-1:] for k, v in frames.items()})


def _env_args(cfg: GenerateConfig) -> dict:
    spec = get_task(cfg.task)
    return robomimic_env_args(spec, robosuite_kwargs(spec, cfg.image_size, cfg.depth, render=True))
