"""The simulated task suite: envs, observations, experts, variation knobs, robomimic generation."""

import json

import h5py
import numpy as np
import pytest

from nostra.modality import paper_modalities
from nostra.sim import Variation, get_task, make_env, sample_variation, task_names
from nostra.sim import _gl, scene
from nostra.sim.experts import make_expert
from nostra.sim.generate import GenerateConfig, generate, run_episode
from nostra.sim.variations import robot_pixel_fraction

pytestmark = pytest.mark.sim

SIX_KEYS = {m.name for m in paper_modalities()}
META_KEYS = {"task", "language", "skill", "objects", "camera_pose", "object_placements", "variation", "success",
             "seed"}


@pytest.fixture(scope="module")
def lift():
    env = make_env("Lift", image_size=48)
    yield env
    env.close()


def test_unknown_task_lists_valid_names():
    with pytest.raises(ValueError, match="valid tasks: Lift, Stack, LiftD1, StackD1, PickPlaceCan, NutAssemblySquare, Door"):
        get_task("Lift2")
    with pytest.raises(ValueError, match="unknown task 'nope'"):
        make_env("nope")
    assert get_task("lift").name == "Lift" and task_names()[:2] == ["Lift", "Stack"]


@pytest.mark.parametrize("task", ["Lift", "Stack", "PickPlaceCan", "NutAssemblySquare", "Door"])
def test_each_task_makes_steps_and_observes(task):
    env = make_env(task, image_size=32)
    try:
        obs = env.reset(seed=3)
        for _ in range(3):
            obs, reward, done, info = env.step(np.r_[np.full(6, 0.1), -1.0])
        assert set(obs) == SIX_KEYS
        for m in paper_modalities(32):
            assert obs[m.name].shape == m.shape, m.name
            assert obs[m.name].dtype == (np.uint8 if m.kind == "rgb" else np.float32), m.name
        depth = obs["agentview_depth"]
        assert 0.05 < depth.min() and depth.max() < 10.0 and 0.3 < np.median(depth) < 3.0  # metres
        assert isinstance(reward, float) and not done and info["success"] is False
        meta = env.metadata()
        assert set(meta) == META_KEYS and meta["task"] == task and meta["seed"] == 3
        assert set(meta["object_placements"]) == set(get_task(task).objects)
        now = env.object_positions()  # what rollouts record each step: where reset put them (a nut placed in
        assert set(now) == set(get_task(task).objects)  # the air drops, so x-y only), the arm far away yet
        for name, pos in now.items():
            np.testing.assert_allclose(pos[:2], meta["object_placements"][name][:2], atol=0.02, err_msg=name)
        assert len(meta["camera_pose"]["agentview"]["quat"]) == 4
        with pytest.raises(ValueError, match="action shape"):
            env.step(np.zeros(6))
    finally:
        env.close()


def test_images_right_side_up(lift):
    obs = lift.reset(seed=0)
    depth, rgb = obs["agentview_depth"][..., 0], obs["agentview_image"].mean(-1)
    # agentview looks down at the table from the front: the near (bright white) table is at the
    # bottom of the image, the robot and the far wall at the top.
    assert depth[-4:].mean() < depth[:4].mean() - 0.5
    assert rgb[-8:].mean() > rgb[:8].mean() + 50
    # the wrist camera sees its (dark) fingers at the bottom of the image
    wrist = obs["robot0_eye_in_hand_image"].mean(-1)
    assert wrist[-6:].mean() < wrist[:6].mean() - 50


def test_lift_expert_succeeds_and_is_deterministic():
    env = make_env("Lift", render=False)
    expert = make_expert(env)
    runs = [run_episode(env, expert, seed, steps_after_success=2) for seed in (0, 1, 1)]
    env.close()
    assert all(r["meta"]["success"] for r in runs)
    assert len(runs[0]["actions"]) < 150
    np.testing.assert_array_equal(runs[1]["actions"], runs[2]["actions"])
    assert set(runs[0]["obs"]) == {"robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"}  # no cameras


