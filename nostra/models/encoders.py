"""Observation encoders: ResNet18 (written here: torchvision would pull another torch build),
a light conv encoder for CPU profiles, and identity for lowdim inputs; each followed by its own MLP.

Image augmentation lives here, inside the encoder, as robomimic's CropRandomizer does: it runs only
in training mode, so a policy in eval mode (every runner) never sees an augmented frame.
``crop`` takes a random (H-p)x(W-p) window in training and the centre one at test time;
``shift`` (DrQ) pads p/2 pixels by edge replication and takes a random HxW window back.
"""

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


class SpatialSoftmax(nn.Module):
    """Feature maps (B,C,H,W) -> 1x1 conv to K maps -> the expected (x, y) in [-1, 1] of each
    map's softmax: (B, 2K) keypoints (Levine et al., 2016; robomimic's image encoder pools this
    way). Written here: ten lines, no library provides it as a module for plain torch."""

    def __init__(self, channels: int, keypoints: int = 32):
        super().__init__()
        self.proj = nn.Conv2d(channels, keypoints, 1)
        self.out_dim = 2 * keypoints

    def forward(self, x):
        x = self.proj(x)
        b, k, h, w = x.shape
        attn = torch.softmax(x.flatten(2), -1).view(b, k, h, w)
        ys = torch.linspace(-1, 1, h, device=x.device, dtype=attn.dtype)
        xs = torch.linspace(-1, 1, w, device=x.device, dtype=attn.dtype)
        return torch.cat([(attn.sum(2) * xs).sum(-1), (attn.sum(3) * ys).sum(-1)], -1)


class SpatialConv(nn.Module):
    """The light trunk pooled to keypoints by a spatial softmax instead of flattened: where things
    are, which is what a pick needs, with robomimic's pooling at the light trunk's cost."""

    def __init__(self, in_channels: int, keypoints: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(in_channels, 32, 8, 4), nn.ReLU(),
            nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
            nn.Conv2d(64, 64, 3, 1), nn.ReLU(),
        )
        self.pool = SpatialSoftmax(64, keypoints)
        self.out_dim = self.pool.out_dim

    def forward(self, x):
        return self.pool(self.net(x))


AUGMENTATIONS = ("none", "crop", "shift")
IMAGE_ENCODERS = ("light", "spatial", "resnet18")


class ImageAug(nn.Module):
    """Random crop or shift of uint8/float images (N,H,W,C) in training mode (module.train()),
    the centre crop (or nothing, for shift) in eval mode."""

    def __init__(self, kind: str = "none", pixels: int = 8):
        super().__init__()
        if kind not in AUGMENTATIONS:
            raise ValueError(f"unknown image augmentation {kind!r}; valid: {', '.join(AUGMENTATIONS)}")
        if kind != "none" and (pixels < 2 or pixels % 2):
            raise ValueError(f"augmentation pixels must be an even number >= 2, got {pixels}")
        self.kind, self.pixels = kind, int(pixels) if kind != "none" else 0

    def out_hw(self, h: int, w: int) -> tuple[int, int]:
        return (h - self.pixels, w - self.pixels) if self.kind == "crop" else (h, w)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.kind == "none":
            return x
        p, (h, w) = self.pixels, x.shape[1:3]
        if self.kind == "shift":
            if not self.training:
                return x
            dtype = x.dtype  # replicate padding needs floats; uint8 frames go back to uint8
            x = torch.nn.functional.pad(x.permute(0, 3, 1, 2).float(), (p // 2,) * 4, mode="replicate")
            x = x.permute(0, 2, 3, 1).to(dtype)
        oh, ow = self.out_hw(h, w)
        if not self.training:
            return x[:, p // 2:p // 2 + oh, p // 2:p // 2 + ow]
        n = x.shape[0]
        dy = torch.randint(0, x.shape[1] - oh + 1, (n, 1), device=x.device)
        dx = torch.randint(0, x.shape[2] - ow + 1, (n, 1), device=x.device)
        iy = (dy + torch.arange(oh, device=x.device))[:, :, None]
        ix = (dx + torch.arange(ow, device=x.device))[:, None, :]
        return x[torch.arange(n, device=x.device)[:, None, None], iy, ix]


class ModalityEncoder(nn.Module):
    """Raw observation of one modality -> embedding.

    rgb: uint8 (...,H,W,3) scaled to [0,1]; depth: float (...,H,W,1) as stored; lowdim: float
    (...,D) already normalised by the policy's normaliser. Leading dims are flattened for the CNN.
    """

    def __init__(self, modality: Modality, image_encoder: str, embed_dim: int, hidden: list[int], norm: str = "group",
                 aug: str = "none", aug_pixels: int = 8, keypoints: int = 32):
        super().__init__()
        self.modality = modality
        self.aug = ImageAug(aug if modality.is_image else "none", aug_pixels)
        if modality.is_image:
            h, w, c = modality.shape
            h, w = self.aug.out_hw(h, w)
            if image_encoder == "resnet18":
                self.trunk = ResNet18(c, norm)
            elif image_encoder == "light":
                self.trunk = LightConv(c, (h, w))
            elif image_encoder == "spatial":
                self.trunk = SpatialConv(c, keypoints)
            else:
                raise ValueError(f"unknown image encoder {image_encoder!r}; valid: {', '.join(IMAGE_ENCODERS)}")
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
        x = self.aug(x.reshape(-1, *x.shape[-3:]))
        x = x.float() / 255.0 if self.modality.kind == "rgb" else x.float()
        x = x.permute(0, 3, 1, 2).contiguous()
        return self.head(self.trunk(x)).reshape(*lead, -1)
