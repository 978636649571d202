"""An episode as every format reader yields it, the per-episode metadata contract, and the checks
that every episode passes before anything is written to the store."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from nostra.data.errors import DataError
from nostra.modality import kind_of_key

# The metadata contract between simulation, store and retrieval, with the defaults used when a
# source lacks a field (external data usually does).
META_DEFAULTS = {
    "task": "", "language": "", "skill": "", "objects": [], "camera_pose": {}, "object_placements": {},
    "variation": {}, "success": None, "seed": None, "robots": [], "controller": {},
}
NESTED = ("objects", "camera_pose", "object_placements", "variation", "masks", "robots", "controller")
# Per-demo arrays that are not observations; kept so an export is a complete robomimic file.
EXTRA_KEYS = ("states", "rewards", "dones")


@dataclass
class Episode:
    """``next_obs``: only when the source has it, per obs key; readers give every step,
    ``check_episode`` keeps the last (the others must be obs shifted by one step)."""
    demo_id: str
    actions: np.ndarray
    obs: dict[str, np.ndarray]
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    next_obs: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.actions)


def normalize_meta(raw: dict, file, demo: str, defaults: dict | None = None) -> dict:
    """Contract fields with sensible types; nested values may arrive as JSON strings."""
    out = {}
    given = {k: v for k, v in (defaults or {}).items() if v is not None}
    for k, default in {**META_DEFAULTS, **given}.items():
        v = raw.get(k)
        if v is None:
            v = default
        out[k] = _coerce(k, v, file, demo)
    out["masks"] = sorted(_coerce("masks", raw.get("masks") or [], file, demo))
    out["model_file"] = str(raw.get("model_file") or "")
    return out


def _coerce(key: str, v, file, demo: str):
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, np.ndarray):
        v = [x.decode() if isinstance(x, bytes) else x for x in v.tolist()]
    if key in NESTED and isinstance(v, str):
        try:
            v = json.loads(v) if v else ([] if key in ("objects", "masks", "robots") else {})
        except json.JSONDecodeError as e:
            raise DataError(file, f"metadata is not valid JSON ({e})", demo, key) from None
    if key == "success":
        return None if v is None else bool(v)
    if key == "seed":
        try:
            return None if v is None or v == "" else int(v)
        except (TypeError, ValueError):
            raise DataError(file, f"seed {v!r} is not an integer", demo, key) from None
    if key in ("task", "language", "skill"):
        return str(v)
    return v


def check_episode(ep: Episode, file, shapes: dict) -> Episode:
    """Validate one episode, dtypes kept. ``shapes`` (key -> per-step shape) is filled from the
    first episode; later episodes must agree with it. next_obs is reduced to its last step."""
    demo = ep.demo_id
    if ep.actions is None:
        raise DataError(file, "missing (every demo needs actions)", demo, "actions")
    n = len(ep.actions) if np.ndim(ep.actions) else 0
    if n == 0:
        raise DataError(file, "empty episode (0 steps)", demo, "actions")
    actions = _lowdim(ep.actions, file, demo, "actions")
    obs = {k: _obs(v, file, demo, k) for k, v in ep.obs.items()}
    extras = {k: _numeric(v, file, demo, k) for k, v in ep.extras.items()}
    for k, v in {"actions": actions, **obs, **extras}.items():
        if len(v) != n:
            raise DataError(file, f"has {len(v)} steps but actions has {n}", demo, k)
        _check_shape(k, v, file, demo, shapes)
    nxt = {k: _next_last(v, obs, file, demo, k) for k, v in ep.next_obs.items()}
    return Episode(demo, actions, obs, extras, ep.meta, nxt)


def _next_last(v, obs: dict, file, demo: str, key: str) -> np.ndarray:
    """The step after the last one; the other steps of next_obs must be obs shifted by one."""
    where = f"next_obs/{key}"
    if key not in obs:
        raise DataError(file, f"next_obs has a key that obs lacks; obs has {sorted(obs)}", demo, where)
    o, v = obs[key], _obs(v, file, demo, where)
    if len(v) == 1 and len(o) != 1:  # already reduced (the store's own episodes)
        v = np.concatenate([o[1:], v])
    if v.shape[1:] != o.shape[1:] or len(v) != len(o):
        raise DataError(file, f"shape {v.shape} differs from obs {o.shape}", demo, where)
    same = (v[:-1] == o[1:]).reshape(len(o) - 1, -1).all(1)
    if not same.all():
        raise DataError(file, f"next_obs is not obs shifted by one step (first difference at step "
                              f"{int(np.argmin(same))}); the store keeps next_obs only as that shift plus the "
                              "last step: ingest with next_obs=false (ingest.next_obs=false) to drop it", demo, where)
    return v[-1:].astype(o.dtype, copy=False)


def as_float32(ep: Episode) -> Episode:
    """Float lowdim obs and actions as float32 (the store's ``float32`` option)."""
    f32 = lambda k, v: v.astype(np.float32, copy=False) if kind_of_key(k) == "lowdim" and v.dtype.kind == "f" else v  # noqa: E731
    return Episode(ep.demo_id, f32("actions", ep.actions), {k: f32(k, v) for k, v in ep.obs.items()}, ep.extras,
                   ep.meta, {k: f32(k, v) for k, v in ep.next_obs.items()})


def _check_shape(key, v, file, demo, shapes):
    if key not in shapes:
        shapes[key] = v.shape[1:]
    elif v.shape[1:] != shapes[key]:
        raise DataError(file, f"per-step shape {v.shape[1:]} differs from {shapes[key]} in earlier demos", demo, key)


def _numeric(v, file, demo, key) -> np.ndarray:
    v = np.asarray(v)
    if v.dtype.kind not in "biuf":
        raise DataError(file, f"dtype {v.dtype} is not numeric (valid: bool, int, uint, float)", demo, key)
    if v.ndim == 0:
        raise DataError(file, "is a scalar; expected one row per step", demo, key)
    if v.dtype.kind == "f" and not np.isfinite(v).all():
        bad = int(np.argwhere(~np.isfinite(v.reshape(len(v), -1)))[0, 0])
        raise DataError(file, f"contains NaN or Inf (first at step {bad})", demo, key)
    return v


def _lowdim(v, file, demo, key) -> np.ndarray:
    v = _numeric(v, file, demo, key)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2:
        raise DataError(file, f"shape {v.shape}: expected (steps, dim)", demo, key)
    return v


def _obs(v, file, demo, key) -> np.ndarray:
    kind = kind_of_key(key)
    if kind == "lowdim":
        return _lowdim(v, file, demo, key)
    v = _numeric(v, file, demo, key)
    if kind == "rgb":
        if v.dtype != np.uint8:
            raise DataError(file, f"rgb images must be uint8, got {v.dtype}", demo, key)
        if v.ndim != 4 or v.shape[-1] != 3:
            raise DataError(file, f"rgb images must be (steps, H, W, 3), got {v.shape}", demo, key)
        return v
    if v.dtype.kind != "f":
        raise DataError(file, f"depth must be float (metres), got {v.dtype}", demo, key)
    if v.ndim == 3:
        v = v[..., None]
    if v.ndim != 4 or v.shape[-1] != 1:
        raise DataError(file, f"depth must be (steps, H, W, 1), got {v.shape}", demo, key)
    return v
