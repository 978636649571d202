"""Modality transformer: fuses one token per latent group, then a small MLP (paper section 3.1)."""

from __future__ import annotations

import torch
from torch import nn

from nostra.models.encoders import mlp


class ModalityTransformer(nn.Module):
    def __init__(self, in_dims: list[int], embed: int = 256, heads: int = 2, blocks: int = 1, out_dim: int = 256):
        super().__init__()
        self.proj = nn.ModuleList([nn.Linear(d, embed) for d in in_dims])
        self.token_embed = nn.Parameter(torch.randn(len(in_dims), embed) * 0.02)  # which modality a token is
        layer = nn.TransformerEncoderLayer(embed, heads, dim_feedforward=2 * embed, dropout=0.0,
                                           batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, blocks, enable_nested_tensor=False)
        self.out = mlp(len(in_dims) * embed, [embed], out_dim)
        self.out_dim = out_dim

    def forward(self, tokens: list[torch.Tensor]) -> torch.Tensor:
        """tokens: one (..., d_i) tensor per group -> (..., out_dim)."""
        lead = tokens[0].shape[:-1]
        x = torch.stack([p(t.reshape(-1, t.shape[-1])) for p, t in zip(self.proj, tokens)], 1)
        x = self.blocks(x + self.token_embed)
        return self.out(x.flatten(1)).reshape(*lead, -1)
