"""Table 3 and AdaMLI's detection at a profile, from offline analyses (`nostra evaluate
evaluate.rollouts=false`, each writing offline.json): per-modality KL on the clean held-out demos
with its interval and share, per analysed checkpoint; AdaMLI's per-modality precision and recall
per noise, and its false imagination on the clean demos; each analysis's one-episode KL figure
(Figure 5: per-modality KL with the noise windows shaded and the imagined steps marked).

    python -m nostra.workflows.offline_report --analyses data/runs/cpu/offline/liftd1 --out reports/cpu/liftd1/offline

Each analysis folder's name below --analyses says what it is (e.g. s0/mask); the report lists them.
A run's folder named `<run>-occluded` or `<run>-blind` is compared with `<run>`, paired over the
demos both analysed (nostra.workflows.views: Table 3); their per-episode KL goes to views_episodes.csv,
which --views-episodes reads back, so seeds trained in other sittings are paired and pooled alike."""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import shutil
from pathlib import Path

import pandas as pd

from nostra.workflows.command_log import command_header
from nostra.workflows.views import figure as views_figure
from nostra.workflows.views import markdown as views_markdown
from nostra.workflows.views import traces_figure, training_changes
from nostra.workflows.views import episode_frame, pooled_changes, view_changes, with_earlier


def load(root: Path) -> list[dict]:
    """Every offline.json under ``root``, with ``name``: its folder relative to ``root``."""
    found = sorted(root.rglob("offline.json"))
    if not found:
        raise FileNotFoundError(f"no offline.json under {root}: run `nostra evaluate evaluate.rollouts=false ...` first")
    return [{"name": p.parent.relative_to(root).as_posix().removesuffix("/offline"), **json.loads(p.read_text()),
             "figure": p.parent / "kl_episode.png"} for p in found]


def copy_figures(analyses: list[dict], out: Path) -> dict[str, str]:
    """Each analysis's kl_episode.png into ``out`` as kl_episode-<name>.png: analysis name -> file name."""
    copied = {}
    for a in analyses:
        if a["figure"].is_file():
            copied[a["name"]] = f"kl_episode-{a['name'].replace('/', '-')}.png"
            shutil.copyfile(a["figure"], out / copied[a["name"]])
    return copied


def kl_table(analyses: list[dict]) -> pd.DataFrame:
    """One row per (checkpoint, modality): the clean KL is the same in every analysis of a checkpoint."""
    rows, seen = [], set()
    for a in analyses:
        if a["checkpoint"] in seen:
            continue
        seen.add(a["checkpoint"])
        total = sum(a["kl_nats"].values())
        for m, v in a["kl_nats"].items():
            lo, hi = a["kl_nats_ci"][m]
            rows.append({"run": a["name"].split("/")[0], "checkpoint": a["checkpoint"],
                         "episodes": len(a["episodes"]), "modality": m,
                         "kl_nats": v, "ci_low": lo, "ci_high": hi, "share": v / total})
    return pd.DataFrame(rows)


def detection_table(analyses: list[dict]) -> pd.DataFrame:
    """Precision and recall where the noise corrupts the modality (elsewhere there is nothing to
    detect: only the false imagination counts)."""
    from nostra.noise import NoiseSchedule

    rows = []
    for a in analyses:
        false, noised = a.get("false_imagination", {}), NoiseSchedule(a["noise"], [(1, 2)]).keys
        for m, s in a.get("detect", {}).items():
            hit = m == "all" or m in noised
            rows.append({"analysis": a["name"], "noise": a["noise"], "checkpoint": a["checkpoint"], "modality": m,
                         "noised": hit, "precision": s["precision"] if hit else None,
                         "recall": s["recall"] if hit else None, "false_imagination": false.get(m)})
    return pd.DataFrame(rows)


def paper_setting(reference: Path) -> str:
    """The sweep's name for the paper's thresholds on the reference's training seed: s<seed>-fo20-fc3."""
    from nostra.policies.imagination import AdaMLIConfig

    cfg = AdaMLIConfig()
    return f"{reference.parent.name}-fo{cfg.f_o:g}-fc{cfg.f_c:g}"


