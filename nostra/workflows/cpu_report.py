"""The CPU profile's report (`make cpu`): success with the best and the last checkpoint, clean and
blind, per training seed; the cost of training and of its rollouts; the rollout learning curves.
Reads what the runs wrote (run.json, rollouts.json, success.csv) and writes index.md, success.csv,
training.json and learning_curves.png into the report folder; a row of the folder's earlier report
whose run or evaluation is not on this disk (another VM, another MODELS) is kept and marked, not
dropped. `recipe` writes the table of `make cpu-recipe`: which switch of the recipe moved success, by
how much, with intervals.

    python -m nostra.workflows.cpu_report --task liftd1 --runs data/runs/cpu --seeds 0 --models lstm nostra --out reports/cpu/liftd1
    python -m nostra.workflows.cpu_report recipe --evaluations data/runs/cpu/evaluate/liftd1/recipe --task liftd1 --out recipe.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import pandas as pd

from nostra.sim.tasks import get_task
from nostra.workflows.claims import copied_variants
from nostra.workflows.command_log import command_header
from nostra.workflows.variants import LABELS


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{os.cpu_count()} cores ({cpu}), {mem:.0f} GiB RAM, no GPU"


def cell(r) -> str:
    return f"{100 * r.success_rate:.0f} [{100 * r.ci_low:.0f}, {100 * r.ci_high:.0f}]"


def success_rows(runs: Path, task: str, seeds: list[int]) -> pd.DataFrame:
    frames = []
    for seed in seeds:
        for ck in ("best", "last"):
            for path in sorted((runs / "evaluate" / task / f"s{seed}" / ck).rglob("success.csv")):  # one per noise
                frames.append(pd.read_csv(path).assign(seed=seed, checkpoint=ck))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


KEPT = "†"
KEY = ["seed", "variant", "noise", "checkpoint"]


def with_kept_rows(df: pd.DataFrame, out: Path, task: str) -> pd.DataFrame:
    """This disk's cells, then the cells of the report already in `out` that this disk has no evaluation
    for (column `kept`), so a report rewritten on another machine or for another model loses nothing."""
    df = df.assign(kept=False)
    old = out / "success.csv"
    if not old.is_file():
        return df
    prev = pd.read_csv(old)
    missing = [c for c in KEY + ["task", "success_rate", "ci_low", "ci_high", "episodes"] if c not in prev.columns]
    if missing:
        raise ValueError(f"{old}: no column {missing[0]!r}; remove the file or give another --out")
    other = sorted(set(prev.task) - {task})
    if other:
        raise ValueError(f"{old} holds cells of task {other[0]!r}, not {task!r}: give this task its own --out")
    if len(df):
        prev = prev[~prev.set_index(KEY).index.isin(df.set_index(KEY).index)]
    prev = prev.drop(columns="kept", errors="ignore").assign(kept=True)
    return pd.concat([df, prev], ignore_index=True).sort_values(["seed"], kind="stable", ignore_index=True)


def success_table(df: pd.DataFrame) -> list[str]:
    """One row per (seed, variant): clean with best and last, blind with best; kept cells marked."""
    cols = [("none", "best", "clean, best"), ("none", "last", "clean, last"), ("blind", "best", "blind, best")]
    lines = ["| Seed | Method | " + " | ".join(c[2] for c in cols) + " |", "|---" * (len(cols) + 2) + "|"]
    for (seed, variant), g in df.groupby(["seed", "variant"], sort=False):
        cells = []
        for noise, ck, _ in cols:
            r = g[(g.noise == noise) & (g.checkpoint == ck)]
            row = next(r.itertuples()) if len(r) else None
            cells.append("–" if row is None else cell(row) + (f" {KEPT}" if getattr(row, "kept", False) else ""))
        label = LABELS.get(variant, variant)
        if variant == "nostra_mli":
            label = "BC-NOSTRA, cameras imagined (MLI)"
        lines.append(f"| {seed} | {label} | " + " | ".join(cells) + " |")
    return lines


def training_rows(runs: Path, task_name: str, seeds: list[int], models: list[str],
                  kept: dict | None = None) -> tuple[list[str], dict, dict]:
    """The training table, the checks to draw, and what training.json keeps: one row per (seed, model)
    trained on this disk, then the kept rows of the folder's earlier report that this disk has no run for."""
    lines = ["| Seed | Model | demos (train + held out) | steps | wall (min) | rollouts (min, share) | checks "
             "| best step (success, episodes) |", "|---|---|---|---|---|---|---|---|"]
    curves, rows, kept = {}, {}, dict(kept or {})
    for seed in seeds:
        for m in models:
            run = runs / "train" / f"pretrain-{m}-{task_name}-s{seed}"
            if (run / "run.json").is_file():
                rows[f"{seed}/{m}"] = trained_row(run, seed, m)
                kept.pop(f"{seed}/{m}", None)
            elif f"{seed}/{m}" not in kept:
                lines.append(f"| {seed} | {LABELS.get(m, m)} | – | – | – | – | – | not trained |")
    for key, r in sorted({**rows, **kept}.items(), key=lambda kv: (int(kv[0].split("/")[0]), kv[0])):
        lines.append(r["row"][:-2] + f" {KEPT} |" if key in kept else r["row"])
        if r.get("checks"):
            curves[tuple(key.split("/"))] = r["checks"]
    return lines, curves, {**rows, **kept}


