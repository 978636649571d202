"""All three policies learn: a few hundred Lightning steps on one small batch drive the loss down,
with an rgb view, lowdim inputs and both action heads exercised."""

import math

import pytest
import torch
from torch.utils.data import DataLoader

from conftest import fit, small_net
from nostra.sim import synthetic as S
from nostra.policies.modules import policy_module


@pytest.mark.parametrize("policy,head", [("nostra", "gaussian"), ("rssm", "gaussian"), ("lstm", "gaussian"),
                                         ("nostra", "gmm")])
def test_loss_goes_down(policy, head):
    torch.manual_seed(0)
    data = S.oscillator(8, 10, seed=0, image_size=40)
    module = policy_module(policy)([m.to_dict() for m in S.oscillator_modalities(image_size=40)], 2,
                                   net={**small_net(policy), "head": head}, optim={"lr": 1e-3})
    module.set_normalization(S.stats_of(data))
    batch = next(iter(S.loader(data, 8)))
    with torch.no_grad():
        before = float(module.net.loss(batch, **module.loss_cfg)["nll"])
    fit(module, DataLoader([batch] * 250, batch_size=None), steps=250)
    with torch.no_grad():
        after = float(module.net.loss(batch, **module.loss_cfg)["nll"])
    if head == "gaussian":  # fixed unit variance: the nll's floor is 0.5 log(2 pi) per action dim
        floor = 0.5 * 2 * math.log(2 * math.pi)
        assert after - floor < 0.05 * (before - floor), (before, after)
    else:  # a gmm's learned variances take the nll far below its start
        assert after < before - 2.0, (before, after)
