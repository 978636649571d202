import os

import lightning as L
import pytest
import torch

# Two cores: one intra-op thread per test process keeps timings stable and avoids oversubscription.
torch.set_num_threads(1)
os.environ.setdefault("HF_HUB_OFFLINE", "1")

# Small networks: the tests check the method's behaviour, not its capacity.
SMALL_NET = dict(embed_dim=32, encoder_hidden=[64], latent_dim=8, deter=64, hidden=64, fusion_embed=32,
                 fusion_out=64, decoder_hidden=[64, 64])
SMALL_LSTM = dict(embed_dim=32, encoder_hidden=[64], rnn_hidden=64, decoder_hidden=[64, 64])


def small_net(policy: str) -> dict:
    return dict(SMALL_LSTM) if policy == "lstm" else dict(SMALL_NET)


def train_spec(policy: str, net: dict | None = None, optim: dict | None = None, **kw):
    """A TrainSpec from flat keyword arguments: TrainConfig's fields (collections, obs_keys,
    out_dir, max_steps, ...) go to its ``train``, the others (store, seq_len, ...) to the spec."""
    from dataclasses import fields

    from nostra.configs import TrainConfig, model_config
    from nostra.workflows.training import TrainSpec

    train = {f.name: kw.pop(f.name) for f in fields(TrainConfig) if f.name in kw}
    return TrainSpec(model=model_config(policy, net=net, optim=optim), train=TrainConfig(**train), **kw)


def fit(module, loader, steps: int, **trainer_kwargs):
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, **trainer_kwargs)
    trainer.fit(module, loader)
    return trainer


def lr_trace(sched, steps: int) -> list[float]:
    """The learning rate a step-wise scheduler gives at each of ``steps`` optimiser steps."""
    lrs = []
    for _ in range(steps):
        lrs.append(sched.get_last_lr()[0])
        sched.optimizer.step()
        sched.step()
    return lrs


@pytest.fixture
def small():
    return small_net