def test_variations_change_image_and_metadata(lift):
    base = lift.reset(seed=0)["agentview_image"]

    textured = lift.reset(seed=0, variation=Variation(table_texture="wood-tiles"))["agentview_image"]
    assert np.abs(textured.astype(int) - base).mean() > 10
    assert lift.metadata()["variation"]["table_texture"] == "wood-tiles"

    moved = lift.reset(seed=0, variation=Variation(camera_pos_offset=(0, 0, 0.1), camera_rot_offset=(5, 0, 0)))
    assert np.abs(moved["agentview_image"].astype(int) - base).mean() > 5
    assert lift.metadata()["camera_pose"]["agentview"]["pos"][2] == pytest.approx(1.35 + 0.1, abs=1e-6)

    blue = lift.reset(seed=0, variation=Variation(object_rgba=(0, 0, 1, 1)))["agentview_image"].astype(int)
    is_blue = lambda im: ((im[..., 2] > 120) & (im[..., :2].max(-1) < 60)).sum()  # noqa: E731
    assert is_blue(blue) > 0 and is_blue(base.astype(int)) == 0

    normal_share = robot_pixel_fraction(lift)
    lift.reset(seed=0, variation=Variation(occluded_agentview=True))
    assert robot_pixel_fraction(lift) > 0.5 > 0.2 > normal_share  # the arm fills most of the occluded view
    assert lift.metadata()["variation"]["occluded_agentview"] is True

    # the blind view (Table 3's control) shows no robot and the same image whatever the arm or the seed does
    blind = lift.reset(seed=0, variation=Variation(blind_agentview=True))["agentview_image"]
    assert robot_pixel_fraction(lift) == 0.0 and np.abs(blind.astype(int) - base).mean() > 10
    moved_arm = [lift.step(np.array([1.0, -1.0, 0.5, 0, 0, 0, 1.0]))[0]["agentview_image"] for _ in range(5)][-1]
    assert np.array_equal(moved_arm, blind)
    assert np.array_equal(lift.reset(seed=3, variation=Variation(blind_agentview=True))["agentview_image"], blind)
    with pytest.raises(ValueError, match="set one"):
        Variation(occluded_agentview=True, blind_agentview=True)

    lift.reset(seed=5, variation=Variation(placement_scale=1e-3))
    assert np.abs(lift.metadata()["object_placements"]["cube"][:2]).max() < 1e-3

    # everything is undone by the next episode without the knobs
    assert np.array_equal(lift.reset(seed=0, variation=Variation())["agentview_image"], base)


def test_object_scale_recompiles_and_rests_on_table():
    env = make_env("Stack", render=False)
    env.reset(seed=0)
    cube = scene.body_geoms(env.model, scene.body_id(env.model, "cubeA_main"), visual_only=False)
    size = env.model.geom_size[cube[0]].copy()
    env.reset(seed=0, variation=Variation(object_scale=1.5))
    np.testing.assert_allclose(env.model.geom_size[cube[0]], 1.5 * size, rtol=1e-6)
    for _ in range(5):
        env.step(np.zeros(7))
    z = env.data.xpos[scene.body_id(env.model, "cubeA_main")][2]
    assert z == pytest.approx(env.raw.table_offset[2] + 1.5 * size[2], abs=2e-3)
    assert env.metadata()["variation"]["object_scale"] == 1.5
    env.close()
    with pytest.raises(ValueError, match="no objects the size knob can scale"):
        make_env("Door", render=False).reset(variation=Variation(object_scale=1.2))


def test_sample_variation_ranges_and_errors():
    ranges = {"camera_pos": 0.02, "camera_rot": 3.0, "table_textures": ["wood-tiles", "gray-felt"],
              "object_colors": [[1, 0, 0]], "object_scale": [0.9, 1.1], "occluded": 0.0}
    a = sample_variation(ranges, np.random.default_rng(1))
    assert a == sample_variation(ranges, np.random.default_rng(1))
    assert max(map(abs, a.camera_pos_offset)) <= 0.02 and a.table_texture in ("wood-tiles", "gray-felt")
    assert a.object_rgba == (1.0, 0.0, 0.0, 1.0) and 0.9 <= a.object_scale <= 1.1
    assert sample_variation({}, np.random.default_rng(0)) == Variation()
    assert sample_variation({"blind": 1.0}, np.random.default_rng(0)) == Variation(blind_agentview=True)
    with pytest.raises(ValueError, match="set one"):  # both views drawn for one episode
        sample_variation({"blind": 1.0, "occluded": 1.0}, np.random.default_rng(0))
    assert Variation.from_dict(json.loads(json.dumps(a.to_dict()))) == a
    with pytest.raises(ValueError, match="valid keys"):
        sample_variation({"camera_shake": 1}, np.random.default_rng(0))
    with pytest.raises(ValueError, match="valid: .*wood-tiles"):
        Variation(table_texture="marble")


