"""The claims pooled over training seeds from each seed's claims report, for seeds whose episode
records are not on one disk (evaluated on different machines, or records since deleted).

    python -m nostra.workflows.claims_pool --reports reports/cpu-rgbd/liftd1/claims \
        reports/cpu-rgbd/liftd1/claims-s1 --out reports/cpu-rgbd/liftd1/claims-pooled

Reads each report's table1.csv and paired.csv (the per-seed rows) and writes the same report pooled.
Nothing is approximated: a pooled success is the sum of the seeds' successes, and a pooled paired
comparison only needs each seed's 2x2 table (both / only a / only b / neither, all in paired.csv),
so the episodes are rebuilt from those counts and go through claims.paired as if read from the
records: the same bootstrap over (training seed, episode) pairs, McNemar's exact p of the summed table.
A cell or pair is pooled only where every seed has it (a pool over some of the seeds would read as
all of them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows import claims
from nostra.workflows.evaluation import wilson

SUCCESS_COLUMNS = ["checkpoint", "seed", "variant", "noise", "k", "n"]
PAIRED_COLUMNS = ["checkpoint", "seed", "noise", "a", "b", "n", "rate_a", "a_only", "b_only"]


def _read(path: Path, columns: list[str]) -> pd.DataFrame:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; a claims report (python -m nostra.workflows.claims) writes it")
    df = pd.read_csv(path, dtype={"seed": str})
    if missing := [c for c in columns if c not in df.columns]:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(columns)}")
    return df[df.seed != claims.POOLED]


def read_reports(reports: list[Path]) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The per-seed rows of every report's table1.csv, paired.csv and false_imagination.csv; a
    training seed found in two reports is an error (it would be counted twice)."""
    success, pairs, fir, owner = [], [], [], {}
    for r in reports:
        s = _read(r / "table1.csv", SUCCESS_COLUMNS)
        for seed in sorted(set(s.seed)):
            if seed in owner:
                raise ValueError(f"training seed {seed} is in both {owner[seed]} and {r}; pool each seed once")
            owner[seed] = r
        success.append(s)
        pairs.append(_read(r / "paired.csv", PAIRED_COLUMNS))
        if (r / "false_imagination.csv").is_file():
            fir.append(_read(r / "false_imagination.csv", ["checkpoint", "seed", "mean", "count"]))
    if len(owner) < 2:
        raise ValueError(f"{', '.join(map(str, reports))}: {len(owner)} training seed(s); pooling needs two or more")
    return pd.concat(success), pd.concat(pairs), pd.concat(fir) if fir else pd.DataFrame()


def _complete(groups, seeds: set[str]):
    """The groups that every training seed has, each once."""
    for key, g in groups:
        if set(g.seed) == seeds and len(g) == len(seeds):
            yield key, g


def pool_success(success: pd.DataFrame) -> pd.DataFrame:
    seeds, rows = set(success.seed), []
    for (ck, v, noise), g in _complete(success.groupby(["checkpoint", "variant", "noise"]), seeds):
        rows.append({"checkpoint": ck, "seed": claims.POOLED, "variant": v, "noise": noise,
                     "k": int(g.k.sum()), "n": int(g.n.sum())})
    pooled = pd.DataFrame(rows)
    out = pd.concat([success[SUCCESS_COLUMNS], pooled], ignore_index=True)
    out["rate"] = out.k / out.n
    out[["ci_low", "ci_high"]] = [wilson(int(k), int(n)) for k, n in zip(out.k, out.n)]
    return out


def _episodes(r) -> tuple[np.ndarray, np.ndarray]:
    """One seed's paired episodes rebuilt from its 2x2 table (episode order does not enter any statistic)."""
    both = int(round(r.n * r.rate_a)) - int(r.a_only)
    neither = int(r.n) - both - int(r.a_only) - int(r.b_only)
    if min(both, neither) < 0:
        raise ValueError(f"paired row {r.a} - {r.b} under {r.noise} (seed {r.seed}): counts do not add up to n = {r.n}")
    counts = [both, int(r.a_only), int(r.b_only), neither]
    x = np.repeat([True, True, False, False], counts)
    y = np.repeat([True, False, True, False], counts)
    return x, y


