"""Noise injectors of the paper's robustness suite (appendix F), applied inside noise windows.

Noise changes what the policy sees, never the simulator's state or its success check: image and
proprioception noise edit a copy of the observation; camera jitter and texture swaps change only
the renderer's view (camera poses, textures) and are undone when the window ends.

Timeline: the observation of step t is corrupted when t lies in a window. Scene noises are set up
before the simulator step that renders that observation (``prepare``), image noises are applied
to the rendered observation (``corrupt``).

Noises that only edit observations (mask, proprio_zero, blind, ...) need no simulator: with
``env=None`` they run on recorded observations (``prepare(None, t, rng, image_size=...)``); scene
noises (camera jitter, table texture: ``needs_env``) refuse to.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nostra.modality import FRONT_IMAGE, WRIST_IMAGE, sim_observations
from nostra.policies.imagination import in_windows, window_mask

# what the injectors corrupt: the simulator's modalities by kind (the observation contract)
SIM = sim_observations()
RGB_KEYS, DEPTH_KEYS, PROPRIO_KEYS = SIM.rgb_keys, SIM.depth_keys, SIM.lowdim_keys
# never used by the generation knobs' defaults, so unseen in training unless configured there
UNSEEN_TABLE_TEXTURE = "red-wood"


class Injector:
    """One kind of noise. ``keys``: the observation keys it corrupts (what an oracle imagines)."""

    keys: tuple[str, ...] = ()
    needs_env: bool = False  # changes the simulated scene, so cannot act on recorded observations

    def begin(self, env, rng: np.random.Generator) -> None:
        """The window starts: choose this window's random parameters, change the scene."""

    def prepare(self, env, rng: np.random.Generator) -> None:
        """Before each in-window simulator step (scene noise that changes every step)."""

    def end(self, env) -> None:
        """The window is over: undo scene changes."""

    def corrupt(self, obs: dict) -> dict:
        return obs


@dataclass
class Mask(Injector):
    """A black square (50 px at 84 px, scaled with resolution) at a random position fully inside
    the image, drawn once per window per camera."""

    keys: tuple[str, ...] = RGB_KEYS
    size: float = 50 / 84
    _corner: dict = field(default_factory=dict, repr=False)

    def begin(self, env, rng):
        self._corner = {}
        for k in self.keys:
            h, w = env.image_size, env.image_size
            s = max(1, round(self.size * h))
            self._corner[k] = (int(rng.integers(0, h - s + 1)), int(rng.integers(0, w - s + 1)), s)

    def corrupt(self, obs):
        obs = dict(obs)
        for k, (y, x, s) in self._corner.items():
            if k in obs:
                img = obs[k].copy()
                img[y:y + s, x:x + s] = 0
                obs[k] = img
        return obs


@dataclass
class CamJitter(Injector):
    """Agent-view and wrist camera positions jittered by N(0, std^2) per axis at every step."""

    std: float = 0.1
    cameras: tuple[str, ...] = SIM.cameras
    _orig: dict = field(default_factory=dict, repr=False)
    needs_env = True

    @property
    def keys(self):
        return tuple(m.name for m in SIM.modalities if m.camera in self.cameras)

    def begin(self, env, rng):
        self._orig = {env.camera_id(c): env.model.cam_pos[env.camera_id(c)].copy() for c in self.cameras}

    def prepare(self, env, rng):
        for cam, pos in self._orig.items():
            env.model.cam_pos[cam] = pos + rng.normal(0.0, self.std, 3)

    def end(self, env):
        for cam, pos in self._orig.items():
            env.model.cam_pos[cam] = pos


@dataclass
class TableTexture(Injector):
    """The table's texture swapped for one never used in training during the window."""

    texture: str = UNSEEN_TABLE_TEXTURE
    keys: tuple[str, ...] = RGB_KEYS
    _saved: dict = field(default_factory=dict, repr=False)
    needs_env = True

    def begin(self, env, rng):
        from nostra.sim import scene

        self._saved = {}
        for mat in env.table_material_ids:
            tex = scene.material_texture(env.model, mat)
            if tex >= 0:
                self._saved[mat] = scene.texture_view(env.model, tex).copy()
        env.set_table_texture(self.texture)

    def end(self, env):
        from nostra.sim import scene

        for mat, image in self._saved.items():
            scene.set_material_texture(env.model, env.render_context, mat, image)


@dataclass
class Blackout(Injector):
    """Every camera (RGB and depth) reads black / zero: the control with no vision at all."""

    keys: tuple[str, ...] = RGB_KEYS + DEPTH_KEYS

    def corrupt(self, obs):
        return {k: (np.zeros_like(v) if k in self.keys else v) for k, v in obs.items()}


@dataclass
class Unchanged(Injector):
    """Corrupts nothing, yet its keys count as noised inside the windows: the oracle variants imagine
    them there while the others see clean frames (imagination's own cost or gain, with no noise)."""

    keys: tuple[str, ...] = RGB_KEYS


@dataclass
class ProprioZero(Injector):
    """Proprioception reads zero (sensor failure)."""

    keys: tuple[str, ...] = PROPRIO_KEYS

    def corrupt(self, obs):
        return {k: (np.zeros_like(v) if k in self.keys else v) for k, v in obs.items()}


