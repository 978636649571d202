"""NOSTRA's sensitivity to beta and gamma at a profile (scripts/cpu_sweep.sh): per setting, success
of 50 clean and 50 masked rollouts (closed loop, + MLI, + AdaMLI, every setting on the same initial
states), the per-modality KL on the held-out demos and AdaMLI's detection under mask, as one table
(sweep.md, sweep.csv) and one figure (sweep.png), with paired comparisons (paired.csv): each setting
against the paper's on the same initial states, and imagination against the closed loop under mask.

    python -m nostra.workflows.sweep_report --evaluations data/runs/cpu/evaluate/liftd1-sweep \
        --offline data/runs/cpu/offline/liftd1-sweep --out reports/cpu/liftd1/sweep

A setting is a folder named b<beta>_g<gamma> under both roots (rollout records under
<setting>/<noise>/**/records, the offline analysis under <setting>/mask/offline/offline.json)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.claims import paired, paired_cells
from nostra.workflows.evaluation import wilson
from nostra.workflows.variants import LABELS

SETTING = re.compile(r"b(?P<beta>[^_]+)_g(?P<gamma>.+)")
PAPER = (1e-4, 0.1)  # beta, gamma: conf/model/nostra.yaml's defaults
CELLS = [("none", "nostra"), ("mask", "nostra"), ("mask", "nostra_mli"), ("mask", "nostra_adamli")]


def parse(name: str) -> dict:
    m = SETTING.fullmatch(name)
    if not m:
        raise ValueError(f"sweep setting folder {name!r}: expected b<beta>_g<gamma>, e.g. b1e-4_g0.1")
    return {"beta": float(m["beta"]), "gamma": float(m["gamma"])}


def episodes(evaluations: Path) -> pd.DataFrame:
    """One row per rollout under ``evaluations/<setting>/``: setting, noise, variant, episode seed, success."""
    rows = []
    for f in sorted(evaluations.glob("*/**/records/*/*/*_seed*.npz")):
        variant, seed = f.stem.rsplit("_seed", 1)
        with np.load(f) as z:
            rows.append({"setting": f.relative_to(evaluations).parts[0], "noise": f.parent.name,
                         "variant": variant, "episode": int(seed), "success": bool(z["success"])})
    return pd.DataFrame(rows, columns=["setting", "noise", "variant", "episode", "success"])


def success(evaluations: Path) -> pd.DataFrame:
    """Success per (setting, noise, variant): k, n, rate and its 95% Wilson interval."""
    g = episodes(evaluations).groupby(["setting", "noise", "variant"])["success"]
    t = g.agg(k="sum", n="count").reset_index()
    t["rate"] = t.k / t.n
    t["ci_low"] = [wilson(int(k), int(n))[0] for k, n in zip(t.k, t.n)]
    t["ci_high"] = [wilson(int(k), int(n))[1] for k, n in zip(t.k, t.n)]
    return t


def paired_table(evaluations: Path, paper: tuple[float, float] = PAPER) -> pd.DataFrame:
    """The comparisons the sweep is for, paired over the initial states both cells met: each setting's
    cell against the paper's setting's, and within a setting imagination under mask (MLI and AdaMLI
    against the closed-loop policy, AdaMLI against MLI)."""
    ep = episodes(evaluations)
    cell = {k: g.set_index("episode")["success"] for k, g in ep.groupby(["setting", "noise", "variant"])}
    settings = sorted({k[0] for k in cell}, key=lambda n: (parse(n)["gamma"], parse(n)["beta"]))
    ref = next((s for s in settings if (parse(s)["beta"], parse(s)["gamma"]) == paper), None)
    rows = []

    def add(setting: str, what: str, a: tuple, b: tuple) -> None:
        if a in cell and b in cell:
            rows.append({**parse(setting), "comparison": what, **paired(cell[a], cell[b])})

    for s in settings:
        if ref is not None and s != ref:
            for noise, variant in CELLS:
                add(s, f"{LABELS[variant]}, {noise}: this setting - the paper's", (s, noise, variant),
                    (ref, noise, variant))
        for a, b in (("nostra_mli", "nostra"), ("nostra_adamli", "nostra"), ("nostra_adamli", "nostra_mli")):
            add(s, f"{LABELS[a]} - {LABELS[b]}, mask", (s, "mask", a), (s, "mask", b))
    return pd.DataFrame(rows)


def offline(root: Path) -> pd.DataFrame:
    """Per setting: KL per modality and in all (nats per step, held-out demos), AdaMLI's detection
    over every modality under mask, and its false imagination on the clean demos."""
    rows = []
    for f in sorted(root.glob("*/mask/offline/offline.json")):
        a = json.loads(f.read_text())
        kl = a["kl_nats"]
        rows.append({"setting": f.relative_to(root).parts[0], **{f"kl {m}": v for m, v in kl.items()},
                     "kl total": sum(kl.values()), "precision": a["detect"]["all"]["precision"],
                     "recall": a["detect"]["all"]["recall"], "false_imagination": a["false_imagination"]["all"]})
    return pd.DataFrame(rows)


def sweep_table(evaluations: Path, offline_root: Path) -> pd.DataFrame:
    """One row per setting: beta, gamma, success per cell (rate, low, high), KL and detection."""
    s = success(evaluations)
    settings = sorted(set(s.setting) | ({p.name for p in offline_root.iterdir() if p.is_dir()}
                                        if offline_root.is_dir() else set()))
    if not settings:
        raise FileNotFoundError(f"no sweep setting under {evaluations} or {offline_root}: "
                                "run scripts/cpu_sweep.sh first")
    table = pd.DataFrame([{"setting": n, **parse(n)} for n in settings])
    for noise, variant in CELLS:
        c = s[(s.noise == noise) & (s.variant == variant)].set_index("setting")
        for col, src in (("", "rate"), (" low", "ci_low"), (" high", "ci_high"), (" n", "n")):
            table[f"{variant} {noise}{col}"] = table.setting.map(c[src])
    off = offline(offline_root) if offline_root.is_dir() else pd.DataFrame()
    if len(off):
        table = table.merge(off, on="setting", how="left")
    return table.sort_values(["gamma", "beta"]).reset_index(drop=True)


def _pct(r, col: str) -> str:
    if pd.isna(r.get(col)):
        return "–"
    return f"{100 * r[col]:.0f} [{100 * r[col + ' low']:.0f}, {100 * r[col + ' high']:.0f}]"


def paired_markdown(pairs: pd.DataFrame) -> list[str]:
    if not len(pairs):
        return []
    lines = ["## Paired comparisons", "",
             "Over the initial states both cells met; difference in points [95% bootstrap interval], the episodes "
             "only one of the two succeeded on, McNemar's exact p (uncorrected for the number of rows).", "",
             "| beta | gamma | comparison | n | difference [95% CI] | only a / only b | McNemar exact p |",
             "|---|---|---|---|---|---|---|"]
    for r in pairs.itertuples():
        lines.append(f"| {r.beta:g} | {r.gamma:g} | {r.comparison} | {r.n} | {paired_cells(r)} |")
    return lines + [""]


def markdown(table: pd.DataFrame, header: list[str], paper: tuple[float, float] = PAPER,
             pairs: pd.DataFrame | None = None) -> str:
    kl_cols = [c for c in table.columns if c.startswith("kl ") and c != "kl total"]
    cells = [f"{v} {n}" for n, v in CELLS]
    lines = ["# NOSTRA's sensitivity to beta and gamma", "", *header, "",
             "Success in % [95% Wilson interval] on the same initial states for every setting (best checkpoint); "
             "KL in nats per step on the clean held-out demos; AdaMLI's detection (precision / recall, every "
             "modality) on the held-out demos under mask, and its false imagination on the clean ones. "
             f"The paper's setting (beta {paper[0]:g}, gamma {paper[1]:g}) is in bold.", "",
             "| beta | gamma | " + " | ".join(f"{LABELS[v]}, {n}" for n, v in CELLS) +
             " | KL total | " + " | ".join(f"KL {c[3:]}" for c in kl_cols) + " | AdaMLI P / R | false imagination |",
             "|---" * (2 + len(CELLS) + 1 + len(kl_cols) + 2) + "|"]
    for _, r in table.iterrows():
        mark = "**" if (r.beta, r.gamma) == paper else ""
        kl = [f"{r[c]:.1f}" if c in r and not pd.isna(r[c]) else "–" for c in ["kl total", *kl_cols]]
        det = ("–", "–") if pd.isna(r.get("precision", np.nan)) else \
            (f"{r.precision:.2f} / {r.recall:.2f}", f"{100 * r.false_imagination:.1f}%")
        lines.append(f"| {mark}{r.beta:g}{mark} | {mark}{r.gamma:g}{mark} | " + " | ".join(_pct(r, c) for c in cells) +
                     " | " + " | ".join(kl) + f" | {det[0]} | {det[1]} |")
    lines += ["", *paired_markdown(pairs if pairs is not None else pd.DataFrame()),
              "![sensitivity to beta and gamma](sweep.png)", ""]
    return "\n".join(lines)


def figure(table: pd.DataFrame, path: Path, paper: tuple[float, float] = PAPER) -> None:
    """Success (clean and mask cells) and total KL against beta (gamma at the paper's) and against
    gamma (beta at the paper's)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(10, 6.5), sharex="col")
    for col, (x, fixed, other) in enumerate((("beta", "gamma", paper[1]), ("gamma", "beta", paper[0]))):
        t = table[np.isclose(table[fixed], other)].sort_values(x)
        for noise, variant in CELLS:
            key = f"{variant} {noise}"
            if key in t and t[key].notna().any():
                axes[0, col].errorbar(t[x], 100 * t[key], yerr=[100 * (t[key] - t[key + " low"]),
                                                                100 * (t[key + " high"] - t[key])],
                                      marker="o", capsize=3, label=f"{LABELS[variant]}, {noise}")
        if "kl total" in t:
            axes[1, col].plot(t[x], t["kl total"], marker="o", color="k")
        axes[0, col].set_ylabel("success (%)"), axes[0, col].set_ylim(-5, 105)
        axes[1, col].set_ylabel("KL (nats per step)"), axes[1, col].set_xlabel(f"{x} ({fixed} = {other:g})")
        if x == "beta":
            axes[0, col].set_xscale("log"), axes[1, col].set_xscale("log")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evaluations", type=Path, required=True, help="<runs>/evaluate/<task>-sweep")
    ap.add_argument("--offline", type=Path, required=True, help="<runs>/offline/<task>-sweep")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--command", default="")
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    from nostra.workflows.command_log import command_header
    from nostra.workflows.cpu_report import machine

    table = sweep_table(args.evaluations, args.offline)
    pairs = paired_table(args.evaluations)
    header = command_header(args.out, args.command, args.wall_seconds) or [f"- Evaluations: `{args.evaluations}`"]
    header.append(f"- Machine: {machine()}")
    ep = episodes(args.evaluations)
    if len(ep):
        per_cell = "/".join(str(n) for n in sorted(ep.groupby(["setting", "noise", "variant"]).size().unique()))
        header.append(f"- Episodes: {per_cell} per cell, initial-state seeds {ep.episode.min()}-{ep.episode.max()}")
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "sweep.csv", index=False)
    pairs.to_csv(args.out / "paired.csv", index=False)
    figure(table, args.out / "sweep.png")
    (args.out / "sweep.md").write_text(markdown(table, header, pairs=pairs))
    print(args.out / "sweep.md")


if __name__ == "__main__":
    main()
