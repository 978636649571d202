"""Imagination over longer windows (scripts/cpu_horizon.sh): per-modality (BC-NOSTRA + MLI) against
joint-latent imagination (BC-RSSM + LI) as the oracle windows grow, read from the episode records of
`nostra evaluate`:

    <evaluations>/<setting>/**/records/<task>/<noise>/<variant>_seed<k>.npz

with <setting> the windows as ``start-end[+start-end...]`` (e.g. ``15-65``, ``15-35+45-60``: a folder
name, so no comma, which Hydra reads as a list), and beside them the claims cells of the same
checkpoint (``--reference``: the task's windows, and the clean rollouts each imagining variant's drift
is measured from).

Per setting: success (95% Wilson interval), MLI - LI paired over the initial states (claims.paired:
bootstrap interval, McNemar exact p), and each variant's end-effector drift: the mean distance, over
the imagined steps both episodes reach, between its path and its own model's clean path from the same
initial state (the paper's Figure 4 as a number), with the paired LI - MLI difference (Wilcoxon).
Where BC-NOSTRA + AdaMLI or the closed-loop BC-NOSTRA or BC-RSSM ran too (scripts/cpu_horizon.sh's VARIANTS),
AdaMLI - MLI (the windows found from the KL against told), MLI - NOSTRA and LI - BC-RSSM (what imagining
saves over seeing the corrupted frames) paired, and how much of the corrupted modalities' noisy steps AdaMLI
imagined (claims.episode_imagination: its switch, read from the records).

    python -m nostra.workflows.horizon_report --evaluations data/runs/cpu/evaluate/liftd1-horizon/s2/mask \
        --reference data/runs/cpu/evaluate/liftd1/s2/best --reference-windows 15-35+45-60 \
        --out reports/cpu/liftd1/horizon-mask-s2
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

from nostra.noise import NoiseSchedule
from nostra.workflows.claims import _cell, episode_imagination, header_lines, paired, paired_cells
from nostra.workflows.evaluation import wilson
from nostra.workflows.variants import LABELS

PAIR = ("nostra_mli", "rssm_li")  # per-modality - joint-latent imagination
# where run (scripts/cpu_horizon.sh's VARIANTS): (prefix, (a, b), the sentence above its table), a - b paired
VERSUS = (("ada", ("nostra_adamli", "nostra_mli"), "decides from the KL where to imagine; against {b} (told the "
           "windows) on the same initial states, paired as above:"),
          ("closed", ("nostra_mli", "nostra"), "against {b}, which sees the corrupted frames and imagines nothing "
           "(what the noise costs without imagination), on the same initial states:"),
          ("joint", ("rssm_li", "rssm"), "against {b} seeing the corrupted frames (imagination's gain or cost for "
           "the joint latent), on the same initial states:"))
# each variant's model, whose clean run its path's drift is measured from
CLEAN = {"nostra_mli": "nostra", "rssm_li": "rssm", "nostra_adamli": "nostra", "nostra": "nostra", "rssm": "rssm"}
SETTING = re.compile(r"\d+-\d+(\+\d+-\d+)*")
SHORT = {"nostra_adamli": "AdaMLI", "nostra_mli": "MLI", "nostra": "NOSTRA", "rssm_li": "LI", "rssm": "RSSM"}
GAP, ALPHA = 0.10, 0.05  # the test stated in the README: MLI - LI >= 10 points with p < 0.05


def parse_setting(name: str) -> list[tuple[int, int]]:
    """'15-35+45-60' -> [(15, 35), (45, 60)]; anything else fails naming the expected form."""
    if not SETTING.fullmatch(name):
        raise ValueError(f"window setting {name!r}: expected start-end[+start-end...], e.g. 15-65 or 15-35+45-60")
    windows = [tuple(map(int, w.split("-"))) for w in name.split("+")]
    if bad := [w for w in windows if not 0 < w[0] < w[1]]:
        raise ValueError(f"window setting {name!r}: windows {bad} must satisfy 0 < start < end")
    return windows


def _records(folder: Path, noise: str, variant: str) -> dict[int, Path]:
    """Episode seed -> record of ``variant`` under ``noise`` anywhere below ``folder`` (a later folder wins)."""
    files = sorted(folder.glob(f"**/records/*/{noise}/{variant}_seed*.npz"))
    return {int(f.stem.rsplit("_seed", 1)[1]): f for f in files}


def drift_cm(imagined: Path, clean: Path | None) -> float:
    """Mean end-effector distance (cm) between an imagined run and the clean run from the same initial
    state, over the imagined run's noisy steps that both episodes reach; NaN without such steps."""
    if clean is None:
        return np.nan
    with np.load(imagined) as a, np.load(clean) as b:
        pa, pb, noisy = a["eef_pos"], b["eef_pos"], a["noise"].astype(bool)
    n = min(len(pa), len(pb), len(noisy))
    steps = np.flatnonzero(noisy[:n])
    return float(np.linalg.norm(pa[steps] - pb[steps], axis=1).mean() * 100) if len(steps) else np.nan