def closed_loop(root: Path, reference: Path | None = None) -> pd.DataFrame:
    """Rollout success per threshold setting and noise, from the episode records under
    ``root/<setting>/`` (the sweep's rollouts of BC-NOSTRA + AdaMLI): setting, noise, k, n, rate and
    its 95% Wilson interval. With ``reference`` (make cpu-claims' records of the same checkpoint), its
    AdaMLI cells are the paper's setting where the sweep did not run that setting under that noise."""
    from nostra.workflows.evaluation import wilson
    from nostra.workflows.sweep_report import success

    s = success(root)
    s = s[s.variant == "nostra_adamli"].drop(columns="variant").reset_index(drop=True)
    if reference is None:
        return s
    paper, rows = paper_setting(reference), []
    have = set(zip(s.setting, s.noise))
    for (noise, variant), won in reference_cells(reference).items():
        if variant == "nostra_adamli" and (paper, noise) not in have:
            k, n = int(won.sum()), len(won)
            low, high = wilson(k, n)
            rows.append({"setting": paper, "noise": noise, "k": k, "n": n, "rate": k / n, "ci_low": low, "ci_high": high})
    return pd.concat([s, pd.DataFrame(rows)], ignore_index=True) if rows else s


def with_success(sweep: pd.DataFrame, rollouts: pd.DataFrame) -> pd.DataFrame:
    """The sweep table with columns success_<noise> (the rate) and success_<noise>_low / _high (its
    interval) per rollout noise, matched on the setting (the analysis folder's first part, e.g. s0-fo20-fc3)."""
    if not len(sweep) or not len(rollouts):
        return sweep
    from nostra.noise import NOISES

    out = sweep.assign(setting=sweep.analysis.str.split("/").str[0])
    for noise in sorted(set(rollouts.noise), key=lambda n: (NOISES.index(n) if n in NOISES else len(NOISES), n)):
        g = rollouts[rollouts.noise == noise].set_index("setting")
        for col, src in (("", "rate"), ("_low", "ci_low"), ("_high", "ci_high")):
            out[f"success_{noise}{col}"] = out.setting.map(g[src])
    return out.drop(columns="setting")


# the cells of `make cpu-claims` (same checkpoint, same initial states) a threshold setting is paired with
REFERENCES = {"nostra_adamli": "paper's thresholds", "nostra_mli": "oracle MLI", "nostra": "clean, closed loop",
              "lstm": "BC-LSTM"}


def reference_cells(reference: Path) -> dict[tuple[str, str], pd.Series]:
    """(noise, variant) -> success by episode seed from the records under ``reference`` (make cpu-claims'
    <evaluate>/<task>/s<seed>/<checkpoint>/); a cell evaluated twice: the later folder wins."""
    from nostra.workflows.sweep_report import episodes

    ep = episodes(reference).drop_duplicates(["noise", "variant", "episode"], keep="last")
    ep = ep[ep.variant.isin(list(REFERENCES))]
    return {k: g.set_index("episode")["success"] for k, g in ep.groupby(["noise", "variant"])}


