"""NOSTRA's beta / gamma sensitivity pooled over training seeds, from each seed's sweep report
(scripts/cpu_sweep.sh, nostra.workflows.sweep_report): success per setting and cell, and the paired
comparisons (each setting against the paper's on the same initial states; MLI and AdaMLI against the
closed loop under mask) pooled exactly from each seed's 2x2 table, as nostra.workflows.claims_pool does;
one figure of each setting's success per seed and pooled.

    python -m nostra.workflows.sweep_pool --reports reports/cpu/liftd1/sweep reports/cpu/liftd1/sweep-s2 \
        --seeds 0 2 --out reports/cpu/liftd1/sweep-pooled-s02

A sweep report does not name its training seed, so --seeds gives one per report, in order. A setting,
cell or comparison is pooled only where every seed has it (a pool over some seeds would read as all).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.claims import POOLED, paired, paired_cells
from nostra.workflows.claims_pool import episodes_from_counts
from nostra.workflows.command_log import command_header
from nostra.workflows.evaluation import wilson
from nostra.workflows.sweep_report import CELLS
from nostra.workflows.variants import LABELS

SETTING = ["beta", "gamma"]
PAIR_COLUMNS = [*SETTING, "comparison", "n", "rate_a", "a_only", "b_only"]


def _read(path: Path, columns: list[str]) -> pd.DataFrame:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; scripts/cpu_sweep.sh (nostra.workflows.sweep_report) writes it")
    df = pd.read_csv(path)
    if missing := [c for c in columns if c not in df.columns]:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(columns)}")
    return df


def read_reports(reports: list[Path], seeds: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Every report's success cells (long: setting, noise, variant, k, n, KL total) and paired rows, each
    with its training seed."""
    if len(reports) != len(seeds):
        raise ValueError(f"--seeds names {len(seeds)} training seed(s) for {len(reports)} report(s); give one per report")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"--seeds {' '.join(seeds)}: a training seed twice would count its episodes twice")
    if len(reports) < 2:
        raise ValueError("pooling needs two or more reports (training seeds)")
    cells, pairs = [], []
    for report, seed in zip(reports, seeds):
        wide = _read(report / "sweep.csv", [*SETTING, "kl total",
                                            *[f"{v} {noise}{x}" for noise, v in CELLS for x in ("", " n")]])
        for noise, v in CELLS:
            n = wide[f"{v} {noise} n"]
            cells.append(pd.DataFrame({"seed": seed, "beta": wide.beta, "gamma": wide.gamma, "noise": noise,
                                       "variant": v, "k": np.round(wide[f"{v} {noise}"] * n).astype(int),
                                       "n": n.astype(int), "kl_total": wide["kl total"]}))
        pairs.append(_read(report / "paired.csv", PAIR_COLUMNS).assign(seed=seed))
    return pd.concat(cells, ignore_index=True), pd.concat(pairs, ignore_index=True)


def _complete(df: pd.DataFrame, keys: list[str], seeds: set[str]):
    for key, g in df.groupby(keys, sort=False):
        if set(g.seed) == seeds and len(g) == len(seeds):
            yield key, g


def pool_cells(cells: pd.DataFrame) -> pd.DataFrame:
    seeds, rows = set(cells.seed), []
    for key, g in _complete(cells, [*SETTING, "noise", "variant"], seeds):
        rows.append({"seed": POOLED, **dict(zip([*SETTING, "noise", "variant"], key)), "k": int(g.k.sum()),
                     "n": int(g.n.sum()), "kl_total": float(g.kl_total.mean())})  # KL: the seeds' mean
    out = pd.concat([cells, pd.DataFrame(rows)], ignore_index=True)
    out["rate"] = out.k / out.n
    out[["ci_low", "ci_high"]] = [wilson(int(k), int(n)) for k, n in zip(out.k, out.n)]
    return out


def pool_pairs(pairs: pd.DataFrame) -> pd.DataFrame:
    seeds, rows = set(pairs.seed), []
    for key, g in _complete(pairs, [*SETTING, "comparison"], seeds):
        xs, ys = zip(*(episodes_from_counts(r, f"{r.comparison} (beta {r.beta}, gamma {r.gamma}, seed {r.seed})")
                       for r in g.itertuples()))
        rows.append({"seed": POOLED, **dict(zip([*SETTING, "comparison"], key)),
                     **paired(pd.Series(np.concatenate(xs)), pd.Series(np.concatenate(ys)))})
    return pd.concat([pairs, pd.DataFrame(rows)], ignore_index=True)


def _setting(beta: float, gamma: float) -> str:
    return f"{beta:g} | {gamma:g}"


