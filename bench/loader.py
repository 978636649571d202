"""Loader throughput: sequence samples/s from the store into training batches, against what one
NOSTRA training step consumes (tiny profile shapes: two 84x84 rgb, one 84x84 depth, three lowdim,
T=16, batch 32, 2 workers). Target: the loader outpaces training by 10x or more.

    .venv/bin/python bench/loader.py [--episodes 40] [--steps 100] [--batches 40]

Prints a JSON object as its last line."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from nostra.data import Store, make_loader

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the synthetic episodes the tests use
import fixtures as F  # noqa: E402
from nostra.data.formats import robomimic_hdf5
from nostra.policies.modules import NostraPolicy

TARGET = 10.0


def build_store(root: Path, episodes: int, steps: int, noise: int = 0) -> tuple[Store, float]:
    rng = np.random.default_rng(0)

    def eps():
        for i in range(episodes):
            ep = F.make_episodes(1, [steps], image_size=84, seed=i)[0]
            ep.demo_id = f"demo_{i}"
            for k, v in ep.obs.items():  # sensor-like noise makes images compress as badly as rendered ones
                if v.dtype == np.uint8 and noise:
                    ep.obs[k] = np.clip(v + rng.integers(-noise, noise + 1, v.shape), 0, 255).astype(np.uint8)
            yield ep

    src = robomimic_hdf5.write(root / "bench.hdf5", eps(), F.ENV_ARGS, total=episodes, next_obs=False, progress=False)
    store = Store(root / "store.zarr")
    t = time.perf_counter()
    store.ingest(src, name="bench", progress=False)
    return store, episodes * steps / (time.perf_counter() - t)


def loader_rate(loader, batches: int) -> float:
    it = iter(loader)
    next(it)  # workers start and fill their prefetch queues
    t = time.perf_counter()
    n = 0
    for _ in range(batches):
        n += next(it)["actions"].shape[0]
    return n / (time.perf_counter() - t)


def train_rate(loader, steps: int = 3) -> float:
    ds = loader.dataset
    module = NostraPolicy(ds.modalities(), ds.action_dim, net={"image_encoder": "light"})
    module.set_normalization(ds.stats())
    opt = torch.optim.Adam(module.parameters(), lr=1e-4)
    batch = next(iter(loader))

    def step():
        opt.zero_grad()
        module.net.loss(batch, **module.loss_cfg)["loss"].backward()
        opt.step()

    step()  # warm-up (allocations)
    t = time.perf_counter()
    for _ in range(steps):
        step()
    return batch["actions"].shape[0] * steps / (time.perf_counter() - t)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--steps", type=int, default=100, help="steps per episode")
    p.add_argument("--batches", type=int, default=40)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--noise", type=int, default=8, help="+- pixel noise added to the synthetic images")
    a = p.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        store, ingest_rate = build_store(Path(tmp), a.episodes, a.steps, a.noise)
        keys = list(F.PAPER_KEYS)
        loader = make_loader(store, ["bench"], keys, seq_len=16, batch_size=32, num_workers=a.workers,
                             num_samples=32 * (a.batches + 8))
        load = loader_rate(loader, a.batches)
        train = train_rate(make_loader(store, ["bench"], keys, seq_len=16, batch_size=32, num_workers=0))
        store_mb = sum(f.stat().st_size for f in store.path.rglob("*") if f.is_file()) / 2 ** 20
    print(f"loader {load:.0f} samples/s, NOSTRA training step {train:.1f} samples/s, ratio {load / train:.1f}x "
          f"(target >= {TARGET:.0f}x); ingest {ingest_rate:.0f} steps/s")
    print(json.dumps({"loader_samples_per_s": round(load, 1), "train_samples_per_s": round(train, 2),
                      "ratio": round(load / train, 1), "target_ratio": TARGET, "meets_target": load / train >= TARGET,
                      "ingest_steps_per_s": round(ingest_rate, 1), "episodes": a.episodes, "steps_per_episode": a.steps,
                      "seq_len": 16, "batch_size": 32, "workers": a.workers, "image_noise": a.noise,
                      "store_mb": round(store_mb, 1)}))


if __name__ == "__main__":
    main()
