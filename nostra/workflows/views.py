"""Table 3's comparison, paired: BC-NOSTRA trained on another agent view (occluded: the robot blocks
the camera, as in the paper; blind: the camera faces the floor, a control with no information at all)
against the same training on the good view, over the demos both analysed (held out, or trained on:
evaluate.offline.split). The other view's collection is generated on the good one's seeds, so
episode i starts from the same state in both and the two runs' per-episode KL can be resampled
together (percentile bootstrap, scipy.stats.bootstrap).

An analysis folder (under offline_report's --analyses) named ``<run>-occluded`` or ``<run>-blind`` is
paired with the one named ``<run>``; offline.json must carry the per-episode KL (``kl_nats_episodes``).
A report keeps every paired arm's per-episode KL in views_episodes.csv; read back (``with_earlier``), those
runs pair and pool like analyses on the disk."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.modality import FRONT_IMAGE

VIEWS = ("occluded", "blind")  # run-name suffixes of the arms compared with the good view
COLORS = {"good": "C0", "occluded": "C1", "blind": "C2"}  # the same view in the same colour in every figure


def view_pairs(analyses: list[dict]) -> list[tuple[str, dict, str, dict]]:
    """(good run's name, its analysis, the other view, that run's analysis) for every run with both
    arms; one analysis per run (the clean KL does not depend on the analysis's noise)."""
    by_run: dict[str, dict] = {}
    for a in analyses:
        by_run.setdefault(a["name"].split("/")[0], a)
    pairs = []
    for r, a in by_run.items():
        for view in VIEWS:
            good = r.removesuffix(f"-{view}")
            if r.endswith(f"-{view}") and good in by_run:
                pairs.append((good, by_run[good], view, a))
    return pairs


EPISODE_COLUMNS = ["run", "episode", "steps", "modality", "kl_nats"]  # views_episodes.csv, one row per arm, episode, modality


def episode_frame(analyses: list[dict]) -> pd.DataFrame:
    """Every paired arm's per-episode KL (mean nats per step) and step count, the long table a report keeps
    as views_episodes.csv so that a later report can pool its seeds with runs no longer on the disk."""
    rows, seen = [], set()
    for run, good, view, other in view_pairs(analyses):
        for name, a in ((run, good), (f"{run}-{view}", other)):
            if name in seen or "kl_nats_episodes" not in a:
                continue
            seen.add(name)
            for i, (_, e) in enumerate(a["episodes"]):
                rows += [{"run": name, "episode": int(e), "steps": int(a["episode_steps"][i]), "modality": m,
                          "kl_nats": float(kl[i])} for m, kl in a["kl_nats_episodes"].items()]
    return pd.DataFrame(rows, columns=EPISODE_COLUMNS)


def read_episodes(path: Path) -> list[dict]:
    """One earlier report's views_episodes.csv, checked, as analyses ``paired_arms`` reads (one per run)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; offline_report writes <out>/views_episodes.csv")
    df = pd.read_csv(path)
    if missing := [c for c in EPISODE_COLUMNS if c not in df.columns]:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(EPISODE_COLUMNS)}")
    try:
        df = df.astype({"run": str, "episode": int, "steps": int, "modality": str, "kl_nats": float})
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: episode and steps must be integers, kl_nats a number ({e})") from None
    if (df.steps <= 0).any():
        raise ValueError(f"{path}: steps must be positive (run {df.run[df.steps <= 0].iloc[0]})")
    analyses = []
    for run, g in df.groupby("run", sort=False):
        wide = g.pivot_table(index="episode", columns="modality", values="kl_nats", sort=True)
        if wide.isna().any().any():
            raise ValueError(f"{path}: run {run} lacks some modality's KL on some episode")
        steps = g.groupby("episode").steps.first().loc[wide.index]
        analyses.append({"name": run, "episodes": [[str(path), int(e)] for e in wide.index],
                         "episode_steps": steps.tolist(), "kl_nats_episodes": {m: wide[m].tolist() for m in wide}})
    return analyses


def with_earlier(analyses: list[dict], paths: list[Path]) -> list[dict]:
    """``analyses`` and the runs of earlier reports' views_episodes.csv; a run in both: the analysis on disk."""
    here = {a["name"].split("/")[0] for a in analyses}
    earlier = [a for p in paths for a in read_episodes(p)]
    return sorted(analyses + [a for a in earlier if a["name"] not in here], key=lambda a: a["name"])


def _nats(a: dict, modalities: list[str], episodes: list[int]) -> np.ndarray:
    """(modalities + 1, episodes): each episode's total KL per modality in nats, then its step count."""
    index = {int(e[1]): i for i, e in enumerate(a["episodes"])}
    rows = [index[e] for e in episodes]
    steps = np.asarray(a["episode_steps"], float)[rows]
    kl = np.asarray([np.asarray(a["kl_nats_episodes"][m], float)[rows] for m in modalities])
    return np.vstack([kl * steps, steps])


def _kl(x: np.ndarray, j: int, idx: np.ndarray):
    """Modality j's mean KL per step over episodes ``idx`` (a row of indices, or a batch of resampled rows)."""
    return x[j][idx].sum(-1) / x[-1][idx].sum(-1)


def _share(x: np.ndarray, j: int, idx: np.ndarray):
    """Modality j's share of the total KL over episodes ``idx``."""
    return x[j][idx].sum(-1) / x[:-1][:, idx].sum(axis=(0, -1))


def _with_interval(stat, n: int, seed: int) -> tuple[float, float, float]:
    """stat over all n episodes and its 95% percentile-bootstrap interval (episodes resampled)."""
    from scipy.stats import bootstrap

    idx = np.arange(n)
    ci = bootstrap((idx,), lambda i, axis=-1: stat(i), vectorized=True, n_resamples=10_000, method="percentile",
                   random_state=np.random.default_rng(seed)).confidence_interval
    return float(stat(idx)), float(ci.low), float(ci.high)


def paired_arms(analyses: list[dict]):
    """(good run's name, other view, modalities, good arm's and other arm's per-episode nats from
    ``_nats``) over the episodes both analysed, for every pair with per-episode KL on >= 2 of them."""
    for run, good, view, occl in view_pairs(analyses):
        if "kl_nats_episodes" not in good or "kl_nats_episodes" not in occl:
            continue
        common = sorted({int(e[1]) for e in good["episodes"]} & {int(e[1]) for e in occl["episodes"]})
        modalities = [m for m in good["kl_nats_episodes"] if m in occl["kl_nats_episodes"]]
        if len(common) >= 2 and modalities:
            yield run, view, modalities, _nats(good, modalities, common), _nats(occl, modalities, common)


def _kl_change(g: np.ndarray, o: np.ndarray, j: int):
    return lambda i: 100 * (_kl(o, j, i) / _kl(g, j, i) - 1)


def _share_change(g: np.ndarray, o: np.ndarray, j: int):
    return lambda i: 100 * (_share(o, j, i) - _share(g, j, i))


CHANGES = (("kl_change_pct", _kl_change, "{:+.0f}"), ("share_change_pts", _share_change, "{:+.1f}"))  # name, stat, format


def view_changes(analyses: list[dict], seed: int = 0) -> pd.DataFrame:
    """Per paired run, other view and modality: mean KL per step on each view, the other view's change
    in % of the good view's, each view's share of the total KL and the change in points, with 95%
    intervals over the common analysed episodes. Empty when no run has both arms with per-episode KL."""
    rows = []
    for run, view, modalities, g, o in paired_arms(analyses):
        n = g.shape[1]
        every = np.arange(n)
        for j, m in enumerate(modalities):
            row = {"run": run, "view": view, "episodes": n, "modality": m, "kl_good": _kl(g, j, every),
                   "kl_view": _kl(o, j, every), "share_good": _share(g, j, every), "share_view": _share(o, j, every)}
            for name, change, _ in CHANGES:
                row[name], row[f"{name}_low"], row[f"{name}_high"] = _with_interval(change(g, o, j), n, seed)
            rows.append(row)
    return pd.DataFrame(rows)


def pooled_changes(analyses: list[dict], seed: int = 0, n_resamples: int = 10_000) -> pd.DataFrame:
    """The changes of ``view_changes`` pooled over training seeds: runs named ``<prefix>-s<seed>`` with
    the same prefix and view, each seed weighted alike (the mean of the per-seed changes), with a
    two-stage bootstrap interval (seeds resampled, then episodes within each), so the spread between
    training seeds widens it. Hand-written: scipy's bootstrap resamples one level only. Empty when
    no prefix and view has two seeds."""
    groups: dict[tuple[str, str], list] = {}
    for run, view, modalities, g, o in paired_arms(analyses):
        if m := re.fullmatch(r"(.+)-s(\d+)", run):
            groups.setdefault((m[1], view), []).append((m[2], modalities, g, o))
    rng, rows = np.random.default_rng(seed), []
    for (prefix, view), arms in groups.items():
        if len(arms) < 2:
            continue
        arms.sort(key=lambda a: int(a[0]))
        k = len(arms)
        draw = rng.integers(k, size=(n_resamples, k))  # stage 1: which seed fills each slot
        resamples = [rng.integers(g.shape[1], size=(n_resamples, k, g.shape[1])) for _, _, g, _ in arms]
        for m in [m for m in arms[0][1] if all(m in a[1] for a in arms)]:
            row = {"run": prefix, "view": view, "seeds": " ".join(a[0] for a in arms), "modality": m}
            for name, change, fmt in CHANGES:
                stats = [change(g, o, mods.index(m)) for _, mods, g, o in arms]
                point = [float(stat(np.arange(g.shape[1]))) for stat, (_, _, g, _) in zip(stats, arms)]
                boot = np.stack([stat(idx) for stat, idx in zip(stats, resamples)])  # (arm, resample, slot)
                pooled = boot[draw, np.arange(n_resamples)[:, None], np.arange(k)].mean(1)
                row[name], row[f"{name}_per_seed"] = float(np.mean(point)), " ".join(fmt.format(p) for p in point)
                row[f"{name}_low"], row[f"{name}_high"] = np.percentile(pooled, [2.5, 97.5]).tolist()
            rows.append(row)
    return pd.DataFrame(rows)


def figure(changes: pd.DataFrame, path) -> None:
    """Each modality's KL change against the good view, one panel per run, one bar per other view,
    with the 95% intervals; the paper's range for the occluded agent view shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = list(dict.fromkeys(changes.run))
    fig, axes = plt.subplots(1, len(runs), figsize=(4.5 * len(runs), 3.6), sharey=True, squeeze=False)
    for ax, run in zip(axes[0], runs):
        g = changes[changes.run == run]
        modalities, views = list(dict.fromkeys(g.modality)), list(dict.fromkeys(g.view))
        width = 0.8 / len(views)
        for k, view in enumerate(views):
            v = g[g.view == view].set_index("modality").loc[modalities]
            x = np.arange(len(modalities)) + (k - (len(views) - 1) / 2) * width
            ax.bar(x, v.kl_change_pct, width, label=view, color=COLORS.get(view),
                   yerr=[v.kl_change_pct - v.kl_change_pct_low, v.kl_change_pct_high - v.kl_change_pct], capsize=3)
        if FRONT_IMAGE in modalities:  # the agent view, the one the paper occludes
            i = modalities.index(FRONT_IMAGE)
            ax.fill_between([i - 0.45, i + 0.45], -32, -10, color="0.8", zorder=0, label="paper (occluded)")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(np.arange(len(modalities)), [m.replace("robot0_", "") for m in modalities], rotation=30,
                      ha="right", fontsize=8)
        ax.set_title(run, fontsize=9)
    axes[0][0].set_ylabel("KL change vs good view (%)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def training_kl(checkpoint: str | None, modality: str) -> pd.Series:
    """A modality's KL per step over training (metrics.jsonl beside the checkpoint), by step; empty
    when the run's metrics are not there."""
    path = Path(checkpoint).parent / "metrics.jsonl" if checkpoint else None
    if path is None or not path.exists():  # no checkpoint: a run read back from views_episodes.csv
        return pd.Series(dtype=float)
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    kl = {r["step"]: r["metrics"][f"kl_nats/{modality}"] for r in rows
          if f"kl_nats/{modality}" in r.get("metrics", {})}
    return pd.Series(kl, dtype=float).sort_index()


def training_changes(analyses: list[dict], last: int = 250) -> pd.DataFrame:
    """Per paired run, other view and modality: the KL on the training batches, averaged over each
    run's last ``last`` steps (what a training log shows), and the other view's change in %; no
    interval (consecutive batches are not independent samples). Empty without the runs' metrics."""
    rows = []
    for run, good, view, other in view_pairs(analyses):
        for m in good.get("kl_nats_episodes", {}):
            g, o = training_kl(good.get("checkpoint"), m), training_kl(other.get("checkpoint"), m)
            if not len(g) or not len(o):
                continue
            g, o = g[g.index > g.index.max() - last].mean(), o[o.index > o.index.max() - last].mean()
            rows.append({"run": run, "view": view, "modality": m, "kl_good": g, "kl_view": o,
                         "kl_change_pct": 100 * (o / g - 1)})
    return pd.DataFrame(rows)


def traces_figure(analyses: list[dict], path, modality: str = FRONT_IMAGE, smooth: int = 10) -> bool:
    """The agent view's KL over training, one panel per paired run, one line per view (running mean
    over ``smooth`` logged steps); False (nothing written) when no paired run's metrics are found."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels: dict[str, dict[str, pd.Series]] = {}
    for run, good, view, other in view_pairs(analyses):
        for name, a in (("good", good), (view, other)):
            kl = training_kl(a.get("checkpoint"), modality)
            if len(kl):
                panels.setdefault(run, {})[name] = kl.rolling(smooth, min_periods=1).mean()
    if not panels:
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4), sharey=True, squeeze=False)
    for ax, (run, lines) in zip(axes[0], panels.items()):
        for name, kl in lines.items():
            ax.plot(kl.index, kl.values, label=name, color=COLORS.get(name))
        ax.set_title(run, fontsize=9), ax.set_xlabel("training step")
    axes[0][0].set_ylabel(f"{modality} KL per step (nats)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def pooled_rows(pooled: pd.DataFrame) -> list[str]:
    """One Markdown row per pooled run, view and modality: the per-seed changes and the pooled ones."""
    return [f"| {r.run}-s* | {r.view} | {r.seeds} | {r.modality} | {r.kl_change_pct_per_seed}% | "
            f"{r.kl_change_pct:+.0f}% [{r.kl_change_pct_low:+.0f}, {r.kl_change_pct_high:+.0f}] | "
            f"{r.share_change_pts_per_seed} | {r.share_change_pts:+.1f} [{r.share_change_pts_low:+.1f}, "
            f"{r.share_change_pts_high:+.1f}] |" for r in pooled.itertuples()]


def markdown(changes: pd.DataFrame, traces: bool = False, batches: pd.DataFrame | None = None,
             pooled: pd.DataFrame | None = None) -> list[str]:
    """The paired comparison as Markdown lines (none when there is nothing to compare)."""
    if not len(changes):
        return []
    lines = ["## Another agent view against the good view, paired (Table 3)", "",
             "Each run trained again on the same seeds' demos with the agent view occluded (the robot blocks it, "
             "as in the paper) or blind (it faces the floor: the same image at every step, a control); mean KL "
             "per step over the demos both arms analysed (same initial states), the other arm's "
             "change in % of the good arm's, and each modality's share of the total KL; 95% "
             "percentile-bootstrap intervals over those episodes, resampled together. The paper: the occluded "
             "view's KL falls (by up to 32%) while the other modalities' rise.", "", "![views](views.png)", ""]
    for (run, view), g in changes.groupby(["run", "view"], sort=False):
        lines += [f"`{run}` vs `{run}-{view}` ({int(g.episodes.iloc[0])} episodes)", "",
                  f"| modality | KL good (nats) | KL {view} | change | share good | share {view} | change (points) |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {r.modality} | {r.kl_good:.2f} | {r.kl_view:.2f} | {r.kl_change_pct:+.0f}% "
                  f"[{r.kl_change_pct_low:+.0f}, {r.kl_change_pct_high:+.0f}] | {100 * r.share_good:.1f}% | "
                  f"{100 * r.share_view:.1f}% | {r.share_change_pts:+.1f} [{r.share_change_pts_low:+.1f}, "
                  f"{r.share_change_pts_high:+.1f}] |" for r in g.itertuples()]
        lines.append("")
    if pooled is not None and len(pooled):
        lines += ["Pooled over training seeds: the mean of the per-seed changes (each seed alike), 95% two-stage "
                  "bootstrap interval (training seeds resampled, then episodes within each):", "",
                  "| runs | view | seeds | modality | KL change per seed | pooled | share change per seed (points) "
                  "| pooled |", "|---|---|---|---|---|---|---|---|"]
        lines += pooled_rows(pooled)
        lines.append("")
    if batches is not None and len(batches):
        lines += ["The same runs' KL on their own training batches, mean over the last 250 steps (what a training "
                  "log shows; each arm on its own view's demos; no interval):", "",
                  "| run | view | modality | KL good | KL view | change |", "|---|---|---|---|---|---|"]
        lines += [f"| {r.run} | {r.view} | {r.modality} | {r.kl_good:.2f} | {r.kl_view:.2f} | {r.kl_change_pct:+.0f}% |"
                  for r in batches.itertuples()]
        lines.append("")
    if traces:
        lines += ["The agent view's KL over training (each arm on its own training batches):", "",
                  "![views_training](views_training.png)", ""]
    return lines
