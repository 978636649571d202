"""The one episode engine (issue 14): simulator rollouts, the offline analysis and the synthetic
demo step their runners through ``nostra.episode.run``. Each is checked against the loop it
replaced, kept here verbatim as the reference, on the same seeds: same actions, KLs, imagination
flags, noise draws and records. Observation noises run on recorded observations (env=None)."""

import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import SMALL_NET
from nostra import episode
from nostra.sim import synthetic as S
from nostra.episode import RecordedSource, oracle_keys
from nostra.policies.imagination import AdaMLIConfig, in_windows, window_mask
from nostra.modality import Modality
from nostra.noise import NOISES, NoiseSchedule
from nostra.policies import (DiffusionNet, DiffusionRunner, LSTMNet, LSTMRunner, NostraNet, NostraRunner, RSSMNet,
                             RSSMRunner)

STEPS, SIZE = 24, 36
WINDOWS = [(5, 11), (15, 19)]
EAGER = AdaMLIConfig(f_o=1.5, k_o=3, f_c=1.5, k_c=2, min_changes=1, warmup=2)


def _data(seed=0):
    """Oscillator episodes under robosuite's key names, so the suite's noises act on them."""
    d = S.oscillator(2, STEPS, seed=seed, image_size=SIZE)
    o = d["obs"]
    image = np.maximum(o["cam_image"], 40)  # nothing black: a mask always shows
    depth = image[..., :1].astype(np.float32) / 255.0
    obs = {"agentview_image": image, "agentview_depth": depth, "robot0_eef_pos": o["pos"], "vel": o["vel"]}
    return obs, d["actions"]


MODS = [Modality("agentview_image", "rgb", (SIZE, SIZE, 3)), Modality("agentview_depth", "depth", (SIZE, SIZE, 1)),
        Modality("robot0_eef_pos", "lowdim", (2,)), Modality("vel", "lowdim", (2,))]


def _runner(policy, **kwargs):
    torch.manual_seed(0)
    net_cls, runner_cls = {"nostra": (NostraNet, NostraRunner), "rssm": (RSSMNet, RSSMRunner),
                           "lstm": (LSTMNet, LSTMRunner), "diffusion": (DiffusionNet, DiffusionRunner)}[policy]
    net = net_cls(MODS, 2, **{"lstm": dict(embed_dim=32, encoder_hidden=[64], rnn_hidden=64, decoder_hidden=[64, 64]),
                              "diffusion": dict(embed_dim=16, encoder_hidden=[32], down_dims=[16, 32], step_embed_dim=16)
                              }.get(policy, SMALL_NET))
    obs, actions = _data(5)
    net.normalizer.set_stats(S.stats_of({"obs": {k: v for k, v in obs.items() if k != "agentview_image"},
                                         "actions": actions}))
    return runner_cls(net, **kwargs)


# ---- the loops the engine replaced, verbatim (but for names) ---------------------------------
class _Frame:
    def __init__(self, image_size):
        self.image_size = image_size


def _old_replay(runner, obs, length, schedule, imagine_keys, image_size, seed):
    """nostra/workflows/analysis.py's _replay before issue 14."""
    rng = np.random.default_rng([seed, 7])
    frame = _Frame(image_size)
    runner.reset()
    actions, infos = [], []
    for t in range(length):
        o = {k: v[t] for k, v in obs.items()}
        if schedule is not None:
            if schedule.active(t) and not schedule.active(t - 1):
                for inj in schedule.injectors:
                    inj.begin(frame, rng)
            o = schedule.corrupt(o, t)
        imagine = imagine_keys if (schedule is not None and schedule.active(t) and imagine_keys) else None
        a, info = runner.step(o, imagine=imagine)
        actions.append(a), infos.append(info)
    return np.asarray(actions), infos