def test_generate_two_demos_with_two_workers(tmp_path):
    out = tmp_path / "raw" / "lift_test.hdf5"
    cfg = GenerateConfig(task="lift", out=str(out), episodes=2, workers=2, image_size=32, max_steps=120,
                         steps_after_success=3, valid_fraction=0.5, variation={"table_textures": ["gray-felt"]})
    summary = generate(cfg, progress=False)
    assert summary["demos"] == 2 and summary["failed"] == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["lift_test.hdf5"]  # no temporary file left
    with h5py.File(out, "r") as f:
        assert set(f) == {"data", "mask"} and set(f["data"]) == {"demo_0", "demo_1"}
        assert set(f["data"].attrs) == {"total", "env_args", "next_obs_derived"}
        assert not f["data"].attrs["next_obs_derived"]  # the simulator's real next observations
        env_args = json.loads(f["data"].attrs["env_args"])
        assert env_args["env_name"] == "Lift" and env_args["type"] == 1
        assert env_args["env_kwargs"]["camera_heights"] == 32 and env_args["env_kwargs"]["robots"] == "Panda"
        total = 0
        for name in ("demo_0", "demo_1"):
            g = f["data"][name]
            assert set(g.attrs) == {"num_samples", "model_file"} | META_KEYS
            assert set(g) == {"states", "actions", "rewards", "dones", "obs", "next_obs"}
            n = g.attrs["num_samples"]
            total += n
            assert g["actions"].shape == (n, 7) and g["states"].shape[0] == n and g["dones"][-1] == 1
            assert set(g["obs"]) == set(g["next_obs"]) == SIX_KEYS
            assert g["obs/agentview_image"].shape == (n, 32, 32, 3) and g["obs/agentview_image"].dtype == np.uint8
            np.testing.assert_array_equal(g["obs/robot0_eef_pos"][1:], g["next_obs/robot0_eef_pos"][:-1])
            assert g.attrs["task"] == "Lift" and g.attrs["success"] and "<mujoco" in g.attrs["model_file"]
            assert json.loads(g.attrs["variation"])["table_texture"] == "gray-felt"
            assert json.loads(g.attrs["objects"]) == ["cube"]
        assert f["data"].attrs["total"] == total
        masks = sorted(list(f["mask/train"][:]) + list(f["mask/valid"][:]))
        assert masks == [b"demo_0", b"demo_1"] and len(f["mask/valid"]) == 1


def test_generate_failure_leaves_no_file(tmp_path):
    out = tmp_path / "never.hdf5"
    cfg = GenerateConfig(task="Lift", out=str(out), episodes=1, workers=1, image_size=32, max_steps=2)
    with pytest.raises(RuntimeError, match="failed all 2 episodes"):
        generate(cfg, progress=False)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="unknown task"):
        GenerateConfig(task="Nope", out=str(out))


def test_gl_error_names_both_backends(monkeypatch):
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setenv("NOSTRA_GL_ERROR", "")
    monkeypatch.setattr(_gl, "probe", lambda backend: f"{backend} missing")
    assert _gl.select_backend() == "egl"
    with pytest.raises(RuntimeError, match="neither EGL nor OSMesa works.*egl: egl missing; osmesa: osmesa missing"):
        _gl.check_render()


def test_generate_stage_cli(tmp_path, capsys):
    from pipeline.generate import main

    out = tmp_path / "cli.hdf5"
    assert main(["task=lift", "generate.episodes=1", "generate.workers=1", "generate.image_size=32",
                 "generate.max_steps=100", "generate.progress=false", f"generate.out={out}"]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["demos"] == 1 and summary["task"] == "Lift" and out.exists()
    with pytest.raises(SystemExit):
        main(["task=lift", "generate.variation.object_scale=[1.2,0.8]", f"generate.out={tmp_path / 'bad.hdf5'}"])
    assert "object_scale: low 1.2 > high 0.8" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["task=lift", "generate.action_noise=0.2", "generate.action_noise_phases=[approach,hover]",
              f"generate.out={tmp_path / 'bad.hdf5'}"])
    err = capsys.readouterr().err
    assert "action_noise_phases: unknown phase(s) ['hover']" in err and "approach, descend" in err
    assert not (tmp_path / "bad.hdf5").exists()


@pytest.mark.parametrize("task", ["Lift", "Stack", "PickPlaceCan", "NutAssemblySquare", "Door"])
def test_generated_demos_ingest_and_round_trip(task, tmp_path):
    """A couple of expert demos per task, small images: generated, ingested into the store, exported
    back to robomimic HDF5 and ingested again to identical arrays."""
    from nostra.data.store import Store

    raw = tmp_path / f"{task.lower()}.hdf5"
    summary = generate(GenerateConfig(task=task, out=str(raw), episodes=2, workers=1, image_size=36,
                                      steps_after_success=2, valid_fraction=0.5), progress=False)
    assert summary["demos"] == 2
    store = Store(tmp_path / "store.zarr")
    name = store.ingest(raw, progress=False)
    table = store.episodes(name)
    assert list(table["task"]) == [task, task] and table["success"].all()
    exported = store.export(name, tmp_path / "export.hdf5")
    other = Store(tmp_path / "other.zarr")  # a fresh store: the first one would recognise the content
    again = other.ingest(exported, progress=False)
    assert store.keys(name) == other.keys(again)
    for key in store.keys(name):
        np.testing.assert_array_equal(store.array(name, key)[:], other.array(again, key)[:])
