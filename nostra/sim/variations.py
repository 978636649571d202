"""Per-episode variation knobs of the simulated scenes, recorded in each episode's metadata.

A :class:`Variation` with all defaults changes nothing. ``sample_variation(ranges, rng)`` draws one
from the ranges of a config (``conf/generate/default.yaml`` -> ``variation:``). The occluded agent
view (paper Table 3) moves the agentview camera behind the robot so the arm fills most of the view;
the blind agent view (a control beyond the paper) turns it to the floor behind the robot, so it shows
the same image at every step of every episode: a view with no information at all.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Mapping

import numpy as np

from nostra.sim import scene

# Occluded agentview: the camera sits just behind and above the robot base and looks past the arm at
# the workspace; the robot then covers ~65% of the image all episode long (robot_pixel_fraction).
# Offsets from the robot base, metres.
OCCLUDED_EYE = (-0.25, 0.0, 0.5)
OCCLUDED_TARGET = (0.55, 0.0, 0.0)
# Blind agentview: above the robot base, looking down and away from the workspace at the floor and the
# back wall; nothing that moves is in view (the arm reaches forward, behind the camera).
BLIND_EYE = (-0.5, 0.0, 0.6)
BLIND_TARGET = (-1.4, 0.0, -0.6)


@dataclass(frozen=True)
class Variation:
    camera_pos_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # agentview, metres, world frame
    camera_rot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # agentview, degrees about its own x, y, z
    table_texture: str | None = None  # a robosuite texture name (scene.texture_names())
    table_rgba: tuple[float, float, float, float] | None = None  # tint of the table material
    object_rgba: tuple[float, float, float, float] | None = None  # flat colour of the task's main object
    object_scale: float = 1.0  # size of the task's free objects (recompiles the scene when it changes)
    placement_scale: float = 1.0  # scales the x/y ranges objects are placed in, about their centre
    occluded_agentview: bool = False  # robot blocks the agentview camera
    blind_agentview: bool = False  # agentview faces the floor behind the robot: a constant image

    def __post_init__(self):
        for name in ("camera_pos_offset", "camera_rot_offset"):
            object.__setattr__(self, name, _vec(getattr(self, name), 3, name))
        for name in ("table_rgba", "object_rgba"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _vec(getattr(self, name), 4, name))
        if self.table_texture is not None and self.table_texture not in scene.texture_names():
            raise ValueError(f"table_texture {self.table_texture!r} unknown; valid: {', '.join(scene.texture_names())}")
        for name in ("object_scale", "placement_scale"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
            object.__setattr__(self, name, round(float(getattr(self, name)), 6))
        for name in ("occluded_agentview", "blind_agentview"):
            object.__setattr__(self, name, bool(getattr(self, name)))
        if self.occluded_agentview and self.blind_agentview:
            raise ValueError("occluded_agentview and blind_agentview are two poses of the same camera: set one")

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Variation":
        valid = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(valid))
        if unknown:
            raise ValueError(f"unknown variation keys {unknown}; valid keys: {', '.join(valid)}")
        return cls(**dict(d))

    def apply_to_model(self, env) -> None:
        """Change env's (restored) model: camera, table, object colour, placement ranges."""
        model, cam = env.model, env.camera_id("agentview")
        pos, quat = model.cam_pos[cam].copy(), model.cam_quat[cam].copy()
        if self.occluded_agentview:
            pos, quat = agentview_pose(env, OCCLUDED_EYE, OCCLUDED_TARGET)
        if self.blind_agentview:
            pos, quat = agentview_pose(env, BLIND_EYE, BLIND_TARGET)
        scene.set_camera_pose(model, cam, pos + self.camera_pos_offset, scene.offset_quat(quat, self.camera_rot_offset))
        if self.table_texture is not None:
            env.set_table_texture(self.table_texture)
        if self.table_rgba is not None:
            model.mat_rgba[env.table_material_ids] = self.table_rgba
        if self.object_rgba is not None:
            for body in env.spec.recolor_bodies:
                scene.set_geom_color(model, scene.body_geoms(model, scene.body_id(model, body)), self.object_rgba)
        for sampler in env.placement_samplers():
            sampler.x_range = scale_range(sampler.x_range, self.placement_scale)
            sampler.y_range = scale_range(sampler.y_range, self.placement_scale)