@dataclass
class ProprioStuck(Injector):
    """Proprioception freezes: every step of a window reads what the sensors read when it opened
    (a stuck sensor: plausible values, no longer true, unlike proprio_zero's obvious failure)."""

    keys: tuple[str, ...] = PROPRIO_KEYS
    _held: dict | None = field(default=None, repr=False)

    def begin(self, env, rng):
        self._held = None

    def corrupt(self, obs):
        if self._held is None:
            self._held = {k: np.array(obs[k], copy=True) for k in self.keys if k in obs}
        return {k: (self._held[k].copy() if k in self._held else v) for k, v in obs.items()}


def _suite(name: str, params: dict) -> list[Injector]:
    unknown = set(params) - {"name", "mask_size", "jitter_std", "texture"}
    if unknown:
        raise ValueError(f"unknown noise parameters {sorted(unknown)}; valid: mask_size, jitter_std, texture")
    mask = params.get("mask_size", 50 / 84)
    rgb = Mask(RGB_KEYS, mask)
    depth = Mask(DEPTH_KEYS, mask)
    return {
        "none": [],
        "mask": [rgb],
        "wrist_mask": [Mask((WRIST_IMAGE,), mask)],  # one camera (the paper's real-robot occlusion, Table 6)
        "agentview_mask": [Mask((FRONT_IMAGE,), mask)],  # the other one
        "depth_mask": [depth],
        "cam_jitter": [CamJitter(params.get("jitter_std", 0.1))],
        "table_tex": [TableTexture(params.get("texture", UNSEEN_TABLE_TEXTURE))],
        "proprio_zero": [ProprioZero()],
        "proprio_stuck": [ProprioStuck()],
        "rgb": [rgb],
        "rgbd": [rgb, depth],
        "all": [rgb, depth, ProprioZero()],
        "blind": [Blackout()],
        "clean_windows": [Unchanged()],
    }[name]


NOISES = ("none", "mask", "wrist_mask", "agentview_mask", "depth_mask", "cam_jitter", "table_tex", "proprio_zero",
          "proprio_stuck", "rgb", "rgbd", "all", "blind", "clean_windows")
WHOLE_EPISODE = ("blind",)  # noises that ignore the windows: active from the first step to the last


def check_noise(name: str) -> str:
    if name not in NOISES:
        raise ValueError(f"unknown noise {name!r}; valid noises: {', '.join(NOISES)}")
    return name


class NoiseSchedule:
    """A noise applied inside half-open step windows [start, end)."""

    def __init__(self, name: str, windows, params: dict | None = None, injectors: list[Injector] | None = None):
        """``name``: one of NOISES, built with ``params``; or, with ``injectors`` given, just a label
        for those (a noise of one's own, e.g. the synthetic demo's stuck sensor)."""
        self.name = check_noise(name) if injectors is None else name
        self.injectors = _suite(name, dict(params or {})) if injectors is None else list(injectors)
        self.windows = [(int(a), int(b)) for a, b in windows]
        for a, b in self.windows:
            if not 0 < a < b:
                raise ValueError(f"noise window [{a}, {b}) must satisfy 0 < start < end")
        if name in WHOLE_EPISODE:  # the blind control: no camera at any step (its injector needs no set-up)
            self.windows = [(0, 2**62)]

    @property
    def keys(self) -> set[str]:
        return {k for inj in self.injectors for k in inj.keys}

    @property
    def needs_env(self) -> bool:
        """Whether this noise changes the simulated scene (it cannot run on recorded observations)."""
        return any(inj.needs_env for inj in self.injectors)

    def active(self, t: int) -> bool:
        return bool(self.injectors) and in_windows(t, self.windows)

    def mask(self, horizon: int) -> np.ndarray:
        """active(t) for t in range(horizon)."""
        return window_mask(horizon, self.windows) & bool(self.injectors)

    def prepare(self, env, t: int, rng: np.random.Generator, image_size: int | None = None) -> None:
        """Call before the simulator step that renders observation ``t``. ``env=None``: there is no
        simulator (recorded observations, whose images are ``image_size`` pixels square)."""
        if env is None:
            env = _NoScene(self, image_size)
        if self.active(t):
            for inj in self.injectors:
                if not self.active(t - 1):
                    inj.begin(env, rng)
                inj.prepare(env, rng)
        elif self.active(t - 1):
            for inj in self.injectors:
                inj.end(env)

    def corrupt(self, obs: dict, t: int) -> dict:
        if not self.active(t):
            return obs
        for inj in self.injectors:
            obs = inj.corrupt(obs)
        return obs

    def close(self, env, t: int) -> None:
        """Undo scene changes if an episode ends inside a window."""
        if env is None:
            env = _NoScene(self, None)
        if self.active(t):
            for inj in self.injectors:
                inj.end(env)


class _NoScene:
    """Stands in for the environment where there is none: observation noises ask it only the image
    size; a scene noise is refused up front."""

    def __init__(self, schedule: NoiseSchedule, image_size: int | None):
        if schedule.needs_env:
            raise ValueError(f"noise {schedule.name!r} changes the simulated scene: it needs the simulator, "
                             "not recorded observations")
        self._image_size = image_size

    @property
    def image_size(self) -> int:
        if self._image_size is None:
            raise ValueError("image noise on recorded observations needs their image_size")
        return self._image_size