def _old_run_episode(env, runner, job):
    """nostra/sim/rollout.py's run_episode before issue 14 (the record and the step count)."""
    from nostra.sim.rollout import _unstable

    schedule = NoiseSchedule(job.noise, job.windows, job.noise_params)
    rng = np.random.default_rng([job.seed, 7])
    oracle = schedule.keys & set(runner.modality_names) if job.mode == "oracle" else None
    obs = env.reset(seed=job.seed)
    runner.reset()
    rec = {"action": [], "eef_pos": [], "noise": [], "kl": [], "imagined": []}
    success, t = False, 0
    try:
        for t in range(job.horizon):
            seen = schedule.corrupt(obs, t)
            if not all(np.isfinite(v).all() for v in seen.values() if v.dtype.kind == "f"):
                return False, t, rec, "simulation became unstable (non-finite observation)"
            action, info = runner.step(seen, imagine=oracle if schedule.active(t) else None)
            rec["action"].append(action), rec["eef_pos"].append(obs["robot0_eef_pos"])
            rec["noise"].append(schedule.active(t)), rec["kl"].append(info.get("kl", {}))
            rec["imagined"].append(info.get("imagined", {}))
            schedule.prepare(env, t + 1, rng)
            obs, _, _, step_info = env.step(np.clip(action, -1.0, 1.0))
            if _unstable(env):
                return False, t + 1, rec, "MuJoCo instability (bad QACC: the simulation diverged)"
            if step_info["success"]:
                success = True
                break
    finally:
        schedule.close(env, t + 1)
    return success, t + 1, rec, ""


def _old_pack(rec):
    """nostra/sim/rollout.py's _pack before issue 14."""
    out = {"action": np.asarray(rec["action"], np.float32).reshape(len(rec["action"]), -1),
           "eef_pos": np.asarray(rec["eef_pos"], np.float32).reshape(len(rec["eef_pos"]), -1),
           "noise": np.asarray(rec["noise"], bool)}
    for name in ("kl", "imagined"):
        keys = sorted({k for row in rec[name] for k in row})
        for k in keys:
            out[f"{name}/{k}"] = np.asarray([row.get(k, np.nan) for row in rec[name]],
                                            np.float32 if name == "kl" else bool)
    return out


class FakeEnv:
    """What a rollout asks of a SimEnv: observations that depend on the actions taken, success once
    a step count is reached, optionally a non-finite observation or a diverging simulation."""

    image_size = SIZE

    def __init__(self, succeed_at=None, nan_at=None, diverge_at=None):
        self.succeed_at, self.nan_at, self.diverge_at = succeed_at, nan_at, diverge_at
        self.data = SimpleNamespace(warning=self)  # data.warning[mjWARN_BADQACC].number

    def __getitem__(self, warning):
        return SimpleNamespace(number=int(self.diverge_at is not None and self.t >= self.diverge_at))

    def _obs(self):
        obs = {k: v[0, min(self.t, STEPS - 1)].copy() for k, v in self.base.items()}
        obs["robot0_eef_pos"] = obs["robot0_eef_pos"] + self.acc
        if self.t == self.nan_at:
            obs["vel"] = obs["vel"] * np.nan
        return obs

    def reset(self, seed):
        self.base, _ = _data(seed)
        self.t, self.acc = 0, np.zeros(2, np.float32)
        return self._obs()

    def step(self, action):
        self.t += 1
        self.acc = self.acc + 0.1 * np.asarray(action, np.float32)
        return self._obs(), 0.0, False, {"success": self.succeed_at is not None and self.t >= self.succeed_at}


# ---- the engine against the loops it replaced ------------------------------------------------
@pytest.mark.parametrize("noise", ["all", "rgbd", "proprio_zero", "blind", "clean_windows"])
@pytest.mark.parametrize("mode", ["closed", "oracle", "adaptive"])
def test_offline_replay_is_the_old_analysis_loop(noise, mode):
    runner = _runner("nostra", adaptive=mode == "adaptive", adamli=EAGER, rnn_horizon=0)
    obs, _ = _data(1)
    obs = {k: v[1] for k, v in obs.items()}
    schedule = NoiseSchedule(noise, WINDOWS)
    keys = schedule.keys & set(runner.modality_names) if mode == "oracle" else None
    want_a, want_i = _old_replay(runner, obs, STEPS, schedule, keys, SIZE, seed=3)
    run = episode.run(RecordedSource(obs, SIZE), runner, NoiseSchedule(noise, WINDOWS), mode, STEPS,
                      np.random.default_rng([3, 7]))
    np.testing.assert_array_equal(np.asarray(run.action), want_a)
    assert run.kl == [i["kl"] for i in want_i] and run.imagined == [i["imagined"] for i in want_i]
    assert run.noise == [schedule.active(t) for t in range(STEPS)] and run.steps == STEPS and not run.reason
    if mode == "oracle":  # the oracle rule: exactly the noised modalities, exactly inside the windows
        for m in runner.modality_names:
            assert [i[m] for i in run.imagined] == list(schedule.mask(STEPS) & (m in schedule.keys))


