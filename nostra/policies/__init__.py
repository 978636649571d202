"""Policies by name: each a LightningModule for training and a stateful runner for rollouts."""

from __future__ import annotations

from nostra.policies.diffusion import DiffusionNet, DiffusionPolicy, DiffusionRunner
from nostra.policies.lstm import LSTMNet, LSTMPolicy, LSTMRunner
from nostra.policies.nostra import NostraNet, NostraPolicy, NostraRunner
from nostra.policies.rssm import RSSMNet, RSSMPolicy, RSSMRunner

POLICIES = {
    "nostra": (NostraPolicy, NostraRunner),
    "rssm": (RSSMPolicy, RSSMRunner),
    "lstm": (LSTMPolicy, LSTMRunner),
    "diffusion": (DiffusionPolicy, DiffusionRunner),
}


def _lookup(name: str):
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; valid: {', '.join(POLICIES)}")
    return POLICIES[name]


def policy_module(name: str):
    return _lookup(name)[0]


def runner_class(name: str):
    return _lookup(name)[1]


__all__ = ["POLICIES", "policy_module", "runner_class", "NostraNet", "NostraPolicy", "NostraRunner",
           "RSSMNet", "RSSMPolicy", "RSSMRunner", "LSTMNet", "LSTMPolicy", "LSTMRunner",
           "DiffusionNet", "DiffusionPolicy", "DiffusionRunner"]