def markdown(cells: pd.DataFrame, pairs: pd.DataFrame, seeds: list[str]) -> list[str]:
    cols = seeds + [POOLED]
    text = ["## Success", "", "Success in % [95% Wilson interval] per training seed and pooled over them; KL total in "
            "nats per step on each seed's clean held-out demos (pooled: the seeds' mean).", "",
            "| beta | gamma | cell | " + " | ".join(f"seed {s}" for s in seeds) + " | pooled |",
            "|---|---|---|" + "---|" * len(cols)]
    for (beta, gamma), g in cells.groupby(SETTING, sort=False):
        kl = g.drop_duplicates("seed").set_index("seed").kl_total
        text.append(f"| {_setting(beta, gamma)} | KL total | " + " | ".join(
            f"{kl[s]:.1f}" if s in kl.index else "–" for s in cols) + " |")
        for noise, v in CELLS:
            c = g[(g.noise == noise) & (g.variant == v)].set_index("seed")
            text.append(f"| {_setting(beta, gamma)} | {LABELS[v]}, {noise} | " + " | ".join(
                f"{100 * c.rate[s]:.0f} [{100 * c.ci_low[s]:.0f}, {100 * c.ci_high[s]:.0f}]" if s in c.index else "–"
                for s in cols) + " |")
    text += ["", "## Paired comparisons", "",
             "Over the initial states both cells met: difference in points [95% bootstrap interval over (seed, "
             "episode) pairs], the episodes only one of the two succeeded on, McNemar's exact p; uncorrected for "
             "the number of rows.", "",
             "| beta | gamma | comparison | training seed | n | difference [95% CI] | only a / only b | McNemar exact p |",
             "|---|---|---|---|---|---|---|---|"]
    for (beta, gamma, what), g in pairs.groupby([*SETTING, "comparison"], sort=False):
        for r in sorted(g.itertuples(), key=lambda r: cols.index(r.seed)):
            text.append(f"| {_setting(beta, gamma)} | {what} | {r.seed} | {r.n} | {paired_cells(r)} |")
    return text


def figure(cells: pd.DataFrame, seeds: list[str], path: Path) -> None:
    """One panel per cell: each setting's success per training seed (small) and pooled (large, with its
    Wilson interval)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = list(dict.fromkeys(zip(cells.beta, cells.gamma)))
    fig, axes = plt.subplots(1, len(CELLS), figsize=(3.2 * len(CELLS), 3.6), sharey=True)
    for ax, (noise, v) in zip(axes, CELLS):
        c = cells[(cells.noise == noise) & (cells.variant == v)]
        for j, seed in enumerate([*seeds, POOLED]):
            s = c[c.seed == seed]
            x = [settings.index(b_g) + 0.12 * (j - len(seeds) / 2) for b_g in zip(s.beta, s.gamma)]
            style = dict(marker="o", ms=7, capsize=3, color="k") if seed == POOLED else dict(marker=".")
            yerr = [100 * (s.rate - s.ci_low), 100 * (s.ci_high - s.rate)] if seed == POOLED else None
            ax.errorbar(x, 100 * s.rate, yerr=yerr, ls="none", label=POOLED if seed == POOLED else f"seed {seed}",
                        **style)
        ax.set_xticks(range(len(settings)), [f"β {b:g}\nγ {g:g}" for b, g in settings], fontsize=7)
        ax.set_title(f"{LABELS[v]}, {noise}", fontsize=9), ax.set_ylim(-5, 105)
    axes[0].set_ylabel("success (%)"), axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_pooled(reports: list[Path], seeds: list[str], out: Path, header: list[str] = ()) -> str:
    cells, pairs = read_reports(reports, seeds)
    cells, pairs = pool_cells(cells), pool_pairs(pairs)
    text = ["# NOSTRA's sensitivity to beta and gamma, pooled over training seeds", "", *[h for h in header if h],
            f"- Training seeds: {', '.join(seeds)} (each report names the command, machine and wall time of its runs)",
            f"- Pooled from the reports {', '.join(f'`{r}`' for r in reports)}: every (training seed, episode) once; "
            "a cell or comparison is pooled only where every seed has it.", "", *markdown(cells, pairs, seeds),
            "![success per setting, each seed and pooled](sweep_pooled.png)", ""]
    out.mkdir(parents=True, exist_ok=True)
    cells.to_csv(out / "success.csv", index=False)
    pairs.to_csv(out / "paired.csv", index=False)
    figure(cells, seeds, out / "sweep_pooled.png")
    (out / "sweep_pooled.md").write_text("\n".join(text))
    return "\n".join(text)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", required=True, nargs="+", type=Path, help="sweep report folders, one per seed")
    ap.add_argument("--seeds", required=True, nargs="+", help="each report's training seed, in order")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None, help="the command that wrote this report (for the header)")
    args = ap.parse_args(argv)
    header = command_header(args.out, args.command)
    print(write_pooled(args.reports, args.seeds, args.out, header))


if __name__ == "__main__":
    main()
