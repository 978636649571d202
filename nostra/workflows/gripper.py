"""Gripper dithering and missed grasps in evaluation records, per cell of one or more studies: how often each
episode's gripper command switches from open to closed (a policy unsure whether to hold commands ~0 and swings
around it: tens of switches, where a successful pick shows one or two), and, where the records hold the
objects' positions (``object/<name>``, written by rollouts since they record them), how far in x-y the gripper
was from the nearest object when it first closed: a grasp farther than ``MISS`` closes beside the object.

    python -m nostra.workflows.gripper --runs "Gaussian head=data/runs/cpu-d1000-cosine/evaluate/stack-h400" \\
        "GMM head=data/runs/cpu-d1000-cosine-gmm/evaluate/stack-h400" --out reports/cpu-d1000-cosine-gmm/gripper

The gripper command is the last action dimension (robosuite's: -1 open, +1 closed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.claims import RECORDS, cell_of, header_lines
from nostra.workflows.paired_runs import labelled
from nostra.workflows.variants import LABELS

DITHER = 10  # open-to-closed switches that make an episode dithering (a success here has at most a few)
MISS = 0.02  # m: x-y distance from the nearest object at the first close that misses it (Stack's red cube:
             # 2 cm half-width, so the fingers close beside it)
CELL = ["study", "seed", "checkpoint", "noise", "variant"]


def closings(action: np.ndarray) -> int:
    """Open-to-closed switches of the gripper command (the last action dimension) over an episode."""
    grip = np.asarray(action)[:, -1]
    return int(((grip[1:] > 0) & (grip[:-1] <= 0)).sum())


def object_keys(z) -> list[str]:
    """A record's object positions (``object/<name>``; rollouts record them since they knew them)."""
    return [k for k in z.files if k.startswith("object/")]


def closing_distance(z) -> float:
    """x-y distance (m) from the end effector to the nearest object at the first closed gripper command; nan
    when the record holds no object positions or the gripper never closed."""
    names = object_keys(z)
    closed = np.flatnonzero(np.asarray(z["action"])[:, -1] > 0)
    if not names or not len(closed) or "eef_pos" not in z.files:
        return float("nan")
    t = closed[0]
    return float(min(np.linalg.norm(z[k][t, :2] - z["eef_pos"][t, :2]) for k in names))


def load_closings(label: str, evaluations: Path) -> pd.DataFrame:
    """One row per episode of the study: its cell, episode, success, gripper closings and the distance
    from the nearest object at the first close (nan without object positions, or when it never closed)."""
    rows = []
    for f in sorted(evaluations.glob(RECORDS)):
        variant, episode = f.stem.rsplit("_seed", 1)
        with np.load(f) as z:
            if "action" not in z.files:
                raise ValueError(f"{f}: no 'action' array (keys: {', '.join(z.files)}); "
                                 "records written by `nostra evaluate` hold one")
            rows.append((label, *cell_of(f, evaluations), variant, int(episode), bool(z["success"]),
                         closings(z["action"]), bool(object_keys(z)), closing_distance(z)))
    return pd.DataFrame(rows, columns=[*CELL, "episode", "success", "closings", "objects", "closing_distance"])


