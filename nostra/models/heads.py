"""Action decoders: an MLP with a fixed-variance Gaussian (paper) or a GMM (robomimic's option)."""

from __future__ import annotations

import torch
from torch import nn
from torch.distributions import Categorical, Independent, MixtureSameFamily, Normal
from torch.nn import functional as F

from nostra.models.encoders import mlp

HEADS = ("gaussian", "gmm")


class GaussianHead(nn.Module):
    """p(a | x) = N(mlp(x), std^2 I) with a fixed std; the rollout action is the mean."""

    def __init__(self, in_dim: int, hidden: list[int], action_dim: int, std: float = 1.0):
        super().__init__()
        self.net = mlp(in_dim, hidden, action_dim)
        self.std = std

    def dist(self, x):
        mean = self.net(x)
        return Independent(Normal(mean, torch.full_like(mean, self.std), validate_args=False), 1)

    def nll(self, x, a):
        return -self.dist(x).log_prob(a)

    def act(self, x):
        return self.net(x)


class GMMHead(nn.Module):
    """Mixture of diagonal Gaussians as robomimic's GMM actor (5 modes, softplus std, min std 1e-4).
    The rollout action is the mean of the most probable mode (deterministic)."""

    def __init__(self, in_dim: int, hidden: list[int], action_dim: int, modes: int = 5, min_std: float = 1e-4):
        super().__init__()
        self.modes, self.action_dim, self.min_std = modes, action_dim, min_std
        self.net = mlp(in_dim, hidden, modes * (2 * action_dim + 1))

    def _params(self, x):
        out = self.net(x)
        k, a = self.modes, self.action_dim
        mean = out[..., : k * a].reshape(*out.shape[:-1], k, a)
        std = F.softplus(out[..., k * a: 2 * k * a].reshape(*out.shape[:-1], k, a)) + self.min_std
        return mean, std, out[..., 2 * k * a:]

    def dist(self, x):
        mean, std, logits = self._params(x)
        comp = Independent(Normal(mean, std, validate_args=False), 1)
        return MixtureSameFamily(Categorical(logits=logits, validate_args=False), comp, validate_args=False)

    def nll(self, x, a):
        return -self.dist(x).log_prob(a)

    def act(self, x):
        mean, _, logits = self._params(x)
        idx = logits.argmax(-1)[..., None, None].expand(*mean.shape[:-2], 1, mean.shape[-1])
        return mean.gather(-2, idx).squeeze(-2)


def make_head(kind: str, in_dim: int, hidden: list[int], action_dim: int, action_std: float = 1.0,
              gmm_modes: int = 5) -> nn.Module:
    if kind == "gaussian":
        return GaussianHead(in_dim, hidden, action_dim, action_std)
    if kind == "gmm":
        return GMMHead(in_dim, hidden, action_dim, gmm_modes)
    raise ValueError(f"unknown action head {kind!r}; valid: {', '.join(HEADS)}")