def trained_row(run: Path, seed: int, m: str) -> dict:
    info = json.loads((run / "run.json").read_text())
    checks = json.loads((run / "rollouts.json").read_text()) if (run / "rollouts.json").is_file() else []
    # train_seconds: the fit's time over every sitting (Lightning's Timer); runs written before it: this process's
    wall = info.get("train_seconds") or info.get("wall_seconds") or float("nan")
    resumed = ", resumed" if info.get("resumed") else ""
    spent = sum(c.get("seconds", 0) for c in checks)
    # the run's own pick (run.json): among the checks at its last horizon, as best.ckpt was chosen
    best = (info.get("rollouts") or {}).get("best") or max(checks, key=lambda c: (c["score"], c["step"]),
                                                           default=None)
    best_s = f"{best['step']} ({100 * best['score']:.0f}%, {best['episodes']})" if best else "–"
    demos = (f"{info['train_episodes']} + {info['val_episodes']}" if "train_episodes" in info else "–")
    return {"row": f"| {seed} | {LABELS.get(m, m)} | {demos} | {info['steps']} | {wall / 60:.1f}{resumed} | "
                   f"{spent / 60:.1f} ({100 * spent / wall:.0f}%) | {len(checks)} | {best_s} |", "checks": checks}


def kept_training(out: Path) -> dict:
    """The training rows the folder's earlier report wrote: training.json, or for a report written before
    training.json existed, the rows of its index.md's training table (no curves then)."""
    if (out / "training.json").is_file():
        return json.loads((out / "training.json").read_text())
    if not (out / "index.md").is_file():
        return {}
    text = (out / "index.md").read_text()
    table = text.split("## Training", 1)[1] if "## Training" in text else ""
    names = {label: m for m, label in LABELS.items()}
    rows = {}
    for line in table.splitlines():
        line = line.replace(f" {KEPT}", "").strip()
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 8 and cells[0].isdigit() and cells[1] in names and cells[-1] != "not trained":
            rows[f"{cells[0]}/{names[cells[1]]}"] = {"row": line, "checks": []}
    return rows


