"""Format readers (and writers): each reader is an iterable of ``Episode`` with ``len``,
``files`` (what the content hash covers) and ``attrs`` (collection-level attributes)."""

from __future__ import annotations

from pathlib import Path

from nostra.data.errors import DataError
from nostra.data.formats import dp_zarr, lerobot, robomimic_hdf5

FORMATS = {
    "robomimic": (robomimic_hdf5.sniff, robomimic_hdf5.RobomimicSource),
    "lerobot": (lerobot.sniff, lerobot.LeRobotSource),
    "dp_zarr": (dp_zarr.sniff, dp_zarr.DPZarrSource),
}
HINT = ("robomimic (HDF5 file with data/demo_N), lerobot (v2.x or v3 directory with meta/info.json), "
        "dp_zarr (zarr directory or .zip with data/<key> and meta/episode_ends)")


def detect(path) -> str:
    path = Path(path)
    if not path.exists():
        raise DataError(path, "no such file or directory")
    for name, (sniff, _) in FORMATS.items():
        if sniff(path):
            return name
    raise DataError(path, f"unknown format; valid: {HINT}")


def open_source(path, fmt: str = "auto", key_map: dict | None = None, keys: list[str] | None = None,
                defaults: dict | None = None, next_obs: bool = True, render: bool = False, render_size: int = 84):
    """A reader for one source. ``render``: robosuite raw demos (no observations) get their
    observations rendered from the recorded states (nostra.sim.raw_demos)."""
    path = Path(path)
    if fmt == "auto":
        fmt = detect(path)
    if fmt not in FORMATS:
        raise DataError(path, f"unknown format {fmt!r}; valid: auto, {', '.join(FORMATS)}")
    if not path.exists():
        raise DataError(path, "no such file or directory")
    cls = FORMATS[fmt][1]
    if fmt == "robomimic" and robomimic_hdf5.is_raw(path) and render:
        from nostra.sim.raw_demos import RawDemoSource  # imports robosuite: only when asked for

        return RawDemoSource(path, render_size, keys, defaults)
    if render:
        raise DataError(path, "ingest.render=true is for robosuite raw demos (states and actions, no observations); "
                              "this source has observations: ingest it without render", key="render")
    if fmt == "robomimic":
        if key_map:
            raise DataError(path, "a key map applies to lerobot and dp_zarr sources only; use 'keys' to pick obs keys")
        return cls(path, keys=keys, defaults=defaults, next_obs=next_obs)
    return cls(path, key_map=key_map, keys=keys, defaults=defaults)
