"""Evaluation throughput: episodes per hour with 1 and 2 worker processes, in one run (Lift,
84x84 RGB-D, a NOSTRA policy with the light encoder and AdaMLI on; untrained weights, so every
episode runs its full horizon). Target: a speed-up of at least 1.7x with 2 workers.

Usage: python bench/rollouts.py [--episodes 24] [--horizon 150]. Last line: JSON."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from nostra.workflows.evaluation import jobs_of, run_jobs, EvalSpec, Variant
from nostra.modality import paper_modalities
from nostra.policies.modules import NostraPolicy


def untrained_checkpoint(path: Path) -> str:
    module = NostraPolicy(paper_modalities(84), 7, net={"image_encoder": "light"})
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, path)
    return str(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=24)
    ap.add_argument("--horizon", type=int, default=150)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())
    ckpt = untrained_checkpoint(tmp / "nostra.ckpt")
    spec = EvalSpec(tasks=["Lift"], noises=["mask"], variants=[Variant("nostra_adamli", ckpt, "adaptive")],
                    out_dir=str(tmp), episodes=args.episodes, horizon=args.horizon, windows={"Lift": [[20, 60]]},
                    videos_per_cell=0)
    result = {}
    for workers in (1, 2):
        start = time.perf_counter()
        done = run_jobs(jobs_of(spec), workers, progress=True)
        elapsed = time.perf_counter() - start
        assert not any(r.reason for r in done), [r.reason for r in done if r.reason]
        result[f"episodes_per_hour_{workers}w"] = round(3600 * len(done) / elapsed, 1)
        result[f"seconds_{workers}w"] = round(elapsed, 1)
        print(f"{workers} worker(s): {len(done)} episodes of {args.horizon} steps in {elapsed:.1f} s", flush=True)
    result["speedup"] = round(result["episodes_per_hour_2w"] / result["episodes_per_hour_1w"], 2)
    result.update(episodes=args.episodes, horizon=args.horizon)
    print(json.dumps({"rollouts": result}))


if __name__ == "__main__":
    main()