IMAGINATION = ("noisy", "hit", "windows", "early", "clean", "false")  # AdaMLI's counts kept per episode


def adamli_counts(f: Path, keys: set[str]) -> dict[str, int]:
    """One AdaMLI record's episode_imagination counts summed over the modalities ``keys`` (those a noise corrupts)."""
    per = [c for m, c in episode_imagination(f).items() if m in keys]
    return {f"imag_{k}": int(sum(c[k] for c in per)) for k in IMAGINATION}


def load(evaluations: Path, reference: Path | None, reference_windows: str | None, noise: str,
         reference_excludes: tuple[str, ...] = ()) -> pd.DataFrame:
    """One row per (setting, variant, episode): success and drift (AdaMLI's: also its imagination counts).
    ``reference_excludes``: variants not read from the reference's noise cell (run with other settings
    there, e.g. the paper's AdaMLI where this study changed AdaMLI's thresholds)."""
    unknown = sorted(set(reference_excludes) - set(CLEAN))
    if unknown:
        raise ValueError(f"--reference-excludes {', '.join(unknown)}: unknown variant; valid: {', '.join(CLEAN)}")
    folders = {d.name: d for d in sorted(evaluations.iterdir()) if d.is_dir()} if evaluations.is_dir() else {}
    from_reference = None
    if reference is not None:
        if not reference_windows:
            raise ValueError("--reference needs --reference-windows (the task's windows, e.g. 15-35+45-60)")
        if reference_windows not in folders:  # a setting run here wins over the claims cell
            folders[reference_windows] = from_reference = reference / noise
    for name in folders:
        parse_setting(name)
    cleans = {v: _records(reference / "none", "none", m) if reference else {} for v, m in CLEAN.items()}
    corrupted = NoiseSchedule(noise, []).keys
    rows = []
    for name, folder in folders.items():
        for variant in CLEAN:
            if folder == from_reference and variant in reference_excludes:
                continue
            for episode, f in _records(folder, noise, variant).items():
                with np.load(f) as z:
                    success = bool(z["success"])
                rows.append({"setting": name, "variant": variant, "episode": episode, "success": success,
                             "drift_cm": drift_cm(f, cleans[variant].get(episode)),
                             **(adamli_counts(f, corrupted) if variant == "nostra_adamli" else {})})
    if not rows:
        raise FileNotFoundError(f"no records of {', '.join(CLEAN)} under {noise!r} in {evaluations}"
                                + (f" or {reference / noise}" if reference else ""))
    return pd.DataFrame(rows)


def imagined_steps(name: str, horizon: int) -> int:
    return sum(min(b, horizon) - a for a, b in parse_setting(name) if a < horizon)


def summary(df: pd.DataFrame, horizon: int) -> pd.DataFrame:
    """Per setting: each variant's success and drift, and MLI - LI paired (success) and LI - MLI (drift)."""
    from scipy.stats import wilcoxon

    rows = []
    for name, g in df.groupby("setting"):
        row = {"setting": name, "steps": imagined_steps(name, horizon)}
        unit = ["seed", "episode"] if "seed" in g else "episode"  # pooled: a (training seed, episode) pair
        cells = {v: c.set_index(unit) for v, c in g.groupby("variant")}
        for v, c in cells.items():
            k, n = int(c.success.sum()), len(c)
            lo, hi = wilson(k, n)
            row |= {f"{v}_k": k, f"{v}_n": n, f"{v}_rate": k / n, f"{v}_ci_low": lo, f"{v}_ci_high": hi,
                    f"{v}_drift_cm": c.drift_cm.mean()}
        if all(v in cells for v in PAIR):
            a, b = (cells[v] for v in PAIR)
            row |= {f"pair_{k}": x for k, x in paired(a.success, b.success).items()}
            d = (b.drift_cm - a.drift_cm).dropna()
            row |= {"drift_diff_cm": d.mean() if len(d) else np.nan, "drift_n": len(d),
                    "drift_p": wilcoxon(d).pvalue if len(d) and np.any(d != 0) else np.nan}
        for prefix, pair, _ in VERSUS:
            if all(v in cells for v in pair):
                row |= {f"{prefix}_{k}": x for k, x in paired(cells[pair[0]].success, cells[pair[1]].success).items()}
        if "imag_noisy" in g and "nostra_adamli" in cells:
            t = cells["nostra_adamli"][[f"imag_{k}" for k in IMAGINATION]].sum()
            ratio = lambda a, b: t[f"imag_{a}"] / t[f"imag_{b}"] if t[f"imag_{b}"] else np.nan  # noqa: E731
            row |= {"ada_recall": ratio("hit", "noisy"), "ada_back": ratio("early", "windows"),
                    "ada_outside": ratio("false", "clean")}
        rows.append(row)
    return pd.DataFrame(rows).sort_values("steps").reset_index(drop=True)


