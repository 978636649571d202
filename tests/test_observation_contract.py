"""The observation contract (issue 14): one declaration of what the simulator renders
(``nostra.modality.sim_observations``) that every other module reads; policies hold Modality
objects and checkpoints store them; evaluation renders exactly a checkpoint's keys at its image
size, whatever the config's profile says, and refuses an explicit size that disagrees."""

from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import small_net
from nostra.modality import Modality, ObservationSpec, render_size, sim_observations, to_plain
from nostra.policies.modules import policy_module

ROOT = Path(__file__).resolve().parents[1]
KEYS, SIZE = ["robot0_eef_pos", "agentview_image"], 36  # a subset, at a size no profile renders


def _checkpoint(path, modalities) -> str:
    """An untrained BC-LSTM checkpoint with PolicyModule's metadata (no Trainer needed)."""
    torch.manual_seed(0)
    module = policy_module("lstm")(modalities, 7, net=small_net("lstm"))
    dims = {m.name: m.shape for m in modalities if m.kind == "lowdim"} | {"actions": (7,)}
    module.set_normalization({k: {"mean": np.zeros(d), "std": np.ones(d)} for k, d in dims.items()})
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, path)
    return str(path)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    return _checkpoint(tmp_path_factory.mktemp("contract") / "lstm.ckpt", sim_observations(SIZE).select(KEYS))


class FakeSim:
    """Stands in for SimEnv: renders every modality of the contract at the size it was built with
    (records what it was built with), never succeeds, never diverges."""

    built: list = []

    def __init__(self, task, image_size=84, **kwargs):
        self.observations = sim_observations(image_size)
        FakeSim.built.append((task, image_size))
        self.data = SimpleNamespace(warning=defaultdict(lambda: SimpleNamespace(number=0)))

    def _obs(self):
        return {m.name: np.zeros(m.shape, np.uint8 if m.kind == "rgb" else np.float32)
                for m in self.observations.modalities}

    def reset(self, seed=None):
        return self._obs()

    def step(self, action):
        return self._obs(), 0.0, False, {"success": False}


@pytest.fixture
def fake_sim(monkeypatch):
    import nostra.sim.env
    import nostra.sim.rollout as rollout

    monkeypatch.setattr(nostra.sim.env, "make_env", FakeSim)
    monkeypatch.setattr(rollout, "_ENVS", {})
    monkeypatch.setattr(rollout, "_RUNNERS", {})
    monkeypatch.setattr(FakeSim, "built", [])
    return FakeSim


# ---- the declaration ----------------------------------------------------------------------------
def test_the_simulator_declares_six_modalities_with_kinds_cameras_and_size():
    sim = sim_observations(40)
    assert len(sim.names) == 6 and sim.image_size == 40
    assert [len(sim.rgb_keys), len(sim.depth_keys), len(sim.lowdim_keys)] == [2, 1, 3]
    assert sim.cameras == ("agentview", "robot0_eye_in_hand") and sim.depth_cameras == ("agentview",)
    assert [sim.camera_of(k) for k in (*sim.rgb_keys, *sim.depth_keys)] == ["agentview", "robot0_eye_in_hand",
                                                                            "agentview"]
    assert all(m.shape[:2] == (40, 40) for m in sim.modalities if m.is_image)
    assert sim.select(KEYS) == [sim[k] for k in KEYS]  # in the order asked for


def test_an_unknown_key_is_refused_naming_the_valid_ones():
    sim = sim_observations()
    with pytest.raises(ValueError, match=r"unknown observation keys \['agentview_rgb'\]; valid: \['agentview_image'"):
        sim.select(["robot0_eef_pos", "agentview_rgb"])
    with pytest.raises(ValueError, match="robot0_gripper_qpos"):  # the message lists every valid key
        sim["wrist_image"]
    with pytest.raises(ValueError, match="not an image"):
        sim.camera_of("robot0_eef_pos")


def test_one_image_size_per_set_and_a_requested_size_never_wins():
    with pytest.raises(ValueError, match="one square size"):
        ObservationSpec((*sim_observations(32).select(["agentview_image"]),
                         *sim_observations(40).select(["robot0_eye_in_hand_image"])))
    mods = sim_observations(SIZE).select(KEYS)
    assert render_size(mods) == render_size(mods, SIZE) == SIZE
    with pytest.raises(ValueError, match=rf"trained on {SIZE}x{SIZE} images, but 84x84"):
        render_size(mods, 84)
    lowdim = sim_observations().select(["robot0_eef_pos"])
    assert render_size(lowdim) == 84 and render_size(lowdim, 40) == 40  # no images: the request, else 84


