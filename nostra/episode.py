"""The one episode engine: a policy runner stepped through an episode under a noise schedule, with
what happened at every step recorded. Simulator rollouts (``nostra.sim.rollout``), the offline
analysis on held-out demos (``nostra.workflows.analysis``) and the synthetic demo (``bench/synthetic_demo.py``)
all run their episodes here; they differ only in where the observations come from.

An observation source has four methods (the engine imports no simulator; see
``nostra.sim.rollout.SimSource`` and :class:`RecordedSource`):

* ``reset(schedule, rng) -> obs``: the episode's first observation;
* ``unusable(obs) -> str``: why a (corrupted) observation cannot be given to the policy, or "";
* ``step(action, schedule, t, rng) -> (obs, success, reason)``: apply the action and return
  observation ``t`` (None once a recorded episode is over), whether the task is done, and why the
  episode broke off ("" when it did not). The source lets ``schedule.prepare`` set up the noise
  of step ``t`` before that observation is produced;
* ``close(schedule, t)``: undo what the schedule changed (an episode ending inside a window);
* optionally ``objects() -> {name: (3,) position}``: where the task's objects are, recorded each step
  beside the end effector (a simulator knows it; a recorded episode does not).

Timeline (the same for both sources): observation t is corrupted when t lies in a window, the
runner sees the corrupted one, and in oracle mode it imagines the noised modalities there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nostra.modality import EEF_POS as EEF_KEY  # recorded alongside the actions when the observation has it


def oracle_keys(schedule, modality_names) -> set[str]:
    """The oracle rule of MLI / LI: imagine the modalities the noise corrupts (inside its windows)."""
    return set(schedule.keys) & set(modality_names)


@dataclass
class Episode:
    """What happened: per-step lists (``action``, ``eef_pos`` when observed, ``objects`` when the source
    knows them, ``noise``: step inside a window, ``kl`` and ``imagined``: the runner's info dicts), frames
    when asked for, and the end."""

    action: list = field(default_factory=list)
    eef_pos: list = field(default_factory=list)
    objects: list = field(default_factory=list)
    noise: list = field(default_factory=list)
    kl: list = field(default_factory=list)
    imagined: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    success: bool = False
    steps: int = 0
    reason: str = ""  # why the episode broke off before its end ("" when it did not)

    def record(self) -> dict:
        """Per-step arrays, the rollout records' format: action, eef_pos, noise, object/<name> (T, 3),
        kl/<key>, imagined/<key>."""
        out = {"action": np.asarray(self.action, np.float32).reshape(len(self.action), -1),
               "eef_pos": np.asarray(self.eef_pos, np.float32).reshape(len(self.eef_pos), -1),
               "noise": np.asarray(self.noise, bool)}
        for name in sorted({k for row in self.objects for k in row}):
            out[f"object/{name}"] = np.asarray([row[name] for row in self.objects], np.float32)
        for name in ("kl", "imagined"):
            rows = getattr(self, name)
            keys = sorted({k for row in rows for k in row})
            for k in keys:
                out[f"{name}/{k}"] = np.asarray([row.get(k, np.nan) for row in rows],
                                                np.float32 if name == "kl" else bool)
        return out


def run(source, runner, schedule, mode: str = "closed", horizon: int | None = None,
        rng: np.random.Generator | None = None, frame_key: str | None = None) -> Episode:
    """Step ``runner`` through the episode of ``source`` for at most ``horizon`` steps (None: until
    the source ends), stopping at success (robomimic's convention) or when the episode breaks off.
    ``mode``: closed | oracle (imagine :func:`oracle_keys` inside the windows) | adaptive (the
    runner decides; it must have been built adaptive). ``rng`` draws the noise's random parameters.
    ``frame_key``: keep that key of every corrupted observation the policy saw (a video)."""
    rng = rng if rng is not None else np.random.default_rng()
    oracle = oracle_keys(schedule, runner.modality_names) if mode == "oracle" else set()
    ep = Episode()
    obs = source.reset(schedule, rng)
    runner.reset()
    t = 0
    try:
        for t in range(horizon if horizon is not None else np.iinfo(np.int64).max):
            seen = schedule.corrupt(obs, t)
            reason = source.unusable(seen)
            if reason:
                ep.steps, ep.reason = t, reason
                return ep
            noisy = schedule.active(t)
            action, info = runner.step(seen, imagine=oracle if noisy and oracle else None)
            if frame_key:
                ep.frames.append(seen.get(frame_key))
            ep.action.append(action), ep.noise.append(noisy)
            if EEF_KEY in obs:
                ep.eef_pos.append(obs[EEF_KEY])
            if hasattr(source, "objects"):
                ep.objects.append(source.objects())
            ep.kl.append(info.get("kl", {})), ep.imagined.append(info.get("imagined", {}))
            obs, success, reason = source.step(action, schedule, t + 1, rng)
            ep.steps = t + 1
            if reason:
                ep.reason = reason
                return ep
            if success:
                ep.success = True
                break
            if obs is None:
                break
    finally:
        source.close(schedule, t + 1)
    return ep


class RecordedSource:
    """A stored episode's observations ``{key: (T, ...)}``, replayed whatever the actions: no
    simulator, so only noises that edit observations apply (``NoiseSchedule.needs_env`` is false).
    ``image_size``: what image noises (the mask's square) size themselves by."""

    def __init__(self, obs: dict[str, np.ndarray], image_size: int | None = None):
        self.obs = obs
        self.length = len(next(iter(obs.values())))
        self.image_size = image_size

    def __len__(self) -> int:
        return self.length

    def _at(self, schedule, t: int, rng) -> dict | None:
        if t >= self.length:
            return None
        schedule.prepare(None, t, rng, image_size=self.image_size)
        return {k: v[t] for k, v in self.obs.items()}

    def reset(self, schedule, rng) -> dict:
        return self._at(schedule, 0, rng)

    def unusable(self, obs: dict) -> str:
        return ""

    def step(self, action, schedule, t: int, rng):
        return self._at(schedule, t, rng), False, ""

    def close(self, schedule, t: int) -> None:
        schedule.close(None, t)