def agentview_pose(env, eye_offset, target_offset) -> tuple[np.ndarray, np.ndarray]:
    """Agentview pose at an offset from the robot base, looking at another offset from it."""
    base = env.data.xpos[scene.body_id(env.model, "robot0_base")]
    eye = base + np.asarray(eye_offset)
    return eye, scene.look_at_quat(eye, base + np.asarray(target_offset))


ROBOT_PREFIXES = ("robot0_", "gripper0_", "fixed_mount0_")


def robot_pixel_fraction(env, camera: str = "agentview", size: int = 64) -> float:
    """Share of a camera's pixels that show the robot (arm, gripper, mount), from a segmentation
    render: how much the robot blocks the view."""
    import mujoco

    seg = env.raw.sim.render(width=size, height=size, camera_name=camera, segmentation=True)
    geoms = seg[..., 1][seg[..., 0] == mujoco.mjtObj.mjOBJ_GEOM]
    m = env.model
    robot_bodies = [b for b in range(m.nbody) if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b).startswith(ROBOT_PREFIXES)]
    return float(np.isin(m.geom_bodyid[geoms], robot_bodies).sum() / size**2)


def _vec(v, n: int, name: str) -> tuple:
    arr = np.asarray(v, dtype=float).ravel()
    if arr.shape != (n,):
        raise ValueError(f"{name} needs {n} numbers, got {v!r}")
    return tuple(round(float(x), 6) for x in arr)


def scale_range(rng, s: float) -> tuple[float, float]:
    lo, hi = float(rng[0]), float(rng[1])
    mid, half = (lo + hi) / 2, (hi - lo) / 2 * s
    return (mid - half, mid + half)


# ---- sampling from config ranges ---------------------------------------------------------------

RANGE_KEYS = {
    "camera_pos": "max |offset| per axis of the agentview position, metres",
    "camera_rot": "max |rotation| per axis of the agentview orientation, degrees",
    "table_textures": "robosuite texture names to draw the table texture from ([] keeps the table)",
    "object_colors": "RGB(A) lists to draw the object colour from, or 'random' ([] keeps it)",
    "object_scale": "[low, high] of the object size factor",
    "placement_scale": "[low, high] of the placement range factor",
    "occluded": "probability of the occluded agentview",
    "blind": "probability of the blind agentview (faces the floor behind the robot; not with occluded)",
}


def sample_variation(ranges: Mapping | None, rng: np.random.Generator) -> Variation:
    """Draw one episode's variation; missing keys mean no change."""
    r = dict(ranges or {})
    unknown = sorted(set(r) - set(RANGE_KEYS))
    if unknown:
        raise ValueError(f"unknown variation range keys {unknown}; valid keys: {', '.join(RANGE_KEYS)}")
    cam_pos, cam_rot = float(r.get("camera_pos", 0.0)), float(r.get("camera_rot", 0.0))
    textures = list(r.get("table_textures") or [])
    return Variation(
        camera_pos_offset=rng.uniform(-cam_pos, cam_pos, 3) if cam_pos else (0.0, 0.0, 0.0),
        camera_rot_offset=rng.uniform(-cam_rot, cam_rot, 3) if cam_rot else (0.0, 0.0, 0.0),
        table_texture=str(textures[rng.integers(len(textures))]) if textures else None,
        object_rgba=_draw_color(r.get("object_colors"), rng),
        object_scale=rng.uniform(*_pair(r.get("object_scale", (1.0, 1.0)), "object_scale")),
        placement_scale=rng.uniform(*_pair(r.get("placement_scale", (1.0, 1.0)), "placement_scale")),
        occluded_agentview=bool(rng.random() < float(r.get("occluded", 0.0))),
        blind_agentview=bool(rng.random() < float(r.get("blind", 0.0))),
    )


def _draw_color(colors, rng) -> tuple | None:
    if not colors:
        return None
    if isinstance(colors, str):
        if colors != "random":
            raise ValueError(f"object_colors must be a list of RGB(A) lists or 'random', got {colors!r}")
        return (*rng.uniform(0, 1, 3), 1.0)
    c = [float(x) for x in colors[rng.integers(len(colors))]]
    return tuple(c + [1.0] * (4 - len(c)))


def _pair(v, name: str) -> tuple[float, float]:
    lo, hi = (float(x) for x in v)
    if lo > hi:
        raise ValueError(f"variation range {name}: low {lo} > high {hi}")
    return lo, hi