# ---- Modality objects all the way; dicts only in the checkpoint ----------------------------------
def test_policies_hold_modalities_and_checkpoints_store_them(ckpt):
    from nostra.policies.checkpoint import load_net, read_meta

    mods = sim_observations(SIZE).select(KEYS)
    module = policy_module("nostra")(mods, 7, net=small_net("nostra"))
    assert module.net.modalities == mods and all(isinstance(m, Modality) for m in module.net.modalities)
    assert module.hparams["modalities"] == to_plain(mods)  # plain, as Lightning's hparams must be
    assert read_meta(ckpt)[0]["modalities"] == to_plain(mods)
    assert load_net(ckpt).modalities == mods


# ---- evaluation renders what the checkpoint says ---------------------------------------------------
def _evaluate_config(profile: str, out_dir: Path, ckpt: str):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from pipeline._hydra import CONF_DIR

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose("config", overrides=[
            f"profile={profile}", "task=lift", "evaluate.noises=[none]", "evaluate.episodes=1",
            "evaluate.horizon=3", "evaluate.workers=1", "evaluate.videos_per_cell=0", "evaluate.offline.enabled=false",
            f"evaluate.out_dir={out_dir}"])
    variants = {name: None for name in cfg.evaluate.variants} | {"lstm": {"checkpoint": ckpt, "mode": "closed"}}
    OmegaConf.update(cfg, "evaluate.variants", variants, merge=True)
    return cfg


@pytest.mark.parametrize("profile", ["ci", "tiny"])  # they render 40 and 84 px; the checkpoint is 36 px
def test_evaluation_takes_keys_and_image_size_from_the_checkpoint(tmp_path, monkeypatch, fake_sim, ckpt, profile):
    import nostra.workflows.figures as figures
    import nostra.workflows.tracking as tracking
    from nostra.configs import typed
    from pipeline.evaluate import _rollouts

    class QuietTracker:  # no MLflow run: this test is about what is rendered
        def __init__(self, *args, **kwargs):
            pass

        log_metrics = log_artifact = lambda self, *a: None
        finish = lambda self: ""  # noqa: E731

    monkeypatch.setattr(tracking, "Tracker", QuietTracker)
    monkeypatch.setattr(figures, "trajectory_figure", lambda *a: None)
    cfg = _evaluate_config(profile, tmp_path / "ev", ckpt)
    assert cfg.profile.image_size != SIZE and cfg.evaluate.image_size is None
    _rollouts(cfg, typed(cfg.evaluate, "evaluate"))
    assert fake_sim.built == [("Lift", SIZE)]
    assert (tmp_path / "ev/failures.log").read_text() == ""  # the runner got its shapes
    record = np.load(tmp_path / "ev/records/Lift/none/lstm_seed1000.npz")
    assert sorted(k.removeprefix("imagined/") for k in record.files if k.startswith("imagined/")) == sorted(KEYS)
    assert record["action"].shape == (3, 7)


def test_an_explicit_image_size_that_disagrees_is_refused_naming_both(tmp_path, ckpt, fake_sim):
    from nostra.sim.rollout import EpisodeJob, work
    from nostra.workflows.evaluation import EvalSpec, Variant, validate

    spec = EvalSpec(tasks=["Lift"], noises=["none"], variants=[Variant("lstm", ckpt)], out_dir=str(tmp_path),
                    image_size=40)
    with pytest.raises(ValueError, match=rf"variant 'lstm'.*trained on {SIZE}x{SIZE} images, but 40x40"):
        validate(spec)
    spec.image_size = SIZE
    validate(spec)  # agreeing is fine
    # a job that asks for another size (no validate before it) fails its episode, saying why
    result = work(EpisodeJob("Lift", "none", "lstm", ckpt, "closed", 0, 3, [], image_size=40))
    assert not result.success and f"trained on {SIZE}x{SIZE} images, but 40x40" in result.reason
    assert fake_sim.built == []


def test_a_policy_the_simulator_cannot_feed_is_refused(tmp_path):
    from nostra.workflows.evaluation import EvalSpec, Variant, validate

    odd = _checkpoint(tmp_path / "odd.ckpt", [Modality("robot0_joint_pos", "lowdim", (7,))])
    spec = EvalSpec(tasks=["Lift"], noises=["none"], variants=[Variant("lstm", odd)], out_dir=str(tmp_path))
    with pytest.raises(ValueError, match=r"unknown observation keys \['robot0_joint_pos'\]; valid: \["):
        validate(spec)
    wrong = _checkpoint(tmp_path / "wrong.ckpt", [Modality("robot0_eef_pos", "lowdim", (7,))])
    with pytest.raises(ValueError, match=r"robot0_eef_pos as lowdim \(7,\); the simulator renders lowdim \(3,\)"):
        validate(EvalSpec(tasks=["Lift"], noises=["none"], variants=[Variant("lstm", wrong)], out_dir=str(tmp_path)))


