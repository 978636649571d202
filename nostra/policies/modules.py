"""The Lightning modules that train each policy's network (nostra.policies.<policy>): teacher-forced
sequence training, optimisers, logging with the design's metric names, and the checkpoint metadata
that nostra.policies.checkpoint reads. Only training imports this module (and Lightning): rollouts
and deployment need the networks and runners alone."""

from __future__ import annotations

import math
from dataclasses import asdict

import lightning as L
import torch
from diffusers.optimization import SchedulerType, get_scheduler
from torch.optim.swa_utils import AveragedModel

from nostra.configs import model_config
from nostra.modality import Modality, as_modalities, to_plain
from nostra.policies.base import PolicyNet
from nostra.policies.checkpoint import write_meta
from nostra.policies.diffusion import DiffusionNet
from nostra.policies.lstm import LSTMNet
from nostra.policies.nostra import NostraNet
from nostra.policies.rssm import RSSMNet

# diffusers' learning-rate schedules, by name (piecewise_constant needs rules no config gives)
SCHEDULES = [t.value for t in SchedulerType if t.value != "piecewise_constant"]


class PolicyModule(L.LightningModule):
    """Lightning wrapper: teacher-forced sequence training, Adam with a constant learning rate
    (paper Table 7; ``optim.lr_scheduler`` may decay it), logging with the design's metric names.
    ``net``, ``optim`` and ``loss`` are plain dicts, completed and checked by the policy's typed
    config (nostra.configs)."""

    net_cls: type[PolicyNet] = PolicyNet

    def __init__(self, modalities: list[Modality], action_dim: int, net: dict | None = None,
                 optim: dict | None = None, loss: dict | None = None):
        super().__init__()
        modalities = as_modalities(modalities)  # dicts too: load_from_checkpoint passes the saved hparams
        self.config = model_config(self.net_cls.policy, net=net, optim=optim, loss=loss)
        # the constructor's arguments (load_from_checkpoint passes them back), plain values only:
        # checkpoints are read with torch.load(weights_only=True)
        sections = {k: v for k, v in asdict(self.config).items() if k != "policy"}
        self.save_hyperparameters({"modalities": to_plain(modalities), "action_dim": int(action_dim), **sections})
        self.net = self.net_cls(modalities, action_dim, **asdict(self.config.net))
        self.loss_cfg = asdict(self.config.loss) if hasattr(self.config, "loss") else {}

    @property
    def policy(self) -> str:
        return self.net_cls.policy

    def set_normalization(self, stats: dict) -> None:
        self.net.normalizer.set_stats(stats)

    def training_step(self, batch, batch_idx):
        out = self.net.loss(batch, **self.loss_cfg)
        self._log("train", out, batch)
        return out["loss"]

    def validation_step(self, batch, batch_idx):
        out = self.net.loss(batch, **self.loss_cfg)
        self._log("val", out, batch)
        return out["loss"]

    def _log(self, prefix: str, out: dict, batch: dict) -> None:
        # sync_dist: under DDP a logged value is the mean over the ranks (the global batch), as one
        # process with the whole batch would log it; a no-op in a single process
        bs = batch["actions"].shape[0]
        for k in ("loss", "nll", "kl"):
            if k in out:
                self.log(f"{prefix}/{k}", out[k], prog_bar=(k == "loss"), batch_size=bs, sync_dist=True)
        for g, v in out.get("kl_nats", {}).items():
            name = f"kl_nats/{g}" if prefix == "train" else f"{prefix}/kl_nats/{g}"
            self.log(name, v, batch_size=bs, sync_dist=True)

    def configure_optimizers(self):
        return self.scheduled(torch.optim.Adam(self.parameters(), lr=self.config.optim.lr))

    def scheduled(self, opt: torch.optim.Optimizer):
        """``opt`` with the config's learning-rate schedule (a diffusers schedule stepped every batch);
        the paper's constant rate without warm-up returns ``opt`` itself."""
        cfg = self.config.optim
        if cfg.lr_scheduler not in SCHEDULES:
            raise ValueError(f"unknown optim.lr_scheduler {cfg.lr_scheduler!r}; valid: {', '.join(SCHEDULES)}")
        name = cfg.lr_scheduler
        if name == "constant":  # diffusers' constant ignores a warm-up
            if not cfg.warmup_steps:
                return opt
            name = "constant_with_warmup"
        total = cfg.total_steps or self.trainer.estimated_stepping_batches
        if not math.isfinite(total):
            raise ValueError(f"the {cfg.lr_scheduler} learning-rate schedule needs a finite length: set the "
                             "trainer's max_steps or max_epochs, or optim.total_steps")
        sched = get_scheduler(name, opt, num_warmup_steps=int(cfg.warmup_steps),
                              num_training_steps=int(total))
        # a run that outlasts `total` (a time budget on a faster machine) holds the schedule's end:
        # diffusers' half-cycle cosine would otherwise climb back up after it
        sched.lr_lambdas = [lambda step, f=f: f(min(step, int(total))) for f in sched.lr_lambdas]
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        write_meta(checkpoint, self.config, self.hparams["modalities"], self.hparams["action_dim"])


