"""Diffusion Policy, CNN variant (Chi et al., 2023), paper Table 8: the encoded observations of the
first ``n_obs_steps`` frames condition a 1D temporal U-Net that denoises the ``horizon``-step action
chunk starting at the first observed frame (actions min-max scaled to [-1, 1]); DDPM training with
100 squared-cosine steps, DDPM or DDIM sampling, EMA weights for deployment, AdamW with a cosine
schedule. The runner executes ``n_action_steps`` actions of each chunk, then re-plans."""

from __future__ import annotations

from collections import deque
from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F
from diffusers import DDIMScheduler, DDPMScheduler

from nostra.models.normalizer import Normalizer
from nostra.models.unet1d import ConditionalUnet1d
from nostra.policies.base import PolicyNet, Runner

SAMPLERS = ("ddpm", "ddim")


class DiffusionNet(PolicyNet):
    policy = "diffusion"

    def __init__(self, modalities, action_dim: int, horizon: int = 16, n_obs_steps: int = 2, n_action_steps: int = 8,
                 down_dims=(256, 512, 1024), kernel_size: int = 5, n_groups: int = 8, step_embed_dim: int = 256,
                 train_steps: int = 100, sampler: str = "ddpm", inference_steps: int | None = None,
                 **encoder_kwargs):
        # the keyword arguments and defaults of nostra.configs.DiffusionNetConfig (a test keeps them equal)
        super().__init__(modalities, action_dim, **encoder_kwargs)
        if n_obs_steps < 1 or n_action_steps < 1 or n_obs_steps - 1 + n_action_steps > horizon:
            raise ValueError(f"need n_obs_steps >= 1, n_action_steps >= 1 and n_obs_steps - 1 + n_action_steps "
                             f"<= horizon; got n_obs_steps={n_obs_steps}, n_action_steps={n_action_steps}, "
                             f"horizon={horizon}")
        self.horizon, self.n_obs_steps, self.n_action_steps = int(horizon), int(n_obs_steps), int(n_action_steps)
        # same keys as the base normaliser, plus min/max of the actions for the [-1, 1] diffusion target
        dims = {k: getattr(self.normalizer, f"{k}__mean").numel() for k in self.normalizer.keys}
        self.normalizer = Normalizer(dims, ranges=("actions",))
        cond_dim = self.n_obs_steps * self.embed_dim * len(self.modalities)
        self.unet = ConditionalUnet1d(self.action_dim, cond_dim, down_dims, kernel_size, n_groups, step_embed_dim)
        self.train_steps = int(train_steps)
        self.noise_scheduler = self.make_scheduler("ddpm")
        self.sampler = self.check_sampler(sampler)
        self.inference_steps = self.check_steps(inference_steps or self.train_steps)

    @staticmethod
    def check_sampler(sampler: str) -> str:
        if sampler not in SAMPLERS:
            raise ValueError(f"unknown diffusion sampler {sampler!r}; valid: {', '.join(SAMPLERS)}")
        return sampler

    def check_steps(self, steps: int) -> int:
        if not 1 <= int(steps) <= self.train_steps:
            raise ValueError(f"inference_steps={steps} must be between 1 and the {self.train_steps} training steps")
        return int(steps)

    def make_scheduler(self, sampler: str | None = None):
        """A fresh scheduler (they keep per-call state) with the training noise schedule."""
        common = dict(num_train_timesteps=self.train_steps, beta_schedule="squaredcos_cap_v2", clip_sample=True,
                      prediction_type="epsilon")
        if self.check_sampler(sampler or self.sampler) == "ddpm":
            return DDPMScheduler(variance_type="fixed_small", **common)
        return DDIMScheduler(set_alpha_to_one=True, steps_offset=0, **common)

    def condition(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, n_obs_steps * M * embed_dim): the per-modality embeddings of the first n_obs_steps frames."""
        obs = {m: obs[m] for m in self.modality_names if m in obs}
        short = {m: x.shape[1] for m, x in obs.items() if x.shape[1] < self.n_obs_steps}
        if short:
            raise ValueError(f"observations span {short} steps; Diffusion Policy needs n_obs_steps={self.n_obs_steps}")
        emb = self.encode({m: x[:, :self.n_obs_steps] for m, x in obs.items()})
        return torch.cat([emb[m] for m in self.modality_names], -1).flatten(1)

    def action_target(self, actions: torch.Tensor) -> torch.Tensor:
        return self.normalizer.to_unit_range("actions", actions)

    def loss(self, batch: dict) -> dict:
        actions = batch["actions"]
        if actions.shape[1] < self.horizon:
            raise ValueError(f"action sequences have {actions.shape[1]} steps; Diffusion Policy predicts "
                             f"horizon={self.horizon} (set the data's seq_len to at least that)")
        x0 = self.action_target(actions[:, :self.horizon])
        cond = self.condition(batch["obs"])
        noise = torch.randn_like(x0)
        t = torch.randint(0, self.train_steps, (x0.shape[0],), device=x0.device)
        mse = F.mse_loss(self.unet(self.noise_scheduler.add_noise(x0, noise, t), t, cond), noise)
        return {"loss": mse, "mse": mse}

    @torch.no_grad()
    def sample(self, obs: dict[str, torch.Tensor], scheduler=None, steps: int | None = None,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """(B, horizon, A) actions in the data's units, denoised from Gaussian noise."""
        scheduler = scheduler or self.make_scheduler()
        scheduler.set_timesteps(self.check_steps(steps or self.inference_steps))
        cond = self.condition(obs)
        x = torch.randn((cond.shape[0], self.horizon, self.action_dim), generator=generator, device=cond.device)
        for t in scheduler.timesteps:
            x = scheduler.step(self.unet(x, t, cond), t, x, generator=generator).prev_sample
        return self.normalizer.from_unit_range("actions", x.clamp(-1, 1))


