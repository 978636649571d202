"""Per-key z-score normalisation of lowdim observations and actions, stored in the state dict so a
checkpoint carries the statistics it was trained with. Keys named in ``ranges`` also keep min/max
for a linear map to [-1, 1] (Diffusion Policy's action normalisation)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

MIN_STD = 1e-4  # constant dims (e.g. a fixed quaternion component) are not blown up


class Normalizer(nn.Module):
    def __init__(self, dims: dict[str, int], ranges: tuple[str, ...] | list[str] = ()):
        super().__init__()
        self.keys = list(dims)
        unknown = [k for k in ranges if k not in dims]
        if unknown:
            raise ValueError(f"min/max ranges requested for unknown keys {unknown}; valid: {self.keys}")
        self.range_keys = list(ranges)
        for k, d in dims.items():
            self.register_buffer(f"{k}__mean", torch.zeros(d))
            self.register_buffer(f"{k}__std", torch.ones(d))
        for k in self.range_keys:  # buffers only where asked: other policies' state dicts stay unchanged
            self.register_buffer(f"{k}__min", -torch.ones(dims[k]))
            self.register_buffer(f"{k}__max", torch.ones(dims[k]))
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
        for k in self.range_keys:
            if "min" not in stats[k] or "max" not in stats[k]:
                raise KeyError(f"normalisation statistics for {k!r} need 'min' and 'max' (this policy maps "
                               f"{k!r} to [-1, 1]); have {sorted(stats[k])}")
            for bound in ("min", "max"):
                getattr(self, f"{k}__{bound}").copy_(torch.as_tensor(np.asarray(stats[k][bound], dtype=np.float32)))
        self.fitted.fill_(True)

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return (x.float() - getattr(self, f"{key}__mean")) / getattr(self, f"{key}__std")

    def unnormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return x * getattr(self, f"{key}__std") + getattr(self, f"{key}__mean")

    def _center_half(self, key: str) -> tuple[torch.Tensor, torch.Tensor]:
        if key not in self.range_keys:
            raise KeyError(f"no min/max kept for {key!r}; range keys: {self.range_keys}")
        lo, hi = getattr(self, f"{key}__min"), getattr(self, f"{key}__max")
        half = (hi - lo) / 2
        # a constant dim maps to 0 (as diffusion_policy's "limits" normaliser) instead of dividing by ~0
        return (hi + lo) / 2, torch.where(half < MIN_STD, torch.ones_like(half), half)

    def to_unit_range(self, key: str, x: torch.Tensor) -> torch.Tensor:
        """[min, max] -> [-1, 1]."""
        center, half = self._center_half(key)
        return (x.float() - center) / half

    def from_unit_range(self, key: str, x: torch.Tensor) -> torch.Tensor:
        """[-1, 1] -> [min, max]."""
        center, half = self._center_half(key)
        return x * half + center
