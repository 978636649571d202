"""Per-key z-score normalisation of lowdim observations and actions, stored in the state dict so a
checkpoint carries the statistics it was trained with."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

MIN_STD = 1e-4  # constant dims (e.g. a fixed quaternion component) are not blown up


class Normalizer(nn.Module):
    def __init__(self, dims: dict[str, int]):
        super().__init__()
        self.keys = list(dims)
        for k, d in dims.items():
            self.register_buffer(f"{k}__mean", torch.zeros(d))
            self.register_buffer(f"{k}__std", torch.ones(d))
        self.register_buffer("fitted", torch.tensor(False))

    def set_stats(self, stats: dict[str, dict]) -> None:
        """stats: key -> {"mean": array, "std": array} (as the store keeps them)."""
        missing = [k for k in self.keys if k not in stats]
        if missing:
            raise KeyError(f"normalisation statistics missing for {missing}; have {sorted(stats)}")
        for k in self.keys:
            mean = torch.as_tensor(np.asarray(stats[k]["mean"], dtype=np.float32))
            std = torch.as_tensor(np.asarray(stats[k]["std"], dtype=np.float32)).clamp_min(MIN_STD)
            buf = getattr(self, f"{k}__mean")
            if mean.shape != buf.shape:
                raise ValueError(f"normalisation statistics for {k!r} have shape {tuple(mean.shape)}, expected {tuple(buf.shape)}")
            buf.copy_(mean)
            getattr(self, f"{k}__std").copy_(std)
        self.fitted.fill_(True)

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return (x.float() - getattr(self, f"{key}__mean")) / getattr(self, f"{key}__std")

    def unnormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return x * getattr(self, f"{key}__std") + getattr(self, f"{key}__mean")


def fit_stats(arrays: dict[str, np.ndarray]) -> dict[str, dict]:
    """Mean and std over all leading dims of each array."""
    out = {}
    for k, a in arrays.items():
        a = np.asarray(a, dtype=np.float64).reshape(-1, np.asarray(a).shape[-1])
        out[k] = {"mean": a.mean(0).astype(np.float32), "std": a.std(0).astype(np.float32)}
    return out