def summary(episodes: pd.DataFrame) -> pd.DataFrame:
    """Per cell: episodes, successes, dithering episodes, failures that dither, median closings of a success
    and of a failure; where the objects were recorded, failures that closed beside every object and the
    median distance at the first close (cm) of a success and of a failure."""
    rows = []
    for key, g in episodes.groupby(CELL, sort=False):
        dither, ok = g["closings"] >= DITHER, g["success"]
        rows.append({**dict(zip(CELL, key)), "episodes": len(g), "successes": int(ok.sum()),
                     "dithering": int(dither.sum()), "failures": int((~ok).sum()),
                     "failures_dithering": int((dither & ~ok).sum()),
                     "median_closings_success": g.loc[ok, "closings"].median(),
                     "median_closings_failure": g.loc[~ok, "closings"].median(),
                     "failures_missing": int((~ok & (g["closing_distance"] >= MISS)).sum())
                     if g["objects"].all() else None,
                     "median_cm_success": 100 * g.loc[ok, "closing_distance"].median(),
                     "median_cm_failure": 100 * g.loc[~ok, "closing_distance"].median()})
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame) -> list[str]:
    lines = ["| Study | Seed | Checkpoint | Noise | Method | success | dithering episodes | failures that dither "
             "| median closings, successes / failures | failures that closed beside every object "
             "| median cm from the nearest object at the first close, successes / failures |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    pair = lambda a, b, fmt: " / ".join("–" if np.isnan(m) else format(m, fmt) for m in (a, b))  # noqa: E731
    for r in df.itertuples():
        missing = "–" if pd.isna(r.failures_missing) else f"{int(r.failures_missing)} of {r.failures}"
        lines.append(f"| {r.study} | {r.seed} | {r.checkpoint} | {r.noise} | {LABELS.get(r.variant, r.variant)} | "
                     f"{r.successes} / {r.episodes} | {r.dithering} | {r.failures_dithering} of {r.failures} | "
                     f"{pair(r.median_closings_success, r.median_closings_failure, 'g')} | {missing} | "
                     f"{pair(r.median_cm_success, r.median_cm_failure, '.1f')} |")
    return lines


def figure(episodes: pd.DataFrame, path: Path) -> None:
    """Per episode, successes and failures apart, one row of points per study and cell: the closings, and
    beside them (where the records hold the objects) the distance from the nearest object at the first close."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = list(episodes.groupby(CELL, sort=False))
    panels = [("closings", "gripper closings in the episode + 1", DITHER + 1, f"{DITHER} closings")]
    if episodes["closing_distance"].notna().any():
        panels.append(("closing_distance", "cm from the nearest object at the first close", 100 * MISS,
                       f"{100 * MISS:g} cm"))
    fig, axes = plt.subplots(1, len(panels), figsize=(8 * len(panels), 0.5 * len(cells) + 1.2), squeeze=False)
    for ax, (column, xlabel, line, line_label) in zip(axes[0], panels):
        for y, (key, g) in enumerate(cells):
            for ok, colour in ((True, "tab:green"), (False, "tab:red")):
                x = g.loc[g["success"] == ok, column]
                x = x + 1 if column == "closings" else 100 * x
                ax.scatter(x, np.full(len(x), y) + (0.12 if ok else -0.12), s=12, c=colour, alpha=0.6,
                           label=("success" if ok else "failure") if y == 0 else None)
        ax.axvline(line, color="grey", ls="--", lw=1, label=line_label)
        ax.set_xscale("log" if column == "closings" else "linear")
        ax.set_yticks(range(len(cells)), [f"{k[0]}, s{k[1]} {k[2]}, {k[3]}" for k, _ in cells])
        ax.set_xlabel(xlabel)
        ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)  # outside: points stay visible
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, type=labelled, help="LABEL=<runs>/evaluate/<task> ...")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None)
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    episodes = pd.concat([load_closings(label, path) for label, path in args.runs], ignore_index=True)
    df = summary(episodes)
    args.out.mkdir(parents=True, exist_ok=True)
    episodes.to_csv(args.out / "episodes.csv", index=False)
    df.to_csv(args.out / "gripper.csv", index=False)
    figure(episodes, args.out / "gripper.png")
    studies = [f"- {label}: `{path}`" for label, path in args.runs]
    header = header_lines(args.runs[0][1], args.command, args.wall_seconds, [], studies, out=args.out)
    text = ["# Gripper dithering and missed grasps, per episode", "", *header,
            f"An episode *dithers* when its gripper command (the last action dimension) switches from open (<= 0) "
            f"to closed (> 0) {DITHER} times or more. A failure *closed beside every object* when, at its first "
            f"closed command, the end effector was {100 * MISS:g} cm or more in x-y from the nearest object "
            "(– where the records hold no object positions).", "", *markdown(df), "",
            "![closings and closing distances per episode](gripper.png)", ""]
    (args.out / "index.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
