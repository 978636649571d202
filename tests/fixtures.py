"""Tiny datasets in every supported format, written by code (no binaries in the repository), for
the tests and bench/loader.py: a robomimic HDF5 with the paper's six keys, a LeRobot v3 dataset and a
diffusion_policy zarr ReplayBuffer, all from the same synthetic episodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nostra.data.episode import Episode
from nostra.data.formats import dp_zarr, lerobot, robomimic_hdf5
from nostra.modality import FRONT_IMAGE, sim_observations

SIM = sim_observations()  # the fixtures' keys are the simulator's (any image size)
RGB_KEYS = SIM.rgb_keys
LOWDIM = {m.name: m.shape[0] for m in SIM.select(SIM.lowdim_keys)}
PAPER_KEYS = SIM.names
ENV_ARGS = {"env_name": "Lift", "type": 1, "env_kwargs": {"robots": ["Panda"], "control_freq": 20}}
# LeRobot keeps proprioception as one concatenated vector: these slices recover our keys.
LEROBOT_STATE_KEYS = list(LOWDIM)


def _lerobot_key_map() -> dict:
    out = {"actions": "action", **{k: f"observation.images.{SIM.camera_of(k)}" for k in RGB_KEYS}}
    start = 0
    for k, n in LOWDIM.items():
        out[k] = f"observation.state[{start}:{start + n}]"
        start += n
    return out


LEROBOT_KEY_MAP = _lerobot_key_map()


def image(t: np.ndarray, size: int, phase: float) -> np.ndarray:
    """Smooth frames with a moving bright square: compressible, and video codecs keep them nearly intact."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    out = np.empty((len(t), size, size, 3), np.uint8)
    for i, ti in enumerate(t):
        base = 60 + 80 * np.stack([xx, yy, 0.5 * (xx + yy)], -1) + 20 * np.sin(phase + 0.2 * ti)
        c = int((0.5 + 0.3 * np.sin(phase + 0.1 * ti)) * (size - 4))
        base[c:c + 4, c:c + 4] = 230
        out[i] = np.clip(base, 0, 255).astype(np.uint8)
    return out


def make_episodes(n: int = 3, lengths=None, image_size: int = 16, seed: int = 0, keys=PAPER_KEYS,
                  action_dim: int = 7, task: str = "Lift") -> list[Episode]:
    rng = np.random.default_rng(seed)
    lengths = list(lengths) if lengths is not None else [int(x) for x in rng.integers(8, 20, size=n)]
    eps = []
    modalities = SIM.select(keys)
    for i, n_steps in enumerate(lengths):
        t = np.arange(n_steps, dtype=np.float64)
        obs = {}
        for j, m in enumerate(modalities):
            if m.kind == "rgb":
                obs[m.name] = image(t, image_size, phase=i + 0.7 * j)
            elif m.kind == "depth":
                obs[m.name] = (1.0 + 0.2 * image(t, image_size, phase=i)[..., :1] / 255).astype(np.float32)
            else:
                obs[m.name] = np.cumsum(rng.normal(0, 0.05, (n_steps, *m.shape)), 0).astype(np.float32)
        actions = rng.uniform(-1, 1, (n_steps, action_dim)).astype(np.float32)
        extras = {"states": rng.normal(size=(n_steps, 10)), "rewards": (t == n_steps - 1).astype(np.float64),
                  "dones": (t == n_steps - 1).astype(np.int64)}
        eps.append(Episode(f"demo_{i}", actions, obs, extras, _meta(i, task, rng)))
    return eps


def _meta(i: int, task: str, rng) -> dict:
    cube = [round(float(x), 4) for x in rng.uniform(-0.1, 0.1, 2)] + [0.82]
    return {"task": task, "language": "lift the red cube", "skill": "pick", "objects": ["cube"],
            "camera_pose": {"agentview": {"pos": [0.5 + 0.01 * i, 0.0, 1.35], "quat": [0.65, 0.27, 0.27, 0.65]}},
            "object_placements": {"cube": cube}, "variation": {"cube_size": 0.02 + 0.001 * i},
            "success": bool(i % 2 == 0), "seed": 100 + i, "masks": ["valid"] if i == 0 else ["train"],
            "model_file": "<mujoco model='lift'/>"}


def write_robomimic(path, n: int = 3, lengths=None, image_size: int = 16, seed: int = 0, keys=PAPER_KEYS,
                    **kw) -> Path:
    eps = make_episodes(n, lengths, image_size, seed, keys, **kw)
    return robomimic_hdf5.write(path, eps, ENV_ARGS, total=len(eps), progress=False)


def write_lerobot(root, n: int = 3, lengths=None, image_size: int = 16, seed: int = 0, video: bool = True) -> Path:
    keys = (*RGB_KEYS, *LOWDIM)
    return lerobot.write(root, make_episodes(n, lengths, image_size, seed, keys), fps=10, video=video,
                         state_keys=LEROBOT_STATE_KEYS)


def write_dp_zarr(path, n: int = 3, lengths=None, image_size: int = 16, seed: int = 0,
                  keys=(FRONT_IMAGE, *LOWDIM)) -> Path:
    return dp_zarr.write(path, make_episodes(n, lengths, image_size, seed, keys), key_map={FRONT_IMAGE: "img"})
