"""Imagination over longer windows pooled over training seeds: each seed's horizon report
(python -m nostra.workflows.horizon_report, scripts/cpu_horizon.sh) read from its episodes.csv, one
paired unit per (training seed, episode), so the bootstrap interval and McNemar's p cover both seeds'
episodes and the drift test their paired distances. A setting is pooled only where every seed has it
(a pool over some of the seeds would read as all of them); the others are named in the report.

    python -m nostra.workflows.horizon_pool --reports reports/cpu/liftd1/horizon-mask-s2 \\
        reports/cpu/liftd1/horizon-mask-s3 --seeds 2 3 --out reports/cpu/liftd1/horizon-mask-pooled
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pandas as pd

from nostra.workflows.claims import header_lines
from nostra.workflows.horizon_report import _windows_text, figure, markdown, summary

COLUMNS = ("setting", "variant", "episode", "success", "drift_cm")
NOISE = re.compile(r"Oracle imagination over each setting's windows under `([^`]+)`")


def _noise(report: Path) -> str:
    """The noise a horizon report ran under, read from its horizon.md."""
    md = report / "horizon.md"
    found = NOISE.search(md.read_text()) if md.is_file() else None
    if not found:
        raise ValueError(f"{md}: not a horizon report (no 'windows under `<noise>`' line); write it with "
                         "python -m nostra.workflows.horizon_report")
    return found.group(1)


def load(reports: list[Path], seeds: list[int], noise: str) -> tuple[pd.DataFrame, list[str]]:
    """The seeds' episodes (column ``seed`` added) over the settings every seed has, and the settings left out."""
    if len(reports) != len(seeds) or len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds {seeds} must name one distinct training seed per report ({len(reports)} reports)")
    frames = []
    for report, seed in zip(reports, seeds):
        f = report / "episodes.csv"
        if not f.is_file():
            raise FileNotFoundError(f"{f}: no episodes.csv (write the seed's report with horizon_report first)")
        df = pd.read_csv(f)
        if missing := sorted(set(COLUMNS) - set(df.columns)):
            raise ValueError(f"{f}: missing columns {missing}; a horizon report's episodes.csv has {list(COLUMNS)}")
        if (got := _noise(report)) != noise:
            raise ValueError(f"{report}: its episodes ran under {got!r}, not --noise {noise!r}")
        frames.append(df.assign(seed=seed, success=df.success.astype(bool)))
    common = set.intersection(*(set(d.setting) for d in frames))
    if not common:
        raise ValueError(f"no window setting is in every report: {[sorted(set(d.setting)) for d in frames]}")
    everything = set().union(*(set(d.setting) for d in frames))
    df = pd.concat(frames, ignore_index=True)
    return df[df.setting.isin(common)].reset_index(drop=True), sorted(everything - common)


def write_pool(reports: list[Path], seeds: list[int], out: Path, noise: str = "mask", horizon: int = 200,
               reference_windows: str | None = None, command: str | None = None) -> str:
    df, left_out = load(reports, seeds, noise)
    s = summary(df, horizon)
    extra = [f"- Pooled over training seeds {', '.join(map(str, seeds))} (reports "
             + ", ".join(f"`{r}`" for r in reports) + "): one paired unit per (training seed, episode)"]
    if left_out:
        extra.append("- Not in every seed's report, so not pooled: " + ", ".join(map(_windows_text, left_out)))
    header = header_lines(reports[0].parent, command, None, [], extra, out=out)
    header = [h for h in header if not h.startswith("- Evaluations:")]  # read from reports, not records
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "episodes.csv", index=False)
    s.to_csv(out / "horizon.csv", index=False)
    figure(s, out / "horizon.png")
    text = "\n".join(markdown(s, noise, header, reference_windows, df.episode, pooled=True))
    (out / "horizon.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", nargs="+", required=True, type=Path, help="each seed's horizon report folder")
    ap.add_argument("--seeds", nargs="+", required=True, type=int, help="the training seed of each report, in order")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--noise", default="mask")
    ap.add_argument("--horizon", type=int, default=200, help="the rollout horizon (caps a window's imagined steps)")
    ap.add_argument("--reference-windows", default=None, help="the task's windows, e.g. 15-35+45-60")
    ap.add_argument("--command", default=None)
    args = ap.parse_args(argv)
    print(write_pool(args.reports, args.seeds, args.out, args.noise, args.horizon, args.reference_windows,
                     args.command))


if __name__ == "__main__":
    main()
