"""Training throughput of BC-LSTM, BC-RSSM and BC-NOSTRA at a profile's shapes, in one run.

Each policy takes optimiser steps (forward, backward, Adam) on random batches shaped like the
profile's (batch x sequence, its observation keys and image size, its encoder and augmentation);
no data loading, so this is the model's own cost. One JSON line per policy with samples (windows)
and frames per second, then a last line with the NOSTRA / BC-LSTM time ratio per sample (the
issue's bound: NOSTRA's per-step GRU loop must not make it more than 1.5x slower).

    python bench/train_step.py                     # the cpu profile's shapes
    python bench/train_step.py --profile tiny --steps 5
    python bench/train_step.py --profile paper --device cuda --steps 50   # on a GPU (bf16 with --bf16)
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import yaml

from nostra.modality import Modality, sim_observations
from nostra.policies.modules import policy_module

ROOT = Path(__file__).resolve().parents[1]


def profile_shapes(name: str) -> dict:
    prof = yaml.safe_load((ROOT / "conf" / "profile" / f"{name}.yaml").read_text())
    keys = prof.get("obs_keys") or list(sim_observations().names)  # as conf/data: the profile's, else all
    return {"batch": prof["batch_size"], "seq": prof["seq_len"], "size": prof["image_size"], "keys": keys,
            "net": {"image_encoder": prof["image_encoder"], "image_aug": prof.get("image_aug", "none")}}


def modalities(keys: list[str], size: int) -> list[Modality]:
    return sim_observations(size).select(keys)


def batch(mods: list[Modality], b: int, t: int, device: str = "cpu") -> dict:
    obs = {}
    for m in mods:
        if m.kind == "rgb":
            obs[m.name] = torch.randint(0, 256, (b, t, *m.shape), dtype=torch.uint8, device=device)
        else:
            obs[m.name] = torch.rand(b, t, *m.shape, device=device)
    return {"obs": obs, "actions": torch.rand(b, t, 7, device=device) * 2 - 1}


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()  # GPU work is asynchronous: time it once it has run


def measure(policy: str, mods, shapes: dict, steps: int, warmup: int = 2, device: str = "cpu",
            bf16: bool = False) -> dict:
    torch.manual_seed(0)
    module = policy_module(policy)(mods, 7, net=dict(shapes["net"])).to(device)
    module.train()
    opt = module.configure_optimizers()
    data = batch(mods, shapes["batch"], shapes["seq"], device)
    autocast = torch.autocast(device.split(":")[0], dtype=torch.bfloat16, enabled=bf16)
    for i in range(warmup + steps):
        if i == warmup:
            sync(device)
            start = time.perf_counter()
        opt.zero_grad()
        with autocast:
            loss = module.training_step(data, i)
        loss.backward()
        opt.step()
    sync(device)
    sec = (time.perf_counter() - start) / steps
    return {"policy": policy, "seconds_per_step": round(sec, 4), "samples_per_s": round(shapes["batch"] / sec, 2),
            "frames_per_s": round(shapes["batch"] * shapes["seq"] / sec, 1),
            "params": sum(p.numel() for p in module.parameters())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--encoder", default=None, help="override the profile's image encoder")
    ap.add_argument("--device", default="cpu", help="cpu, cuda, cuda:1, ...")
    ap.add_argument("--bf16", action="store_true", help="bfloat16 autocast (Lightning's precision='bf16-mixed')")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    shapes = profile_shapes(args.profile)
    if args.encoder:
        shapes["net"]["image_encoder"] = args.encoder
    mods = modalities(shapes["keys"], shapes["size"])
    common = {"profile": args.profile, "batch": shapes["batch"], "seq": shapes["seq"], "image_size": shapes["size"],
              "keys": len(mods), **shapes["net"], "threads": torch.get_num_threads(), "device": args.device,
              "bf16": args.bf16}
    rows = {}
    for policy in ("lstm", "rssm", "nostra"):
        rows[policy] = measure(policy, mods, shapes, args.steps, device=args.device, bf16=args.bf16)
        print(json.dumps({**common, **rows[policy]}), flush=True)
    ratio = rows["nostra"]["seconds_per_step"] / rows["lstm"]["seconds_per_step"]
    print(json.dumps({"nostra_over_lstm_per_sample": round(ratio, 3), "bound": 1.5, "within": ratio <= 1.5}))


if __name__ == "__main__":
    main()
