"""Modality transformer: fuses one token per latent group, then a small MLP (paper section 3.1)."""

from __future__ import annotations

import torch
from torch import nn

from nostra.models.encoders import mlp


class ModalityTransformer(nn.Module):
    def __init__(self, groups: int, in_dim: int, embed: int = 256, heads: int = 2, blocks: int = 1,
                 out_dim: int = 256):
        super().__init__()
        # one projection per group (stacked): tokens of different modalities live in different spaces
        self.proj_w = nn.Parameter(torch.randn(groups, in_dim, embed) / in_dim ** 0.5)
        self.token_embed = nn.Parameter(torch.randn(groups, embed) * 0.02)  # which modality a token is
        layer = nn.TransformerEncoderLayer(embed, heads, dim_feedforward=2 * embed, dropout=0.0,
                                           batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(layer, blocks, enable_nested_tensor=False)
        self.out = mlp(groups * embed, [embed], out_dim)
        self.out_dim = out_dim

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens: (..., G, Z) -> (..., out_dim)."""
        lead = tokens.shape[:-2]
        x = torch.einsum("ngz,gze->nge", tokens.reshape(-1, *tokens.shape[-2:]), self.proj_w)
        x = self.blocks(x + self.token_embed)
        return self.out(x.flatten(1)).reshape(*lead, -1)