class DiffusionRunner(Runner):
    """Keeps the last n_obs_steps observations (the first repeated at episode start), plans a
    horizon-step chunk and executes its actions [n_obs_steps - 1, n_obs_steps - 1 + n_action_steps)
    one per step before planning again (receding horizon)."""

    policy = "diffusion"

    def __init__(self, net: DiffusionNet, device: str = "cpu", sampler: str | None = None,
                 inference_steps: int | None = None, seed: int | None = None):
        self.seed = seed
        super().__init__(net, device)
        self.scheduler = self.net.make_scheduler(sampler)
        self.inference_steps = self.net.check_steps(inference_steps or self.net.inference_steps)

    def reset(self) -> None:
        self.history: deque = deque(maxlen=self.net.n_obs_steps)
        self.plan: deque = deque()
        self.generator = None
        if self.seed is not None:  # reproducible sampling noise per episode
            self.generator = torch.Generator(self.device).manual_seed(self.seed)

    @torch.no_grad()
    def step(self, obs: dict[str, np.ndarray], imagine: Iterable[str] | None = None):
        if imagine:
            raise ValueError(f"Diffusion Policy has no latent to imagine (got imagine={sorted(imagine)}); "
                             f"run it with imagine=None")
        x = self._to_tensors(obs)
        if not self.history:  # episode start: the first observation stands in for the missing past
            self.history.extend([x] * self.net.n_obs_steps)
        else:
            self.history.append(x)
        replanned = not self.plan
        if replanned:
            seq = {k: torch.stack([h[k] for h in self.history], 1) for k in x}  # (1, n_obs_steps, ...)
            chunk = self.net.sample(seq, self.scheduler, self.inference_steps, self.generator)[0]
            start = self.net.n_obs_steps - 1  # the chunk starts at the oldest observed frame
            self.plan.extend(chunk[start:start + self.net.n_action_steps].cpu().numpy())
        action = self.plan.popleft()
        return action, {"kl": {}, "imagined": {m: False for m in self.modality_names}, "replanned": replanned}
