"""Table 3 pooled over training seeds from the views reports' per-seed changes alone (each report's
views.csv): the mean of the per-seed changes, each seed alike, with a t interval over the seeds. This is
for reports whose runs' per-episode KL was not kept (written before views_episodes.csv) and whose runs are
gone from the disk; the interval is seed-level only (each seed's own episodes are not resampled), which
here is the larger part of the spread. Where every seed's views_episodes.csv is at hand, pass them to
``offline_report --views-episodes`` instead: its two-stage bootstrap covers both levels.

    python -m nostra.workflows.views_pool --reports reports/cpu/liftd1/views reports/cpu/liftd1/views-s3 \\
        --out reports/cpu/liftd1/views-pooled
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.command_log import command_header
from nostra.workflows.views import pooled_rows

COLUMNS = ["run", "view", "modality", "kl_change_pct", "share_change_pts"]
STATS = (("kl_change_pct", "{:+.0f}"), ("share_change_pts", "{:+.1f}"))  # pooled columns, per-seed format


def load(reports: list[Path]) -> pd.DataFrame:
    """Every report's per-seed changes, the run split into its prefix and training seed; a run in two
    reports is taken from the first listed."""
    frames = []
    for report in reports:
        f = report / "views.csv"
        if not f.is_file():
            raise FileNotFoundError(f"{f}: no views.csv; write the report with scripts/cpu_views.sh or "
                                    "python -m nostra.workflows.offline_report")
        df = pd.read_csv(f)
        if missing := [c for c in COLUMNS if c not in df.columns]:
            raise ValueError(f"{f}: missing column(s) {', '.join(missing)}; a views.csv has {', '.join(COLUMNS)}")
        parts = df.run.astype(str).str.extract(r"^(.+)-s(\d+)$")
        if parts.isna().any().any():
            raise ValueError(f"{f}: run {df.run[parts.isna().any(axis=1)].iloc[0]!r} does not end in -s<training seed>")
        frames.append(df[COLUMNS].assign(prefix=parts[0], seed=parts[1].astype(int), report=str(report)))
    df = pd.concat(frames, ignore_index=True)
    return df.drop_duplicates(["prefix", "seed", "view", "modality"], keep="first").reset_index(drop=True)


def pool(df: pd.DataFrame) -> pd.DataFrame:
    """Per run prefix, view and modality with two or more seeds: the mean of the per-seed changes and its
    95% t interval over the seeds (scipy.stats.t)."""
    from scipy import stats

    rows = []
    for (prefix, view, modality), g in df.groupby(["prefix", "view", "modality"], sort=False):
        g = g.sort_values("seed")
        n = len(g)
        if n < 2:
            continue
        row = {"run": prefix, "view": view, "modality": modality, "seeds": " ".join(map(str, g.seed))}
        for name, fmt in STATS:
            x = g[name].to_numpy(float)
            low, high = stats.t.interval(0.95, n - 1, loc=x.mean(), scale=x.std(ddof=1) / np.sqrt(n))
            row |= {name: x.mean(), f"{name}_per_seed": " ".join(fmt.format(v) for v in x),
                    f"{name}_low": low, f"{name}_high": high}
        rows.append(row)
    return pd.DataFrame(rows)


def markdown(pooled: pd.DataFrame, reports: list[Path], header: list[str]) -> str:
    lines = ["# Table 3 pooled over training seeds from the per-seed changes", "", *header,
             "- Reports: " + ", ".join(f"`{r}`" for r in reports) + " (their views.csv; a run in two: the first)", "",
             "The other view's change against the good view, per training seed (each over its held-out or training "
             "episodes, as its report says), their mean (each seed alike) and a 95% t interval over the seeds: "
             "seed-level only, the episodes within each seed are not resampled.", "",
             "| runs | view | seeds | modality | KL change per seed | pooled [95% t CI] | share change per seed "
             "(points) | pooled |", "|---|---|---|---|---|---|---|---|"]
    return "\n".join(lines + pooled_rows(pooled)) + "\n"


def write_pool(reports: list[Path], out: Path, command: str | None = None) -> str:
    pooled = pool(load(reports))
    if not len(pooled):
        raise ValueError(f"no run, view and modality has two training seeds in {', '.join(map(str, reports))}")
    header = command_header(out, command)  # a malformed log beside the report fails before anything is written
    pooled.to_csv(out / "views_pooled.csv", index=False)
    text = markdown(pooled, reports, header)
    (out / "views_pooled.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", nargs="+", required=True, type=Path, help="views report folders (views.csv)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None)
    args = ap.parse_args(argv)
    command = args.command or "python -m nostra.workflows.views_pool --reports " + " ".join(map(str, args.reports)) \
        + f" --out {args.out}"
    print(write_pool(args.reports, args.out, command))


if __name__ == "__main__":
    main()
