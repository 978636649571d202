"""Open-loop action error of trained policies on their own held-out (or training) demos, per checkpoint: each demo's
observations are replayed to the policy's runner step by step (the demo, not the policy, decides where the
robot goes) and the runner's actions are compared with the demo's, per action channel. A policy that fails
in closed loop with a small error here fails through compounding errors or precision; a large one says it
has not fit the demos yet.

    python -m nostra.workflows.open_loop --store data/store.zarr \\
        --runs "Diffusion Policy=data/runs/cpu/train/pretrain-diffusion-Stack-s0" \\
               "BC-LSTM=data/runs/cpu/train/pretrain-lstm-Stack-s0" \\
        --checkpoints step=2000 step=8000 last --episodes 10 --out reports/cpu/stack/open-loop

Per channel: the mean absolute difference over the demo's steps, then over the demos; arm: the mean over all
channels but the last; gripper agreement: the share of steps whose last channel has the demo's sign (robosuite:
-1 open, +1 closed). A sampling policy (Diffusion Policy) draws its noise from the demo's index, as a rollout
draws it from the episode's seed, so a rerun gives the same numbers.
"""

from __future__ import annotations

import argparse
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from nostra import episode
from nostra.data import Store
from nostra.data.dataset import SPLIT_PARTS, run_episodes
from nostra.episode import RecordedSource
from nostra.noise import NoiseSchedule
from nostra.policies.checkpoint import load_runner, select_checkpoint
from nostra.workflows.analysis import SPLIT_WORDS, mean_interval
from nostra.workflows.command_log import command_header
from nostra.workflows.cpu_report import machine


def replay(runner, obs: dict[str, np.ndarray], seed: int) -> np.ndarray:
    """(T, A): the runner's actions on a stored episode's observations, nothing corrupted."""
    if hasattr(runner, "seed"):  # a sampling policy: its noise fixed by the demo
        runner.seed = seed
    ep = episode.run(RecordedSource(obs), runner, NoiseSchedule("none", []), "closed")
    return np.asarray(ep.action, np.float64).reshape(len(ep.action), -1)