def test_clean_replay_is_the_old_loop_without_a_schedule():
    runner = _runner("rssm", rnn_horizon=0)
    obs, _ = _data(2)
    obs = {k: v[0] for k, v in obs.items()}
    want_a, want_i = _old_replay(runner, obs, STEPS, None, None, SIZE, seed=0)
    run = episode.run(RecordedSource(obs, SIZE), runner, NoiseSchedule("none", []), "closed", STEPS)
    np.testing.assert_array_equal(np.asarray(run.action), want_a)
    assert run.kl == [i["kl"] for i in want_i] and not any(run.noise)


@pytest.mark.parametrize("case", [
    dict(policy="nostra", mode="oracle", noise="all", env={}),
    dict(policy="nostra", mode="adaptive", noise="rgb", env={"succeed_at": 13}),
    dict(policy="rssm", mode="oracle", noise="clean_windows", env={"succeed_at": 7}),
    dict(policy="lstm", mode="closed", noise="mask", env={}),
    dict(policy="nostra", mode="closed", noise="proprio_zero", env={"nan_at": 9}),
    dict(policy="nostra", mode="oracle", noise="rgbd", env={"diverge_at": 16}),
    dict(policy="nostra", mode="closed", noise="blind", env={"nan_at": 3}),
])
def test_sim_rollout_is_the_old_rollout_loop(case):
    from nostra.sim.rollout import EpisodeJob, run_episode

    kwargs = {"adaptive": True, "adamli": EAGER} if case["mode"] == "adaptive" else {}
    runner = _runner(case["policy"], **kwargs)
    job = EpisodeJob("Fake", case["noise"], "v", "ckpt", case["mode"], seed=4, horizon=20, windows=WINDOWS)
    success, steps, rec, reason = _old_run_episode(FakeEnv(**case["env"]), runner, job)
    want = _old_pack(rec)
    got = run_episode(FakeEnv(**case["env"]), runner, job)
    assert (got.success, got.steps, got.reason) == (success, steps, reason)
    assert sorted(got.record) == sorted(want)
    for k in want:
        np.testing.assert_array_equal(got.record[k], want[k], err_msg=k)
        assert got.record[k].dtype == want[k].dtype
    assert {"action", "eef_pos", "noise"} <= set(got.record)
    env = case["env"]  # the cases do what they say
    if "succeed_at" in env:
        assert success and steps == env["succeed_at"]
    if "nan_at" in env:
        assert "non-finite" in reason and steps == env["nan_at"]
    if "diverge_at" in env:
        assert "instability" in reason and steps == env["diverge_at"]
    if case["mode"] != "closed":
        assert any(got.record[k].any() for k in got.record if k.startswith("imagined/"))


class ObjectsEnv(FakeEnv):
    """A FakeEnv that says where its one object is: at x = the step count."""

    def object_positions(self):
        return {"cube": np.array([self.t, 0.0, 0.8])}


def test_sim_rollout_records_where_the_objects_were_at_each_observation():
    from nostra.sim.rollout import EpisodeJob, run_episode

    job = EpisodeJob("Fake", "none", "v", "ckpt", "closed", seed=4, horizon=20, windows=WINDOWS)
    got = run_episode(ObjectsEnv(succeed_at=13), _runner("nostra"), job)
    assert got.success and got.steps == 13
    cube = got.record["object/cube"]
    assert cube.shape == (13, 3) and cube.dtype == np.float32
    np.testing.assert_array_equal(cube[:, 0], np.arange(13))  # the position seen with observation t
    assert "object/cube" not in run_episode(FakeEnv(succeed_at=13), _runner("nostra"), job).record


