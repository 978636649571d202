"""How demos label the gripper at the grasp point: per demo, the place where the expert first closes the gripper,
the open steps it spent there just before closing, and the share of all its steps there (until it leaves after
closing) labelled open. A policy that reaches that place sees what the demos say there, and a decoder's mean over
mixed labels stays open when most of them are open.

    python -m nostra.workflows.grasp_labels --store data/store.zarr \\
        --collections "noise 0.05=stack_cpu,stack_cpu_plus800" "noise 0.2=stack_cpu_n0p2,stack_cpu_n0p2_plus800" \\
        --out reports/cpu-d1000-n0.2-cosine/stack-h600/grasp-labels

"At the grasp point" is within NEAR_XY in x-y and NEAR_Z in height of the end effector's position at the first
closed command (the last action dimension > 0; robosuite's -1 open, +1 closed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.data import Store
from nostra.modality import EEF_POS as EEF
from nostra.workflows.command_log import command_header
from nostra.workflows.cpu_report import machine

NEAR_XY = 0.02  # m: half the width of Stack's red cube, the x-y distance at which a close misses it
NEAR_Z = 0.01   # m: the height band of the grasp (a descent covers it in a few steps)


def grasp_labels(grip: np.ndarray, pos: np.ndarray) -> tuple[int, float] | None:
    """(open steps at the grasp point just before the first close, share of the steps there labelled open) for
    one demo's gripper commands (T,) and end-effector positions (T, 3); None when it never closes. "There" runs
    from the start to the first step after the close that leaves the grasp point."""
    closed = np.flatnonzero(grip > 0)
    if not len(closed):
        return None
    c = closed[0]
    d = pos - pos[c]
    near = (np.linalg.norm(d[:, :2], axis=1) < NEAR_XY) & (np.abs(d[:, 2]) < NEAR_Z)
    before = near[:c][::-1]
    run = int(np.argmin(before)) if not before.all() else c  # the near steps just before the close
    left = np.flatnonzero(~near[c:])
    end = c + (left[0] if len(left) else len(near) - c)
    there = near[:end]
    return run, float((grip[:end][there] <= 0).mean())


def load(store: Store, label: str, collections: list[str]) -> pd.DataFrame:
    """One row per demo of the collections: whether it closed, the open run before closing, the open share."""
    rows = []
    for name in collections:
        ends = store.episode_ends(name)
        grip = store.array(name, "actions")[:, -1]
        pos = store.array(name, EEF)[:]
        for i, (a, b) in enumerate(zip(np.r_[0, ends[:-1]], ends)):
            got = grasp_labels(grip[a:b], pos[a:b])
            rows.append((label, name, i, got is not None, *(got or (np.nan, np.nan))))
    return pd.DataFrame(rows, columns=["label", "collection", "episode", "closes", "open_run", "open_share"])


def summary(demos: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for label, g in demos.groupby("label", sort=False):
        c = g[g["closes"]]
        rows.append({"label": label, "demos": len(g), "closing": len(c),
                     "open_run_median": c["open_run"].median(), "open_run_p90": c["open_run"].quantile(0.9),
                     "open_share_mean": c["open_share"].mean(), "open_share_median": c["open_share"].median(),
                     "half_or_more_open": int((c["open_share"] >= 0.5).sum())})
    return pd.DataFrame(rows)


def markdown(df: pd.DataFrame) -> list[str]:
    lines = ["| Demos | demos (closing) | open steps at the grasp point just before closing, median / p90 "
             "| share of the steps there labelled open, mean / median | demos with half or more open |",
             "|---|---|---|---|---|"]
    for r in df.itertuples():
        lines.append(f"| {r.label} | {r.demos} ({r.closing}) | {r.open_run_median:g} / {r.open_run_p90:g} | "
                     f"{r.open_share_mean:.2f} / {r.open_share_median:.2f} | {r.half_or_more_open} of {r.closing} |")
    return lines


def figure(demos: pd.DataFrame, path: Path) -> None:
    """Histogram per label of each demo's share of open labels at its grasp point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    bins = np.linspace(0, 1, 21)
    for label, g in demos[demos["closes"]].groupby("label", sort=False):
        ax.hist(g["open_share"], bins=bins, alpha=0.5, label=f"{label} ({len(g)} demos)")
    ax.set_xlabel("share of the demo's steps at its grasp point labelled open")
    ax.set_ylabel("demos")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def labelled_collections(text: str) -> tuple[str, list[str]]:
    label, sep, names = text.partition("=")
    if not sep or not label or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LABEL=<collection>[,<collection>...]")
    return label, names.split(",")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", required=True, type=Path)
    ap.add_argument("--collections", nargs="+", required=True, type=labelled_collections,
                    help="LABEL=<collection>[,<collection>...] ...")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None)
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    store = Store(args.store)
    demos = pd.concat([load(store, label, names) for label, names in args.collections], ignore_index=True)
    df = summary(demos)
    args.out.mkdir(parents=True, exist_ok=True)
    demos.to_csv(args.out / "demos.csv", index=False)
    df.to_csv(args.out / "grasp_labels.csv", index=False)
    figure(demos, args.out / "grasp_labels.png")
    sources = [f"- {label}: {', '.join(f'`{n}`' for n in names)}" for label, names in args.collections]
    header = [*command_header(args.out, args.command, args.wall_seconds), f"- Machine: {machine()}",
              f"- Store: `{args.store}`", *sources, ""]
    text = ["# How the demos label the gripper at the grasp point", "", *header,
            f"The grasp point of a demo: within {100 * NEAR_XY:g} cm in x-y and {100 * NEAR_Z:g} cm in height of "
            "where the end effector was at the first closed command (the last action dimension > 0). *Just before "
            "closing*: the unbroken run of open steps there that ends at the close; *the steps there*: from the "
            "start until the first step after the close that leaves it.", "", *markdown(df), "",
            "![open share per demo](grasp_labels.png)", ""]
    (args.out / "index.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
