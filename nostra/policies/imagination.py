"""Multimodal latent imagination (MLI) and its adaptive form AdaMLI (paper section 3.2).

AdaMLI watches each modality's KL series D(t) = KL[q(z_t^m | h_t, o_t^m) || p(z_t^m | h_t)] and
switches that modality to its imagined (prior) latent when the KL jumps, back to the observed
(posterior) latent when it drops. Read literally, the paper keeps a running average of KL
changes r(T, k) = mean |D(t) - D(t-1)| over the k steps before T, with k = k_c while the
modality is closed-loop and k = k_o while it is open-loop, reset at each switch:

* closed -> open when  D(T) - D(T-1) >  f_o * r(T, k_c)
* open -> closed when  D(T-1) - D(T) >  f_c * r(T, k_o)

As printed, the sum in r runs up to T itself, which would make opening impossible
(f_o / k_c = 10 > 1); we average the k changes before T. Pairing the windows by subscript
instead (f_o with k_o) closes at every smooth local maximum of the KL inside a noise window: its
recall on the traces of ``bench/adamli_traces.py`` falls to 0.3-0.9.

Choices the paper leaves open:
* a decision needs at least ``min_changes`` changes since the last switch; the average runs over
  up to k of them;
* detection starts ``warmup`` steps into an episode (the first steps carry h_0's transient), so a
  corruption already there by then shows no jump and is never imagined (README: warm-up 0 mended it);
* r is floored at ``eps`` so a perfectly flat KL series does not fire on round-off.

Limits, measured: the thresholds assume a KL that moves smoothly from step to step, as on
continuous sensor streams under structured corruption (a mask, a stuck or dead sensor).
``bench/adamli_traces.py`` shows detection degrading with step-to-step KL jitter; on a small
trained policy whose clean KL jitters, clean modalities get imagined on ~10% of steps
(tests/test_effects.py bounds it); white noise on a sensor makes the KL inside the window jump
by its own size each step, so the drop at the window's end is rarely 3x larger and the modality
stays imagined after the noise ends. Camera jitter in closed loop (README, *Why AdaMLI loses under cam_jitter*)
makes a camera's KL swing as much as it jumped into the window, so a chance drop of 3x the recent
changes switches the camera back mid-window (45% of the agent view's windows on LiftD1; f_c = 12: 0%).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AdaMLIConfig:
    f_o: float = 20.0
    k_o: int = 10
    f_c: float = 3.0
    k_c: int = 2
    min_changes: int = 5
    warmup: int = 10
    eps: float = 1e-3  # nats: a thousandth of a nat is no information change

    @classmethod
    def from_dict(cls, params: dict | None) -> "AdaMLIConfig":
        """The thresholds a config gives (evaluate.variants.<id>.adamli, evaluate.offline.adamli);
        an unknown key fails naming the valid ones; the rest keep the paper's values."""
        fields = {f.name: f.type for f in dataclasses.fields(cls)}
        unknown = sorted(set(params or {}) - set(fields))
        if unknown:
            raise ValueError(f"unknown AdaMLI parameter(s) {unknown}; valid: {', '.join(fields)}")
        cast = {"int": int, "float": float, int: int, float: float}  # annotations may be strings
        return cls(**{k: cast[fields[k]](v) for k, v in (params or {}).items()})


class KLSwitch:
    """AdaMLI's state machine for one modality: feed KL values, read whether to imagine."""

    def __init__(self, cfg: AdaMLIConfig = AdaMLIConfig()):
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.imagining = False
        self.prev: float | None = None
        self.t = 0
        self.changes: deque[float] = deque(maxlen=max(self.cfg.k_o, self.cfg.k_c))

    def update(self, kl: float) -> bool:
        cfg, prev = self.cfg, self.prev
        self.prev, self.t = float(kl), self.t + 1
        if prev is None:
            return self.imagining
        change = float(kl) - prev
        k, f = (cfg.k_o, cfg.f_c) if self.imagining else (cfg.k_c, cfg.f_o)
        hist = list(self.changes)[-k:]
        if self.t > cfg.warmup and len(hist) >= min(cfg.min_changes, k):
            r = max(float(np.mean(np.abs(hist))), cfg.eps)
            if (not self.imagining and change > f * r) or (self.imagining and -change > f * r):
                self.imagining = not self.imagining
                self.changes.clear()
                return self.imagining
        self.changes.append(change)
        return self.imagining


class AdaMLI:
    """One KLSwitch per latent group (a modality for NOSTRA, the joint latent for BC-RSSM)."""

    def __init__(self, groups: list[str], cfg: AdaMLIConfig = AdaMLIConfig()):
        self.switches = {g: KLSwitch(cfg) for g in groups}

    def reset(self) -> None:
        for s in self.switches.values():
            s.reset()

    def update(self, kl: dict[str, float]) -> dict[str, bool]:
        return {g: s.update(kl[g]) for g, s in self.switches.items()}


def adamli_flags(kl: np.ndarray, cfg: AdaMLIConfig = AdaMLIConfig()) -> np.ndarray:
    """Run AdaMLI over a recorded KL series (T,) and return the per-step imagination flags."""
    switch = KLSwitch(cfg)
    return np.array([switch.update(v) for v in np.asarray(kl, dtype=float)], dtype=bool)


def detection_scores(flags: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Per-step precision and recall of imagination flags against the true noise steps."""
    flags, truth = np.asarray(flags, bool), np.asarray(truth, bool)
    tp = float(np.sum(flags & truth))
    precision = tp / flags.sum() if flags.sum() else (1.0 if not truth.any() else 0.0)
    recall = tp / truth.sum() if truth.sum() else 1.0
    return {"precision": precision, "recall": recall}


def in_windows(t: int, windows) -> bool:
    """Whether step t lies inside one of the half-open windows [start, end): the one such test
    (noise schedules, the oracle's imagination and the detection ground truth all use it)."""
    return any(start <= t < end for start, end in windows)


def window_mask(horizon: int, windows: list[tuple[int, int]]) -> np.ndarray:
    """Boolean (horizon,) mask that is true inside the half-open windows [start, end)."""
    return np.array([in_windows(t, windows) for t in range(horizon)], dtype=bool)
