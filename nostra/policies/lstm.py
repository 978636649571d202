"""BC-LSTM, robomimic's BC-RNN: concatenated modality embeddings -> 2-layer LSTM -> MLP or GMM
action head; deterministic hidden state, so nothing can be imagined.

It is trained on windows of ``rnn_horizon`` steps that start from a zero state, so at rollout
the runner resets the hidden state every ``rnn_horizon`` steps (robomimic does the same): the
LSTM never runs longer than it was trained to. ``rnn_horizon=0`` carries the state all episode."""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch
from torch import nn

from nostra.models.heads import make_head
from nostra.policies.base import PolicyNet, Runner


class LSTMNet(PolicyNet):
    policy = "lstm"

    def __init__(self, modalities, action_dim: int, rnn_hidden: int = 400, rnn_layers: int = 2,
                 decoder_hidden=(400, 400), head: str = "gaussian", action_std: float = 1.0, gmm_modes: int = 5,
                 rnn_horizon: int = 0, **encoder_kwargs):
        # the keyword arguments and defaults of nostra.configs.LSTMNetConfig (a test keeps them equal)
        super().__init__(modalities, action_dim, **encoder_kwargs)
        if rnn_horizon < 0:
            raise ValueError(f"rnn_horizon must be >= 0 (0: never reset), got {rnn_horizon}")
        self.rnn_horizon = int(rnn_horizon)
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


class LSTMRunner(Runner):
    policy = "lstm"

    def __init__(self, net: LSTMNet, device: str = "cpu", rnn_horizon: int | None = None):
        self.rnn_horizon = net.rnn_horizon if rnn_horizon is None else int(rnn_horizon)
        super().__init__(net, device)

    def reset(self) -> None:
        self.state, self.t = None, 0

    @torch.no_grad()
    def step(self, obs: dict[str, np.ndarray], imagine: Iterable[str] | None = None):
        if imagine:
            raise ValueError("BC-LSTM has no latent to imagine; run it with imagine=None")
        if self.rnn_horizon and self.t % self.rnn_horizon == 0:
            self.state = None  # a fresh window, as in training
        self.t += 1
        x = {k: v.unsqueeze(1) for k, v in self._to_tensors(obs).items()}  # (1, 1, ...)
        feats, self.state = self.net.features(x, self.state)
        action = self.net.act(feats[:, -1])[0].cpu().numpy()
        return action, {"kl": {}, "imagined": {m: False for m in self.modality_names}}
