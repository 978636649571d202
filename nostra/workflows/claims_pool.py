"""A report pooled over training seeds from each seed's report, for seeds whose episode records are
not on one disk (evaluated on different machines, or records since deleted): claims reports
(Tables 1 and 2, python -m nostra.workflows.claims) or transfer reports (Tables 4 and 5,
python -m nostra.workflows.transfer_report), told apart by their files.

    python -m nostra.workflows.claims_pool --reports reports/cpu-rgbd/liftd1/claims \
        reports/cpu-rgbd/liftd1/claims-s1 --out reports/cpu-rgbd/liftd1/claims-pooled

Reads each report's success table (table1.csv or success.csv) and paired.csv (the per-seed rows) and
writes the same report pooled.
Nothing is approximated: a pooled success is the sum of the seeds' successes, and a pooled paired
comparison only needs each seed's 2x2 table (both / only a / only b / neither, all in paired.csv),
so the episodes are rebuilt from those counts and go through claims.paired as if read from the
records: the same bootstrap over (training seed, episode) pairs, McNemar's exact p of the summed table.
A cell or pair is pooled only where every seed has it (a pool over some of the seeds would read as
all of them).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows import claims, transfer_report
from nostra.workflows.command_log import command_header
from nostra.workflows.evaluation import wilson


@dataclass(frozen=True)
class Kind:
    """A report's files and the columns that name one cell (success) and one comparison (paired)."""
    name: str
    success_file: str
    cell: list[str]
    pair: list[str]


CLAIMS = Kind("claims", "table1.csv", ["checkpoint", "variant", "noise"], ["checkpoint", "noise", "a", "b"])
TRANSFER = Kind("transfer", "success.csv", ["setting", "variant"], ["table", "a_setting", "a", "b_setting", "b"])
COUNTS = ["seed", "n", "rate_a", "a_only", "b_only"]


def kind_of(report: Path) -> Kind:
    for kind in (CLAIMS, TRANSFER):
        if (report / kind.success_file).is_file():
            return kind
    raise FileNotFoundError(f"{report}: neither table1.csv (a claims report) nor success.csv (a transfer report)")


def _read(path: Path, columns: list[str]) -> pd.DataFrame:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; the report's command writes it")
    df = pd.read_csv(path, dtype={"seed": str, "seeds": str})
    if missing := [c for c in columns if c not in df.columns]:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(columns)}")
    return df[df.seed != claims.POOLED]