# ---- noise without a simulator ---------------------------------------------------------------
def test_observation_noises_run_on_recorded_observations():
    obs, _ = _data(0)
    obs = {k: v[0] for k, v in obs.items()}
    obs["robot0_eye_in_hand_image"] = obs["agentview_image"].copy()  # a second camera, for wrist_mask
    for noise in NOISES:
        schedule = NoiseSchedule(noise, WINDOWS)
        if schedule.needs_env:
            assert noise in ("cam_jitter", "table_tex")
            with pytest.raises(ValueError, match="needs the simulator"):
                schedule.prepare(None, 0, np.random.default_rng(0), image_size=SIZE)
            continue
        rng = np.random.default_rng(0)
        changed = []
        for t in range(STEPS):
            schedule.prepare(None, t, rng, image_size=SIZE)
            o = {k: v[t] for k, v in obs.items()}
            seen = schedule.corrupt(o, t)
            changed.append(any(not np.array_equal(seen[k], o[k]) for k in o))
        schedule.close(None, STEPS)
        if noise in ("none", "clean_windows"):
            assert not any(changed)
        else:  # every noise that corrupts does so inside its windows only
            want = list(schedule.mask(STEPS))
            if noise == "proprio_stuck":  # a window's first step reads what the sensor holds from then on
                for start, _ in WINDOWS:
                    want[start] = False
            assert changed == want and any(changed)
    with pytest.raises(ValueError, match="image_size"):
        NoiseSchedule("mask", WINDOWS).prepare(None, WINDOWS[0][0], np.random.default_rng(0))


def test_one_window_test():
    windows = [(2, 4), (8, 20), (-5, -2)]
    assert window_mask(10, windows).tolist() == [in_windows(t, windows) for t in range(10)]
    assert window_mask(10, windows).tolist() == [False, False, True, True, False, False, False, False, True, True]
    s = NoiseSchedule("mask", [(2, 4), (8, 20)])
    assert s.mask(10).tolist() == [s.active(t) for t in range(10)] == window_mask(10, [(2, 4), (8, 20)]).tolist()
    assert not NoiseSchedule("none", [(2, 4)]).mask(10).any()  # no noise: never active
    assert NoiseSchedule("blind", []).mask(5).all()


def test_oracle_keys():
    assert oracle_keys(NoiseSchedule("all", WINDOWS), ["agentview_image", "robot0_eef_pos", "vel"]) == \
        {"agentview_image", "robot0_eef_pos"}
    assert oracle_keys(NoiseSchedule("none", WINDOWS), ["agentview_image"]) == set()
    cams = ["agentview_image", "robot0_eye_in_hand_image", "robot0_eef_pos"]
    assert oracle_keys(NoiseSchedule("wrist_mask", WINDOWS), cams) == {"robot0_eye_in_hand_image"}  # one camera
    assert oracle_keys(NoiseSchedule("agentview_mask", WINDOWS), cams) == {"agentview_image"}


def test_wrist_mask_leaves_the_agent_view():
    obs, _ = _data(0)
    t = WINDOWS[0][0]
    image = obs["agentview_image"][0][t]  # episode 0, step t
    o = {"agentview_image": image, "robot0_eye_in_hand_image": image.copy()}
    schedule = NoiseSchedule("wrist_mask", WINDOWS)
    schedule.prepare(None, t, np.random.default_rng(0), image_size=SIZE)
    seen = schedule.corrupt(o, t)
    assert np.array_equal(seen["agentview_image"], o["agentview_image"])
    black = (seen["robot0_eye_in_hand_image"] == 0).all(axis=-1).sum()
    assert black == round(50 / 84 * SIZE) ** 2  # the paper's 50 px square at 84 px, scaled


def test_engine_and_noise_need_no_simulator():
    code = ("import sys, nostra.episode, nostra.noise, nostra.workflows.analysis; "
            "bad = [m for m in ('mujoco', 'robosuite') if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_diffusion_sampling_noise_is_fixed_by_the_episode():
    """Diffusion Policy samples its plans: a rollout of one checkpoint on one initial state must not depend
    on what the process's torch generator did before (two evaluations of a checkpoint agree)."""
    from nostra.sim.rollout import EpisodeJob, run_episode

    runner = _runner("diffusion", sampler="ddim", inference_steps=2)
    job = EpisodeJob("Fake", "none", "v", "ckpt", "closed", seed=4, horizon=12, windows=WINDOWS)
    first = run_episode(FakeEnv(), runner, job).record["action"]
    torch.manual_seed(123)  # the process's generator elsewhere
    again = run_episode(FakeEnv(), runner, job).record["action"]
    np.testing.assert_array_equal(first, again)
