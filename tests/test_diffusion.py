"""Diffusion Policy: the denoiser learns a conditioned action chunk, sampling stays in the data's
range, the checkpoint deploys the EMA weights, and the runner re-plans every n_action_steps."""

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from conftest import fit, lr_trace
from nostra.configs import DiffusionConfig
from nostra.data.stats import fit_stats
from nostra.models.normalizer import Normalizer
from nostra.policies.modules import policy_module
from nostra.policies.checkpoint import load_net, load_runner
from nostra.policies.diffusion import DiffusionNet, DiffusionRunner
from nostra.policies.modules import DiffusionPolicy

MODS = [{"name": "pos", "kind": "lowdim", "shape": [2]}]
TINY = dict(embed_dim=16, encoder_hidden=[32], down_dims=[16, 32], step_embed_dim=16)
PHASES, STEPS = 4, 400


def circle_task():
    """Four episodes on the unit circle, one per start phase: obs = the point, action = the next point,
    so the 16-step chunk is a sinusoid fixed by the observed phase."""
    phase = np.linspace(0, 2 * np.pi, PHASES, endpoint=False)[:, None]
    point = np.stack([np.cos(phase + 0.3 * np.arange(17)), np.sin(phase + 0.3 * np.arange(17))], -1).astype(np.float32)
    return {"pos": torch.as_tensor(point[:, :-1])}, torch.as_tensor(point[:, 1:])


def seeded_loss(net, batch, seed=0):
    torch.manual_seed(seed)  # same noise and diffusion steps for every call
    with torch.no_grad():
        return float(net.loss(batch)["mse"])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    torch.manual_seed(0)
    obs, actions = circle_task()
    module = DiffusionPolicy(MODS, 2, net=TINY, optim={"lr": 3e-3, "warmup_steps": 20})
    module.set_normalization(fit_stats({"pos": obs["pos"].numpy(), "actions": actions.numpy()}))
    batch = {"obs": {"pos": obs["pos"].repeat(16, 1, 1)}, "actions": actions.repeat(16, 1, 1)}
    before = seeded_loss(module.net, batch)
    trainer = fit(module, DataLoader([batch] * STEPS, batch_size=None), STEPS)
    path = tmp_path_factory.mktemp("dp") / "dp.ckpt"
    trainer.save_checkpoint(path)
    return SimpleNamespace(module=module, trainer=trainer, batch=batch, before=before, path=path, obs=obs,
                           actions=actions)


def test_denoising_loss_falls_and_is_logged(trained):
    after = seeded_loss(trained.module.net, trained.batch)
    assert after < 0.1 * trained.before, (trained.before, after)
    assert {"train/loss", "train/mse"} <= set(trained.trainer.callback_metrics)


def test_reproduces_the_conditioned_chunk(trained):
    net = trained.module.ema_net.module
    pred = net.sample(trained.obs, net.make_scheduler("ddpm"), 100, torch.Generator().manual_seed(0))
    truth = trained.actions
    rmse = float((pred - truth).pow(2).mean().sqrt())
    mean_rmse = float((truth.mean(0, keepdim=True) - truth).pow(2).mean().sqrt())  # ignoring the observation
    assert rmse < 0.15 and rmse < 0.25 * mean_rmse, (rmse, mean_rmse)
    # each episode's chunk is nearest to its own truth: the observation conditions the samples
    dist = (pred[:, None] - truth[None]).pow(2).mean((2, 3))
    assert torch.equal(dist.argmin(1), torch.arange(PHASES)), dist


