"""Normalisation statistics: streamed per collection while ingesting (Chan's parallel update, so
no array is held whole) and combined exactly over collections."""

from __future__ import annotations

import numpy as np


class RunningStats:
    """Count, mean, sum of squared deviations, min and max over the leading dims, in float64."""

    def __init__(self):
        self.n, self.mean, self.m2, self.min, self.max = 0, None, None, None, None

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
        if not len(x):
            return
        self._merge(len(x), x.mean(0), ((x - x.mean(0)) ** 2).sum(0), x.min(0), x.max(0))

    def _merge(self, n, mean, m2, lo, hi) -> None:
        if self.n == 0:
            self.n, self.mean, self.m2, self.min, self.max = n, mean, m2, lo, hi
            return
        tot = self.n + n
        delta = mean - self.mean
        self.mean = self.mean + delta * n / tot
        self.m2 = self.m2 + m2 + delta ** 2 * self.n * n / tot
        self.min, self.max, self.n = np.minimum(self.min, lo), np.maximum(self.max, hi), tot

    def to_dict(self) -> dict:
        return {"count": int(self.n), "mean": self.mean.tolist(), "std": np.sqrt(self.m2 / self.n).tolist(),
                "min": self.min.tolist(), "max": self.max.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "RunningStats":
        s = cls()
        s.n, s.mean = int(d["count"]), np.asarray(d["mean"], np.float64)
        s.m2 = np.asarray(d["std"], np.float64) ** 2 * s.n
        s.min, s.max = np.asarray(d["min"], np.float64), np.asarray(d["max"], np.float64)
        return s


def combine(parts: list[dict]) -> dict:
    """One key's statistics over several collections (as stored) -> float32 arrays."""
    acc = RunningStats()
    for p in parts:
        s = RunningStats.from_dict(p)
        acc._merge(s.n, s.mean, s.m2, s.min, s.max)
    d = acc.to_dict()
    return {k: (np.asarray(d[k], np.float32) if k != "count" else d[k]) for k in ("mean", "std", "min", "max", "count")}


def fit_stats(arrays: dict[str, np.ndarray]) -> dict[str, dict]:
    """The same statistics of whole in-memory arrays (over all leading dims), as ``combine`` gives them."""
    out = {}
    for k, a in arrays.items():
        a, acc = np.asarray(a), RunningStats()
        acc.update(a.reshape(-1, a.shape[-1]))
        out[k] = combine([acc.to_dict()])
    return out
