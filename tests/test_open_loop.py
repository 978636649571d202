"""nostra.workflows.open_loop: a policy's actions on its held-out demos' observations against the demos'."""
import os

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import small_net, train_spec
from fixtures import write_robomimic
from nostra.data.dataset import run_episodes
from nostra.data.store import Store
from nostra.policies.checkpoint import load_runner
from nostra.workflows.open_loop import errors, main, replay
from nostra.workflows.training import train

KEYS = ["agentview_image", "robot0_eef_pos", "robot0_gripper_qpos"]


def test_errors_per_channel_and_gripper_sign():
    target = np.array([[0.0, 1.0, -1.0], [0.5, 0.0, 1.0], [1.0, -1.0, 1.0], [0.0, 0.0, -1.0]])
    actions = target + np.array([[0.1, 0.0, 0.0], [0.1, -0.2, -1.5], [-0.3, 0.0, 0.0], [0.0, 0.2, 1.2]])
    mae, agree = errors(actions, target)
    np.testing.assert_allclose(mae, [0.5 / 4, 0.4 / 4, 2.7 / 4])
    assert agree == 0.5  # steps 1 and 3 flip the gripper
    with pytest.raises(ValueError, match=r"shape \(4, 2\), the demo has \(4, 3\)"):
        errors(actions[:, :2], target)


class _Echo:
    """Acts with the stored eef position it is shown, remembering the steps and the seed it was given."""
    modality_names = ["robot0_eef_pos"]
    seed = None

    def reset(self):
        self.seen = []

    def step(self, obs, imagine=None):
        self.seen.append(obs["robot0_eef_pos"].copy())
        return obs["robot0_eef_pos"] * 2, {}


def test_replay_feeds_every_stored_step_in_order_with_the_demos_seed():
    pos = np.arange(15, dtype=np.float32).reshape(5, 3)
    runner = _Echo()
    np.testing.assert_array_equal(replay(runner, {"robot0_eef_pos": pos}, seed=7), 2 * pos)
    np.testing.assert_array_equal(np.stack(runner.seen), pos)
    assert runner.seed == 7


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("open_loop")
    here = os.getcwd()
    os.chdir(root)  # the embedded mlflow.db lands in the working directory
    store = Store(root / "store.zarr")
    store.ingest(write_robomimic(root / "d.hdf5", n=8, lengths=[12] * 8, image_size=40), name="d", progress=False)
    torch.manual_seed(0)
    spec = train_spec(policy="lstm", store=str(store.path), collections=["d"], obs_keys=KEYS, out_dir=str(root / "run"),
                      net=small_net("lstm"), optim={"lr": 1e-3}, seq_len=8, batch_size=4, max_steps=4,
                      num_workers=0, val_every=2, progress=False, experiment="test")
    try:
        train(spec)
    finally:
        os.chdir(here)
    return store, root / "run"


def test_report_matches_a_replay_by_hand(run, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    store, rdir = run
    out = tmp_path / "report"
    main(["--store", str(store.path), "--runs", f"LSTM={rdir}", "--checkpoints", "last", "--episodes", "2",
          "--split", "train", "--out", str(out)])
    row = pd.read_csv(out / "open_loop.csv").iloc[0]
    assert row["step"] == 4 and row["demos"] == 2 and row["label"] == "LSTM"
    runner = load_runner(rdir / "policy.ckpt")
    by_hand = []
    for i, (c, e) in enumerate(run_episodes(rdir, part="train")[:2]):
        data = store.episode(c, e)
        by_hand.append(np.abs(replay(runner, {k: data[k] for k in KEYS}, i) - data["actions"]).mean(0))
    by_hand = np.mean(by_hand, 0)
    assert row["arm_mae"] == pytest.approx(by_hand[:-1].mean(), rel=1e-5) and row["arm_mae"] > 0
    assert row["mae_0"] == pytest.approx(by_hand[0], rel=1e-5)
    demos = pd.read_csv(out / "open_loop_demos.csv")
    assert len(demos) == 2 * len(by_hand)
    assert (out / "open_loop.png").stat().st_size > 0 and "| LSTM | last | 4 |" in (out / "index.md").read_text()


def test_a_missing_checkpoint_is_named_before_anything_is_written(run, tmp_path):
    store, rdir = run
    with pytest.raises(FileNotFoundError, match=r"checkpoint=step=99: .* does not exist"):
        main(["--store", str(store.path), "--runs", f"LSTM={rdir}", "--checkpoints", "last", "step=99",
              "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r").exists()
