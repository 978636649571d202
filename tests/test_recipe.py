"""The training recipe of the CPU profile: image augmentation in training only, recurrent state
reset every rnn_horizon steps at rollout, noise-injected demos (executed vs expert actions), the
blind control, rollouts during training with the best checkpoint, and checkpoint selection."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import small_net, train_spec
from fixtures import write_robomimic
from nostra.data.store import Store
from nostra.modality import Modality
from nostra.models.encoders import ImageAug
from nostra.policies import LSTMNet, LSTMRunner, NostraNet, NostraRunner
from nostra.policies.checkpoint import select_checkpoint
from nostra.noise import NoiseSchedule
from nostra.configs import RolloutConfig
from nostra.workflows.training import train
from nostra.workflows.training_rollouts import RolloutEnv

MODS = [Modality("agentview_image", "rgb", (40, 40, 3)), Modality("robot0_eef_pos", "lowdim", (3,))]


def _obs(rng, n):
    return [{"agentview_image": rng.integers(0, 256, (40, 40, 3), dtype=np.uint8),
             "robot0_eef_pos": rng.normal(size=3).astype(np.float32)} for _ in range(n)]


@pytest.mark.parametrize("kind", ["crop", "shift"])
def test_augmentation_changes_training_batches_never_evaluation(kind):
    torch.manual_seed(0)
    net = LSTMNet(MODS, 7, image_aug=kind, aug_pixels=4, **small_net("lstm"))
    frames = torch.randint(0, 256, (4, 2, 40, 40, 3), dtype=torch.uint8)
    obs = {"agentview_image": frames, "robot0_eef_pos": torch.zeros(4, 2, 3)}
    net.train()
    a, b = net.encode(obs)["agentview_image"], net.encode(obs)["agentview_image"]
    assert not torch.allclose(a, b)  # a new random window each time
    net.eval()
    c, d = net.encode(obs)["agentview_image"], net.encode(obs)["agentview_image"]
    torch.testing.assert_close(c, d)
    aug = ImageAug(kind, 4).eval()
    flat = frames.reshape(-1, 40, 40, 3)
    expected = flat[:, 2:38, 2:38] if kind == "crop" else flat
    assert torch.equal(aug(flat), expected)  # centre crop / untouched at evaluation
    # runners put the network in eval mode: the same observation gives the same action
    runner = LSTMRunner(net, rnn_horizon=1)
    o = _obs(np.random.default_rng(0), 1)[0]
    np.testing.assert_array_equal(runner.step(o)[0], runner.step(o)[0])


def test_unknown_augmentation_is_refused():
    with pytest.raises(ValueError, match="crop, shift"):
        ImageAug("flip")


@pytest.mark.parametrize("cls,runner_cls", [(LSTMNet, LSTMRunner), (NostraNet, NostraRunner)])
def test_state_is_reset_exactly_every_rnn_horizon_steps(cls, runner_cls):
    torch.manual_seed(0)
    net = cls(MODS, 7, **small_net("lstm" if cls is LSTMNet else "nostra")).eval()
    steps = _obs(np.random.default_rng(1), 7)
    every3 = runner_cls(net, rnn_horizon=3)
    acts = [every3.step(o)[0] for o in steps]
    fresh = runner_cls(net, rnn_horizon=0)
    for start in (0, 3, 6):  # a window starts here: the same actions as a runner just reset
        fresh.reset()
        for t in range(start, min(start + 3, 7)):
            np.testing.assert_allclose(acts[t], fresh.step(steps[t])[0], rtol=1e-5, atol=1e-6)
    carried = runner_cls(net, rnn_horizon=0)
    carried_acts = [carried.step(o)[0] for o in steps]
    np.testing.assert_allclose(acts[:3], carried_acts[:3], rtol=1e-5, atol=1e-6)
    assert not np.allclose(acts[3], carried_acts[3])  # carrying the state differs after the reset point


def test_blind_noise_blacks_every_camera_from_the_first_step():
    s = NoiseSchedule("blind", [[15, 35]])
    assert s.active(0) and s.active(500)
    obs = {"agentview_image": np.full((4, 4, 3), 200, np.uint8), "agentview_depth": np.ones((4, 4, 1), np.float32),
           "robot0_eef_pos": np.ones(3, np.float32)}
    seen = s.corrupt(obs, 0)
    assert not seen["agentview_image"].any() and not seen["agentview_depth"].any()
    np.testing.assert_array_equal(seen["robot0_eef_pos"], obs["robot0_eef_pos"])
    assert {"agentview_image", "robot0_eye_in_hand_image", "agentview_depth"} == s.keys


@pytest.mark.sim
def test_noisy_demos_store_the_expert_action_or_the_executed_one():
    from nostra.sim.env import make_env
    from nostra.sim.experts import make_expert
    from nostra.sim.generate import run_episode

    env = make_env("Lift", render=False)
    expert = make_expert(env)
    clean = run_episode(env, expert, 3, max_steps=25)
    dart = run_episode(env, expert, 3, max_steps=25, action_noise=0.2, record="expert")
    mimic = run_episode(env, expert, 3, max_steps=25, action_noise=0.2, record="executed")
    np.testing.assert_array_equal(dart["states"], mimic["states"])  # the same noise, the same executed path
    assert not np.allclose(dart["states"], clean["states"])  # ... which the noise changed
    diff = mimic["actions"] - dart["actions"]  # executed = clip(expert + noise)
    assert 0.05 < np.abs(diff).mean() < 0.3 and np.abs(mimic["actions"]).max() <= 1.0
    env.close()


@pytest.mark.sim
def test_noise_in_some_phases_only_leaves_the_other_phases_executed_as_the_expert_said():
    from nostra.sim.env import make_env
    from nostra.sim.experts import make_expert
    from nostra.sim.generate import run_episode

    env = make_env("Lift", render=False)
    expert, phases = make_expert(env), []
    act = expert.act
    expert.act = lambda obs=None: (act(obs), phases.append(expert.phase))[0]  # the phase of each action
    run = lambda **kw: run_episode(env, expert, 3, max_steps=60, action_noise=0.2, **kw)  # noqa: E731
    everywhere = run(record="executed")
    phases.clear()
    executed = run(record="executed", noise_phases=("approach",))
    said = run(record="expert", noise_phases=("approach",))
    approach = np.array([p == "approach" for p in phases[:len(executed["actions"])]])
    k = int(approach.sum())
    assert 0 < k < len(approach) and approach[:k].all()  # the approach, then the descent
    np.testing.assert_array_equal(executed["actions"][:k], everywhere["actions"][:k])  # the same draws
    assert not np.allclose(executed["actions"][:k], said["actions"][:k])  # noised there
    np.testing.assert_array_equal(executed["actions"][k:], said["actions"][k:])  # and nowhere else
    env.close()


def test_checkpoint_selection(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "policy.ckpt").write_bytes(b"x")
    assert select_checkpoint(run / "policy.ckpt", "last") == str(run / "policy.ckpt")
    with pytest.raises(FileNotFoundError, match="without in-training rollouts"):
        select_checkpoint(run / "policy.ckpt", "best")
    (run / "checkpoints" / "step=20.ckpt").write_bytes(b"x")
    assert select_checkpoint(run, "step=20").endswith("step=20.ckpt")
    with pytest.raises(FileNotFoundError, match="step=20"):
        select_checkpoint(run, "step=30")
    with pytest.raises(ValueError, match="best | last"):
        select_checkpoint(run, "first")


@pytest.mark.sim
def test_rollouts_during_training_log_success_and_keep_the_best(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    keys = ["agentview_image", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
    s = Store(tmp_path / "store.zarr")
    s.ingest(write_robomimic(tmp_path / "t.hdf5", n=4, lengths=[12] * 4, image_size=40), name="t", progress=False)
    common = dict(store=str(s.path), collections=["t"], obs_keys=keys, seq_len=6, batch_size=2, num_workers=0,
                  progress=False, val_fraction=0, experiment="t", rollout_env=RolloutEnv("Lift"),
                  rollout=RolloutConfig(every=2, episodes=2, final_episodes=3, modes=["closed", "oracle"],
                                        noises=["none", "blind"], horizon=5, workers=1))
    out = tmp_path / "run"
    torch.manual_seed(0)
    result = train(train_spec("nostra", net=small_net("nostra"), out_dir=str(out), max_steps=4, **common))
    checks = json.loads((out / "rollouts.json").read_text())
    assert [(c["step"], c["episodes"]) for c in checks] == [(2, 2), (4, 2), (4, 3)]
    assert set(checks[0]["success"]) == {"none/nostra", "none/nostra_mli", "blind/nostra", "blind/nostra_mli"}
    assert (out / "checkpoints/best.ckpt").is_file() and (out / "checkpoints/step=2.ckpt").is_file()
    assert result["rollouts"]["checks"] == 3 and result["best_checkpoint"].endswith("best.ckpt")
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    steps = [m["step"] for m in logged if "rollout/Lift/none/nostra" in m.get("metrics", {})]
    assert steps == [2, 4, 4]
    assert select_checkpoint(out / "policy.ckpt", "best") == str(out / "checkpoints/best.ckpt")
    with pytest.raises(ValueError, match="cannot imagine"):
        train(train_spec("lstm", net=small_net("lstm"), out_dir=str(tmp_path / "l"), max_steps=2, **common))


def test_windows_override_from_the_command_line_reaches_evaluation_and_training_rollouts():
    from hydra import compose, initialize_config_dir

    from pipeline._hydra import CONF_DIR
    from pipeline.evaluate import noise_windows

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose("config", overrides=["task=liftd1", "evaluate.windows={LiftD1: [[30, 60]]}"])
        default = compose("config", overrides=["task=liftd1"])
    assert noise_windows(cfg) == {"LiftD1": [[30, 60]]}
    assert noise_windows(default) == {"LiftD1": [[15, 35], [45, 60]]}  # the task config's


def test_bad_windows_fail_before_any_worker_starts(tmp_path):
    from nostra.workflows.evaluation import EvalSpec, validate

    spec = EvalSpec(tasks=["Lift"], noises=["none", "mask"], variants=[], out_dir=str(tmp_path),
                    windows={"Lift": [[0, 10]]})
    with pytest.raises(ValueError, match=r"task Lift, noise 'none', windows \[\[0, 10\]\].*0 < start < end"):
        validate(spec)
    spec.windows = {"Lift": [[5]]}
    with pytest.raises(ValueError, match="task Lift"):
        validate(spec)


def test_every_phase_the_scripts_name_is_one_the_noise_can_be_restricted_to():
    import re

    from nostra.sim import experts

    source = Path(experts.__file__).read_text()
    named = set(re.findall(r'(?:move|hold)\("(\w+)"', source)) | set(re.findall(r'phase = "(\w+)"', source))
    assert {"approach", "descend", "grasp", "place", "release"} <= named
    assert named - {""} == set(experts.PHASES)
