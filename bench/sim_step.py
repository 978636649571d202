"""Env steps/s of one worker with two 84x84 RGB-D cameras (agentview + wrist, agentview depth):
robosuite's default render settings vs the tuned ones (no shadows, reflections, multisampling).

    .venv/bin/python bench/sim_step.py [--task Lift] [--steps 150] [--size 84] [--cores 1]

Pinned to `--cores` CPUs (Mesa's llvmpipe renders with threads). Saves a tuned frame as a PNG.
Target: tuned >= 30 steps/s on one core. The last line is a JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def steps_per_s(task: str, size: int, steps: int, tuned: bool) -> tuple[float, float, dict]:
    from nostra.sim import make_env
    from nostra.sim.experts import make_expert

    env = make_env(task, image_size=size, depth=True, tuned_render=tuned)
    expert = make_expert(env)
    t0 = time.perf_counter()
    obs = env.reset(seed=0)
    reset_s = time.perf_counter() - t0
    expert.reset()
    for _ in range(5):  # warm up the renderer
        obs, *_ = env.step(expert.act(obs))
    t0 = time.perf_counter()
    for _ in range(steps):
        obs, *_ = env.step(expert.act(obs))
    rate = steps / (time.perf_counter() - t0)
    env.close()
    return rate, reset_s, obs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="Lift")
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--size", type=int, default=84)
    p.add_argument("--cores", type=int, default=1, help="CPUs to pin this process to (0 = no pinning)")
    p.add_argument("--png", default="data/bench/sim_step_tuned.png")
    args = p.parse_args()
    if args.cores > 0 and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: args.cores])

    default_rate, default_reset, _ = steps_per_s(args.task, args.size, args.steps, tuned=False)
    tuned_rate, tuned_reset, obs = steps_per_s(args.task, args.size, args.steps, tuned=True)

    from PIL import Image

    from nostra.modality import sim_observations

    frame = np.concatenate([obs[k] for k in sim_observations().rgb_keys], axis=1)
    Path(args.png).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(frame).resize((frame.shape[1] * 3, frame.shape[0] * 3), Image.NEAREST).save(args.png)
    print(f"default render: {default_rate:.1f} steps/s, tuned: {tuned_rate:.1f} steps/s; frame -> {args.png}")
    print(json.dumps({
        "bench": "sim_step", "task": args.task, "image_size": args.size, "cameras": 2, "depth": True,
        "cores": args.cores or os.cpu_count(), "steps": args.steps,
        "default_steps_per_s": round(default_rate, 1), "tuned_steps_per_s": round(tuned_rate, 1),
        "speedup": round(tuned_rate / default_rate, 2), "reset_s": round(tuned_reset, 3),
        "target_tuned_steps_per_s": 30, "meets_target": tuned_rate >= 30, "png": args.png,
    }))


if __name__ == "__main__":
    main()
