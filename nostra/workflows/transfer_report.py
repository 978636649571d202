"""Tables 4 and 5 at a profile (scripts/cpu_transfer.sh): fine-tuning policies pretrained with a
non-informative (occluded) agent view on N target demos, and co-training NOSTRA on target demos alone
or with a retrieved manifest (obj_skill, all), read from the episode records of `nostra evaluate`:

    <evaluations>/s<training seed>/<setting>/**/records/<task>/none/<variant>_seed<k>.npz

with <setting> ``finetune-n<N>`` (Table 4) or ``cotrain-<target_only|obj_skill|all>`` (Table 5).
Every cell meets the same initial states, so cells are compared paired (claims.paired: bootstrap
interval, McNemar exact p): NOSTRA against BC-RSSM and BC-LSTM at each N, fine-tuned against trained
from scratch on as many demos (target only), each retrieval against target only.

    python -m nostra.workflows.transfer_report --evaluations data/runs/cpu/evaluate/liftd1-transfer \
        --out reports/cpu/liftd1/transfer

The report keeps every episode's outcome (episodes.csv), so cells whose records are gone (another
machine, an earlier sitting) are read back with ``--episodes <report>/episodes.csv`` and paired with
new records: a baseline run later meets the same initial states as the cells it is compared with.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.claims import (POOLED, RECORDS, _with_pooled, header_lines, paired, paired_cells,
                                     read_episode_file)
from nostra.workflows.evaluation import wilson
from nostra.workflows.variants import LABELS

FINETUNE = re.compile(r"finetune-n(?P<n>\d+)")
COTRAIN = ["target_only", "obj_skill", "all"]
MODELS = ["lstm", "diffusion", "rssm", "nostra"]
ALPHA = 0.05


def setting_name(folder: str) -> str:
    if FINETUNE.fullmatch(folder) or folder in {f"cotrain-{c}" for c in COTRAIN}:
        return folder
    raise ValueError(f"transfer setting folder {folder!r}: expected finetune-n<N> (e.g. finetune-n10) "
                     f"or one of {', '.join(f'cotrain-{c}' for c in COTRAIN)}")


def load_records(evaluations: Path) -> pd.DataFrame:
    """One row per episode: seed (training), setting, variant, episode, success."""
    rows = {}
    for f in sorted(evaluations.glob(RECORDS)):
        seed_dir = next(p for p in f.parents if p.parent == evaluations)
        setting = setting_name(f.relative_to(seed_dir).parts[0])
        variant, episode = f.stem.rsplit("_seed", 1)
        with np.load(f) as z:
            rows[(int(seed_dir.name[1:]), setting, variant, int(episode))] = bool(z["success"])
    if not rows:
        raise FileNotFoundError(f"no episode records under {evaluations}/s<seed>/<setting>/**/records")
    index = pd.MultiIndex.from_tuples(rows, names=["seed", "setting", "variant", "episode"])
    return pd.DataFrame({"success": list(rows.values())}, index=index).reset_index()


EPISODE_KEY = ["seed", "setting", "variant", "episode"]
EPISODE_COLUMNS = EPISODE_KEY + ["success"]  # episodes.csv: load_records' columns


def read_episodes(paths: list[Path]) -> pd.DataFrame:
    """Episodes from earlier reports' episodes.csv, in load_records' columns."""
    frames = []
    for path in paths:
        df = read_episode_file(path, EPISODE_COLUMNS, "transfer")[EPISODE_COLUMNS]
        for folder in set(df.setting):
            try:
                setting_name(folder)
            except ValueError as e:
                raise ValueError(f"{path}: {e}") from None
        frames.append(df)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=EPISODE_COLUMNS)


def episodes(evaluations: Path, earlier: list[Path] = ()) -> pd.DataFrame:
    """The records under ``evaluations`` and the episodes of earlier reports; an episode in both: the record."""
    old = read_episodes(list(earlier))
    try:
        new = load_records(evaluations)
    except FileNotFoundError:
        if old.empty:
            raise
        new = pd.DataFrame(columns=EPISODE_COLUMNS)  # every cell from earlier reports
    df = pd.concat([d for d in (old, new) if len(d)], ignore_index=True)
    return df.drop_duplicates(EPISODE_KEY, keep="last").reset_index(drop=True)


def chosen_episodes(evaluations: Path, earlier: list[Path] = (), seeds: list[int] | None = None) -> pd.DataFrame:
    """``episodes`` of the training ``seeds`` only (a seed reported apart from its siblings on this disk)."""
    df = episodes(evaluations, earlier)
    if seeds is not None:
        df = df[df.seed.astype(int).isin(seeds)].reset_index(drop=True)
        if df.empty:
            raise FileNotFoundError(f"no episodes of training seeds {seeds} under {evaluations}/s<seed>/<setting>"
                                    f"/**/records" + (" or in the --episodes files" if earlier else ""))
    return df


def success_table(df: pd.DataFrame) -> pd.DataFrame:
    """Success per (seed or pooled, setting, variant): k, n, rate and its 95% Wilson interval."""
    t = _with_pooled(df).groupby(["seed", "setting", "variant"])["success"].agg(k="sum", n="count").reset_index()
    t["rate"] = t.k / t.n
    t[["ci_low", "ci_high"]] = [wilson(int(k), int(n)) for k, n in zip(t.k, t.n)]
    return t


def _demos(setting: str) -> int | None:
    m = FINETUNE.fullmatch(setting)
    return int(m["n"]) if m else None


def comparisons(settings: set[str], target_demos: int | None) -> list[tuple]:
    """(table, a=(setting, variant), b=(setting, variant)): what each table compares, a - b."""
    out = []
    for s in sorted((s for s in settings if _demos(s)), key=_demos):
        out += [("Table 4", (s, "nostra"), (s, b)) for b in ("rssm", "lstm", "diffusion")]
        if _demos(s) == target_demos:  # pretrained with the occluded view vs from scratch on as many demos
            out += [("Table 4", (s, m), ("cotrain-target_only", m)) for m in MODELS]
    for c in COTRAIN[1:]:
        out += [("Table 5", (f"cotrain-{c}", m), ("cotrain-target_only", m)) for m in MODELS]
    out += [("Table 5", ("cotrain-all", m), ("cotrain-obj_skill", m)) for m in MODELS]  # the paper's +all step
    out += [("Table 5", (f"cotrain-{c}", "nostra"), (f"cotrain-{c}", b)) for c in COTRAIN for b in ("rssm", "lstm")]
    return out


def paired_table(df: pd.DataFrame, target_demos: int | None) -> pd.DataFrame:
    rows = []
    for seed, g in _with_pooled(df).groupby("seed"):
        cells = {k: c.set_index("episode")["success"] for k, c in g.groupby(["setting", "variant"])}
        for table, a, b in comparisons(set(g.setting), target_demos):
            if a in cells and b in cells:
                rows.append({"seed": seed, "table": table, "a_setting": a[0], "a": a[1], "b_setting": b[0],
                             "b": b[1], **paired(cells[a], cells[b])})
    return pd.DataFrame(rows)


def _cell(r) -> str:
    return f"{100 * r.rate:.0f} [{100 * r.ci_low:.0f}, {100 * r.ci_high:.0f}]"


def _grid(s: pd.DataFrame, settings: list[str], heads: list[str]) -> list[str]:
    lines = ["| Method | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for v in [v for v in MODELS if v in set(s[s.setting.isin(settings)].variant)]:
        r = s[s.variant == v].set_index("setting")
        lines.append(f"| {LABELS[v]} | " + " | ".join(_cell(r.loc[x]) if x in r.index else "–" for x in settings) + " |")
    return lines


def tables_markdown(success: pd.DataFrame, seed: str) -> list[str]:
    s = success[success.seed == seed]
    ft = sorted((x for x in set(s.setting) if _demos(x)), key=_demos)
    co = [f"cotrain-{c}" for c in COTRAIN if f"cotrain-{c}" in set(s.setting)]
    out = []
    if ft:
        out += ["Table 4: pretrained with an occluded agent view, fine-tuned on N target demos (good view)", "",
                *_grid(s, ft, [f"{_demos(x)} demos" for x in ft]), ""]
    if co:
        out += ["Table 5: target demos alone or co-trained with a retrieved manifest", "",
                *_grid(s, co, [c.removeprefix("cotrain-") for c in co]), ""]
    return out


def _side(setting: str, variant: str) -> str:
    what = {"cotrain-target_only": "from scratch (target only)"}.get(setting, setting.replace("cotrain-", "co-trained, "))
    if _demos(setting):
        what = f"fine-tuned, {_demos(setting)} demos"
    return f"{LABELS.get(variant, variant)} {what}"


def paired_markdown(pairs: pd.DataFrame, seed: str) -> list[str]:
    p = pairs[pairs.seed == seed] if len(pairs) else pairs
    lines = ["| Table | a | b | n | a - b (points) [95% CI] | only a / only b | McNemar exact p |",
             "|---|---|---|---|---|---|---|"]
    for r in p.itertuples():
        lines.append(f"| {r.table} | {_side(r.a_setting, r.a)} | {_side(r.b_setting, r.b)} | {r.n} | {paired_cells(r)} |")
    return lines


def verdicts(pairs: pd.DataFrame, seed: str = POOLED) -> list[str]:
    """The paper's claims for Tables 4 and 5 that the runs can test: a is above b with McNemar
    p < 0.05 (shown), above but not significantly (not shown: the direction only), or not above."""
    p = pairs[pairs.seed == seed] if len(pairs) else pairs
    claims = [("BC-NOSTRA fine-tunes above BC-RSSM", "Table 4", "rssm", None, None),
              ("BC-NOSTRA fine-tunes above BC-LSTM", "Table 4", "lstm", None, None),
              ("(context) pretraining with the occluded view helps BC-NOSTRA over from scratch, as many demos", "Table 4",
               "nostra", None, "cotrain-target_only"),
              ("co-training with obj_skill retrieval improves BC-NOSTRA over target only", "Table 5", "nostra",
               "cotrain-obj_skill", "cotrain-target_only"),
              ("co-training with all retrieval improves BC-NOSTRA over target only", "Table 5", "nostra", "cotrain-all",
               "cotrain-target_only"),
              ("all retrieval improves BC-NOSTRA over obj_skill", "Table 5", "nostra", "cotrain-all", "cotrain-obj_skill")]
    claims += [(f"BC-NOSTRA co-trains above {LABELS[b]}", "Table 5", b, f"cotrain-{c}", None)  # the paper's rows
               for b in ("rssm", "lstm") for c in COTRAIN[1:]]
    lines = ["| Claim (paper) | setting | a - b (points) [95% CI], p | verdict |", "|---|---|---|---|"]
    for text, table, b, a_setting, b_setting in claims:
        rows = p[(p.table == table) & (p.a == "nostra") & (p.b == b)] if len(p) else p
        if len(rows):  # Table 4's a is any fine-tuned setting; b the same setting unless named
            rows = rows[rows.b_setting == (b_setting or rows.a_setting)]
            rows = rows[rows.a_setting == a_setting] if a_setting else rows
        if not len(rows):
            lines.append(f"| {text} | {a_setting or '–'} | – | not measured |")
        for r in rows.itertuples():
            verdict = ("shown" if r.diff > 0 and r.p < ALPHA else
                       "not shown (higher, not significant)" if r.diff > 0 else "not shown")
            lines.append(f"| {text} | {r.a_setting} | {100 * r.diff:+.0f} [{100 * r.ci_low:+.0f}, "
                         f"{100 * r.ci_high:+.0f}], p = {r.p:.2g} | {verdict} |")
    return lines


def figure(success: pd.DataFrame, path: Path) -> None:
    """Pooled success with Wilson intervals: one panel per table, a bar per method and setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = success[success.seed == POOLED]
    panels = [("Table 4: fine-tuning (N target demos)", sorted((x for x in set(s.setting) if _demos(x)), key=_demos)),
              ("Table 5: co-training", [f"cotrain-{c}" for c in COTRAIN if f"cotrain-{c}" in set(s.setting)])]
    panels = [(t, xs) for t, xs in panels if xs]
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), squeeze=False)
    for ax, (title, settings) in zip(axes[0], panels):
        models = [m for m in MODELS if m in set(s[s.setting.isin(settings)].variant)]
        width = 0.8 / len(models)
        for i, m in enumerate(models):
            r = s[s.variant == m].set_index("setting").reindex(settings)
            x = np.arange(len(settings)) + (i - (len(models) - 1) / 2) * width
            err = np.vstack([r.rate - r.ci_low, r.ci_high - r.rate]) * 100
            ax.bar(x, r.rate * 100, width, yerr=err, capsize=3, label=LABELS[m])
        ax.set_xticks(np.arange(len(settings)),
                      [f"{_demos(x)} demos" if _demos(x) else x.removeprefix("cotrain-") for x in settings])
        ax.set_ylim(0, 100)
        ax.set_ylabel("success (%), 95% Wilson interval")
        ax.set_title(title)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(evaluations: Path, out: Path, header: list[str] = (), target_demos: int | None = None,
                 earlier: list[Path] = (), seeds: list[int] | None = None, chosen: pd.DataFrame | None = None) -> str:
    """``chosen``: the episodes, read already by ``chosen_episodes`` (main reads them before logging its command)."""
    df = chosen_episodes(evaluations, earlier, seeds) if chosen is None else chosen
    out.mkdir(parents=True, exist_ok=True)
    success, pairs = success_table(df), paired_table(df, target_demos)
    df.sort_values(EPISODE_KEY).to_csv(out / "episodes.csv", index=False)
    success.to_csv(out / "success.csv", index=False)
    pairs.to_csv(out / "paired.csv", index=False)
    figure(success, out / "transfer.png")
    seeds = sorted(set(success.seed) - {POOLED}, key=str)
    seeds = seeds + [POOLED] if len(seeds) > 1 else seeds  # one training seed: pooled is the same table
    text = ["# Tables 4 and 5 at CPU scale", "", *header,
            "Success in % over the episodes of each cell (95% Wilson interval), clean rollouts with each run's best "
            "checkpoint (in-training checks: the paper's peak performance). Every cell meets the same initial states. "
            "Pooled: every (training seed, episode) once.", ""]
    for seed in seeds:
        text += [f"## Training seed {seed}", "", *tables_markdown(success, seed)]
    text += ["## Paired comparisons (pooled)", "", *paired_markdown(pairs, POOLED), "",
             "## Claims (pooled)", "", *verdicts(pairs), "", "![success per cell](transfer.png)", ""]
    (out / "transfer.md").write_text("\n".join(text))
    return "\n".join(text)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evaluations", required=True, type=Path, help="<runs>/evaluate/<task>-transfer")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--target-demos", type=int, default=None,
                    help="the target demos of the co-training runs: Table 4 compares fine-tuning on as many with them")
    ap.add_argument("--command", default=None, help="the command that made the evaluations (for the header)")
    ap.add_argument("--wall-seconds", type=float, default=None)
    ap.add_argument("--note", action="append", default=[], help="a line for the header")
    ap.add_argument("--episodes", nargs="+", type=Path, default=[],
                    help="earlier reports' episodes.csv, read beside the records (cells whose records are elsewhere)")
    ap.add_argument("--seeds", nargs="+", type=int, default=None,
                    help="only these training seeds (default: every s<seed> folder and earlier episode)")
    args = ap.parse_args(argv)
    chosen = chosen_episodes(args.evaluations, args.episodes, args.seeds)  # bad input: refused before the header logs it
    extra = [f"- Episodes read from earlier reports too: {', '.join(f'`{p}`' for p in args.episodes)}"] \
        if args.episodes else []
    header = header_lines(args.evaluations, args.command, args.wall_seconds, args.note, extra, out=args.out)
    print(write_report(args.evaluations, args.out, header, args.target_demos, chosen=chosen))


if __name__ == "__main__":
    main()
