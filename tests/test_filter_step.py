"""One filter step (issue 14): the sequence filter of training and the runner of rollouts both run
``MultimodalRSSM.step``, so filtering a whole sequence and stepping the runner through it one
observation at a time give the same latents, KLs and actions, with and without imagination."""

import numpy as np
import pytest
import torch

from conftest import SMALL_NET
from nostra.sim import synthetic as S
from nostra.policies.imagination import AdaMLIConfig
from nostra.models.rssm import MultimodalRSSM, diag_kl
from nostra.policies import NostraNet, NostraRunner, RSSMNet, RSSMRunner

STEPS, EPISODES, WINDOW = 16, 2, (6, 11)
NETS = {"nostra": (NostraNet, NostraRunner), "rssm": (RSSMNet, RSSMRunner)}
# AdaMLI made easy to trigger, so the adaptive case imagines on an untrained net
EAGER = AdaMLIConfig(f_o=1.5, k_o=3, f_c=1.5, k_c=2, min_changes=1, warmup=2)


def _setup(policy):
    data = S.oscillator(EPISODES, STEPS, seed=3)
    pos = data["obs"]["pos"]
    pos[:, WINDOW[0]:WINDOW[1]] = pos[:, WINDOW[0] - 1:WINDOW[0]] + 3.0  # a stuck sensor reading far off
    torch.manual_seed(0)
    net_cls, runner_cls = NETS[policy]
    net = net_cls(S.oscillator_modalities(), 2, **SMALL_NET)
    net.normalizer.set_stats(S.stats_of(S.oscillator(8, STEPS, seed=0)))
    return net.eval(), runner_cls, data


def _sequence(net, data, imagine=None):
    """The training-side filter over all episodes at once (eval mode, latent means)."""
    obs = {k: torch.as_tensor(v) for k, v in data["obs"].items()}
    mask = None if imagine is None else {g: torch.as_tensor(m) for g, m in imagine.items()}
    with torch.no_grad():
        feats, post, prior = net.rollout(obs, imagine=mask, sample=False)
        return net.act(feats).numpy(), diag_kl(post, prior).numpy()  # (B,T,A), (G,B,T)


def _stepped(runner, data, ep, imagine_at=None):
    runner.reset()
    actions, kls, flags = [], [], []
    for t in range(STEPS):
        obs = {k: v[ep, t] for k, v in data["obs"].items()}
        a, info = runner.step(obs, imagine=imagine_at(t) if imagine_at else None)
        actions.append(a), kls.append([info["kl"][g] for g in runner.net.groups])
        flags.append([info["imagined"][ms[0]] for ms in runner.net.groups.values()])
    return np.array(actions), np.array(kls).T, np.array(flags).T  # (T,A), (G,T), (G,T)


@pytest.mark.parametrize("policy", ["nostra", "rssm"])
def test_sequence_filter_equals_stepping_the_runner(policy):
    net, runner_cls, data = _setup(policy)
    runner = runner_cls(net, rnn_horizon=0)
    act, kl = _sequence(net, data)
    for ep in range(EPISODES):
        a, k, f = _stepped(runner, data, ep)
        np.testing.assert_allclose(a, act[ep], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(k, kl[:, ep], rtol=1e-5, atol=1e-6)
        assert not f.any()


@pytest.mark.parametrize("policy", ["nostra", "rssm"])
def test_imagination_is_the_same_in_the_sequence_filter_and_the_runner(policy):
    """Oracle MLI (NOSTRA: only ``pos``'s latent) / LI (BC-RSSM: the joint latent) inside the window."""
    net, runner_cls, data = _setup(policy)
    runner = runner_cls(net, rnn_horizon=0)
    inside = np.zeros((EPISODES, STEPS), bool)
    inside[:, WINDOW[0]:WINDOW[1]] = True
    act, kl = _sequence(net, data, {net.group_of("pos"): inside})
    closed, _ = _sequence(net, data)
    assert not np.allclose(act, closed)  # imagination changed the actions: the test can tell them apart
    for ep in range(EPISODES):
        a, k, f = _stepped(runner, data, ep, lambda t: {"pos"} if inside[ep, t] else None)
        np.testing.assert_allclose(a, act[ep], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(k, kl[:, ep], rtol=1e-5, atol=1e-6)
        assert (f[list(net.groups).index(net.group_of("pos"))] == inside[ep]).all()


@pytest.mark.parametrize("policy", ["nostra", "rssm"])
def test_adaptive_choices_replayed_through_the_sequence_filter(policy):
    """AdaMLI decides inside the step from the step's KL; its decisions, given to the sequence filter
    as a prior-forcing mask, reproduce the runner's actions and KLs."""
    net, runner_cls, data = _setup(policy)
    runner = runner_cls(net, rnn_horizon=0, adaptive=True, adamli=EAGER)
    runs = [_stepped(runner, data, ep) for ep in range(EPISODES)]
    flags = np.stack([f for _, _, f in runs], 1)  # (G,B,T)
    assert flags.any()
    act, kl = _sequence(net, data, {g: flags[i] for i, g in enumerate(net.groups)})
    for ep, (a, k, _) in enumerate(runs):
        np.testing.assert_allclose(a, act[ep], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(k, kl[:, ep], rtol=1e-5, atol=1e-6)


def test_both_paths_run_the_one_step(monkeypatch):
    net, runner_cls, data = _setup("nostra")
    calls = []
    original = MultimodalRSSM.step

    def counted(self, *args, **kwargs):
        calls.append(args[1].shape[1])  # the batch size of the step's embeddings
        return original(self, *args, **kwargs)

    monkeypatch.setattr(MultimodalRSSM, "step", counted)
    _sequence(net, data)
    assert calls == [EPISODES] * STEPS
    calls.clear()
    _stepped(runner_cls(net), data, 0)
    assert calls == [1] * STEPS