def _rate(r, v: str) -> str:
    if pd.isna(r.get(f"{v}_rate")):
        return "–"
    return _cell(SimpleNamespace(rate=r[f"{v}_rate"], ci_low=r[f"{v}_ci_low"], ci_high=r[f"{v}_ci_high"]))


def _pair(r, prefix: str = "pair") -> str:
    if pd.isna(r.get(f"{prefix}_diff")):
        return "– | – | –"
    f = {k: r[f"{prefix}_{k}"] for k in ("diff", "ci_low", "ci_high", "a_only", "b_only", "p")}
    return paired_cells(SimpleNamespace(**f | {"a_only": int(f["a_only"]), "b_only": int(f["b_only"])}))


def _windows_text(name: str) -> str:
    return " + ".join(f"[{a}, {b})" for a, b in parse_setting(name))


def markdown(s: pd.DataFrame, noise: str, header: list[str], reference_windows: str | None,
             episodes: pd.Series | None = None, pooled: bool = False) -> list[str]:
    mli, li = (LABELS[v] for v in PAIR)
    seeds = ([f"- Initial states: environment seeds {episodes.min()}-{episodes.max()} ({episodes.nunique()} distinct, "
              "the same in every cell)"] if episodes is not None and len(episodes) else [])
    text = [f"# Imagination over longer windows{', pooled' if pooled else ''}: per-modality vs joint-latent", "", *[h for h in header if h], *seeds, "",
            f"Oracle imagination over each setting's windows under `{noise}`: {mli} imagines the modalities "
            f"the noise corrupts and observes the rest, {li} imagines its joint latent (every modality). Success in % "
            "(95% Wilson interval) over the paired episodes (the same initial states in every cell); "
            f"{mli} - {li} with a 95% bootstrap interval, discordant episodes and McNemar's exact p. Drift: "
            "the mean end-effector distance (cm), over the imagined steps both episodes reach, from the same "
            "model's clean run from the same initial state; LI - MLI paired, Wilcoxon p."
            + (f" The row {_windows_text(reference_windows)} is the task's windows (the claims cells)."
               if reference_windows in set(s.setting) else ""), "",
            f"| windows | imagined steps | {mli} | {li} | MLI - LI | only MLI / only LI | p | drift MLI (cm) | "
            "drift LI (cm) | LI - MLI drift (cm), p |", "|---|---|---|---|---|---|---|---|---|---|"]
    versus = [line for prefix, pair, intro in VERSUS for line in versus_table(s, prefix, pair, intro)]
    tail = imagination_table(s, noise) + ["![success and drift per window setting](horizon.png)", ""]
    if f"{PAIR[1]}_rate" not in s:  # the command's VARIANTS left LI out: only the pairs that ran
        return text[:-2] + [f"{li} did not run here (the command's VARIANTS); the pairs that did:", ""] + versus + tail
    for _, r in s.iterrows():
        drift = (f"{r.drift_diff_cm:+.1f}, p = {r.drift_p:.2g}" if not pd.isna(r.get("drift_p")) else "–")
        text.append(f"| {_windows_text(r.setting)} | {r.steps} | {_rate(r, PAIR[0])} | {_rate(r, PAIR[1])} | "
                    f"{_pair(r)} | {r.get(f'{PAIR[0]}_drift_cm', np.nan):.1f} | {r.get(f'{PAIR[1]}_drift_cm', np.nan):.1f} "
                    f"| {drift} |")
    gap = [r for _, r in s.iterrows() if r.get("pair_diff", np.nan) >= GAP and r.get("pair_p", 1) < ALPHA]
    text += ["", f"Settings where {mli} beats {li} by >= {100 * GAP:.0f} points with p < {ALPHA}: "
             + (", ".join(_windows_text(r.setting) for r in gap) if gap else "none") + ".", ""]
    return text + versus + tail


