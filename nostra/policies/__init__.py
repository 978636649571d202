"""Policies by name: each a network and a stateful runner for rollouts (importing this package does
not import Lightning), and a LightningModule for training (nostra.policies.modules, which imports Lightning:
``policy_module(name)`` there)."""

from __future__ import annotations

from nostra.policies.diffusion import DiffusionNet, DiffusionRunner
from nostra.policies.lstm import LSTMNet, LSTMRunner
from nostra.policies.nostra import NostraNet, NostraRunner
from nostra.policies.rssm import RSSMNet, RSSMRunner

# name -> (network, runner)
POLICIES = {
    "nostra": (NostraNet, NostraRunner),
    "rssm": (RSSMNet, RSSMRunner),
    "lstm": (LSTMNet, LSTMRunner),
    "diffusion": (DiffusionNet, DiffusionRunner),
}


def _lookup(name: str):
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; valid: {', '.join(POLICIES)}")
    return POLICIES[name]


def net_class(name: str):
    return _lookup(name)[0]


def runner_class(name: str):
    return _lookup(name)[1]


__all__ = ["POLICIES", "net_class", "runner_class", "NostraNet", "NostraRunner", "RSSMNet",
           "RSSMRunner", "LSTMNet", "LSTMRunner", "DiffusionNet", "DiffusionRunner"]
