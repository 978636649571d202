"""Inference latency of each policy's runner: batch 1, two 84x84 RGB views plus lowdim (eef pos,
eef quat, gripper), light encoder, in one run. NOSTRA runs with AdaMLI active (posterior and prior
computed every step). Diffusion Policy plans a 16-step chunk every 8 steps and pops a queued action
in between, so a median over all its steps (a pop: ~0.03 ms) says nothing about its cost.

Every policy is therefore measured the same way, over whole action-chunk cycles: the runner is
reset after warm-up so that measurement starts with a planning step, and ``--steps`` is rounded up
to a multiple of the cycle (``n_action_steps`` for a chunking policy, 1 for one that computes its
action every step), so that every plan's cost is spread over exactly the steps it serves.

- ``amortised_ms``: total time / steps: the per-step cost over whole cycles (like with like);
- ``max_ms``: the worst single step (a chunking policy's planning step: what control waits on);
- ``p50_ms``, ``p95_ms``: percentiles of the single-step times;
- ``planning_ms``: the median over the steps that ran the model (re-planned); for a policy that
  computes its action every step, that is every step.

Usage: python bench/policy_step.py [--steps 200] [--warmup 20] [--threads 2] [--variants a,b]

Output (stdout, JSON lines; human-readable lines go to stderr): one line per variant,
  {"variant": "diffusion_ddim10", "policy": "diffusion", "steps": 200, "cycle": 8, "plans": 25,
   "amortised_ms": ..., "p50_ms": ..., "p95_ms": ..., "max_ms": ..., "planning_ms": ...}
then, as the last line, the summary
  {"policy_step_ms": {variant: amortised_ms, ...}, "worst_step_ms": {variant: max_ms, ...},
   "ratio_nostra_lstm": amortised NOSTRA / amortised BC-LSTM (null unless both ran),
   "threads": ..., "steps": ..., "warmup": ...}"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np
import torch

from nostra.modality import sim_observations
from nostra.policies import POLICIES
from nostra.policies.modules import policy_module

# what the simulator renders at 84 px, but depth: two RGB views and the proprioception
MODALITIES = [m for m in sim_observations(84).modalities if m.kind != "depth"]

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


def cycle_length(runner) -> int:
    """Steps served by one model evaluation: a chunking policy's ``n_action_steps``, else 1."""
    return int(getattr(runner.net, "n_action_steps", 1))


def step_times_ms(runner, steps: int, warmup: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Per-step latencies in ms over whole cycles (``steps`` rounded up to a multiple of the
    cycle, starting right after a reset) and whether each step re-planned (True for every step of
    a policy that does not report ``replanned``, i.e. one that computes its action every step)."""
    rng = np.random.default_rng(0)
    obs = [observation(rng) for _ in range(16)]
    cycle = cycle_length(runner)
    runner.reset()
    for i in range(warmup):
        runner.step(obs[i % 16])
    runner.reset()  # the measured steps start a cycle: the first one plans
    n = max(1, math.ceil(steps / cycle)) * cycle
    times, planned = [], []
    for i in range(n):
        t = time.perf_counter()
        _, info = runner.step(obs[i % 16])
        times.append(time.perf_counter() - t)
        planned.append(info.get("replanned", True))
    planned = np.asarray(planned, dtype=bool)
    expected = np.arange(n) % cycle == 0
    if cycle > 1 and not (planned == expected).all():
        raise RuntimeError(f"{type(runner).__name__} re-planned at steps {np.flatnonzero(planned).tolist()}, "
                           f"expected every {cycle} steps from 0")
    return 1000 * np.asarray(times), planned


def summarise(times: np.ndarray, planned: np.ndarray, cycle: int) -> dict:
    """The statistics of one variant (ms, rounded to 3 decimals)."""
    r = lambda x: round(float(x), 3)  # noqa: E731
    return {"steps": int(len(times)), "cycle": int(cycle), "plans": int(planned.sum()),
            "amortised_ms": r(times.sum() / len(times)), "p50_ms": r(np.percentile(times, 50)),
            "p95_ms": r(np.percentile(times, 95)), "max_ms": r(times.max()),
            "planning_ms": r(np.median(times[planned]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200, help="measured steps, rounded up to whole cycles")
    ap.add_argument("--warmup", type=int, default=20, help="unmeasured steps before the measurement")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated subset of {list(VARIANTS)}")
    args = ap.parse_args()
    names = [v for v in args.variants.split(",") if v]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; valid: {list(VARIANTS)}")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    amortised, worst = {}, {}
    for name in names:
        policy, kwargs = VARIANTS[name]
        runner_cls = POLICIES[policy][1]
        net = policy_module(policy)(MODALITIES, 7, net={"image_encoder": "light"}).net
        runner = runner_cls(net, **kwargs)
        times, planned = step_times_ms(runner, args.steps, args.warmup)
        stats = summarise(times, planned, cycle_length(runner))
        amortised[name], worst[name] = stats["amortised_ms"], stats["max_ms"]
        print(f"{name:>18}: {stats['amortised_ms']:.2f} ms / step amortised, worst {stats['max_ms']:.2f} ms, "
              f"p50 {stats['p50_ms']:.2f}, p95 {stats['p95_ms']:.2f} ({stats['plans']} plans in "
              f"{stats['steps']} steps)", file=sys.stderr, flush=True)
        print(json.dumps({"variant": name, "policy": policy, **stats}), flush=True)
    ratio = (round(amortised["nostra_adamli"] / amortised["lstm"], 3)
             if "nostra_adamli" in amortised and "lstm" in amortised else None)
    print(json.dumps({"policy_step_ms": amortised, "worst_step_ms": worst, "ratio_nostra_lstm": ratio,
                      "threads": args.threads, "steps": args.steps, "warmup": args.warmup}), flush=True)


if __name__ == "__main__":
    main()