def imagination_table(s: pd.DataFrame, noise: str) -> list[str]:
    """Where AdaMLI ran: the share of the corrupted modalities' noisy steps it imagined, of their windows it
    switched back to observed before the end, and of their other steps it imagined."""
    rows = s[s["ada_recall"].notna()] if "ada_recall" in s else s.iloc[:0]
    if rows.empty:
        return []
    pct = lambda x: "–" if pd.isna(x) else f"{100 * x:.1f}%"  # noqa: E731
    keys = ", ".join(f"`{k}`" for k in sorted(NoiseSchedule(noise, []).keys))
    text = [f"{LABELS['nostra_adamli']}'s switch on the modalities `{noise}` corrupts ({keys}), over all its "
            "episodes (its detection starts after AdaMLIConfig.warmup steps: 10 unless the command sets ADAMLI):", "",
            "| windows | noisy steps imagined | windows switched back before their end | other steps imagined |",
            "|---|---|---|---|"]
    for _, r in rows.iterrows():
        text.append(f"| {_windows_text(r.setting)} | {pct(r.ada_recall)} | {pct(r.ada_back)} | {pct(r.ada_outside)} |")
    return text + [""]


def versus_table(s: pd.DataFrame, prefix: str, pair: tuple[str, str], intro: str) -> list[str]:
    """One of VERSUS (a - b paired) over the settings where both ran; nothing where they did not."""
    rows = s[s[f"{prefix}_diff"].notna()] if f"{prefix}_diff" in s else s.iloc[:0]
    if rows.empty:
        return []
    (a, b), (sa, sb) = (LABELS[v] for v in pair), (SHORT[v] for v in pair)
    text = [f"{a} {intro.format(b=b)}", "",
            f"| windows | {a} | {b} | {sa} - {sb} | only {sa} / only {sb} | p | drift {sa} (cm) |",
            "|---|---|---|---|---|---|---|"]
    for _, r in rows.iterrows():
        text.append(f"| {_windows_text(r.setting)} | {_rate(r, pair[0])} | {_rate(r, pair[1])} | "
                    f"{_pair(r, prefix)} | {r.get(f'{pair[0]}_drift_cm', np.nan):.1f} |")
    return text + [""]


def figure(s: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    x = np.arange(len(s))
    for i, v in enumerate(CLEAN):
        if f"{v}_rate" not in s:
            continue
        err = np.vstack([s[f"{v}_rate"] - s[f"{v}_ci_low"], s[f"{v}_ci_high"] - s[f"{v}_rate"]]) * 100
        ax.errorbar(x + (i - 1) * 0.1, s[f"{v}_rate"] * 100, yerr=err, marker="o", capsize=3, label=LABELS[v])
        bx.plot(x, s[f"{v}_drift_cm"], marker="o", label=LABELS[v])
    labels = [f"{_windows_text(n)}\n{k} steps" for n, k in zip(s.setting, s.steps)]
    for a, title, unit in ((ax, "success", "success (%), 95% Wilson"), (bx, "end-effector drift", "cm from the clean run")):
        a.set_xticks(x, labels, fontsize=7)
        a.set_title(title)
        a.set_ylabel(unit)
        a.legend(fontsize=8)
    ax.set_ylim(0, 100)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(evaluations: Path, out: Path, noise: str = "mask", reference: Path | None = None,
                 reference_windows: str | None = None, horizon: int = 200, header: list[str] = (),
                 reference_excludes: tuple[str, ...] = ()) -> str:
    df = load(evaluations, reference, reference_windows, noise, tuple(reference_excludes))
    s = summary(df, horizon)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "episodes.csv", index=False)
    s.to_csv(out / "horizon.csv", index=False)
    figure(s, out / "horizon.png")
    text = "\n".join(markdown(s, noise, list(header), reference_windows, df.episode))
    (out / "horizon.md").write_text(text)
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evaluations", required=True, type=Path, help="<runs>/evaluate/<task>-horizon/s<seed>/<noise>")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--noise", default="mask")
    ap.add_argument("--reference", type=Path, default=None,
                    help="<runs>/evaluate/<task>/s<seed>/best: the claims cells (task's windows, clean runs)")
    ap.add_argument("--reference-windows", default=None, help="the reference's windows, e.g. 15-35+45-60")
    ap.add_argument("--reference-excludes", nargs="+", default=[],
                    help="variants not read from the reference's noise cell (e.g. nostra_adamli when AdaMLI's "
                         "settings here differ from the claims cells')")
    ap.add_argument("--horizon", type=int, default=200, help="the rollout horizon (caps a window's imagined steps)")
    ap.add_argument("--command", default=None)
    ap.add_argument("--wall-seconds", type=float, default=None)
    args = ap.parse_args(argv)
    header = header_lines(args.evaluations, args.command, args.wall_seconds, [], out=args.out)
    print(write_report(args.evaluations, args.out, args.noise, args.reference, args.reference_windows,
                       args.horizon, header, args.reference_excludes))


if __name__ == "__main__":
    main()