def paired_thresholds(sweep: pd.DataFrame, root: Path, reference: Path | None = None) -> pd.DataFrame:
    """Each threshold setting's closed-loop success per rollout noise against the paper's setting
    (AdaMLIConfig's defaults: the sweep's own cell, else the reference's nostra_adamli), and, with
    ``reference`` (make cpu-claims' records of the same checkpoint), against the oracle MLI and BC-LSTM
    under the same noise and the closed-loop policy with no noise; paired over the initial states both met:
    difference, 95% CI, McNemar exact p (claims.paired). Column ``against`` names the other cell; a
    setting s<k>-... is paired only with cells of training seed k."""
    from nostra.policies.imagination import AdaMLIConfig
    from nostra.workflows.claims import paired
    from nostra.workflows.sweep_report import episodes

    ep = episodes(root)
    ep = ep[ep.variant == "nostra_adamli"]
    if not len(sweep) or not len(ep):
        return pd.DataFrame()
    varied = _varied(sweep)
    params = sweep.assign(setting=sweep.analysis.str.split("/").str[0]).drop_duplicates("setting").set_index("setting")
    paper = {k: getattr(AdaMLIConfig(), k) for k in varied}
    seed = lambda setting: setting.split("-")[0]  # noqa: E731  (s<training seed>-fo..-fc..: one checkpoint per seed)
    ref = {seed(s): s for s, r in params.iterrows() if all(r[k] == v for k, v in paper.items())}
    cell = {k: g.set_index("episode")["success"] for k, g in ep.groupby(["setting", "noise"])}
    # the reference's cells belong to one training seed: its folder <evaluate>/<task>/s<seed>/<checkpoint>
    claims_seed, claims = (reference.parent.name, reference_cells(reference)) if reference is not None else (None, {})
    rows = []
    for (s, noise), c in cell.items():
        if s not in params.index:
            continue
        refs, mine = (claims if claims_seed == seed(s) else {}), ref.get(seed(s))
        others = {"nostra_adamli": cell.get((mine, noise), refs.get((noise, "nostra_adamli"))) if s != mine else None,
                  "nostra_mli": refs.get((noise, "nostra_mli")),
                  "nostra": refs.get(("none", "nostra")) if noise != "none" else None,
                  "lstm": refs.get((noise, "lstm"))}
        rows += [{"seed": int(seed(s)[1:]), **{k: params.loc[s, k] for k in varied}, "noise": noise,
                  "against": REFERENCES[v], **paired(c, b)} for v, b in others.items() if b is not None]
    if not rows:
        return pd.DataFrame()
    return pd.DataFrame(rows).sort_values(["seed", *varied, "noise"], kind="stable").reset_index(drop=True)


def switching(root: Path, reference: Path | None = None) -> pd.DataFrame:
    """BC-NOSTRA + AdaMLI's imagination in the sweep's rollouts per (setting, rollout noise, modality):
    claims.imagination_ratios of its episode records under ``root/<setting>/``; with ``reference`` (make
    cpu-claims' records of the same checkpoint, <evaluate>/<task>/s<seed>/<checkpoint>) its AdaMLI cells
    join as the paper's setting s<seed>-fo<f_o>-fc<f_c>, unless the sweep ran that setting itself."""
    from nostra.workflows.claims import episode_imagination, imagination_ratios

    def counts(files, setting_of) -> dict:
        return {(setting_of(f), f.parent.name, m, f.stem): c  # a cell evaluated twice: the later wins
                for f in sorted(files) for m, c in episode_imagination(f).items()}

    found = {}
    if reference is not None:
        paper = paper_setting(reference)
        found = counts(reference.glob("**/records/*/*/nostra_adamli_seed*.npz"), lambda f: paper)
    found |= counts(root.glob("*/**/records/*/*/nostra_adamli_seed*.npz"), lambda f: f.relative_to(root).parts[0])
    if not found:
        return pd.DataFrame()
    rows = [{"setting": st, "noise": noise, "modality": m, **c} for (st, noise, m, _), c in found.items()]
    return imagination_ratios(pd.DataFrame(rows).groupby(["setting", "noise", "modality"]).sum().reset_index())


def _natural(name: str) -> list:
    """Sort key that orders s2-fo20-fc3 before s2-fo20-fc12 (numbers compared as numbers)."""
    return [float(t) if t.replace(".", "", 1).isdigit() else t for t in re.split(r"(\d+(?:\.\d+)?)", name)]


def switching_markdown(sw: pd.DataFrame) -> list[str]:
    """Per setting and rollout noise, the modalities the noise corrupts (every modality on clean episodes)."""
    from nostra.noise import NOISES, NoiseSchedule
    from nostra.workflows.claims import LATE, nats_cell, percent

    lines = ["## AdaMLI's switching in closed loop", "",
             "BC-NOSTRA + AdaMLI's rollouts per setting (`adamli_switching.csv`): for each modality the noise "
             "corrupts, the share of the windows' steps it imagined and of the other steps, the share of windows "
             f"it did not imagine in their first {LATE} steps (opened late) or stopped imagining before they ended "
             "(switched back inside), and the KL jump into a window beside the KL's mean step-to-step change "
             "inside (nats); on clean episodes, the share of steps each modality was imagined.", "",
             "| setting | rollout noise | modality | imagined in the windows | imagined outside them | windows opened "
             "late | switched back inside | KL jump in / step change inside |", "|---|---|---|---|---|---|---|---|"]
    order = lambda n: NOISES.index(n) if n in NOISES else len(NOISES)  # noqa: E731
    for r in sorted(sw.itertuples(), key=lambda r: (_natural(r.setting), order(r.noise), r.modality)):
        corrupted = NoiseSchedule(r.noise, []).keys
        if r.noise != "none" and r.modality not in corrupted:
            continue
        cells = (f"– | {percent(r.outside)} | – | – | –" if r.noise == "none" else
                 f"{percent(r.recall)} | {percent(r.outside)} | {percent(r.opened_late)} | {percent(r.closed_early)} | "
                 f"{nats_cell(r.kl_jump)} / {nats_cell(r.kl_swing)}")
        lines.append(f"| {r.setting} | {r.noise} | {r.modality} | {cells} |")
    return lines + [""]