@pytest.mark.parametrize("sampler,steps", [("ddpm", 100), ("ddim", 10)])
def test_samples_stay_in_the_data_range(trained, sampler, steps):
    torch.manual_seed(0)
    net = DiffusionNet(MODS, 2, **TINY)  # untrained: its raw samples hit the clip on both sides
    lo, hi = np.array([2.0, -0.1], np.float32), np.array([5.0, 0.3], np.float32)
    net.normalizer.set_stats({"pos": {"mean": [0, 0], "std": [1, 1]},
                              "actions": {"mean": (lo + hi) / 2, "std": [1, 1], "min": lo, "max": hi}})
    for model in (net, trained.module.ema_net.module):
        a = model.sample(trained.obs, model.make_scheduler(sampler), steps).numpy()
        a_lo, a_hi = model.normalizer.actions__min.numpy(), model.normalizer.actions__max.numpy()
        assert a.shape == (PHASES, 16, 2)
        assert (a >= a_lo - 1e-5).all() and (a <= a_hi + 1e-5).all(), (a.min((0, 1)), a.max((0, 1)), a_lo, a_hi)
    assert a_lo[0] < 0 < a_hi[0]  # the trained model's range is the circle's, not the untrained one's


def test_checkpoint_deploys_ema_weights_and_round_trips(trained):
    ema, raw = trained.module.ema_net.module.state_dict(), trained.module.net.state_dict()
    loaded = load_net(trained.path).state_dict()
    assert all(torch.equal(loaded[k], ema[k]) for k in ema)
    assert any(not torch.equal(ema[k], raw[k]) for k in ema)  # EMA weights really differ from the trained ones
    resumed = DiffusionPolicy.load_from_checkpoint(trained.path)  # training resumes with both copies
    assert all(torch.equal(resumed.ema_net.module.state_dict()[k], ema[k]) for k in ema)

    kwargs = dict(sampler="ddim", inference_steps=10, seed=3)
    a = DiffusionRunner(copy.deepcopy(trained.module.ema_net.module), **kwargs)
    b = load_runner(trained.path, modalities=["pos"], **kwargs)
    assert isinstance(b, DiffusionRunner)
    for t in range(10):
        o = {"pos": trained.obs["pos"][1, t].numpy()}
        np.testing.assert_allclose(a.step(o)[0], b.step(o)[0], atol=1e-6)


def test_runner_replans_every_action_horizon(trained):
    net = copy.deepcopy(trained.module.ema_net.module)
    runner = DiffusionRunner(net, sampler="ddim", inference_steps=10, seed=0)
    obs = trained.obs["pos"][2]
    actions, flags = [], []
    for t in range(16):
        a, info = runner.step({"pos": obs[t].numpy()})
        assert info["kl"] == {} and info["imagined"] == {"pos": False}
        actions.append(a)
        flags.append(info["replanned"])
    assert flags == [t % 8 == 0 for t in range(16)]
    # the same draws by hand: plan 1 sees the first frame twice, plan 2 frames 7 and 8; each executes
    # chunk steps [1, 9) (the chunk starts at the older observed frame)
    g = torch.Generator().manual_seed(0)
    sched = net.make_scheduler("ddim")
    plan1 = net.sample({"pos": obs[[0, 0]][None]}, sched, 10, g)[0, 1:9]
    plan2 = net.sample({"pos": obs[[7, 8]][None]}, sched, 10, g)[0, 1:9]
    np.testing.assert_allclose(np.stack(actions), torch.cat([plan1, plan2]).numpy(), atol=1e-6)
    runner.reset()
    assert runner.step({"pos": obs[0].numpy()})[1]["replanned"]


def test_runner_rejects_imagination(trained):
    runner = DiffusionRunner(copy.deepcopy(trained.module.ema_net.module), sampler="ddim", inference_steps=2)
    with pytest.raises(ValueError, match="no latent to imagine"):
        runner.step({"pos": np.zeros(2, np.float32)}, imagine=["pos"])
    runner.step({"pos": np.zeros(2, np.float32)}, imagine=[])  # nothing to imagine is fine


def test_clear_errors():
    with pytest.raises(ValueError, match="valid: ddpm, ddim"):
        DiffusionNet(MODS, 2, sampler="euler", **TINY)
    with pytest.raises(ValueError, match="inference_steps=200"):
        DiffusionNet(MODS, 2, inference_steps=200, **TINY)
    with pytest.raises(ValueError, match="n_action_steps=16"):
        DiffusionNet(MODS, 2, n_action_steps=16, **TINY)
    net = DiffusionNet(MODS, 2, **TINY)
    with pytest.raises(ValueError, match="horizon=16"):
        net.loss({"obs": {"pos": torch.zeros(2, 8, 2)}, "actions": torch.zeros(2, 8, 2)})
    with pytest.raises(KeyError, match="'min' and 'max'"):
        net.normalizer.set_stats({k: {"mean": [0, 0], "std": [1, 1]} for k in ("pos", "actions")})
    with pytest.raises(ValueError, match="unknown keys"):
        Normalizer({"actions": 2}, ranges=["action"])


