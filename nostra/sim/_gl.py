"""Headless OpenGL backend for MuJoCo rendering: EGL first, OSMesa as the fallback.

MuJoCo and robosuite read ``MUJOCO_GL`` when they are imported, so the choice is made before that,
by rendering a tiny model in a subprocess. The choice is stored in ``MUJOCO_GL`` and therefore
inherited by worker processes, which do not probe again.
"""

from __future__ import annotations

import os
import subprocess
import sys

BACKENDS = ("egl", "osmesa")
_ERROR_VAR = "NOSTRA_GL_ERROR"  # why no backend worked, for the error raised when rendering is asked for

_PROBE = """
import mujoco
ctx = mujoco.GLContext(16, 16)
ctx.make_current()
con = mujoco.MjrContext(mujoco.MjModel.from_xml_string("<mujoco/>"), mujoco.mjtFontScale.mjFONTSCALE_150)
con.free(); ctx.free()
"""

HINT = ("EGL needs a working libEGL (e.g. Mesa: `apt-get install -y libegl1 libgl1`); OSMesa needs "
        "`apt-get install -y libosmesa6`. Select one with MUJOCO_GL=egl or MUJOCO_GL=osmesa.")


def probe(backend: str, timeout: float = 60.0) -> str | None:
    """None when MuJoCo can render with `backend`, else the reason it cannot."""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    try:
        res = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout:.0f} s"
    if res.returncode == 0:
        return None
    lines = (res.stderr or res.stdout).strip().splitlines()
    return lines[-1] if lines else f"exit code {res.returncode}"


def select_backend() -> str:
    """Set MUJOCO_GL to the first working backend unless the user already chose one."""
    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    errors = {}
    for backend in BACKENDS:
        errors[backend] = probe(backend)
        if errors[backend] is None:
            os.environ["MUJOCO_GL"] = backend
            return backend
    # Physics without cameras still works; rendering raises render_error() when asked for.
    os.environ["MUJOCO_GL"] = "egl"
    os.environ[_ERROR_VAR] = "; ".join(f"{b}: {e}" for b, e in errors.items())
    return "egl"


def render_error(cause: BaseException | None = None) -> RuntimeError:
    """The error raised when offscreen rendering cannot start."""
    tried = os.environ.get(_ERROR_VAR) or f"{os.environ.get('MUJOCO_GL')}: {cause!r}"
    return RuntimeError(f"MuJoCo offscreen rendering is unavailable: neither EGL nor OSMesa works ({tried}). {HINT}")


def check_render() -> None:
    """Raise the clear error now if the backend probe already found that nothing renders."""
    if os.environ.get(_ERROR_VAR):
        raise render_error()
