"""The robustness harness on a small sim: same initial states for every variant, per-step records
with noise and imagination flags, videos, Wilson intervals, errors as failed episodes with a reason,
unknown names refused at start; and the offline analyses on stored demos."""

import json

import numpy as np
import pytest
import torch

from conftest import small_net, train_spec
from nostra.workflows.analysis import OfflineSpec, analyse
from fixtures import write_robomimic
from nostra.data.store import Store
from nostra.workflows.evaluation import EvalSpec, Variant, evaluate, wilson
from nostra.noise import NoiseSchedule
from nostra.workflows.training import train

pytestmark = pytest.mark.sim
KEYS = ["agentview_image", "robot0_eye_in_hand_image", "agentview_depth", "robot0_eef_pos", "robot0_eef_quat",
        "robot0_gripper_qpos"]


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    s = Store(root / "store.zarr")
    s.ingest(write_robomimic(root / "t.hdf5", n=4, lengths=[12] * 4, image_size=40), name="t", progress=False)
    out = {}
    for p in ("nostra", "lstm"):
        torch.manual_seed(0)
        out[p] = train(train_spec(p, store=str(s.path), collections=["t"], obs_keys=KEYS, out_dir=str(root / p),
                                  net=small_net(p), seq_len=6, batch_size=2, max_steps=2, num_workers=0,
                                  progress=False, val_fraction=0, experiment="t"))["checkpoint"]
    return root, s, out


def _spec(tmp_path, ckpts, **kw):
    _, _, c = ckpts
    base = dict(tasks=["Lift"], noises=["none", "mask"], out_dir=str(tmp_path / "ev"), episodes=2, horizon=12,
                windows={"Lift": [[4, 8]]}, workers=1, videos_per_cell=1, progress=False,
                experiment="t", variants=[Variant("nostra", c["nostra"]), Variant("nostra_mli", c["nostra"], "oracle"),
                                          Variant("lstm", c["lstm"])])
    return EvalSpec(**{**base, **kw})


def test_rollouts_records_tables_and_videos(tmp_path, ckpts, monkeypatch):
    monkeypatch.chdir(tmp_path)
    table = evaluate(_spec(tmp_path, ckpts))
    assert len(table) == 2 * 3 and set(table["episodes"]) == {2}
    out = tmp_path / "ev"
    mli = np.load(out / "records/Lift/mask/nostra_mli_seed1000.npz")
    assert mli["noise"].tolist() == [False] * 4 + [True] * 4 + [False] * 4
    np.testing.assert_array_equal(mli["imagined/agentview_image"], mli["noise"])  # the oracle imagines the window
    assert not mli["imagined/robot0_eef_pos"].any()
    closed = np.load(out / "records/Lift/mask/nostra_seed1000.npz")
    assert not closed["imagined/agentview_image"].any()
    # every variant met the same initial state: same first eef position
    first = {v: np.load(out / f"records/Lift/none/{v}_seed1001.npz")["eef_pos"][0] for v in ("nostra", "lstm")}
    np.testing.assert_allclose(first["nostra"], first["lstm"])
    assert (out / "videos/Lift/mask/nostra_ep0.mp4").stat().st_size > 0
    assert not (out / "videos/Lift/mask/nostra_ep1.mp4").exists()
    md = (out / "success.md").read_text()
    assert "| BC-NOSTRA + MLI |" in md and "95% Wilson" in md
    metrics = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert any("success/Lift/mask/nostra_mli" in m.get("metrics", {}) for m in metrics)


def test_bad_names_fail_before_any_rollout(tmp_path, ckpts):
    _, _, c = ckpts
    with pytest.raises(ValueError, match="unknown task 'Lfit'; valid tasks: Lift"):
        evaluate(_spec(tmp_path, ckpts, tasks=["Lfit"]))
    with pytest.raises(ValueError, match="unknown noise 'blur'; valid noises: none, mask"):
        evaluate(_spec(tmp_path, ckpts, noises=["blur"]))
    with pytest.raises(ValueError, match="'lstm' policy cannot imagine"):
        evaluate(_spec(tmp_path, ckpts, variants=[Variant("lstm_li", c["lstm"], "oracle")]))
    with pytest.raises(ValueError, match="trained on 40x40 images, but 84x84 were asked for"):
        evaluate(_spec(tmp_path, ckpts, image_size=84))  # the checkpoint's size (40) is rendered unless told otherwise
    assert not (tmp_path / "ev").exists()


def test_a_crashing_episode_is_a_failure_with_a_reason(tmp_path, ckpts, monkeypatch):
    import nostra.sim.rollout as rollout

    monkeypatch.chdir(tmp_path)

    def explode(env, runner, job):
        raise FloatingPointError("simulated MuJoCo blow-up")

    monkeypatch.setattr(rollout, "run_episode", explode)
    table = evaluate(_spec(tmp_path, ckpts, noises=["none"], episodes=1))
    assert (table["errors"] == 1).all() and (table["successes"] == 0).all()
    assert "simulated MuJoCo blow-up" in (tmp_path / "ev/failures.log").read_text()


