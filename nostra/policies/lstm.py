"""BC-LSTM, robomimic's BC-RNN: concatenated modality embeddings -> 2-layer LSTM -> MLP or GMM
action head; deterministic hidden state, so nothing can be imagined."""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch
from torch import nn

from nostra.models.heads import make_head
from nostra.policies.base import PolicyModule, PolicyNet, Runner


class LSTMNet(PolicyNet):
    policy = "lstm"

    def __init__(self, modalities, action_dim: int, rnn_hidden: int = 400, rnn_layers: int = 2,
                 decoder_hidden=(400, 400), head: str = "gaussian", action_std: float = 1.0, gmm_modes: int = 5,
                 **encoder_kwargs):
        super().__init__(modalities, action_dim, **encoder_kwargs)
        self.rnn = nn.LSTM(self.embed_dim * len(self.modalities), rnn_hidden, rnn_layers, batch_first=True)
        self.head = make_head(head, rnn_hidden, list(decoder_hidden), action_dim, action_std, gmm_modes)

    def features(self, obs: dict[str, torch.Tensor], state=None):
        emb = self.encode(obs)
        x = torch.cat([emb[m] for m in self.modality_names], -1)
        return self.rnn(x, state)

    def loss(self, batch: dict) -> dict:
        feats, _ = self.features(batch["obs"])
        nll = self.head.nll(feats, self.action_target(batch["actions"])).mean()
        return {"loss": nll, "nll": nll}

    def act(self, feats: torch.Tensor) -> torch.Tensor:
        return self.normalizer.unnormalize("actions", self.head.act(feats))


class LSTMPolicy(PolicyModule):
    net_cls = LSTMNet


class LSTMRunner(Runner):
    policy = "lstm"

    def reset(self) -> None:
        self.state = None

    @torch.no_grad()
    def step(self, obs: dict[str, np.ndarray], imagine: Iterable[str] | None = None):
        if imagine:
            raise ValueError("BC-LSTM has no latent to imagine; run it with imagine=None")
        x = {k: v.unsqueeze(1) for k, v in self._to_tensors(obs).items()}  # (1, 1, ...)
        feats, self.state = self.net.features(x, self.state)
        action = self.net.act(feats[:, -1])[0].cpu().numpy()
        return action, {"kl": {}, "imagined": {m: False for m in self.modality_names}}