def curve_figure(curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for (seed, m), checks in sorted(curves.items(), key=lambda kv: (int(kv[0][0]), kv[0][1])):
        horizons = sorted({c.get("horizon") for c in checks}, key=str)
        for h in horizons:  # a run resumed at another horizon: one line per horizon
            part = [c for c in checks if c.get("horizon") == h]
            ax.plot([c["step"] for c in part], [100 * c["score"] for c in part], marker="o",
                    label=f"{LABELS.get(m, m)} s{seed}" + (f", {h} steps" if len(horizons) > 1 and h else ""))
    ax.set_xlabel("training step")
    ax.set_ylabel("clean success (%)")
    ax.set_ylim(-5, 105)
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(fontsize=8)
    ax.set_title("Rollouts during training")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def episode_successes(folder: Path) -> dict[int, bool]:
    """seed -> success of every clean episode an evaluation folder recorded (one variant each)."""
    out = {}
    for f in sorted((folder / "records").glob("*/none/*_seed*.npz")):
        import numpy as np

        out[int(f.stem.rsplit("_seed", 1)[1])] = bool(np.load(f)["success"])
    return out


# (label, evaluation, the one it is compared with, paired: same checkpoint and seeds, only the runner differs)
RECIPE = [
    ("BC-LSTM, the recipe (crop, noise-injected demos, reset every 10 steps)", "base", None, False),
    ("BC-LSTM, image augmentation off", "noaug", "base", False),
    ("BC-LSTM, noise-free demos", "nonoise", "base", False),
    ("BC-LSTM, learning rate 3e-4 (recipe: the paper's 1e-4)", "lr3e-4", "base", False),
    ("BC-LSTM best checkpoint, state reset every 10 steps", "reset10", None, False),
    ("BC-LSTM best checkpoint, state carried all episode", "carry", "reset10", True),
    ("BC-NOSTRA best checkpoint, filter carried all episode", "nostra_carry", None, False),
    ("BC-NOSTRA best checkpoint, filter restarted every 10 steps", "nostra_reset10", "nostra_carry", True),
]


def compare(a: dict[int, bool], b: dict[int, bool], paired: bool) -> str:
    """Difference a - b in points with a 95% interval; McNemar's exact p where paired, else
    Newcombe's interval for two independent proportions."""
    from statsmodels.stats.proportion import confint_proportions_2indep

    from nostra.workflows.claims import paired as paired_test

    ka, na, kb, nb = sum(a.values()), len(a), sum(b.values()), len(b)
    diff = 100 * (ka / na - kb / nb)
    if paired:  # the claims report's paired test, over the seeds both evaluated
        p = paired_test(pd.Series(a, dtype=bool), pd.Series(b, dtype=bool))["p"]
        return f"{diff:+.0f} (McNemar exact p = {p:.2g})"
    lo, hi = confint_proportions_2indep(ka, na, kb, nb, method="newcomb")
    return f"{diff:+.0f} [{100 * lo:+.0f}, {100 * hi:+.0f}]"


def recipe_main(argv: list[str]) -> None:
    from nostra.workflows.evaluation import wilson

    ap = argparse.ArgumentParser(prog="python -m nostra.workflows.cpu_report recipe")
    ap.add_argument("--evaluations", required=True)
    ap.add_argument("--task", required=True)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--out", required=True)
    ap.add_argument("--command", default=None,
                    help="the command that made the evaluations (for the header; none: the log's history kept)")
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    ev = Path(args.evaluations)
    found = {name: episode_successes(ev / name) for _, name, _, _ in RECIPE if (ev / name).is_dir()}
    commands = command_header(Path(args.out).with_suffix(".commands.jsonl"), args.command, args.wall_seconds)
    lines = [f"# Which switches of the CPU recipe move success ({get_task(args.task).name})", "",
             *commands, f"- Machine: {machine()}",
             f"- Training runs compared at the same step ({args.steps}); clean rollouts on the evaluation seeds, "
             "the same for every row", "",
             "| Setting | success % [95% CI] | difference (points) |", "|---|---|---|"]
    for label, name, ref, paired in RECIPE:
        if name not in found or not found[name]:
            lines.append(f"| {label} | – (not run) | |")
            continue
        k, n = sum(found[name].values()), len(found[name])
        lo, hi = wilson(k, n)
        diff = compare(found[name], found[ref], paired) if ref in found and found.get(ref) else ""
        lines.append(f"| {label} | {100 * k / n:.0f} [{100 * lo:.0f}, {100 * hi:.0f}] (n={n}) | {diff} |")
    lines += ["", "Differences against the row each switch changes: Newcombe 95% intervals where two trainings are "
              "compared; where one checkpoint runs with two state-reset rules on the same seeds, the pairs are "
              "compared with McNemar's exact test.", ""]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> None:
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["recipe"]:
        return recipe_main(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", required=True)
    ap.add_argument("--runs", required=True)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--models", nargs="+", default=["lstm", "nostra"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--command", default=None,
                    help="the command that made the evaluations (for the header; none: the log's history kept)")
    ap.add_argument("--wall-seconds", type=float, default=None)
    ap.add_argument("--demos", default="expert seeds from 0", help="where the training demos came from")
    ap.add_argument("--horizon", type=int, default=None,
                    help="the rollout horizon make cpu's HORIZON set: its cells are in <runs>/evaluate/<task>-h<N>")
    args = ap.parse_args(argv)
    task = get_task(args.task).name  # unknown task -> the valid ones
    runs, out = Path(args.runs), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = args.task + (f"-h{args.horizon}" if args.horizon else "")  # named as the command named the task
    df = with_kept_rows(success_rows(runs, folder, args.seeds), out, task)
    train_lines, curves, training = training_rows(runs, task, args.seeds, args.models, kept_training(out))
    if len(df):
        df.drop(columns="kept").to_csv(out / "success.csv", index=False)
    (out / "training.json").write_text(json.dumps(training, indent=1))
    curve_figure(curves, out / "learning_curves.png")
    episodes = int(df["episodes"].max()) if len(df) else 0
    commands = command_header(out, args.command, args.wall_seconds)
    if not any(c.startswith("- Wall time") for c in commands):
        commands.append("- Wall time of the command: see the training table")
    copies = sorted(p.parent for seed in args.seeds
                    for p in (runs / "evaluate" / folder).glob(f"s{seed}/last/*/SAME_AS_BEST.txt"))
    kept = bool(len(df) and df["kept"].any()) or any(line.endswith(f"{KEPT} |") for line in train_lines)
    text = [f"# CPU profile: {task}", "",
            *commands, f"- Machine: {machine()}" + (f" (this disk's runs; rows marked {KEPT} ran where their "
                                                   "command did)" if kept else ""),
            f"- Training seeds: {', '.join(map(str, args.seeds))}; demos: {args.demos}; "
            f"rollouts: seeds 1000-{1000 + max(episodes, 1) - 1} (never used by demos), the same for every variant",
            *([f"- Rollout horizon: {args.horizon} steps, set for these cells (`HORIZON`; evaluations in "
               f"`{runs / 'evaluate' / folder}`); the best checkpoint is the one the training's own checks picked"]
              if args.horizon else []),
            *(["- Last = best checkpoint (the final check was the best), so these last cells are copies of the best "
               "cells, not a second run: " + ", ".join(
                   f"`{c.relative_to(runs / 'evaluate' / folder)}` ({copied_variants(c, c)})" for c in copies)]
              if copies else []),
            "", "## Success", "",
            f"Success rate in % over {episodes} episodes per cell, 95% Wilson interval in brackets. "
            "*best*: the checkpoint with the best in-training rollout success (the peak, as the paper and "
            "diffusion_policy report); *last*: the end of training. *blind*: no camera at any step (black frames; "
            "for the MLI row the camera latents are imagined from step 1).", "",
            *(success_table(df) if len(df) else ["(no evaluation found)"]), "",
            "## Training", "", *train_lines, "", "![learning curves](learning_curves.png)", "",
            *([f"{KEPT} kept from this folder's earlier report: the run or evaluation is not on this disk (another "
               "machine, or a command with other seeds or models; commands.jsonl lists the commands that made "
               "them). Remove the folder to start afresh.", ""] if kept else [])]
    (out / "index.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
