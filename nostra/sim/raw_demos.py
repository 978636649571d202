"""robosuite raw demonstrations -> episodes with the six modalities, rendered from the states.

What ``robosuite.scripts.collect_human_demonstrations`` writes (``gather_demonstrations_as_hdf5``):
``data`` attrs ``env`` and ``env_info`` (JSON: env_name, robots, controller_configs), ``data/demo_N``
with ``states`` (T, 1 + nq + nv: time, qpos, qvel; state t is before action t), ``actions`` (T, A)
and attr ``model_file`` (the episode's MJCF). There are no observations: this source rebuilds the
env from ``env_info``, loads each demo's model as robosuite's playback script does, sets every
recorded state and renders agentview/wrist RGB, agentview depth (metres), eef pos/quat and gripper
qpos, right side up, at the requested size. It also replays the actions open loop from the first
state (in a second env without cameras) and reports how far the replay drifts from the recorded
states, per demo: ``divergence[demo]`` (max over steps of the norm of the state difference) and in
the collection's ``source_attrs.replay_divergence``; a demo is never dropped for it."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np

from nostra.data.episode import Episode, normalize_meta
from nostra.data.errors import DataError
from nostra.sim.env import camera_kwargs, contract_obs, import_robosuite, rendered_observations

log = logging.getLogger(__name__)
FMT = "robosuite_raw"
DIVERGED = 0.01  # robosuite's playback script warns on any difference; we warn past this norm


class RawDemoSource:
    fmt = FMT

    def __init__(self, path, image_size: int = 84, keys: list[str] | None = None, defaults: dict | None = None):
        self.path, self.size, self.defaults = Path(path), int(image_size), defaults or {}
        self.observations = rendered_observations(self.size)
        self.keys = list(keys) if keys is not None else list(self.observations.names)
        bad = [k for k in self.keys if k not in self.observations.names]
        if bad:
            raise DataError(self.path, f"cannot render {bad}; valid: {list(self.observations.names)}", key=bad[0])
        with _open(self.path) as f:
            data = f["data"]
            self.env_info = _env_info(data, self.path)
            self.version = _str(data.attrs.get("repository_version", ""))
            self.demos = sorted(data.keys(), key=lambda d: [int(t) if t.isdigit() else t for t in d.split("_")])
            for d in self.demos:
                for k in ("states", "actions"):
                    if k not in data[d]:
                        raise DataError(self.path, "missing (a raw demo needs states and actions)", d, k)
                if "model_file" not in data[d].attrs:
                    raise DataError(self.path, "missing attribute (the demo's MJCF model)", d, "model_file")
        self.divergence: dict[str, float] = {}

    @property
    def files(self) -> list[Path]:
        return [self.path]

    @property
    def attrs(self) -> dict:
        kwargs = {k: v for k, v in self.env_info.items() if k != "env_name"}
        return {"env_args": {"env_name": self.env_info["env_name"], "env_version": self.version, "type": 1,
                             "env_kwargs": kwargs},
                "rendered": {"image_size": self.size, "keys": self.keys},
                "replay_divergence": dict(self.divergence)}

    def __len__(self) -> int:
        return len(self.demos)

    def __iter__(self):
        render_env, replay_env = self._make(True), self._make(False)
        try:
            with _open(self.path) as f:
                for demo in self.demos:
                    g = f["data"][demo]
                    states, actions = np.asarray(g["states"][()]), np.asarray(g["actions"][()])
                    model = _str(g.attrs["model_file"])
                    try:
                        obs = self._render(render_env, model, states)
                        self.divergence[demo] = self._replay(replay_env, model, states, actions)
                    except DataError:
                        raise
                    except Exception as e:  # MuJoCo/robosuite errors for a state or model that does not fit
                        raise DataError(self.path, f"cannot be rendered ({type(e).__name__}: {e})", demo) from None
                    level = logging.WARNING if self.divergence[demo] > DIVERGED else logging.INFO
                    log.log(level, "%s %s: replaying the actions diverges from the recorded states by %.4g at most",
                            self.path.name, demo, self.divergence[demo])
                    yield Episode(demo, actions, obs, {"states": states}, self._meta(g, demo))
        finally:
            render_env.close()
            replay_env.close()

    def _make(self, render: bool):
        suite = import_robosuite()
        kw = dict(has_renderer=False, has_offscreen_renderer=render, use_camera_obs=render, ignore_done=True,
                  reward_shaping=True, control_freq=20)
        if render:
            kw |= camera_kwargs(self.observations)
        try:
            return suite.make(**self.env_info, **kw)
        except Exception as e:
            raise DataError(self.path, f"cannot rebuild the env from env_info ({type(e).__name__}: {e})",
                            key="env_info") from None

    @staticmethod
    def _load(env, model: str) -> None:
        """The demo's own model, as robosuite's playback_demonstrations_from_hdf5 loads it."""
        env.reset()
        env.reset_from_xml_string(env.edit_model_xml(model))
        env.sim.reset()

    def _render(self, env, model: str, states: np.ndarray) -> dict[str, np.ndarray]:
        self._load(env, model)
        frames = {k: [] for k in self.keys}
        for state in states:
            env.sim.set_state_from_flattened(state)
            env.sim.forward()
            obs = contract_obs(env.sim, env._get_observations(force_update=True), self.observations)
            for k in self.keys:
                frames[k].append(obs[k])
        return {k: np.stack(v) for k, v in frames.items()}

    def _replay(self, env, model: str, states: np.ndarray, actions: np.ndarray) -> float:
        """Max over steps of |recorded state - replayed state| after playing the actions open loop."""
        self._load(env, model)
        env.sim.set_state_from_flattened(states[0])
        env.sim.forward()
        worst = 0.0
        for j, action in enumerate(actions[:-1]):
            env.step(action)
            worst = max(worst, float(np.linalg.norm(states[j + 1] - env.sim.get_state().flatten())))
        return worst

    def _meta(self, g, demo: str) -> dict:
        ctrl = self.env_info.get("controller_configs") or {}
        raw = {"task": self.env_info["env_name"], "robots": _as_list(self.env_info.get("robots")),
               "controller": ctrl if isinstance(ctrl, dict) else {"type": str(ctrl)},
               "model_file": _str(g.attrs["model_file"])}
        return normalize_meta(raw, self.path, demo, self.defaults)


def _open(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise DataError(path, f"cannot be read as HDF5 (truncated or corrupt?): {e}") from None


def _str(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _as_list(v) -> list:
    return [] if v is None else [v] if isinstance(v, str) else list(v)


def _env_info(data, path: Path) -> dict:
    raw = data.attrs.get("env_info")
    if raw is None:
        raise DataError(path, "no env_info attribute (JSON with env_name, robots, controller_configs, written by "
                              "robosuite's collect_human_demonstrations)", key="data.attrs['env_info']")
    try:
        info = json.loads(_str(raw))
    except json.JSONDecodeError as e:
        raise DataError(path, f"env_info is not JSON ({e})", key="data.attrs['env_info']") from None
    if not isinstance(info, dict):
        raise DataError(path, "env_info is not a JSON object", key="data.attrs['env_info']")
    info.setdefault("env_name", _str(data.attrs.get("env", "")))
    if not info["env_name"]:
        raise DataError(path, "env_info has no env_name and data has no 'env' attribute", key="env_name")
    return info
