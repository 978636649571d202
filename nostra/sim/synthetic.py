"""Synthetic multimodal sequence tasks with known structure, for tests, the benchmark and quick
sanity runs: the policies must show the paper's effects here before they are trusted in simulation.

The oscillator task: a hidden 2-D point rotates at an episode-specific speed; the expert action is
the point's next position. ``pos`` observes the point, ``vel`` its last displacement, and
``distractor`` carries no information about the actions (white noise, a stand-in for a
non-informative sensor)."""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset

from nostra.modality import Modality


def oscillator(n: int, steps: int, seed: int = 0, distractor_dim: int = 8, obs_noise: float = 0.001,
               image_size: int | None = None) -> dict:
    """Episodes of the oscillator task; with ``image_size`` an rgb view ``cam_image`` shows the point."""
    rng = np.random.default_rng(seed)
    omega = rng.uniform(0.15, 0.35, size=(n, 1))
    phase = rng.uniform(0, 2 * np.pi, size=(n, 1))
    angle = omega * np.arange(steps + 1)[None] + phase  # (n, steps+1)
    point = np.stack([np.cos(angle), np.sin(angle)], -1).astype(np.float32)
    pos = point[:, :-1] + rng.normal(0, obs_noise, size=(n, steps, 2))
    vel = np.diff(point, axis=1, prepend=point[:, :1])[:, :-1] + rng.normal(0, obs_noise, size=(n, steps, 2))
    dis = rng.normal(0, 1, size=(n, steps, distractor_dim))
    obs = {k: v.astype(np.float32) for k, v in {"pos": pos, "vel": vel, "distractor": dis}.items()}
    if image_size:
        obs["cam_image"] = point_images(point[:, :-1], image_size)
    return {"obs": obs, "actions": point[:, 1:].copy()}


def point_images(point: np.ndarray, size: int) -> np.ndarray:
    """uint8 (..., size, size, 3) images with a white square where the point is."""
    img = np.zeros((*point.shape[:-1], size, size, 3), dtype=np.uint8)
    pix = np.clip(((point + 1.2) / 2.4 * size).astype(int), 2, size - 3)
    for idx in np.ndindex(point.shape[:-1]):
        x, y = pix[idx]
        img[idx][y - 2:y + 3, x - 2:x + 3] = 255
    return img


def oscillator_modalities(distractor_dim: int = 8, image_size: int | None = None) -> list[Modality]:
    mods = [Modality("pos", "lowdim", (2,)), Modality("vel", "lowdim", (2,)),
            Modality("distractor", "lowdim", (distractor_dim,))]
    return mods + ([Modality("cam_image", "rgb", (image_size, image_size, 3))] if image_size else [])


def stats_of(data: dict) -> dict:
    from nostra.data.stats import fit_stats

    lowdim = {k: v for k, v in data["obs"].items() if v.dtype != np.uint8}
    return fit_stats({**lowdim, "actions": data["actions"]})


def loader(data: dict, batch_size: int, seed: int = 0) -> DataLoader:
    """Batches in the policies' format: {"obs": {key: (B,T,..)}, "actions": (B,T,A)}."""
    keys = list(data["obs"])
    tensors = [torch.as_tensor(data["obs"][k]) for k in keys] + [torch.as_tensor(data["actions"])]

    def collate(rows):
        cols = [torch.stack(c) for c in zip(*rows)]
        return {"obs": dict(zip(keys, cols[:-1])), "actions": cols[-1]}

    g = torch.Generator().manual_seed(seed)
    return DataLoader(TensorDataset(*tensors), batch_size=batch_size, shuffle=True, collate_fn=collate, generator=g)


def kl_trace(steps: int, windows: list[tuple[int, int]], seed: int = 0, base: float = 3.0, jump: float = 2.0,
             wobble: float = 0.15, jitter: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """A per-modality KL series like a trained policy's on a continuous sensor stream: a level that
    wobbles smoothly (three random sinusoids, periods 20-100 steps, about ``wobble`` nats each),
    tiny step-to-step jitter, and about ``jump`` more nats inside each noise window.
    Returns (kl, truth mask)."""
    from nostra.policies.imagination import window_mask

    rng = np.random.default_rng(seed)
    t = np.arange(steps)[:, None]
    periods, phases = rng.uniform(20, 100, 3), rng.uniform(0, 2 * np.pi, 3)
    amps = wobble * rng.uniform(0.5, 1.5, 3)
    level = base + (amps * np.sin(2 * np.pi * t / periods + phases)).sum(1) + rng.normal(0, jitter, steps)
    truth = window_mask(steps, windows)
    return level + truth * jump * rng.uniform(0.8, 1.5), truth
