"""A robosuite task behind a small interface that speaks the toolkit's observation contract.

``make_env("Lift")`` builds a Panda with robosuite's BASIC composite controller (OSC_POSE arm,
7-d delta actions: 3 position, 3 axis-angle rotation, 1 gripper) at 20 Hz. Observations are the
modalities of the observation contract, ``nostra.modality.sim_observations(image_size)`` (also
``env.observations``): each camera's RGB image (uint8 HxWx3, right side up), the agent view's
depth (float32 HxWx1, metres) and the float32 proprioception (the quaternion x, y, z, w as
robosuite gives it).

For run-time scene changes (noise injectors) use ``env.model`` / ``env.data`` (mujoco.MjModel /
MjData) with the helpers of :mod:`nostra.sim.scene`: ``env.camera_id("agentview")`` for
``model.cam_pos`` / ``model.cam_quat``, ``env.table_material_ids`` for the table's materials
(``scene.set_material_texture(env.model, env.render_context, mat, "wood-tiles")``), and call
``env.observe()`` to render observations after a change. ``env.restore_scene()`` undoes them.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
import types

import numpy as np

from nostra.modality import ObservationSpec, sim_observations
from nostra.sim import _gl, scene
from nostra.sim.tasks import CONTROL_FREQ, ROBOT, TaskSpec, get_task
from nostra.sim.variations import Variation, scale_range


def import_robosuite():
    """Import robosuite with right-side-up images and quiet logs (through robosuite's own
    `macros_private` hook, which is read while robosuite is first imported)."""
    _gl.select_backend()
    if "robosuite" not in sys.modules:
        private = types.ModuleType("robosuite.macros_private")
        private.IMAGE_CONVENTION = "opencv"
        private.CONSOLE_LOGGING_LEVEL = "ERROR"  # not the optional robots/IK/gym notices
        sys.modules.setdefault("robosuite.macros_private", private)
        with contextlib.redirect_stdout(io.StringIO()):  # its wrappers print a gym notice on import
            import robosuite
            import robosuite.utils.camera_utils  # noqa: F401  (imports the wrappers)
    import robosuite
    import robosuite.macros as macros

    macros.IMAGE_CONVENTION = "opencv"  # in case robosuite was imported before us
    logging.getLogger("robosuite_logs").setLevel(logging.ERROR)
    return robosuite


def robosuite_kwargs(spec: TaskSpec, image_size: int = 84, depth: bool = True, render: bool = True) -> dict:
    """Keyword arguments of ``robosuite.make`` for a task (JSON-serialisable: robomimic's env_kwargs)."""
    import_robosuite()
    from robosuite.controllers import load_composite_controller_config

    kwargs = dict(
        robots=ROBOT, controller_configs=load_composite_controller_config(controller="BASIC", robot=ROBOT),
        has_renderer=False, has_offscreen_renderer=render, use_camera_obs=render, use_object_obs=False,
        reward_shaping=False, control_freq=CONTROL_FREQ, horizon=spec.horizon, ignore_done=True, hard_reset=False,
        **spec.env_kwargs,
    )
    if render:
        kwargs.update(camera_kwargs(rendered_observations(image_size, depth)))
    return kwargs


def rendered_observations(image_size: int, depth: bool = True, render: bool = True) -> ObservationSpec:
    """The contract's modalities that an env built with these arguments returns."""
    kinds = {"lowdim"} | ({"rgb"} if render else set()) | ({"depth"} if render and depth else set())
    return ObservationSpec(tuple(m for m in sim_observations(image_size).modalities if m.kind in kinds))


def camera_kwargs(spec: ObservationSpec) -> dict:
    """robosuite's camera arguments that render ``spec``'s images (one size; depth where it has depth)."""
    size = spec.image_size
    return dict(camera_names=list(spec.cameras), camera_heights=size, camera_widths=size,
                camera_depths=[cam in spec.depth_cameras for cam in spec.cameras])


def robomimic_env_args(spec: TaskSpec, kwargs: dict) -> dict:
    """robomimic's `env_args` of a dataset (type 1 = robosuite)."""
    import robosuite

    return {"env_name": spec.env_name, "env_version": robosuite.__version__, "type": 1,
            "env_kwargs": json.loads(json.dumps(kwargs))}


class SimEnv:
    """One robosuite task instance; ``reset`` applies an episode's seed and variation."""

    def __init__(self, spec: TaskSpec, image_size: int, variation: Variation | None, seed: int, depth: bool,
                 tuned_render: bool, render: bool):
        self.spec, self.image_size, self.depth, self.render = spec, int(image_size), bool(depth), bool(render)
        self.observations = rendered_observations(self.image_size, self.depth, self.render)  # what observe() returns
        self.tuned_render = bool(tuned_render)
        self.variation = variation or Variation()
        self.kwargs = robosuite_kwargs(spec, image_size, depth, render)
        self._build_seed, self._next_seed = int(seed), int(seed)
        self._scale = 1.0  # object scale the current model was compiled with
        robosuite = import_robosuite()
        if render:
            _gl.check_render()
        try:
            self.raw = robosuite.make(spec.env_name, seed=self._build_seed, **self.kwargs)
        except Exception as exc:
            if render and _looks_like_gl_error(exc):
                raise _gl.render_error(exc) from exc
            raise
        self.raw._xml_processors.append(self._scale_xml)
        for sampler in self.placement_samplers():  # the task's own range (D1 variants), before it is recorded
            sampler.x_range = scale_range(sampler.x_range, spec.placement_scale)
            sampler.y_range = scale_range(sampler.y_range, spec.placement_scale)
        self._on_new_sim()
        self.seed, self.steps, self._placements = self._build_seed, 0, {}

    # ---- access to the simulator -----------------------------------------------------------
    @property
    def model(self):
        """The mujoco.MjModel (replaced when a size variation recompiles the scene)."""
        return self.raw.sim.model._model

    @property
    def data(self):
        return self.raw.sim.data._data

    @property
    def render_context(self):
        return self.raw.sim._render_context_offscreen

    def camera_id(self, name: str = "agentview") -> int:
        return scene.camera_id(self.model, name)

    @property
    def table_material_ids(self) -> list[int]:
        return [scene.material_id(self.model, m) for m in self.spec.table_materials]

    def sim_state(self) -> np.ndarray:
        """The flattened MuJoCo state (time, qpos, qvel) that robomimic stores as `states`."""
        return np.asarray(self.raw.sim.get_state().flatten())

    def model_xml(self) -> str:
        return self.raw.sim.model.get_xml()

    def env_args(self) -> dict:
        return robomimic_env_args(self.spec, self.kwargs)

    # ---- episode interface -----------------------------------------------------------------
    def reset(self, seed: int | None = None, variation: Variation | None = None) -> dict:
        """Start an episode: seeded placements, then the variation's scene changes."""
        if variation is not None:
            self.variation = variation
        self.seed = self._next_seed if seed is None else int(seed)
        self._next_seed = self.seed + 1
        if self.variation.object_scale != self._scale:
            self._rebuild(self.variation.object_scale)
        self.restore_scene()
        self.variation.apply_to_model(self)
        self.raw.rng.bit_generator.state = np.random.default_rng(self.seed).bit_generator.state
        self.raw.reset()
        if self._scale != 1.0:
            self._settle_scaled_objects()
        self.steps = 0
        self._placements = {name: pos.round(6).tolist() for name, pos in self.object_positions().items()}
        return self.observe()

    def object_positions(self) -> dict[str, np.ndarray]:
        """Where the task's objects are now (world frame), by the task's object names."""
        return {name: self.data.xpos[scene.body_id(self.model, body)].copy()
                for name, body in self.spec.bodies.items()}

    def step(self, action) -> tuple[dict, float, bool, dict]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (self.raw.action_dim,):
            raise ValueError(f"action shape {action.shape} != ({self.raw.action_dim},) for task {self.spec.name}")
        raw_obs, reward, _, _ = self.raw.step(action)
        self.steps += 1
        success = self.is_success()
        done = self.steps >= self.spec.horizon
        return self._convert(raw_obs), float(reward), done, {"success": success}

    def is_success(self) -> bool:
        return bool(self.spec.success(self.raw))

    def observe(self) -> dict:
        """Observations of the current state, re-rendered (after a scene change, for example)."""
        return self._convert(self.raw._get_observations(force_update=True))

    def metadata(self) -> dict:
        """The per-episode metadata of the contract (success as of now)."""
        self.raw.sim.forward()
        cam = self.camera_id("agentview")
        return {
            "task": self.spec.name, "language": self.spec.language, "skill": self.spec.skill,
            "objects": self.spec.objects,
            "camera_pose": {"agentview": scene.camera_pose(self.model, self.data, cam)},
            "object_placements": dict(self._placements), "variation": self.variation.to_dict(),
            "success": self.is_success(), "seed": int(self.seed),
        }

    def restore_scene(self) -> None:
        """Undo every model change (cameras, colours, textures, placement ranges) since build."""
        m, orig = self.model, self._orig
        m.cam_pos[:], m.cam_quat[:] = orig["cam_pos"], orig["cam_quat"]
        m.geom_rgba[:], m.geom_matid[:], m.mat_rgba[:] = orig["geom_rgba"], orig["geom_matid"], orig["mat_rgba"]
        for tex in list(self._dirty_textures):
            scene.texture_view(m, tex)[...] = orig["textures"][tex]
            if self.render_context is not None:
                self.render_context.upload_texture(tex)
        self._dirty_textures.clear()
        for sampler, (xr, yr) in orig["ranges"].items():
            sampler.x_range, sampler.y_range = xr, yr

    def set_table_texture(self, image) -> None:
        """Retexture the table (a robosuite texture name or an HxWx3 uint8 image)."""
        for mat in self.table_material_ids:
            tex = scene.material_texture(self.model, mat)
            if tex >= 0 and tex not in self._orig["textures"]:
                self._orig["textures"][tex] = scene.texture_view(self.model, tex).copy()
            self._dirty_textures.add(tex)
            scene.set_material_texture(self.model, self.render_context, mat, image)

    def placement_samplers(self) -> list:
        """robosuite's object placement samplers (their x/y ranges are the placement knob)."""
        return _leaf_samplers(getattr(self.raw, "placement_initializer", None))

    def close(self) -> None:
        self.raw.close()

    # ---- internals ---------------------------------------------------------------------------
    def _convert(self, raw: dict) -> dict:
        return contract_obs(self.raw.sim, raw, self.observations)

    def _on_new_sim(self) -> None:
        """Tune rendering and remember the pristine model of a freshly compiled sim."""
        if self.render and self.tuned_render:
            tune_rendering(self.raw.sim)
        m = self.model
        self._orig = {"cam_pos": m.cam_pos.copy(), "cam_quat": m.cam_quat.copy(), "geom_rgba": m.geom_rgba.copy(),
                      "geom_matid": m.geom_matid.copy(), "mat_rgba": m.mat_rgba.copy(), "textures": {},
                      "ranges": {s: (tuple(s.x_range), tuple(s.y_range)) for s in self.placement_samplers()}}
        self._dirty_textures = set()

    def _scale_xml(self, xml: str) -> str:
        return scene.scale_bodies_xml(xml, self.spec.rescale_bodies, self._scale)

    def _rebuild(self, scale: float) -> None:
        """Recompile the scene with objects scaled (sizes are fixed in a compiled model)."""
        if scale != 1.0 and not self.spec.rescale_bodies:
            raise ValueError(f"task {self.spec.name} has no objects the size knob can scale (object_scale={scale})")
        self.restore_scene()  # the placement samplers outlive the model
        self._scale = float(scale)
        self.raw.rng.bit_generator.state = np.random.default_rng(self._build_seed).bit_generator.state
        self.raw._destroy_sim()
        self.raw.hard_reset = True
        try:
            self.raw.reset()
        finally:
            self.raw.hard_reset = False
        self._on_new_sim()

    def _settle_scaled_objects(self) -> None:
        """robosuite placed scaled objects by their unscaled bottom; lift them onto the surface."""
        for obj in self.raw.model.mujoco_objects:
            if obj.root_body in self.spec.rescale_bodies and obj.joints:
                qpos = self.raw.sim.data.get_joint_qpos(obj.joints[0]).copy()
                qpos[2] += (self._scale - 1.0) * -obj.bottom_offset[2]
                self.raw.sim.data.set_joint_qpos(obj.joints[0], qpos)
        self.raw.sim.forward()


def contract_obs(sim, raw: dict, spec: ObservationSpec) -> dict:
    """robosuite's observations of the modalities of ``spec`` (robosuite names them as the contract
    does), depth in metres."""
    obs = {}
    for m in spec.modalities:
        if m.kind == "lowdim":
            obs[m.name] = np.asarray(raw[m.name], dtype=np.float32)
        elif m.kind == "rgb":
            obs[m.name] = np.ascontiguousarray(raw[m.name], dtype=np.uint8)
        else:
            from robosuite.utils.camera_utils import get_real_depth_map

            obs[m.name] = get_real_depth_map(sim, raw[m.name]).astype(np.float32)
    return obs


def tune_rendering(sim) -> None:
    """Turn off shadows, reflections and offscreen multisampling (~3x faster on a CPU renderer)."""
    import mujoco

    ctx = sim._render_context_offscreen
    ctx.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    ctx.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    if sim.model._model.vis.quality.offsamples != 0:
        sim.model._model.vis.quality.offsamples = 0
        ctx.gl_ctx.make_current()
        ctx.con.free()
        ctx._set_mujoco_context_and_buffers()  # the framebuffer is created with the sample count


def _leaf_samplers(sampler) -> list:
    if sampler is None:
        return []
    if hasattr(sampler, "samplers"):  # SequentialCompositeSampler
        return [leaf for s in sampler.samplers.values() for leaf in _leaf_samplers(s)]
    return [sampler]


def _looks_like_gl_error(exc: BaseException) -> bool:
    text = f"{type(exc).__name__} {exc}".lower()
    return any(w in text for w in ("egl", "osmesa", "opengl", "glcontext", "gl context", "libgl", "display"))


def make_env(task: str, image_size: int = 84, variation: Variation | None = None, seed: int = 0,
             depth: bool = True, tuned_render: bool = True, render: bool = True) -> SimEnv:
    """Build a task by registry name. `render=False` skips cameras (fast, for expert checks)."""
    return SimEnv(get_task(task), image_size, variation, seed, depth, tuned_render, render)