def read_reports(reports: list[Path], only: list[str] | None = None
                 ) -> tuple[Kind, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The reports' kind and the per-seed rows of their success table, paired.csv and (claims)
    false_imagination.csv, of the training seeds ``only`` (default: all). A seed's cells may come from
    several reports (Table 4 from one sitting, Table 5 from another); one cell of one seed found in two
    reports is an error (it would count twice)."""
    kinds = {r: kind_of(r) for r in reports}
    if len({k.name for k in kinds.values()}) > 1:
        raise ValueError("reports of different kinds: " + ", ".join(f"{r} ({k.name})" for r, k in kinds.items()))
    kind = kinds[reports[0]]
    success, pairs, fir, held, owner = [], [], [], set(), {}
    keep = (lambda d: d) if only is None else (lambda d: d[d.seed.isin(only)])
    for r in reports:
        s = _read(r / kind.success_file, ["seed", *kind.cell, "k", "n"])
        held |= set(s.seed)
        s = keep(s)
        for seed, *cell in s[["seed", *kind.cell]].itertuples(index=False):
            if (seed, *cell) in owner:
                raise ValueError(f"training seed {seed}'s cell {' / '.join(map(str, cell))} is in both "
                                 f"{owner[seed, *cell]} and {r}; pool each seed's cell once")
            owner[seed, *cell] = r
        success.append(s)
        pairs.append(keep(_read(r / "paired.csv", kind.pair + COUNTS)))
        if (r / "false_imagination.csv").is_file():
            fir.append(keep(_read(r / "false_imagination.csv", ["checkpoint", "seed", "mean", "count"])))
    if only is not None and (unknown := sorted(set(only) - held, key=int)):
        raise ValueError(f"training seed(s) {', '.join(unknown)} in none of the reports; they hold "
                         f"{', '.join(sorted(held, key=int))}")
    seeds = {key[0] for key in owner}
    if len(seeds) < 2:
        raise ValueError(f"{', '.join(map(str, reports))}: {len(seeds)} training seed(s); pooling needs two or more")
    return kind, pd.concat(success), pd.concat(pairs), pd.concat(fir) if fir else pd.DataFrame()


def _complete(groups, seeds: set[str]):
    """The groups that every training seed has, each once."""
    for key, g in groups:
        if set(g.seed) == seeds and len(g) == len(seeds):
            yield key, g


def pool_success(success: pd.DataFrame, kind: Kind = CLAIMS) -> pd.DataFrame:
    seeds, rows = set(success.seed), []
    for key, g in _complete(success.groupby(kind.cell), seeds):
        rows.append({"seed": claims.POOLED, **dict(zip(kind.cell, key)), "k": int(g.k.sum()), "n": int(g.n.sum()),
                     "seeds": " ".join(sorted(seeds, key=int))})  # every seed: pooled only where all ran
    out = pd.concat([success[["seed", *kind.cell, "k", "n"]].assign(seeds=success.seed), pd.DataFrame(rows)],
                    ignore_index=True)
    out["rate"] = out.k / out.n
    out[["ci_low", "ci_high"]] = [wilson(int(k), int(n)) for k, n in zip(out.k, out.n)]
    return out[[c for c in success.columns if c in out.columns]]  # the reports' columns, in their order


def episodes_from_counts(r, what: str) -> tuple[np.ndarray, np.ndarray]:
    """One seed's paired episodes (a, b) rebuilt from a paired row's n, rate_a, a_only and b_only: its 2x2
    table (episode order does not enter any statistic); ``what`` names the row in the error."""
    both = int(round(r.n * r.rate_a)) - int(r.a_only)
    neither = int(r.n) - both - int(r.a_only) - int(r.b_only)
    if min(both, neither) < 0:
        raise ValueError(f"paired row {what}: counts do not add up to n = {r.n}")
    counts = [both, int(r.a_only), int(r.b_only), neither]
    return np.repeat([True, True, False, False], counts), np.repeat([True, False, True, False], counts)


def _episodes(r) -> tuple[np.ndarray, np.ndarray]:
    return episodes_from_counts(r, f"{r.a} - {r.b} (seed {r.seed})")


def pool_pairs(pairs: pd.DataFrame, kind: Kind = CLAIMS) -> pd.DataFrame:
    seeds, rows = set(pairs.seed), []
    for key, g in _complete(pairs.groupby(kind.pair, sort=False), seeds):
        xs, ys = zip(*(_episodes(r) for r in g.itertuples()))
        rows.append({"seed": claims.POOLED, **dict(zip(kind.pair, key)),
                     **claims.paired(pd.Series(np.concatenate(xs)), pd.Series(np.concatenate(ys)))})
    return pd.concat([pairs, pd.DataFrame(rows)], ignore_index=True)


def pool_false_imagination(fir: pd.DataFrame) -> pd.DataFrame:
    if fir.empty:
        return fir
    seeds, rows = set(fir.seed), []
    for ck, g in _complete(fir.groupby("checkpoint"), seeds):
        rows.append({"checkpoint": ck, "seed": claims.POOLED, "count": int(g["count"].sum()),
                     "mean": float(np.average(g["mean"], weights=g["count"]))})
    return pd.concat([fir, pd.DataFrame(rows)], ignore_index=True)


def claims_markdown(success: pd.DataFrame, pairs: pd.DataFrame, fir: pd.DataFrame, seeds: list[str]) -> list[str]:
    text = ["Success in % over the episodes of each cell (95% Wilson interval).", ""]
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
    return text


def transfer_markdown(success: pd.DataFrame, pairs: pd.DataFrame, seeds: list[str]) -> list[str]:
    text = ["Success in % over the episodes of each cell (95% Wilson interval), clean rollouts with each run's best "
            "checkpoint.", ""]
    for seed in seeds + [claims.POOLED]:
        text += [f"## Training seed {seed}", "", *transfer_report.tables_markdown(success, seed)]
    for seed in seeds + [claims.POOLED]:
        text += [f"## Paired comparisons, training seed {seed}", "", *transfer_report.paired_markdown(pairs, seed), ""]
    return text + ["## Claims (pooled)", "", *transfer_report.verdicts(pairs), "",
                   "![success per cell, pooled](transfer.png)", ""]


def write_pooled(reports: list[Path], out: Path, header: list[str] = (), only: list[str] | None = None) -> str:
    kind, success, pairs, fir = read_reports(reports, only)
    success, pairs, fir = pool_success(success, kind), pool_pairs(pairs, kind), pool_false_imagination(fir)
    seeds = sorted(set(success.seed) - {claims.POOLED}, key=int)
    title = {"claims": "The paper's claims at CPU scale", "transfer": "Tables 4 and 5 at CPU scale"}[kind.name]
    text = [f"# {title}, pooled over training seeds", "", *[h for h in header if h],
            f"- Training seeds: {', '.join(seeds)} (each report names the command, machine and wall time of its runs)",
            f"- Pooled from the reports {', '.join(f'`{r}`' for r in reports)}: every (training seed, episode) "
            "once; a cell or comparison is pooled only where every seed has it.", ""]
    text += (claims_markdown(success, pairs, fir, seeds) if kind is CLAIMS else transfer_markdown(success, pairs, seeds))
    out.mkdir(parents=True, exist_ok=True)
    success.to_csv(out / kind.success_file, index=False)
    pairs.to_csv(out / "paired.csv", index=False)
    if len(fir):
        fir.to_csv(out / "false_imagination.csv", index=False)
    if kind is TRANSFER:
        transfer_report.figure(success, out / "transfer.png")
    (out / f"{kind.name}.md").write_text("\n".join(text))
    return "\n".join(text)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", required=True, nargs="+", type=Path, help="report folders, one or more seeds each")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--seeds", nargs="+", default=None,
                    help="pool only these training seeds (e.g. the ones that ran a model the others did not)")
    ap.add_argument("--command", default=None, help="the command that wrote this report (for the header)")
    args = ap.parse_args(argv)
    header = command_header(args.out, args.command)
    print(write_pooled(args.reports, args.out, header, args.seeds))


if __name__ == "__main__":
    main()