# ---- no module but the contract spells the keys -------------------------------------------------
# retrieval/ is left out: it imports nothing of nostra (a Store-like API only); its frames key is a
# default argument. Configs may name a selection (a profile's obs_keys): the code checks it here.
ALLOWED = {"nostra/modality.py"}


def spellings(texts: dict[str, str]) -> dict[str, list[str]]:
    """path -> the contract's keys its text spells, for every file but the contract."""
    keys = sim_observations().names
    found = {path: [k for k in keys if k in text] for path, text in texts.items() if path not in ALLOWED}
    return {path: ks for path, ks in found.items() if ks}


def test_only_the_contract_spells_the_observation_keys():
    texts = {p.relative_to(ROOT).as_posix(): p.read_text() for d in ("nostra", "pipeline", "bench")
             for p in sorted((ROOT / d).rglob("*.py"))}
    assert "nostra/noise.py" in texts and "bench/policy_step.py" in texts
    assert spellings(texts) == {}


def test_the_spelling_check_can_fail():
    texts = {"nostra/modality.py": 'Modality("agentview_depth", "depth", (84, 84, 1))',
             "nostra/noise.py": 'DEPTH_KEYS = ("agentview_depth",)  # robot0_eef_pos too'}
    assert spellings(texts) == {"nostra/noise.py": ["agentview_depth", "robot0_eef_pos"]}


def test_windows_that_start_past_the_horizon_are_named_before_any_rollout(tmp_path, ckpt, fake_sim, recwarn):
    from nostra.workflows.evaluation import EvalSpec, Variant, validate

    spec = EvalSpec(tasks=["Lift"], noises=["mask"], variants=[Variant("lstm", ckpt)], out_dir=str(tmp_path),
                    horizon=40, windows={"Lift": [[15, 35], [45, 60]]})
    with pytest.warns(UserWarning, match=r"task Lift: noise windows \[\[45, 60\]\] start at or after the rollout horizon 40"):
        validate(spec)
    spec.horizon = 60  # [45, 60) ends at the horizon: applied in full
    recwarn.clear()
    validate(spec)
    assert not [w for w in recwarn if "rollout horizon" in str(w.message)]
    assert fake_sim.built == []


def test_the_eval_spec_is_built_from_the_typed_config():
    from dataclasses import fields

    from nostra.configs import EvaluateConfig
    from nostra.workflows.evaluation import EvalSpec

    e = EvaluateConfig(tasks=["Lift"], noises=["mask"], out_dir="ev", episodes=7, seed=5, horizon=60, workers=1,
                       videos_per_cell=0, checkpoint="best", experiment="x", noise_params={"mask": {}})
    spec = EvalSpec.from_config(e, variants=[], windows={"Lift": [[1, 2]]}, run_name="r")
    shared = {f.name for f in fields(EvalSpec)} & {f.name for f in fields(EvaluateConfig)} - {"variants", "windows"}
    assert shared >= {"episodes", "seed", "horizon", "workers", "checkpoint", "noise_params", "image_size"}
    assert all(getattr(spec, n) == getattr(e, n) for n in shared)
    assert (spec.variants, spec.windows, spec.run_name) == ([], {"Lift": [[1, 2]]}, "r")


@pytest.mark.parametrize("profile", sorted(p.stem for p in (ROOT / "conf" / "profile").glob("*.yaml")))
def test_every_profile_selects_keys_the_simulator_renders(profile):
    from omegaconf import OmegaConf

    from nostra.modality import sim_observations

    keys = OmegaConf.load(ROOT / "conf" / "profile" / f"{profile}.yaml").get("obs_keys") or []
    assert set(keys) <= set(sim_observations().names), sorted(set(keys) - set(sim_observations().names))


def test_cpu_rgbd_is_the_cpu_profile_seeing_depth_too():
    """Table 2's profile (OBS=rgbd in scripts/cpu.sh): the cpu profile's budget and shapes, and the
    observation set with agentview depth added."""
    from hydra import compose, initialize_config_dir

    from pipeline._hydra import CONF_DIR

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cpu = compose("config", overrides=["profile=cpu"])
        rgbd = compose("config", overrides=["profile=cpu_rgbd"])
    assert rgbd.data.obs_keys == cpu.data.obs_keys[:2] + ["agentview_depth"] + cpu.data.obs_keys[2:]
    assert {k: v for k, v in rgbd.profile.items() if k not in ("name", "obs_keys")} == \
        {k: v for k, v in cpu.profile.items() if k not in ("name", "obs_keys")}
