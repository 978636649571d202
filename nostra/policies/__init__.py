"""Policies by name: each a network and a stateful runner for rollouts (importing this package does
not import Lightning), and a LightningModule for training (nostra.policies.modules, loaded on use)."""

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
_MODULES = ("NostraPolicy", "RSSMPolicy", "LSTMPolicy", "DiffusionPolicy", "PolicyModule")


def _lookup(name: str):
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; valid: {', '.join(POLICIES)}")
    return POLICIES[name]


def net_class(name: str):
    return _lookup(name)[0]


def runner_class(name: str):
    return _lookup(name)[1]


def policy_module(name: str):
    """The LightningModule class that trains policy ``name`` (imports Lightning)."""
    _lookup(name)
    from nostra.policies.modules import MODULES

    return MODULES[name]


def __getattr__(name: str):  # the Lightning modules by name, imported on first use
    if name in _MODULES:
        from nostra.policies import modules

        return getattr(modules, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["POLICIES", "net_class", "policy_module", "runner_class", "NostraNet", "NostraRunner", "RSSMNet",
           "RSSMRunner", "LSTMNet", "LSTMRunner", "DiffusionNet", "DiffusionRunner", *_MODULES]
