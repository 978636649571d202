"""What every policy shares: the network base (encoders + normaliser) and the stateful runner used
by rollouts and deployment; no Lightning (the training wrappers: nostra.policies.modules), so
evaluation and deployment start without importing it.

Batches are ``{"obs": {key: (B,T,...)}, "actions": (B,T,A)}`` with raw values (images uint8,
lowdim and actions unnormalised): the network normalises, so training and rollouts share one path.
"""

from __future__ import annotations

from typing import Any, Iterable

import numpy as np
import torch
from torch import nn

from nostra.modality import Modality, as_modalities
from nostra.models.encoders import ModalityEncoder
from nostra.models.normalizer import Normalizer

# The version of the metadata nostra.policies.checkpoint writes (write_meta, on every Lightning save)
# and reads (it refuses other versions). The dependency is one-way: checkpoint.py imports
# this module (and the policy registry), this module knows nothing of reading checkpoints.
CHECKPOINT_FORMAT = 1


class PolicyNet(nn.Module):
    """Per-modality encoders (each with its own MLP) and the normaliser."""

    policy: str = ""

    def __init__(self, modalities, action_dim: int, embed_dim: int = 128, encoder_hidden=(256,),
                 image_encoder: str = "light", image_norm: str = "group", image_aug: str = "none",
                 aug_pixels: int = 8, keypoints: int = 32):
        # the keyword arguments and defaults of nostra.configs.EncoderConfig (a test keeps them equal)
        super().__init__()
        self.modalities: list[Modality] = as_modalities(modalities)
        self.action_dim = int(action_dim)
        self.embed_dim = embed_dim
        self.encoders = nn.ModuleDict({
            m.name: ModalityEncoder(m, image_encoder, embed_dim, list(encoder_hidden), image_norm, image_aug,
                                    aug_pixels, keypoints)
            for m in self.modalities
        })
        lowdim = {m.name: m.shape[0] for m in self.modalities if m.kind == "lowdim"}
        self.normalizer = Normalizer({**lowdim, "actions": self.action_dim})

    @property
    def modality_names(self) -> list[str]:
        return [m.name for m in self.modalities]

    def encode(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        missing = [k for k in self.modality_names if k not in obs]
        if missing:
            raise KeyError(f"observation is missing {missing}; this policy needs {self.modality_names}")
        out = {}
        for m in self.modalities:
            x = obs[m.name]
            if m.kind == "lowdim":
                x = self.normalizer.normalize(m.name, x)
            out[m.name] = self.encoders[m.name](x)
        return out

    def action_target(self, actions: torch.Tensor) -> torch.Tensor:
        return self.normalizer.normalize("actions", actions)

    def loss(self, batch: dict, **cfg) -> dict[str, Any]:
        raise NotImplementedError


class Runner:
    """Stateful step-by-step execution of a trained policy: ``reset()`` then ``step(obs)``.
    From a checkpoint: ``nostra.policies.checkpoint.load_runner(path, expected_policy=...)``.

    ``obs`` maps each modality name to one step's array (no batch dim). ``imagine`` (where the
    policy supports it) names modalities whose prior latent replaces the posterior this step.
    """

    policy: str = ""
    can_imagine: bool = False  # whether step(imagine=...) and adaptive imagination are supported

    def __init__(self, net: PolicyNet, device: str = "cpu"):
        if net.policy != self.policy:
            raise TypeError(f"{type(self).__name__} runs '{self.policy}' networks, got '{net.policy}'")
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.reset()

    @property
    def modality_names(self) -> list[str]:
        return self.net.modality_names

    def reset(self) -> None:
        raise NotImplementedError

    def step(self, obs: dict[str, np.ndarray], imagine: Iterable[str] | None = None):
        raise NotImplementedError

    def _to_tensors(self, obs: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        out = {}
        for m in self.net.modalities:
            if m.name not in obs:
                raise KeyError(f"observation is missing {m.name!r}; this policy needs {self.modality_names}")
            x = np.asarray(obs[m.name])
            if x.shape != m.shape:
                raise ValueError(f"observation {m.name!r} has shape {x.shape}, the policy expects {m.shape}")
            out[m.name] = torch.as_tensor(x, device=self.device).unsqueeze(0)
        return out

    def _check_imagine(self, imagine: Iterable[str] | None) -> set[str] | None:
        if imagine is None:
            return None
        names = set(imagine)
        unknown = names - set(self.modality_names)
        if unknown:
            raise ValueError(f"cannot imagine unknown modalities {sorted(unknown)}; valid: {self.modality_names}")
        return names
