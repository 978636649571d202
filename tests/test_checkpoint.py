"""A checkpoint loads into a runner with no training code; step-by-step execution matches the
batched rollout; another model, another modality set or a non-checkpoint file gives a clear error."""

import numpy as np
import pytest
import torch

from conftest import fit, small_net
from nostra.sim import synthetic as S
from nostra.policies import runner_class
from nostra.policies.modules import policy_module
from nostra.policies.checkpoint import CheckpointError, load_net, load_runner


def _train_and_save(tmp_path, policy: str) -> tuple:
    torch.manual_seed(0)
    data = S.oscillator(8, 12, seed=0, image_size=40)
    module = policy_module(policy)([m.to_dict() for m in S.oscillator_modalities(image_size=40)], 2,
                                   net=small_net(policy), optim={"lr": 1e-3})
    module.set_normalization(S.stats_of(data))
    trainer = fit(module, S.loader(data, 4), steps=5)
    path = tmp_path / f"{policy}.ckpt"
    trainer.save_checkpoint(path)
    return path, module.eval(), data


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    return {p: _train_and_save(root, p) for p in ("nostra", "rssm", "lstm")}


@pytest.mark.parametrize("policy", ["nostra", "rssm", "lstm"])
def test_runner_matches_batched_rollout(saved, policy):
    path, module, data = saved[policy]
    runner = load_runner(path)
    assert type(runner) is runner_class(policy)
    steps = [runner.step({k: v[0, t] for k, v in data["obs"].items()})[0] for t in range(12)]
    batch = {k: torch.as_tensor(v[:1]) for k, v in data["obs"].items()}
    with torch.no_grad():
        if policy == "lstm":
            feats, _ = module.net.features(batch)
        else:
            feats, _, _ = module.net.rollout(batch, sample=False)
        expected = module.net.act(feats)[0].numpy()
    np.testing.assert_allclose(np.stack(steps), expected, rtol=1e-4, atol=1e-5)
    # normalisation statistics travel with the checkpoint
    torch.testing.assert_close(runner.net.normalizer.state_dict(), module.net.normalizer.state_dict())


def test_reset_restarts_the_episode(saved):
    path, _, data = saved["nostra"]
    runner = load_runner(path)
    obs = [{k: v[0, t] for k, v in data["obs"].items()} for t in range(5)]
    first = [runner.step(o)[0] for o in obs]
    runner.reset()
    again = [runner.step(o)[0] for o in obs]
    np.testing.assert_allclose(first, again)


def test_prior_forcing_ignores_the_imagined_input(saved):
    """With a modality imagined at every step its observation cannot change the actions, while
    its KL is still computed from it."""
    path, _, data = saved["nostra"]
    runner = load_runner(path)
    outs = []
    for scale in (1.0, 5.0):
        runner.reset()
        acts, kls = [], []
        for t in range(8):
            obs = {k: v[0, t] for k, v in data["obs"].items()}
            obs["pos"] = obs["pos"] * scale
            a, info = runner.step(obs, imagine={"pos"})
            acts.append(a), kls.append(info["kl"]["pos"])
            assert info["imagined"] == {"pos": True, "vel": False, "distractor": False, "cam_image": False}
        outs.append((np.array(acts), np.array(kls)))
    np.testing.assert_allclose(outs[0][0], outs[1][0])
    assert not np.allclose(outs[0][1], outs[1][1])


def test_rssm_imagines_the_whole_latent(saved):
    runner = load_runner(saved["rssm"][0])
    obs = {k: v[0, 0] for k, v in saved["rssm"][2]["obs"].items()}
    _, info = runner.step(obs, imagine={"cam_image"})
    assert all(info["imagined"].values()) and list(info["kl"]) == ["joint"]


def test_wrong_policy_is_refused(saved):
    with pytest.raises(CheckpointError, match="holds a 'lstm' policy, not 'nostra'"):
        load_runner(saved["lstm"][0], expected_policy="nostra")
    with pytest.raises(CheckpointError, match="holds a 'lstm' policy, not 'nostra'"):
        load_net(saved["lstm"][0], expected_policy="nostra")
    assert type(load_runner(saved["lstm"][0], expected_policy="lstm")) is runner_class("lstm")


def test_wrong_modality_set_is_refused(saved):
    with pytest.raises(CheckpointError, match="trained on modalities"):
        load_net(saved["nostra"][0], expected_modalities=["pos", "vel"])


def test_not_a_checkpoint(tmp_path):
    bad = tmp_path / "notes.ckpt"
    bad.write_text("hello")
    with pytest.raises(CheckpointError, match="notes.ckpt"):
        load_net(bad)
    plain = tmp_path / "plain.pt"
    torch.save({"state_dict": {}}, plain)
    with pytest.raises(CheckpointError, match="not a nostra policy checkpoint"):
        load_net(plain)
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        load_net(tmp_path / "missing.ckpt")


def test_bad_observations_and_imagine_names(saved):
    path, _, data = saved["nostra"]
    runner = load_runner(path)
    obs = {k: v[0, 0] for k, v in data["obs"].items()}
    with pytest.raises(KeyError, match="missing 'vel'"):
        runner.step({k: v for k, v in obs.items() if k != "vel"})
    with pytest.raises(ValueError, match=r"'pos' has shape \(3,\)"):
        runner.step({**obs, "pos": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="unknown modalities \\['depth'\\]"):
        runner.step(obs, imagine={"depth"})
    with pytest.raises(ValueError, match="no latent to imagine"):
        load_runner(saved["lstm"][0]).step(obs, imagine={"pos"})
