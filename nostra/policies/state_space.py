"""The state-space policy shared by BC-NOSTRA and BC-RSSM: encoders -> multimodal RSSM ->
modality transformer -> action decoder. The two differ only in how the latent is split: one group
per modality (NOSTRA) or one joint group over all modalities (BC-RSSM, latent size 40 x M so both
have the same capacity)."""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch
from torch.distributions import Normal

from nostra.policies.imagination import AdaMLI, AdaMLIConfig
from nostra.models.fusion import ModalityTransformer
from nostra.models.heads import make_head
from nostra.models.rssm import MultimodalRSSM, balanced_kl, diag_kl
from nostra.policies.base import PolicyNet, Runner

JOINT = "joint"


class StateSpaceNet(PolicyNet):
    joint_latent = False

    def __init__(self, modalities, action_dim: int, latent_dim: int = 40, deter: int = 256, hidden: int = 256,
                 min_std: float = 0.1, fusion_embed: int = 256, fusion_heads: int = 2, fusion_blocks: int = 1,
                 fusion_out: int = 256, decoder_hidden=(400, 400), head: str = "gaussian", action_std: float = 1.0,
                 gmm_modes: int = 5, rnn_horizon: int = 0, **encoder_kwargs):
        # the keyword arguments and defaults of nostra.configs.StateSpaceNetConfig (a test keeps them equal)
        super().__init__(modalities, action_dim, **encoder_kwargs)
        if rnn_horizon < 0:
            raise ValueError(f"rnn_horizon must be >= 0 (0: carry the state all episode), got {rnn_horizon}")
        self.rnn_horizon = int(rnn_horizon)  # runner: restart the filter every this many steps (0: never)
        names = self.modality_names
        self.groups: dict[str, list[str]] = {JOINT: names} if self.joint_latent else {n: [n] for n in names}
        per_group = len(names) if self.joint_latent else 1
        self.core = MultimodalRSSM(len(self.groups), self.embed_dim * per_group, latent_dim * per_group,
                                   deter=deter, hidden=hidden, min_std=min_std)
        self.fusion = ModalityTransformer(len(self.groups), latent_dim * per_group, fusion_embed, fusion_heads,
                                          fusion_blocks, fusion_out)
        self.head = make_head(head, fusion_out, list(decoder_hidden), action_dim, action_std, gmm_modes)

    def group_embeds(self, embeds: dict[str, torch.Tensor]) -> torch.Tensor:
        """Per-modality embeddings (..., E) -> stacked group inputs (G, ..., E_g)."""
        return torch.stack([torch.cat([embeds[m] for m in ms], -1) for ms in self.groups.values()])

    def group_of(self, modality: str) -> str:
        return JOINT if self.joint_latent else modality

    def imagine_mask(self, imagine: dict[str, torch.Tensor]) -> torch.Tensor:
        """{group: bool tensor} -> stacked (G, ...) mask; groups not named are never imagined."""
        unknown = set(imagine) - set(self.groups)
        if unknown:
            raise ValueError(f"cannot imagine unknown groups {sorted(unknown)}; valid: {list(self.groups)}")
        like = next(iter(imagine.values()))
        return torch.stack([imagine[g] if g in imagine else torch.zeros_like(like) for g in self.groups])

    def rollout(self, obs: dict[str, torch.Tensor], imagine: dict[str, torch.Tensor] | None = None,
                sample: bool = True):
        """Filter a (B,T) sequence. imagine: group -> (B,T) bool prior-forcing mask (MLI / LI).
        Returns fused features (B,T,F) and the posteriors and priors over (G,B,T,Z)."""
        emb = self.group_embeds(self.encode(obs))  # (G,B,T,E)
        steps = emb.shape[2]
        mask = None if imagine is None else self.imagine_mask(imagine)
        state = self.core.initial(emb.shape[1], emb.device)
        zs, posts, priors = [], [], []
        for t in range(steps):
            state, post, prior = self.core.step(state, emb[:, :, t], None if mask is None else mask[:, :, t], sample)
            zs.append(state[1]), posts.append(post), priors.append(prior)
        feats = self.fusion(torch.stack(zs, 2).permute(1, 2, 0, 3))  # tokens (B,T,G,Z)
        return feats, _stack(posts), _stack(priors)

    def loss(self, batch: dict, beta: float = 1e-4, gamma: float = 0.1) -> dict:
        """L = NLL + beta * [gamma KL(q || sg(p)) + (1 - gamma) KL(sg(q) || p)], KL summed over
        latent dims and groups, NLL summed over action dims; both averaged over batch and time."""
        feats, post, prior = self.rollout(batch["obs"])
        nll = self.head.nll(feats, self.action_target(batch["actions"])).mean()
        kl = diag_kl(post, prior).flatten(1).mean(1)  # (G,) nats per group
        bal = balanced_kl(post, prior, gamma).flatten(1).mean(1).sum()
        return {"loss": nll + beta * bal, "nll": nll, "kl": kl.sum(), "kl_nats": dict(zip(self.groups, kl))}

    def act(self, feats: torch.Tensor) -> torch.Tensor:
        return self.normalizer.unnormalize("actions", self.head.act(feats))


