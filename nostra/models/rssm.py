"""The multimodal state-space core (paper section 3.1).

A GRU shared by prior and posterior carries the deterministic state h_t. The stochastic latent is
split into G groups: NOSTRA has one group per modality, BC-RSSM one joint group over all of them.
For every group g there is an open-loop prior p(z_t^g | h_t) and a closed-loop posterior
q(z_t^g | h_t, e_t^g), both diagonal Gaussians with learned mean and std.

Groups share their sizes, so their heads are stored as stacked weights and run as one batched
matmul (G small MLPs in one call): per-step cost then hardly grows with the number of modalities.
Tensors of the groups are stacked on the leading dim: (G, B, ...).

Initial state (the paper leaves it open): h_0 = 0 and z_0 = 0, so the first step's prior is a
learned function of a constant and every episode starts from the same state.
"""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import nn
from torch.distributions import Normal, kl_divergence
from torch.nn import functional as F


class GroupedLinear(nn.Module):
    """G independent linear layers applied to (G, B, in) in one batched matmul."""

    def __init__(self, groups: int, in_dim: int, out_dim: int):
        super().__init__()
        bound = 1 / math.sqrt(in_dim)  # nn.Linear's default init
        self.weight = nn.Parameter(torch.empty(groups, in_dim, out_dim).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(groups, 1, out_dim).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


def grouped_mlp(groups: int, in_dim: int, hidden: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(GroupedLinear(groups, in_dim, hidden), nn.ELU(), GroupedLinear(groups, hidden, out_dim))


class LatentHeads(nn.Module):
    """Per group: an MLP followed by two small MLPs for the mean and the std (paper section 3.1)."""

    def __init__(self, groups: int, in_dim: int, hidden: int, latent: int, min_std: float):
        super().__init__()
        self.groups = groups
        self.trunk = nn.Sequential(GroupedLinear(groups, in_dim, hidden), nn.ELU())
        self.mean = grouped_mlp(groups, hidden, hidden, latent)
        self.std = grouped_mlp(groups, hidden, hidden, latent)
        self.min_std = min_std

    def forward(self, x: torch.Tensor) -> Normal:
        """x: (G, B, in), or (B, in) shared by all groups -> Normal over (G, B, latent)."""
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.groups, -1, -1)
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
    def __init__(self, groups: int, embed: int, latent_dim: int, deter: int = 256, hidden: int = 256,
                 min_std: float = 0.1):
        super().__init__()
        self.groups, self.latent_dim, self.deter = groups, latent_dim, deter
        self.inp = nn.Sequential(nn.Linear(groups * latent_dim, hidden), nn.ELU())
        self.gru = nn.GRUCell(hidden, deter)
        self.prior = LatentHeads(groups, deter, hidden, latent_dim, min_std)
        self.post = LatentHeads(groups, deter + embed, hidden, latent_dim, min_std)

    def initial(self, batch: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.zeros(batch, self.deter, device=device),
                torch.zeros(self.groups, batch, self.latent_dim, device=device))

    def transition(self, h: torch.Tensor, z_prev: torch.Tensor) -> tuple[torch.Tensor, Normal]:
        """h_t = GRU(h_{t-1}, z_{t-1}^{1:G}); open-loop priors p(z_t^g | h_t) over (G, B, Z)."""
        x = z_prev.transpose(0, 1).reshape(z_prev.shape[1], -1)
        h = self.gru(self.inp(x), h)
        return h, self.prior(h)

    def posteriors(self, h: torch.Tensor, embeds: torch.Tensor) -> Normal:
        """Closed-loop posteriors q(z_t^g | h_t, e_t^g); embeds (G, B, E)."""
        return self.post(torch.cat([h.unsqueeze(0).expand(self.groups, -1, -1), embeds], -1))

    def step(self, state: tuple[torch.Tensor, torch.Tensor], embeds: torch.Tensor,
             imagine: torch.Tensor | Callable[[Normal, Normal], torch.Tensor] | None = None,
             sample: bool = True) -> tuple[tuple[torch.Tensor, torch.Tensor], Normal, Normal]:
        """One filter step, the only one: the sequence filter of training loops over it and the
        runner calls it once per control step (like DreamerV3's shared obs/img step).

        state (h_{t-1}, z_{t-1}); embeds (G, B, E) of step t. The GRU advances h, the prior and the
        posterior of every group are computed, and z_t is the posterior latent except where
        ``imagine`` (G, B) is true: there the prior's replaces it (MLI / LI). ``imagine`` may be a
        function of (posterior, prior) returning that mask, for a choice that needs the step's
        KL (AdaMLI). The model has no action input: h_t = GRU(h_{t-1}, z_{t-1}) (section 3.1).
        Returns the new state, the posteriors and the priors over (G, B, Z)."""
        h, prior = self.transition(*state)
        post = self.posteriors(h, embeds)
        mask = imagine(post, prior) if callable(imagine) else imagine
        return (h, self.select(post, prior, mask, sample)), post, prior

    @staticmethod
    def select(post: Normal, prior: Normal, imagine: torch.Tensor | None, sample: bool) -> torch.Tensor:
        """Prior forcing: where imagine (G, B) is true the prior latent replaces the posterior one."""
        z = latent(post, sample)
        if imagine is None:
            return z
        return torch.where(imagine.unsqueeze(-1), latent(prior, sample), z)