def errors(actions: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """(mean absolute error per channel (A,), share of steps whose last channel has the target's sign)."""
    if actions.shape != target.shape:
        raise ValueError(f"the policy gave actions of shape {actions.shape}, the demo has {target.shape}")
    return np.abs(actions - target).mean(0), float((np.sign(actions[:, -1]) == np.sign(target[:, -1])).mean())


def checkpoint_step(path: str, which: str) -> int:
    """The training step a checkpoint was saved at: its name's, or the one Lightning stored in it."""
    named = re.fullmatch(r"step=(\d+)", which)
    if named:
        return int(named[1])
    return int(torch.load(path, map_location="cpu", weights_only=True).get("global_step", -1))


def evaluate(store: Store, label: str, run: Path, which: str, demos: list[tuple[str, int]],
             progress: bool = True) -> tuple[dict, pd.DataFrame]:
    """One checkpoint of one run on the demos: (summary row, one row per demo and channel)."""
    path = select_checkpoint(run, which)
    runner = load_runner(path)
    names = runner.modality_names
    per_demo, rows = [], []
    for i, (coll, idx) in enumerate(tqdm(demos, desc=f"{label} {which}", disable=not progress)):
        data = store.episode(coll, idx, [*names, "actions"])
        mae, agree = errors(replay(runner, {k: data[k] for k in names}, seed=i), data["actions"].astype(np.float64))
        per_demo.append((mae, agree))
        rows += [{"label": label, "checkpoint": which, "collection": coll, "episode": idx, "channel": c,
                  "mae": float(e)} for c, e in enumerate(mae)]
    mae = np.array([m for m, _ in per_demo])
    arm = mae[:, :-1].mean(1)
    agree = np.array([a for _, a in per_demo])
    row = {"label": label, "run": str(run), "checkpoint": which, "step": checkpoint_step(path, which),
           "demos": len(demos), "arm_mae": float(arm.mean()), "arm_mae_ci": mean_interval(arm),
           "gripper_mae": float(mae[:, -1].mean()), "gripper_agreement": float(agree.mean()),
           **{f"mae_{c}": float(v) for c, v in enumerate(mae.mean(0))}}
    return row, pd.DataFrame(rows)


def demo_spread(store: Store, demos: list[tuple[str, int]]) -> np.ndarray:
    """(A,): the demos' mean per-channel standard deviation of the action, the scale the errors compare with."""
    return np.mean([store.episode(c, i, ["actions"])["actions"].std(0) for c, i in demos], 0)


def markdown(df: pd.DataFrame, spread: np.ndarray) -> list[str]:
    chans = [c for c in df.columns if c.startswith("mae_")]
    lines = ["| Policy | checkpoint | step | arm error [95% interval over demos] | gripper agreement | "
             + " | ".join(f"ch {c[4:]}" for c in chans) + " |", "|---|---|---|---|---|" + "---|" * len(chans)]
    for r in df.itertuples():
        lo, hi = r.arm_mae_ci
        lines.append(f"| {r.label} | {r.checkpoint} | {r.step} | {r.arm_mae:.3f} [{lo:.3f}, {hi:.3f}] | "
                     f"{100 * r.gripper_agreement:.1f}% | " + " | ".join(f"{getattr(r, c):.3f}" for c in chans) + " |")
    lines.append(f"| *demo spread (std of the action)* | | | {spread[:-1].mean():.3f} | | "
                 + " | ".join(f"{s:.3f}" for s in spread) + " |")
    return lines


def figure(df: pd.DataFrame, path: Path) -> None:
    """Arm error and gripper agreement against the training step, one line per policy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.5))
    for label, g in df.sort_values("step").groupby("label", sort=False):
        lo, hi = zip(*g["arm_mae_ci"])
        a.plot(g["step"], g["arm_mae"], marker="o", label=label)
        a.fill_between(g["step"], lo, hi, alpha=0.2)
        b.plot(g["step"], 100 * g["gripper_agreement"], marker="o", label=label)
    a.set(xlabel="training step", ylabel="open-loop arm error (mean |a - a_demo|)")
    b.set(xlabel="training step", ylabel="gripper sign agreement (%)")
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def labelled_run(text: str) -> tuple[str, Path]:
    label, sep, run = text.partition("=")
    if not sep or not label or not run:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LABEL=<training run folder>")
    return label, Path(run)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True, type=Path)
    ap.add_argument("--runs", nargs="+", required=True, type=labelled_run, help="LABEL=<training run folder> ...")
    ap.add_argument("--checkpoints", nargs="+", default=["last"], help="best | last | step=<n>, for every run")
    ap.add_argument("--episodes", type=int, default=10, help="the first this many of each run's demos in --split")
    ap.add_argument("--split", choices=SPLIT_PARTS, default="held_out", help="the run's demos it held out or trained on")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None)
    args = ap.parse_args(argv)
    store, start = Store(args.store), time.time()
    plan = [(label, run, which, run_episodes(run, part=args.split)[:args.episodes])
            for label, run in args.runs for which in args.checkpoints]
    for label, run, which, demos in plan:  # every checkpoint and split is there before any replay
        select_checkpoint(run, which)
        if not demos:
            raise ValueError(f"{run}: its episodes.json has no {args.split} demos to replay")
    results = [evaluate(store, label, run, which, demos) for label, run, which, demos in plan]
    df = pd.DataFrame([r for r, _ in results])
    spread = demo_spread(store, sorted({d for *_, demos in plan for d in demos}))
    args.out.mkdir(parents=True, exist_ok=True)
    pd.concat([d for _, d in results], ignore_index=True).to_csv(args.out / "open_loop_demos.csv", index=False)
    df.to_csv(args.out / "open_loop.csv", index=False)
    figure(df, args.out / "open_loop.png")
    runs = [f"- {label}: `{run}`" for label, run in args.runs]
    header = [*command_header(args.out, args.command, time.time() - start), f"- Machine: {machine()}",
              f"- Store: `{args.store}`; the first {args.episodes} {SPLIT_WORDS[args.split]} demos of each run", *runs, ""]
    text = [f"# Open-loop action error on {SPLIT_WORDS[args.split]} demos", "", *header,
            "Each demo's observations replayed to the policy, its actions compared with the demo's: mean absolute "
            "error per action channel (ch), *arm*: over all channels but the last (gripper); *gripper agreement*: "
            "steps whose gripper command has the demo's sign. The last row: the demos' own spread.", "",
            *markdown(df, spread), "", "![open-loop error against the training step](open_loop.png)", ""]
    (args.out / "index.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