def test_wilson_interval():
    lo, hi = wilson(8, 10)
    assert 0.49 < lo < 0.5 and 0.94 < hi < 0.95  # the textbook values for 8/10
    assert wilson(0, 5)[0] == 0.0


def test_noise_window_timeline():
    s = NoiseSchedule("proprio_zero", [(2, 4)])
    assert [s.active(t) for t in range(6)] == [False, False, True, True, False, False]
    obs = {"robot0_eef_pos": np.ones(3, np.float32), "agentview_image": np.ones((4, 4, 3), np.uint8)}
    assert s.corrupt(obs, 2)["robot0_eef_pos"].sum() == 0 and s.corrupt(obs, 1)["robot0_eef_pos"].sum() == 3
    assert s.corrupt(obs, 2)["agentview_image"].sum() == 48
    with pytest.raises(ValueError, match="0 < start < end"):
        NoiseSchedule("mask", [(5, 5)])


def test_a_stuck_sensor_holds_what_it_read_when_the_window_opened():
    s = NoiseSchedule("proprio_stuck", [(2, 4), (5, 7)])
    pos = lambda t: {"robot0_eef_pos": np.full(3, t, np.float32), "agentview_image": np.full((2, 2, 3), t, np.uint8)}  # noqa: E731
    seen = []
    for t in range(8):
        s.prepare(None, t, np.random.default_rng(0), image_size=2)
        seen.append(s.corrupt(pos(t), t))
    assert [float(o["robot0_eef_pos"][0]) for o in seen] == [0, 1, 2, 2, 4, 5, 5, 7]  # each window holds its first
    assert [int(o["agentview_image"][0, 0, 0]) for o in seen] == list(range(8))      # cameras untouched
    assert s.keys == {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}


def test_offline_analysis(tmp_path, ckpts):
    _, s, c = ckpts
    result = analyse(OfflineSpec(c["nostra"], str(s.path), [("t", 0), ("t", 1)], noise="rgb",
                                 out_dir=str(tmp_path / "off"), progress=False))
    assert set(result["action_mse"]) == {"clean", "closed", "oracle", "adaptive"}
    assert set(result["kl_nats"]) == set(KEYS)
    assert "agentview_image" in result["detect"]
    assert set(result["false_imagination"]) == set(KEYS) | {"all"}
    assert all(0 <= v <= 1 for v in result["false_imagination"].values())
    for m in KEYS:  # an interval over the 2 episodes around the mean of their means
        lo, hi = result["kl_nats_ci"][m]
        assert lo <= hi and (lo <= result["kl_nats"][m] <= hi or np.isclose(lo, hi))
    saved = json.loads((tmp_path / "off/offline.json").read_text())
    assert saved["noise"] == "rgb" and saved["episodes"] == [["t", 0], ["t", 1]] and saved["kl_nats"] == result["kl_nats"]
    for m in KEYS:  # per episode too (views.py pairs two runs on them): their step-weighted mean is the pooled KL
        per_ep, steps = np.array(saved["kl_nats_episodes"][m]), np.array(saved["episode_steps"])
        assert len(per_ep) == 2 and np.isclose((per_ep * steps).sum() / steps.sum(), result["kl_nats"][m])
    assert (tmp_path / "off/kl_episode.png").is_file() and "AdaMLI precision" in (tmp_path / "off/offline.md").read_text()
    assert saved["adamli"]["f_o"] == 20.0 and saved["adamli"]["k_o"] == 10  # the paper's thresholds by default
    # thresholds reach AdaMLI: a warm-up longer than the episodes leaves it nothing to imagine
    late = analyse(OfflineSpec(c["nostra"], str(s.path), [("t", 0), ("t", 1)], noise="rgb", out_dir=str(tmp_path / "late"),
                               progress=False, adamli={"warmup": 10_000, "f_o": 5}))
    assert late["false_imagination"]["all"] == 0 and late["detect"]["all"]["recall"] == 0
    assert json.loads((tmp_path / "late/offline.json").read_text())["adamli"]["warmup"] == 10_000
    with pytest.raises(ValueError, match=r"unknown AdaMLI parameter\(s\) \['fo'\]; valid: f_o, k_o"):
        analyse(OfflineSpec(c["nostra"], str(s.path), [("t", 0)], noise="rgb", adamli={"fo": 5}))
    with pytest.raises(ValueError, match="needs the simulator"):
        analyse(OfflineSpec(c["nostra"], str(s.path), [("t", 0)], noise="cam_jitter"))
    with pytest.raises(ValueError, match=r"noise windows \[\[500, 600\]\] cover no step of the episodes"):
        analyse(OfflineSpec(c["nostra"], str(s.path), [("t", 0)], noise="mask", windows=[[500, 600]]))
