"""Simulated tasks (robosuite), their variation knobs, scripted experts and demo generation."""

import logging

from nostra.sim import _gl

_gl.select_backend()  # before anything imports mujoco/robosuite: they read MUJOCO_GL on import
logging.getLogger("OpenGL").setLevel(logging.WARNING)  # mujoco's EGL import logs an INFO notice

from nostra.sim.tasks import TASKS, TaskSpec, get_task, register_task, task_names  # noqa: E402
from nostra.sim.variations import Variation, sample_variation  # noqa: E402
from nostra.sim.env import SimEnv, make_env  # noqa: E402

__all__ = ["TASKS", "TaskSpec", "get_task", "register_task", "task_names", "Variation", "sample_variation",
           "SimEnv", "make_env"]
