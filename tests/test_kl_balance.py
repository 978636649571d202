"""KL balancing: gradients of gamma KL(q||sg p) + (1-gamma) KL(sg q||p) reach q and p in the
proportions the formula says (checked with autograd against the plain KL)."""

import torch
from torch.distributions import Normal

from conftest import SMALL_NET
from nostra.sim import synthetic as S
from nostra.models.rssm import balanced_kl, diag_kl
from nostra.policies import NostraNet


def _leaf_gaussians(seed):
    g = torch.Generator().manual_seed(seed)
    params = [torch.randn(5, 40, generator=g, requires_grad=True) for _ in range(4)]
    q = Normal(params[0], torch.nn.functional.softplus(params[1]) + 0.1)
    p = Normal(params[2], torch.nn.functional.softplus(params[3]) + 0.1)
    return params, q, p


def test_balanced_kl_gradient_proportions():
    gamma = 0.1
    params, q, p = _leaf_gaussians(0)
    bal = torch.autograd.grad(balanced_kl(q, p, gamma).sum(), params)
    params, q, p = _leaf_gaussians(0)
    plain = torch.autograd.grad(diag_kl(q, p).sum(), params)
    for i in (0, 1):  # posterior parameters get gamma of the plain gradient
        torch.testing.assert_close(bal[i], gamma * plain[i])
    for i in (2, 3):  # prior parameters get 1 - gamma
        torch.testing.assert_close(bal[i], (1 - gamma) * plain[i])
    # and the value is the plain KL: balancing changes gradients, not the objective
    params, q, p = _leaf_gaussians(0)
    torch.testing.assert_close(balanced_kl(q, p, gamma), diag_kl(q, p))


def test_prior_network_gets_beta_one_minus_gamma_of_kl_gradient():
    beta, gamma = 1e-4, 0.1
    data = S.oscillator(4, 6, seed=0)
    batch = {"obs": {k: torch.as_tensor(v) for k, v in data["obs"].items()}, "actions": torch.as_tensor(data["actions"])}
    torch.manual_seed(0)
    net = NostraNet(S.oscillator_modalities(), 2, **SMALL_NET)
    prior_params = [p for p in net.core.prior.parameters()]

    torch.manual_seed(1)
    loss = net.loss(batch, beta=beta, gamma=gamma)["loss"]
    g_loss = torch.autograd.grad(loss, prior_params)

    torch.manual_seed(1)  # same reparameterisation noise
    _, post, prior = net.rollout(batch["obs"])
    kl = diag_kl(post, prior).flatten(1).mean(1).sum()
    g_kl = torch.autograd.grad(kl, prior_params)

    assert any(g.abs().sum() > 0 for g in g_kl)
    for a, b in zip(g_loss, g_kl):
        torch.testing.assert_close(a, beta * (1 - gamma) * b, rtol=1e-4, atol=1e-10)