class LSTMPolicy(PolicyModule):
    net_cls = LSTMNet


class StateSpaceModule(PolicyModule):
    """Trains with the KL-balanced loss; beta and gamma: the config's ``loss`` (nostra.configs.KLLossConfig)."""


class NostraPolicy(StateSpaceModule):
    net_cls = NostraNet


class RSSMPolicy(StateSpaceModule):
    net_cls = RSSMNet


def ema_multi_avg(power: float = 0.75, max_decay: float = 0.9999):
    """diffusion_policy's EMA warm-up: decay = 1 - (1 + step) ** -power (0 at the first update, so
    short runs are not stuck near the initial weights), capped at max_decay."""

    def update(ema_params, params, n_averaged):
        decay = min(max_decay, 1.0 - float(n_averaged) ** -power)  # n_averaged >= 1 here
        for e, p in zip(ema_params, params):
            e.lerp_(p, 1.0 - decay)

    return update


class DiffusionPolicy(PolicyModule):
    """Trains ``net``; ``ema_net`` (an AveragedModel of it) holds the weights that are validated
    and deployed (checkpoint.load_net picks them)."""

    net_cls = DiffusionNet

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        optim = self.config.optim  # nostra.configs.DiffusionOptimConfig
        self.ema_net = AveragedModel(self.net, multi_avg_fn=ema_multi_avg(optim.ema_power, optim.ema_max_decay))
        self.ema_net.requires_grad_(False)

    def set_normalization(self, stats: dict) -> None:
        super().set_normalization(stats)
        self.ema_net.module.normalizer.set_stats(stats)

    def optimizer_step(self, *args, **kwargs) -> None:
        # the EMA follows every optimiser step at once, so that a callback at the batch's end (a checkpoint, an
        # in-training check) sees the weights of that step; Lightning calls callbacks' on_train_batch_end first
        super().optimizer_step(*args, **kwargs)
        self.ema_net.update_parameters(self.net)
        for e, b in zip(self.ema_net.module.buffers(), self.net.buffers()):  # buffers are copied, not averaged
            e.copy_(b)

    def validation_step(self, batch, batch_idx):
        out = self.ema_net.module.loss(batch)
        self._log("val", out, batch)
        return out["loss"]

    def _log(self, prefix: str, out: dict, batch: dict) -> None:
        super()._log(prefix, out, batch)
        self.log(f"{prefix}/mse", out["mse"], batch_size=batch["actions"].shape[0], sync_dist=True)

    def configure_optimizers(self):
        cfg = self.config.optim
        return self.scheduled(torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, betas=tuple(cfg.betas),
                                                eps=cfg.eps, weight_decay=cfg.weight_decay))


MODULES = {"nostra": NostraPolicy, "rssm": RSSMPolicy, "lstm": LSTMPolicy, "diffusion": DiffusionPolicy}


def policy_module(name: str):
    """The LightningModule class that trains policy ``name``."""
    if name not in MODULES:
        raise ValueError(f"unknown policy {name!r}; valid: {', '.join(MODULES)}")
    return MODULES[name]