def _stack(seq: list[Normal]) -> Normal:
    """Per-step (G,B,Z) distributions -> one over (G,B,T,Z)."""
    return Normal(torch.stack([d.loc for d in seq], 2), torch.stack([d.scale for d in seq], 2), validate_args=False)


class StateSpaceRunner(Runner):
    """Runs the filter one step at a time. Both the posterior and the prior are computed at every
    step, so the per-group KL is always observed; ``adaptive=True`` lets AdaMLI pick the latents."""

    can_imagine = True

    def __init__(self, net: StateSpaceNet, device: str = "cpu", adaptive: bool = False,
                 adamli: AdaMLIConfig | dict | None = None, rnn_horizon: int | None = None):
        cfg = adamli if isinstance(adamli, AdaMLIConfig) else AdaMLIConfig.from_dict(adamli)
        self.detector = AdaMLI(list(net.groups), cfg) if adaptive else None
        self.rnn_horizon = net.rnn_horizon if rnn_horizon is None else int(rnn_horizon)
        super().__init__(net, device)

    def reset(self) -> None:
        self.h, self.z = self.net.core.initial(1, self.device)
        self.t = 0
        if self.detector is not None:
            self.detector.reset()

    @torch.no_grad()
    def step(self, obs: dict[str, np.ndarray], imagine: Iterable[str] | None = None):
        net, core = self.net, self.net.core
        forced = self._check_imagine(imagine)
        if self.rnn_horizon and self.t and self.t % self.rnn_horizon == 0:
            self.h, self.z = core.initial(1, self.device)  # restart the filter; AdaMLI keeps its windows
        self.t += 1
        emb = net.group_embeds(net.encode(self._to_tensors(obs)))
        seen: dict = {}

        def choose(post, prior):  # which latents to imagine, once this step's KL is known
            seen["kl"] = kl = dict(zip(net.groups, diag_kl(post, prior)[:, 0].tolist()))
            flags = self.detector.update(kl) if self.detector is not None else {g: False for g in net.groups}
            if forced is not None:
                flags = {g: any(m in forced for m in ms) for g, ms in net.groups.items()}
            seen["flags"] = flags
            return torch.tensor([[flags[g]] for g in net.groups], device=self.device)

        (self.h, self.z), _, _ = core.step((self.h, self.z), emb, imagine=choose, sample=False)
        kl, flags = seen["kl"], seen["flags"]
        action = net.act(net.fusion(self.z.transpose(0, 1)))[0].cpu().numpy()
        info = {"kl": kl, "imagined": {m: bool(flags[net.group_of(m)]) for m in net.modality_names}}
        return action, info
