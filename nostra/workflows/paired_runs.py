"""Two studies of one task compared cell by cell, paired on the initial states both met (e.g. a policy
trained on 200 demos against one trained on 1000): every (training seed, checkpoint, noise, variant) cell
that both evaluation folders hold, as each success rate with its 95% Wilson interval and the difference
with a 95% bootstrap interval and McNemar's exact p (``claims.paired``).

    python -m nostra.workflows.paired_runs --a "1000 demos=data/runs/cpu-d1000/evaluate/stack" \\
        --b "200 demos=data/runs/cpu/evaluate/stack" --out reports/cpu-d1000/stack/vs-200
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd

from nostra.workflows.claims import RECORDS, header_lines, load_records, paired
from nostra.workflows.evaluation import wilson
from nostra.workflows.variants import LABELS

CELL = ["seed", "checkpoint", "noise", "variant"]


def labelled(arg: str) -> tuple[str, Path]:
    """``LABEL=<folder>`` -> (label, folder); the folder must hold evaluation records."""
    label, sep, folder = arg.partition("=")
    if not sep or not label or not folder:
        raise argparse.ArgumentTypeError(f"{arg!r}: expected LABEL=<runs>/evaluate/<task>")
    path = Path(folder)
    if not any(path.glob(RECORDS)):
        raise argparse.ArgumentTypeError(f"{path}: no episode records (s<seed>/<checkpoint>/.../records/"
                                         "<task>/<noise>/<variant>_seed<n>.npz) under it")
    return label, path


def compare(a: pd.DataFrame, b: pd.DataFrame) -> pd.DataFrame:
    """One row per cell both hold: n, rate_a, rate_b, diff, ci_low, ci_high, a_only, b_only, p."""
    cells_b = {k: g.set_index("episode")["success"] for k, g in b.groupby(CELL)}
    rows = [{**dict(zip(CELL, k)), **paired(g.set_index("episode")["success"], cells_b[k])}
            for k, g in a.groupby(CELL) if k in cells_b]
    return pd.DataFrame(rows)


def rate_cell(rate: float, n: int) -> str:
    lo, hi = wilson(round(rate * n), n)
    return f"{100 * rate:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]"


def markdown(df: pd.DataFrame, label_a: str, label_b: str) -> list[str]:
    lines = [f"| Seed | Checkpoint | Noise | Method | {label_a} | {label_b} | {label_a} - {label_b} [95% CI] "
             f"| only {label_a} / only {label_b} | McNemar p | episodes |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in df.itertuples():
        lines.append(f"| {r.seed} | {r.checkpoint} | {r.noise} | {LABELS.get(r.variant, r.variant)} | "
                     f"{rate_cell(r.rate_a, r.n)} | {rate_cell(r.rate_b, r.n)} | {100 * r.diff:+.0f} "
                     f"[{100 * r.ci_low:+.0f}, {100 * r.ci_high:+.0f}] | {r.a_only} / {r.b_only} | {r.p:.2g} | {r.n} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--a", required=True, type=labelled, help="LABEL=<runs>/evaluate/<task>")
    ap.add_argument("--b", required=True, type=labelled, help="LABEL=<runs>/evaluate/<task>, the reference")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None)
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    (label_a, path_a), (label_b, path_b) = args.a, args.b
    df = compare(load_records(path_a), load_records(path_b))
    if df.empty:
        raise SystemExit(f"{path_a} and {path_b} hold no cell in common (training seed, checkpoint, noise, variant)")
    args.out.mkdir(parents=True, exist_ok=True)
    df.to_csv(args.out / "paired.csv", index=False)
    seeds = [f"- Training seeds: {', '.join(map(str, sorted(df['seed'].unique())))}"]
    header = header_lines(path_a, args.command, args.wall_seconds, [f"Reference ({label_b}): `{path_b}`"], seeds,
                          out=args.out)
    text = [f"# {label_a} vs {label_b}, paired on the initial states both met", "", *header,
            "Success in % with a 95% Wilson interval; the difference in points with a 95% bootstrap interval over "
            "the paired episodes; McNemar's exact test on the episodes only one of them succeeded on.", "",
            *markdown(df, label_a, label_b), ""]
    (args.out / "index.md").write_text("\n".join(text))
    print("\n".join(text))


if __name__ == "__main__":
    main()