def pool_pairs(pairs: pd.DataFrame) -> pd.DataFrame:
    seeds, rows = set(pairs.seed), []
    for (ck, noise, a, b), g in _complete(pairs.groupby(["checkpoint", "noise", "a", "b"], sort=False), seeds):
        xs, ys = zip(*(_episodes(r) for r in g.itertuples()))
        x, y = np.concatenate(xs), np.concatenate(ys)
        rows.append({"checkpoint": ck, "seed": claims.POOLED, "noise": noise, "a": a, "b": b,
                     **claims.paired(pd.Series(x), pd.Series(y))})
    return pd.concat([pairs, pd.DataFrame(rows)], ignore_index=True)


def pool_false_imagination(fir: pd.DataFrame) -> pd.DataFrame:
    if fir.empty:
        return fir
    seeds, rows = set(fir.seed), []
    for ck, g in _complete(fir.groupby("checkpoint"), seeds):
        rows.append({"checkpoint": ck, "seed": claims.POOLED, "count": int(g["count"].sum()),
                     "mean": float(np.average(g["mean"], weights=g["count"]))})
    return pd.concat([fir, pd.DataFrame(rows)], ignore_index=True)


def write_pooled(reports: list[Path], out: Path, header: list[str] = ()) -> str:
    success, pairs, fir = read_reports(reports)
    success, pairs, fir = pool_success(success), pool_pairs(pairs), pool_false_imagination(fir)
    seeds = sorted(set(success.seed) - {claims.POOLED}, key=int)
    text = ["# The paper's claims at CPU scale, pooled over training seeds", "", *[h for h in header if h],
            f"- Training seeds: {', '.join(seeds)} (each report names the command, machine and wall time of its runs)",
            f"- Pooled from the claims reports {', '.join(f'`{r}`' for r in reports)}: every (training seed, "
            "episode) once; a cell or comparison is pooled only where every seed has it.", "", "Success in % over the episodes of each cell (95% Wilson interval).", ""]
    for ck in [c for c in ("best", "last") if c in set(success.checkpoint)]:
        text += [f"## Checkpoint: {ck}", ""]
        for seed in seeds + [claims.POOLED]:
            text += [f"### Training seed {seed}", "", *claims.success_markdown(success, ck, seed), ""]
        for seed in [s for s in seeds + [claims.POOLED] if ((pairs.checkpoint == ck) & (pairs.seed == s)).any()]:
            text += [f"### Paired comparisons, training seed {seed}", "",
                     *claims.paired_markdown(pairs, ck, seed), ""]
        if ((pairs.checkpoint == ck) & (pairs.seed == claims.POOLED)).any():  # no verdict from clean cells alone
            text += ["### Claims (pooled)", "", *claims.verdicts(success, pairs, ck), ""]
        f = fir[(fir.checkpoint == ck) & (fir.seed == claims.POOLED)] if len(fir) else fir
        if len(f):
            text += [f"AdaMLI false imagination on clean episodes: {100 * f['mean'].iloc[0]:.0f}% of steps "
                     f"({int(f['count'].iloc[0])} episodes).", ""]
    out.mkdir(parents=True, exist_ok=True)
    success.to_csv(out / "table1.csv", index=False)
    pairs.to_csv(out / "paired.csv", index=False)
    if len(fir):
        fir.to_csv(out / "false_imagination.csv", index=False)
    (out / "claims.md").write_text("\n".join(text))
    return "\n".join(text)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", required=True, nargs="+", type=Path, help="claims report folders, one or more seeds each")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None, help="the command that wrote this report (for the header)")
    args = ap.parse_args(argv)
    header = [f"- Command: `{args.command}`"] if args.command else []
    print(write_pooled(args.reports, args.out, header))


if __name__ == "__main__":
    main()
