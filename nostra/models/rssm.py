"""The multimodal state-space core (paper section 3.1).

A GRU shared by prior and posterior carries the deterministic state h_t. The stochastic latent is
split into groups: NOSTRA has one group per modality, BC-RSSM one joint group over all of them.
For every group g there is an open-loop prior p(z_t^g | h_t) and a closed-loop posterior
q(z_t^g | h_t, e_t^g), both diagonal Gaussians with learned mean and std.

Initial state (the paper leaves it open): h_0 = 0 and z_0 = 0, so the first step's prior is a
learned function of a constant and every episode starts from the same state.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.distributions import Normal, kl_divergence
from torch.nn import functional as F

from nostra.models.encoders import mlp


class LatentHead(nn.Module):
    """An MLP followed by two small MLPs for the mean and the std (paper: implementation details)."""

    def __init__(self, in_dim: int, hidden: int, latent: int, min_std: float):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(in_dim, hidden), nn.ELU())
        self.mean = mlp(hidden, [hidden], latent)
        self.std = mlp(hidden, [hidden], latent)
        self.min_std = min_std

    def forward(self, x: torch.Tensor) -> Normal:
        y = self.trunk(x)
        return Normal(self.mean(y), F.softplus(self.std(y)) + self.min_std, validate_args=False)


def diag_kl(q: Normal, p: Normal) -> torch.Tensor:
    """KL(q || p) of diagonal Gaussians, summed over latent dims (nats)."""
    return kl_divergence(q, p).sum(-1)


def detach(d: Normal) -> Normal:
    return Normal(d.loc.detach(), d.scale.detach(), validate_args=False)


def balanced_kl(q: Normal, p: Normal, gamma: float) -> torch.Tensor:
    """gamma * KL(q || sg(p)) + (1 - gamma) * KL(sg(q) || p)  (paper section 3.1)."""
    return gamma * diag_kl(q, detach(p)) + (1.0 - gamma) * diag_kl(detach(q), p)


def latent(d: Normal, sample: bool) -> torch.Tensor:
    """Reparameterised sample for training, the mean for deterministic rollouts."""
    return d.rsample() if sample else d.mean


class MultimodalRSSM(nn.Module):
    """groups: name -> (embedding dim of its inputs, latent dim)."""

    def __init__(self, groups: dict[str, tuple[int, int]], deter: int = 256, hidden: int = 256, min_std: float = 0.1):
        super().__init__()
        self.groups = list(groups)
        self.latent_dims = {g: z for g, (_, z) in groups.items()}
        self.deter = deter
        zsum = sum(self.latent_dims.values())
        self.inp = nn.Sequential(nn.Linear(zsum, hidden), nn.ELU())
        self.gru = nn.GRUCell(hidden, deter)
        self.prior = nn.ModuleDict({g: LatentHead(deter, hidden, z, min_std) for g, (_, z) in groups.items()})
        self.post = nn.ModuleDict({g: LatentHead(deter + e, hidden, z, min_std) for g, (e, z) in groups.items()})

    def initial(self, batch: int, device=None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        h = torch.zeros(batch, self.deter, device=device)
        z = {g: torch.zeros(batch, d, device=device) for g, d in self.latent_dims.items()}
        return h, z

    def transition(self, h: torch.Tensor, z_prev: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, Normal]]:
        """h_t = GRU(h_{t-1}, z_{t-1}^{1:G}); open-loop priors p(z_t^g | h_t)."""
        x = torch.cat([z_prev[g] for g in self.groups], -1)
        h = self.gru(self.inp(x), h)
        return h, {g: self.prior[g](h) for g in self.groups}

    def posteriors(self, h: torch.Tensor, embeds: dict[str, torch.Tensor]) -> dict[str, Normal]:
        """Closed-loop posteriors q(z_t^g | h_t, e_t^g)."""
        return {g: self.post[g](torch.cat([h, embeds[g]], -1)) for g in self.groups}

    @staticmethod
    def select(posts: dict[str, Normal], priors: dict[str, Normal], imagine: dict[str, torch.Tensor] | None,
               sample: bool) -> dict[str, torch.Tensor]:
        """Prior forcing: where imagine[g] is true the prior latent replaces the posterior one."""
        out = {}
        for g, q in posts.items():
            zq = latent(q, sample)
            if imagine is None or g not in imagine:
                out[g] = zq
            else:
                out[g] = torch.where(imagine[g].unsqueeze(-1), latent(priors[g], sample), zq)
        return out
