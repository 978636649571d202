"""Figures people look at: end-effector trajectories with and without imagination (paper Figure 4)
and per-modality KL over an episode (Figure 5)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def _shade(ax, windows) -> None:
    for a, b in windows:
        ax.axvspan(a, b, color="red", alpha=0.12)


def trajectory_figure(results, spec, path: Path) -> bool:
    """EEF x/y/z of the first episode of the first task: clean NOSTRA vs noisy NOSTRA with and
    without MLI for each noise (the variants present are drawn; nothing is drawn without a clean run)."""
    if not results:
        return False
    task, seed = results[0].job.task, results[0].job.seed
    by = {(r.job.noise, r.job.variant): r for r in results if r.job.task == task and r.job.seed == seed}
    noises = [n for n in spec.noises if n != "none"]
    clean_variant = next((v.name for v in spec.variants if v.mode == "closed"), spec.variants[0].name)
    clean = by.get(("none", clean_variant))
    if clean is None or not noises or not len(clean.record.get("eef_pos", [])):
        return False
    fig, axes = plt.subplots(len(noises), 3, figsize=(11, 2.6 * len(noises)), squeeze=False)
    for row, noise in zip(axes, noises):
        for d, ax in enumerate(row):
            ax.plot(clean.record["eef_pos"][:, d], "k-", lw=1.5, label=f"{clean_variant}, no noise")
            for v in spec.variants:
                r = by.get((noise, v.name))
                if r is not None and len(r.record.get("eef_pos", [])):
                    ax.plot(r.record["eef_pos"][:, d], lw=1, label=f"{v.label}, {noise}")
            _shade(ax, results[0].job.windows)
            ax.set_title(f"{task} / {noise}: eef {'xyz'[d]}", fontsize=8)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def kl_figure(kl: dict[str, np.ndarray], windows, path: Path, flags: dict[str, np.ndarray] | None = None,
              title: str = "") -> None:
    """Per-modality KL (nats) over an episode, noise windows shaded, imagined steps marked."""
    fig, ax = plt.subplots(figsize=(8, 3.2))
    for m, series in kl.items():
        ax.semilogy(series, lw=1.2, label=m)
    _shade(ax, windows)
    if flags:
        top = max(float(np.nanmax(s)) for s in kl.values())
        for i, (m, f) in enumerate(flags.items()):
            idx = np.flatnonzero(f)
            ax.plot(idx, np.full(len(idx), top * 1.5 ** (i + 1)), "|", ms=5, label=f"imagined: {m}")
    ax.set_xlabel("step"), ax.set_ylabel("KL (nats)"), ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