def test_registered_and_config_fits():
    """The paper's settings (Table 8); the typed config's fields are DiffusionNet's arguments and
    conf/model/diffusion.yaml extends it (tests/test_typed_config.py)."""
    assert policy_module("diffusion") is DiffusionPolicy
    cfg = DiffusionConfig()
    assert (cfg.net.horizon, cfg.net.n_obs_steps, cfg.net.n_action_steps, cfg.net.train_steps) == (16, 2, 8, 100)
    assert (cfg.optim.lr, cfg.optim.betas, cfg.optim.weight_decay, cfg.optim.lr_scheduler) == (1e-4, [0.95, 0.999],
                                                                                              1e-6, "cosine")


def test_cosine_schedule_holds_its_end_past_total_steps():
    """optim.total_steps sets the cosine's length (the cpu profile: what its time budget buys); a run
    that goes on past it stays at the schedule's end instead of climbing back up."""
    module = DiffusionPolicy(MODS, 2, net=TINY, optim={"lr": 1.0, "warmup_steps": 2, "total_steps": 10})
    lrs = lr_trace(module.configure_optimizers()["lr_scheduler"]["scheduler"], 30)
    assert lrs[2] == pytest.approx(1.0) and 0 < lrs[6] < 1.0
    assert lrs[10] == pytest.approx(0.0, abs=1e-9) and max(lrs[10:]) == pytest.approx(0.0, abs=1e-9)


def test_cpu_profile_sizes_the_schedule_to_its_budget():
    from hydra import compose, initialize_config_dir

    from pipeline._hydra import CONF_DIR

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cpu = compose("config", overrides=["profile=cpu", "model=diffusion"])
        tiny = compose("config", overrides=["profile=tiny", "model=diffusion"])
    assert cpu.model.optim.total_steps == cpu.profile.dp_total_steps < cpu.profile.train_steps
    assert tiny.model.optim.total_steps is None


def test_training_windows_cover_the_prediction_horizon():
    """A profile's data.seq_len shorter than the horizon (the cpu profile's 10) is raised to it for
    Diffusion Policy only; a longer one is kept."""
    from nostra.configs import LSTMConfig
    from nostra.workflows.training import window_length

    assert window_length(SimpleNamespace(seq_len=10, model=DiffusionConfig())) == 16
    assert window_length(SimpleNamespace(seq_len=20, model=DiffusionConfig())) == 20
    assert window_length(SimpleNamespace(seq_len=10, model=LSTMConfig())) == 10


def test_a_callback_at_the_batch_end_sees_the_ema_of_that_step():
    """In-training checks and step checkpoints run in callbacks' on_train_batch_end, which Lightning calls before
    the module's: the EMA must already hold the step's update there (it lagged one step when updated in the hook)."""
    import lightning as L

    class Seen(L.Callback):
        def __init__(self):
            self.pairs = []

        def on_train_batch_end(self, trainer, pl_module, *args):
            self.pairs.append((trainer.global_step, int(pl_module.ema_net.n_averaged)))

    torch.manual_seed(0)
    obs, actions = circle_task()
    module = DiffusionPolicy(MODS, 2, net=TINY, optim={"lr": 1e-3, "warmup_steps": 2})
    module.set_normalization(fit_stats({"pos": obs["pos"].numpy(), "actions": actions.numpy()}))
    seen = Seen()
    fit(module, DataLoader([{"obs": obs, "actions": actions}] * 3, batch_size=None), 3, callbacks=[seen])
    assert seen.pairs == [(1, 1), (2, 2), (3, 3)]
