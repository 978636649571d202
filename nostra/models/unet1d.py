"""The 1D temporal U-Net of Diffusion Policy's CNN variant (Chi et al., 2023): Conv1d residual
blocks with GroupNorm and Mish over the action sequence, FiLM-conditioned on a global vector
(the encoded observations plus a sinusoidal embedding of the diffusion step)."""

from __future__ import annotations

import math

import torch
from torch import nn


class SinusoidalPosEmb(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        if dim % 2:
            raise ValueError(f"sinusoidal embedding dim must be even, got {dim}")
        self.dim = dim

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        half = self.dim // 2
        freq = torch.exp(-math.log(10000) * torch.arange(half, device=t.device) / (half - 1))
        arg = t.float()[:, None] * freq[None]
        return torch.cat([arg.sin(), arg.cos()], -1)


class Conv1dBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, kernel_size: int, n_groups: int):
        super().__init__(nn.Conv1d(cin, cout, kernel_size, padding=kernel_size // 2),
                         nn.GroupNorm(n_groups, cout), nn.Mish())


class CondResBlock1d(nn.Module):
    """Two conv blocks; FiLM (per-channel scale and bias from the condition) between them."""

    def __init__(self, cin: int, cout: int, cond_dim: int, kernel_size: int, n_groups: int):
        super().__init__()
        self.block1 = Conv1dBlock(cin, cout, kernel_size, n_groups)
        self.block2 = Conv1dBlock(cout, cout, kernel_size, n_groups)
        self.film = nn.Sequential(nn.Mish(), nn.Linear(cond_dim, 2 * cout))
        self.residual = nn.Conv1d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, bias = self.film(cond).unsqueeze(-1).chunk(2, dim=1)
        return self.block2(scale * self.block1(x) + bias) + self.residual(x)


class ConditionalUnet1d(nn.Module):
    """(B, T, A) noisy action sequence, (B,) diffusion steps, (B, C) condition -> (B, T, A).

    Each level but the deepest halves T, so T must be divisible by 2 ** (len(down_dims) - 1).
    """

    def __init__(self, action_dim: int, cond_dim: int, down_dims=(256, 512, 1024), kernel_size: int = 5,
                 n_groups: int = 8, step_embed_dim: int = 256):
        super().__init__()
        down_dims = [int(d) for d in down_dims]
        bad = [d for d in down_dims if d % n_groups]
        if not down_dims or bad:
            raise ValueError(f"down_dims {down_dims} must be non-empty and divisible by n_groups={n_groups}")
        self.levels = len(down_dims)
        e = step_embed_dim
        self.step_encoder = nn.Sequential(SinusoidalPosEmb(e), nn.Linear(e, 4 * e), nn.Mish(), nn.Linear(4 * e, e))
        cdim = step_embed_dim + cond_dim
        block = lambda i, o: CondResBlock1d(i, o, cdim, kernel_size, n_groups)  # noqa: E731
        dims = [action_dim] + down_dims
        pairs = list(zip(dims[:-1], dims[1:]))
        self.down = nn.ModuleList([
            nn.ModuleList([block(i, o), block(o, o),
                           nn.Conv1d(o, o, 3, 2, 1) if k < len(pairs) - 1 else nn.Identity()])
            for k, (i, o) in enumerate(pairs)])
        self.mid = nn.ModuleList([block(down_dims[-1], down_dims[-1]), block(down_dims[-1], down_dims[-1])])
        self.up = nn.ModuleList([
            nn.ModuleList([block(2 * o, i), block(i, i), nn.ConvTranspose1d(i, i, 4, 2, 1)])
            for i, o in reversed(pairs[1:])])
        self.final = nn.Sequential(Conv1dBlock(down_dims[0], down_dims[0], kernel_size, n_groups),
                                   nn.Conv1d(down_dims[0], action_dim, 1))

    def forward(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        if x.shape[1] % 2 ** (self.levels - 1):
            raise ValueError(f"sequence length {x.shape[1]} is not divisible by 2**{self.levels - 1} "
                             f"(one halving per U-Net level after the first)")
        t = torch.as_tensor(t, device=x.device).reshape(-1).expand(x.shape[0])  # a scheduler's scalar step or (B,)
        c = torch.cat([self.step_encoder(t), cond], -1)
        x = x.transpose(1, 2)  # channels = action dims, convolved over time
        skips = []
        for res1, res2, down in self.down:
            x = res2(res1(x, c), c)
            skips.append(x)
            x = down(x)
        for res in self.mid:
            x = res(x, c)
        for res1, res2, up in self.up:
            x = up(res2(res1(torch.cat([x, skips.pop()], 1), c), c))
        return self.final(x).transpose(1, 2)
