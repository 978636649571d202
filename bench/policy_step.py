"""Per-step inference latency of each policy's runner: batch 1, two 84x84 RGB views plus lowdim
(eef pos, eef quat, gripper), light encoder; median over 200 steps after warm-up, in one run.
NOSTRA runs with AdaMLI active (posterior and prior computed every step). Diffusion Policy plans a
16-step chunk every 8 steps and pops a queued action in between: its entry in ``policy_step_ms``
is the median over all steps, ``planning_step_ms`` the median over the re-planning steps only.

Usage: python bench/policy_step.py [--steps 200] [--threads 2]
Last line: JSON with the medians in ms and the ratio NOSTRA / BC-LSTM."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from nostra.modality import Modality
from nostra.policies import POLICIES

MODALITIES = [
    Modality("agentview_image", "rgb", (84, 84, 3)),
    Modality("robot0_eye_in_hand_image", "rgb", (84, 84, 3)),
    Modality("robot0_eef_pos", "lowdim", (3,)),
    Modality("robot0_eef_quat", "lowdim", (4,)),
    Modality("robot0_gripper_qpos", "lowdim", (2,)),
]

# name -> (policy, runner kwargs); policies added later extend this table.
VARIANTS = {
    "nostra_adamli": ("nostra", {"adaptive": True}),
    "rssm": ("rssm", {}),
    "lstm": ("lstm", {}),
    "diffusion_ddpm100": ("diffusion", {"sampler": "ddpm", "inference_steps": 100}),
    "diffusion_ddim10": ("diffusion", {"sampler": "ddim", "inference_steps": 10}),
}


def observation(rng: np.random.Generator) -> dict:
    return {m.name: (rng.integers(0, 256, m.shape, dtype=np.uint8) if m.kind == "rgb"
                     else rng.normal(size=m.shape).astype(np.float32)) for m in MODALITIES}


def step_times_ms(runner, steps: int, warmup: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Per-step latencies in ms and whether each step re-planned (True for every step of a policy
    that does not report ``replanned``, i.e. one that computes its action every step)."""
    rng = np.random.default_rng(0)
    obs = [observation(rng) for _ in range(16)]
    runner.reset()
    for i in range(warmup):
        runner.step(obs[i % 16])
    times, planned = [], []
    for i in range(steps):
        t = time.perf_counter()
        _, info = runner.step(obs[i % 16])
        times.append(time.perf_counter() - t)
        planned.append(info.get("replanned", True))
    return 1000 * np.asarray(times), np.asarray(planned)


def median_step_ms(runner, steps: int, warmup: int = 20) -> float:
    return float(np.median(step_times_ms(runner, steps, warmup)[0]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    result, planning = {}, {}
    for name, (policy, kwargs) in VARIANTS.items():
        module_cls, runner_cls = POLICIES[policy]
        net = module_cls([m.to_dict() for m in MODALITIES], 7, net={"image_encoder": "light"}).net
        times, planned = step_times_ms(runner_cls(net, **kwargs), args.steps)
        result[name] = round(float(np.median(times)), 3)
        line = f"{name:>18}: {result[name]:.2f} ms / step"
        if not planned.all():  # chunking policies: the steps that run the model are what control waits on
            planning[name] = round(float(np.median(times[planned])), 3)
            line += f" (planning steps: {planning[name]:.2f} ms, {int(planned.sum())} of {len(planned)})"
        print(line, flush=True)
    result["ratio_nostra_lstm"] = round(result["nostra_adamli"] / result["lstm"], 3)
    result["threads"] = args.threads
    print(json.dumps({"policy_step_ms": result, "planning_step_ms": planning}))


if __name__ == "__main__":
    main()
