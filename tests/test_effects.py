"""The paper's effects on a synthetic task with known structure (oscillator: actions follow a
hidden rotating point; `distractor` is white noise with no information about the actions).

Trained with the paper's beta = 1e-4 and gamma = 0.1; the learning rate is 1e-3 instead of 1e-4
so that a few hundred steps stand in for the paper's hundreds of epochs."""

import numpy as np
import pytest
import torch

from conftest import SMALL_NET, fit
from nostra.sim import synthetic as S
from nostra.policies.imagination import detection_scores
from nostra.policies import NostraRunner
from nostra.policies.modules import NostraPolicy

STEPS, WINDOW = 40, (20, 30)


@pytest.fixture(scope="module")
def trained():
    torch.manual_seed(0)
    data = S.oscillator(256, STEPS, seed=0)
    module = NostraPolicy([m.to_dict() for m in S.oscillator_modalities()], 2, net=SMALL_NET, optim={"lr": 1e-3})
    module.set_normalization(S.stats_of(data))
    fit(module, S.loader(data, 32), steps=400)
    return module.eval(), S.oscillator(32, STEPS, seed=1)


def test_uninformative_modality_carries_least_information(trained):
    """Table 3 effect: the per-modality KL (nats) of the non-informative input ends clearly below
    that of the informative ones."""
    module, test = trained
    with torch.no_grad():
        out = module.net.loss({"obs": {k: torch.as_tensor(v) for k, v in test["obs"].items()},
                               "actions": torch.as_tensor(test["actions"])})
    kl = {k: float(v) for k, v in out["kl_nats"].items()}
    assert kl["distractor"] < 0.25 * min(kl["pos"], kl["vel"]), kl


def _window_error(module, test, mode: str, seed: int = 5) -> float:
    """Mean squared action error inside the window where `pos` is replaced by noise."""
    rng = np.random.default_rng(seed)
    errors = []
    for ep in range(len(test["actions"])):
        runner = NostraRunner(module.net)
        for t in range(STEPS):
            obs = {k: v[ep, t] for k, v in test["obs"].items()}
            inside = WINDOW[0] <= t < WINDOW[1]
            if inside and mode != "clean":
                obs["pos"] = rng.normal(0, 1, 2).astype(np.float32)
            action, info = runner.step(obs, imagine={"pos"} if inside and mode == "mli" else None)
            if inside:
                errors.append(np.sum((action - test["actions"][ep, t]) ** 2))
                assert info["imagined"]["pos"] == (mode == "mli")
                assert not info["imagined"]["vel"]
    return float(np.mean(errors))


def test_mli_keeps_actions_on_track_under_noise(trained):
    """Figure 4 effect: with the noisy modality imagined (oracle MLI) the action error inside the
    noise window stays near the clean error and far below the error without MLI."""
    module, test = trained
    clean, noisy, mli = (_window_error(module, test, m) for m in ("clean", "noisy", "mli"))
    assert mli < 0.1 * noisy, (clean, noisy, mli)
    assert noisy > 10 * clean, (clean, noisy, mli)


def test_adamli_imagines_the_noisy_modality_only(trained):
    """AdaMLI in the runner: a stuck sensor (pos frozen at a wrong reading) is switched to its prior
    inside the window and back after it. The clean modalities' KL jitters from step to step on this
    small model and the paper's 2-step baseline sometimes takes a jitter for noise: we measured
    about 9% of steps and bound it at 25%."""
    module, test = trained
    flags, truth, others = [], [], []
    for ep in range(8):
        runner = NostraRunner(module.net, adaptive=True)
        for t in range(STEPS):
            obs = {k: v[ep, t] for k, v in test["obs"].items()}
            inside = WINDOW[0] <= t < WINDOW[1]
            if inside:
                obs["pos"] = test["obs"]["pos"][ep, WINDOW[0] - 1] + 0.5
            info = runner.step(obs)[1]
            flags.append(info["imagined"]["pos"]), truth.append(inside)
            others.append(info["imagined"]["vel"] or info["imagined"]["distractor"])
    scores = detection_scores(np.array(flags), np.array(truth))
    assert scores["precision"] >= 0.9 and scores["recall"] >= 0.9, scores
    assert np.mean(others) < 0.25, np.mean(others)
