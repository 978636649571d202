"""Success rate of the scripted experts over seeds (physics only, no cameras: the experts read
privileged state, so rendering does not change their actions).

    .venv/bin/python bench/expert_success.py [--tasks Lift Stack ...] [--seeds 50] [--seed-offset 0]

Targets: >= 95% on Lift and Stack, >= 85% on the other tasks. The last line is a JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

TARGETS = {"Lift": 0.95, "Stack": 0.95}
DEFAULT_TARGET = 0.85


def measure(task: str, seeds: list[int]) -> dict:
    from nostra.sim import make_env
    from nostra.sim.experts import make_expert
    from nostra.sim.generate import run_episode

    env = make_env(task, render=False)
    expert = make_expert(env)
    start, results = time.time(), []
    for seed in seeds:
        ep = run_episode(env, expert, seed)
        results.append((ep["meta"]["success"], len(ep["actions"]), seed))
    env.close()
    ok = [r for r in results if r[0]]
    rate = len(ok) / len(results)
    return {"success_rate": round(rate, 4), "episodes": len(results),
            "mean_steps_success": round(float(np.mean([r[1] for r in ok])), 1) if ok else None,
            "failed_seeds": [r[2] for r in results if not r[0]], "target": TARGETS.get(task, DEFAULT_TARGET),
            "meets_target": rate >= TARGETS.get(task, DEFAULT_TARGET), "seconds": round(time.time() - start, 1)}


def main() -> None:
    from nostra.sim import task_names

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=task_names())
    p.add_argument("--seeds", type=int, default=50)
    p.add_argument("--seed-offset", type=int, default=0)
    args = p.parse_args()
    seeds = list(range(args.seed_offset, args.seed_offset + args.seeds))
    out = {}
    for task in args.tasks:
        out[task] = measure(task, seeds)
        print(f"{task}: {out[task]['success_rate']:.0%} success over {len(seeds)} seeds "
              f"(mean {out[task]['mean_steps_success']} steps, {out[task]['seconds']} s)", flush=True)
    print(json.dumps({"bench": "expert_success", "seeds": args.seeds, "seed_offset": args.seed_offset,
                      "tasks": out, "all_meet_target": all(v["meets_target"] for v in out.values())}))


if __name__ == "__main__":
    main()