def _varied(sweep: pd.DataFrame) -> list[str]:
    return [c for c in sweep.columns if c not in ("analysis", "noise", "precision", "recall", "false_imagination")
            and not c.startswith("success_")]


def sweep_table(analyses: list[dict]) -> pd.DataFrame:
    """One row per analysis with AdaMLI's thresholds and its detection over every modality: the
    threshold sensitivity when the analyses differ in their thresholds, or from the paper's (one setting
    alone, e.g. f_c = 12, then paired with make cpu-claims' cells); empty otherwise."""
    from nostra.policies.imagination import AdaMLIConfig

    rows = [{"analysis": a["name"], "noise": a["noise"], **a["adamli"], "precision": a["detect"]["all"]["precision"],
             "recall": a["detect"]["all"]["recall"], "false_imagination": a["false_imagination"]["all"]}
            for a in analyses if "adamli" in a and "detect" in a]
    params = {k for r in rows for k in r} - {"analysis", "noise", "precision", "recall", "false_imagination"}
    paper = dataclasses.asdict(AdaMLIConfig())
    varied = [k for k in sorted(params) if len({r.get(k) for r in rows}) > 1 or {r.get(k) for r in rows} != {paper.get(k)}]
    if not varied:
        return pd.DataFrame()
    return pd.DataFrame(rows).sort_values(["noise", *varied]).reset_index(drop=True)[
        ["analysis", "noise", *varied, "precision", "recall", "false_imagination"]]


