"""Observation encoders: ResNet18 (written here: torchvision would pull another torch build),
a light conv encoder for CPU profiles, and identity for lowdim inputs; each followed by its own MLP."""

from __future__ import annotations

import torch
from torch import nn

from nostra.modality import Modality


def mlp(in_dim: int, hidden: list[int] | tuple[int, ...], out_dim: int, act=nn.ELU) -> nn.Sequential:
    layers, d = [], in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), act()]
        d = h
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


def _norm(channels: int, kind: str) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":  # as diffusion_policy: stable with small batches and batch-1 rollouts
        return nn.GroupNorm(max(1, channels // 16), channels)
    raise ValueError(f"unknown norm {kind!r}; valid: batch, group")


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, norm: str):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = _norm(cout, norm)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = _norm(cout, norm)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), _norm(cout, norm))

    def forward(self, x):
        idt = x if self.down is None else self.down(x)
        y = torch.relu(self.bn1(self.conv1(x)))
        return torch.relu(self.bn2(self.conv2(y)) + idt)


class ResNet18(nn.Module):
    """ResNet18 (He et al., 2016) trunk with global average pooling: (B,C,H,W) -> (B,512)."""

    def __init__(self, in_channels: int = 3, norm: str = "group"):
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, 64, 7, 2, 3, bias=False), _norm(64, norm), nn.ReLU(), nn.MaxPool2d(3, 2, 1)
        )
        stages, cin = [], 64
        for cout, stride in ((64, 1), (128, 2), (256, 2), (512, 2)):
            stages += [BasicBlock(cin, cout, stride, norm), BasicBlock(cout, cout, 1, norm)]
            cin = cout
        self.stages = nn.Sequential(*stages)
        self.out_dim = 512

    def forward(self, x):
        return self.stages(self.stem(x)).mean(dim=(2, 3))


class LightConv(nn.Module):
    """Three conv layers (Nature-DQN sizes): fast enough for CPU training and 20 Hz control."""

    def __init__(self, in_channels: int, image_hw: tuple[int, int]):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(in_channels, 32, 8, 4), nn.ReLU(),
            nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
            nn.Conv2d(64, 64, 3, 1), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            self.out_dim = self.net(torch.zeros(1, in_channels, *image_hw)).shape[1]

    def forward(self, x):
        return self.net(x)


class ModalityEncoder(nn.Module):
    """Raw observation of one modality -> embedding.

    rgb: uint8 (...,H,W,3) scaled to [0,1]; depth: float (...,H,W,1) as stored; lowdim: float
    (...,D) already normalised by the policy's normaliser. Leading dims are flattened for the CNN.
    """

    def __init__(self, modality: Modality, image_encoder: str, embed_dim: int, hidden: list[int], norm: str = "group"):
        super().__init__()
        self.modality = modality
        if modality.is_image:
            h, w, c = modality.shape
            if image_encoder == "resnet18":
                self.trunk = ResNet18(c, norm)
            elif image_encoder == "light":
                self.trunk = LightConv(c, (h, w))
            else:
                raise ValueError(f"unknown image encoder {image_encoder!r}; valid: resnet18, light")
            feat = self.trunk.out_dim
        else:
            self.trunk = nn.Identity()
            feat = modality.shape[0]
        self.head = mlp(feat, hidden, embed_dim)
        self.out_dim = embed_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.modality.is_image:
            return self.head(x.float())
        lead = x.shape[:-3]
        x = x.reshape(-1, *x.shape[-3:])
        x = x.float() / 255.0 if self.modality.kind == "rgb" else x.float()
        x = x.permute(0, 3, 1, 2).contiguous()
        return self.head(self.trunk(x)).reshape(*lead, -1)