def sweep_figure(sweep: pd.DataFrame, path: Path) -> None:
    """Precision, recall, false imagination (and closed-loop success per rollout noise, where the
    sweep ran rollouts) against f_o, one line per f_c (per noise)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, line = ("f_o", "f_c") if {"f_o", "f_c"} <= set(sweep.columns) else (sweep.columns[2], None)
    metrics = ["precision", "recall", "false_imagination"] + _success_columns(sweep)
    fig, axes = plt.subplots(1, len(metrics), figsize=(4 * len(metrics), 3.4), sharex=True)
    for ax, metric in zip(axes, metrics):
        for key, g in sweep.groupby(["noise", line] if line else ["noise"]):
            g = g.sort_values(x)
            ax.plot(g[x], g[metric], marker="o", label=f"{key[0]}, {line} = {key[1]:g}" if line else key[0])
        ax.set_xscale("log"), ax.set_xlabel(x), ax.set_title(metric.replace("_", " ")), ax.set_ylim(0, 1)
        ax.minorticks_off(), ax.set_xticks(sorted(sweep[x].unique()), [f"{v:g}" for v in sorted(sweep[x].unique())])
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _success_columns(sweep: pd.DataFrame) -> list[str]:
    return [c for c in sweep.columns if c.startswith("success_") and not c.endswith(("_low", "_high"))]


def _score(x) -> str:
    return "– (not noised)" if pd.isna(x) else f"{x:.2f}"


def markdown(kl: pd.DataFrame, detect: pd.DataFrame, command: str | list[str], figures: dict[str, str] | None = None,
             sweep: pd.DataFrame | None = None, pairs: pd.DataFrame | None = None,
             changes: pd.DataFrame | None = None, traces: bool = False, demos: str = "held-out",
             batches: pd.DataFrame | None = None, pooled: pd.DataFrame | None = None) -> str:
    said = [f"`{command}`"] if isinstance(command, str) else command  # one command, or the log's header lines
    lines = [f"# Where the nats go, and what AdaMLI detects (offline, {demos} demos)", "", *said, "",
             f"## Per-modality KL on the clean {demos} demos (Table 3)", "",
             f"Mean KL per step in nats, 95% t-interval over the {demos} episodes, share of the total.", ""]
    for ckpt, g in kl.groupby("checkpoint", sort=False):
        lines += [f"`{ckpt}` ({int(g.episodes.iloc[0])} episodes)", "", "| modality | KL (nats) | 95% CI | share |",
                  "|---|---|---|---|"]
        lines += [f"| {r.modality} | {r.kl_nats:.2f} | [{r.ci_low:.2f}, {r.ci_high:.2f}] | {100 * r.share:.0f}% |"
                  for r in g.itertuples()]
        lines.append("")
    if kl.run.nunique() > 1:  # e.g. the good and the occluded view (Table 3): each modality's share side by side
        shares = kl.pivot_table(index="modality", columns="run", values="share", sort=False)
        runs = list(shares.columns)
        lines += ["Each modality's share of the KL per analysed run (folder under --analyses):", "",
                  "| modality | " + " | ".join(runs) + " |", "|---" * (len(runs) + 1) + "|"]
        lines += [f"| {m} | " + " | ".join(f"{100 * v:.0f}%" for v in row) + " |" for m, row in shares.iterrows()]
        lines.append("")
    if changes is not None:
        lines += views_markdown(changes, traces, batches, pooled)
    lines += ["## AdaMLI detection per noise", "",
              "Per-step precision and recall of AdaMLI's imagination flags against the injected windows; false "
              "imagination: share of the clean demos' steps on which AdaMLI imagines the modality.", ""]
    for (name, noise), g in (detect.groupby(["analysis", "noise"], sort=False) if len(detect) else []):
        lines += [f"`{name}`: noise `{noise}`", "", "| modality | precision | recall | false imagination (clean) |",
                  "|---|---|---|---|"]
        lines += [f"| {r.modality} | {_score(r.precision)} | {_score(r.recall)} | "
                  f"{'' if pd.isna(r.false_imagination) else f'{100 * r.false_imagination:.1f}%'} |"
                  for r in g.itertuples()]
        lines.append("")
    if sweep is not None and len(sweep):
        success, varied = _success_columns(sweep), _varied(sweep)
        lines += ["## AdaMLI's thresholds (sensitivity)", "",
                  "Detection over every modality per threshold setting (the others at the paper's values); "
                  "false imagination on the clean demos"
                  + ("; closed-loop success of BC-NOSTRA + AdaMLI with those thresholds, % over the rollouts "
                     "[95% Wilson interval]" if success else "") + ". `adamli_sweep.png` plots it.", "",
                  "| noise | " + " | ".join(varied + ["precision", "recall", "false imagination"] +
                                            [f"closed-loop success, {c[8:]}" for c in success]) + " |",
                  "|---" * (len(varied) + 4 + len(success)) + "|"]
        def cell(r, c: str) -> str:
            return "–" if pd.isna(r[c]) else f"{100 * r[c]:.0f} [{100 * r[c + '_low']:.0f}, {100 * r[c + '_high']:.0f}]"
        lines += ["| " + " | ".join([r["noise"], *(f"{r[k]:g}" for k in varied)]) +
                  f" | {r.precision:.2f} | {r.recall:.2f} | {100 * r.false_imagination:.1f}% |" +
                  "".join(f" {cell(r, c)} |" for c in success) for _, r in sweep.iterrows()]
        lines += ["", "![AdaMLI threshold sensitivity](adamli_sweep.png)", ""]
    if pairs is not None and len(pairs):
        from nostra.workflows.claims import paired_cells

        varied = list(pairs.columns[:pairs.columns.get_loc("noise")])  # seed, the thresholds: paired_thresholds' order
        lines += ["Closed-loop success of each setting minus another cell's, paired over the initial states both met "
                  "(`adamli_paired.csv`): the paper's thresholds, and where make cpu-claims' cells of the same checkpoint "
                  "were given, the oracle MLI and BC-LSTM under the same noise and the closed-loop policy with no noise:", "",
                  "| " + " | ".join(varied) + " | rollout noise | minus | n | difference (points) [95% CI] | "
                  "only this / only the other | McNemar exact p |", "|---" * (len(varied) + 6) + "|"]
        lines += ["| " + " | ".join(f"{getattr(r, k):g}" for k in varied) + f" | {r.noise} | {r.against} | {r.n} | "
                  f"{paired_cells(r)} |" for r in pairs.itertuples()]
        lines.append("")
    if figures:
        lines += ["## Per-modality KL over one held-out episode (Figure 5)", "",
                  "Noise windows shaded, the steps AdaMLI imagines marked above the curves.", ""]
        lines += [f"`{name}`\n\n![{name}]({f})\n" for name, f in figures.items()]
    return "\n".join(lines)


def demos_word(analyses: list[dict]) -> str:
    """Which of the training runs' demos the analyses replayed (older offline.json: held out)."""
    from nostra.workflows.analysis import SPLIT_WORDS

    return " and ".join(sorted({SPLIT_WORDS.get(a.get("split", "held_out"), a.get("split")) for a in analyses}))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--analyses", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--command", default="")
    ap.add_argument("--no-figures", action="store_true", help="leave out each analysis's one-episode figure")
    ap.add_argument("--rollouts", type=Path, default=None,
                    help="the threshold sweep's rollouts (<dir>/<setting>/**/records): closed-loop success per setting")
    ap.add_argument("--reference", type=Path, default=None,
                    help="make cpu-claims' records of the same checkpoint (<evaluate>/<task>/s<seed>/best): each "
                         "setting is paired with its oracle MLI, its clean closed loop, its paper's AdaMLI and BC-LSTM")
    ap.add_argument("--views-episodes", type=Path, nargs="+", default=[],
                    help="earlier reports' views_episodes.csv: their runs are paired and pooled with these analyses' "
                         "(Table 3 over sittings whose runs are no longer on this disk)")
    args = ap.parse_args(argv)
    if args.reference is not None and not args.reference.is_dir():
        raise FileNotFoundError(f"--reference {args.reference}: no such folder (make cpu-claims writes "
                                "<runs>/evaluate/<task>/s<seed>/<checkpoint>/)")
    analyses = load(args.analyses)
    arms = with_earlier(analyses, args.views_episodes)  # read (and checked) before anything is written
    kl, detect = kl_table(analyses), detection_table(analyses)
    args.out.mkdir(parents=True, exist_ok=True)
    kl.to_csv(args.out / "kl.csv", index=False)
    detect.to_csv(args.out / "detection.csv", index=False)
    command = command_header(args.out, args.command) or \
        f"python -m nostra.workflows.offline_report --analyses {args.analyses} --out {args.out}"
    figures, sweep = ({} if args.no_figures else copy_figures(analyses, args.out)), sweep_table(analyses)
    changes, traces, batches = view_changes(arms), False, training_changes(arms)
    pooled = pooled_changes(arms)
    if len(changes):
        changes.to_csv(args.out / "views.csv", index=False)
        episode_frame(arms).to_csv(args.out / "views_episodes.csv", index=False)
        views_figure(changes, args.out / "views.png")
        traces = traces_figure(analyses, args.out / "views_training.png")
    if len(batches):
        batches.to_csv(args.out / "views_training.csv", index=False)
    if len(pooled):
        pooled.to_csv(args.out / "views_pooled.csv", index=False)
    pairs = pd.DataFrame()
    if args.rollouts is not None:
        pairs = paired_thresholds(sweep, args.rollouts, args.reference)
        sweep = with_success(sweep, closed_loop(args.rollouts, args.reference))
    if len(sweep):
        sweep.to_csv(args.out / "adamli_sweep.csv", index=False)
        sweep_figure(sweep, args.out / "adamli_sweep.png")
    if len(pairs):
        pairs.to_csv(args.out / "adamli_paired.csv", index=False)
    sw = switching(args.rollouts, args.reference) if args.rollouts is not None else pd.DataFrame()
    if len(sw):
        sw.to_csv(args.out / "adamli_switching.csv", index=False)
    text = markdown(kl, detect, command, figures, sweep, pairs, changes, traces, demos_word(analyses), batches, pooled)
    (args.out / "offline.md").write_text(text + ("\n\n" + "\n".join(switching_markdown(sw)) if len(sw) else ""))
    print(args.out / "offline.md")


if __name__ == "__main__":
    main()
