"""The paper's claims at CPU scale (`make cpu-claims`): Table 1 (and Table 2's multimodal noises,
`OBS=rgbd`) per training seed and pooled, the controls, the paired comparisons and a verdict per
claim, all read from the episode records that `nostra evaluate` wrote
(records/<task>/<noise>/<variant>_seed<k>.npz under any folder of <runs>/evaluate/<task>/s<training
seed>/<checkpoint>/).

    python -m nostra.workflows.claims --evaluations data/runs/cpu/evaluate/liftd1 --out reports/cpu/liftd1/claims

The report keeps every episode's outcome (episodes.csv), so a seed evaluated on another disk, or whose
records are gone, can be read back with ``--episodes <report>/episodes.csv`` and paired with new records.

Every variant meets the same initial states (episode seed k), so variants are compared paired: the
difference in points with a 95% percentile-bootstrap interval of the mean paired difference
(scipy.stats.bootstrap) and McNemar's exact p (statsmodels). Pooled over training seeds, an episode
is the pair (training seed, episode seed).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.evaluation import wilson
from nostra.workflows.variants import LABELS

TABLE1_NOISES = ["none", "mask", "cam_jitter", "table_tex"]
TABLE2_NOISES = ["rgb", "rgbd", "all"]  # multimodal noise (cameras, + depth, + proprioception), AdaMLI's table
CONTROL_NOISES = ["clean_windows", "blind"]
# single-modality noises, run to tell which part of a multimodal noise AdaMLI fails on, or what per-modality
# imagination keeps when one camera is lost (no claim rests on them)
DIAGNOSTIC_NOISES = ["wrist_mask", "agentview_mask", "depth_mask", "proprio_zero", "proprio_stuck"]
NOISE_ORDER = TABLE1_NOISES + TABLE2_NOISES + DIAGNOSTIC_NOISES + CONTROL_NOISES  # the tables' columns
ROWS = ["lstm", "diffusion", "rssm", "rssm_li", "nostra", "nostra_mli", "nostra_adamli"]
# (a, b, noises): a - b, paired on the same initial states
PAIRS = [("nostra_mli", "nostra", TABLE1_NOISES[1:]), ("nostra_mli", "lstm", TABLE1_NOISES),
         ("nostra_mli", "diffusion", TABLE1_NOISES + TABLE2_NOISES),
         ("nostra_mli", "rssm_li", TABLE1_NOISES[1:] + TABLE2_NOISES + ["wrist_mask", "agentview_mask"]),
         ("nostra_adamli", "nostra_mli", TABLE1_NOISES[1:] + TABLE2_NOISES + DIAGNOSTIC_NOISES)] + [
    ("nostra_adamli", b, TABLE2_NOISES + DIAGNOSTIC_NOISES) for b in ("nostra", "lstm", "diffusion", "rssm")]
CLEAN_MIN, BLIND_MAX, WITHIN = 0.85, 0.20, 0.10  # the bars: clean >= 85%, blind <= 20%, within 10 points
POOLED = "pooled"
RECORDS = "s*/*/**/records/*/*/*_seed*.npz"  # <evaluations>/s<seed>/<checkpoint>/.../<task>/<noise>/<variant>_seed<n>.npz
COPIED = "same-as-best"  # the folder of a last cell's records copied from its best cell (scripts/cpu_claims.sh)


def cell_of(f: Path, evaluations: Path) -> tuple[int, str, str]:
    """(training seed, checkpoint, noise) of a record <evaluations>/s<seed>/<checkpoint>/**/<noise>/<file>."""
    seed_dir = next(p for p in f.parents if p.parent == evaluations)
    return int(seed_dir.name[1:]), f.relative_to(seed_dir).parts[0], f.parent.name


def percent(x: float) -> str:
    return "–" if np.isnan(x) else f"{100 * x:.0f}%"


def load_records(evaluations: Path) -> pd.DataFrame:
    """One row per episode: seed (training), checkpoint, noise, variant, episode, success, and for
    clean episodes the share of steps on which any modality was imagined."""
    rows = {}
    # a same-as-best copy stands in for a last cell not evaluated; where the last checkpoint was evaluated
    # itself, its own records win: read after the copies
    for f in sorted(evaluations.glob(RECORDS), key=lambda f: (COPIED not in f.parts, f)):
        variant, episode = f.stem.rsplit("_seed", 1)
        with np.load(f) as z:
            imagined = [z[k] for k in z.files if k.startswith("imagined/")]
            share = float(np.any(imagined, axis=0).mean()) if imagined else np.nan
            key = (*cell_of(f, evaluations), variant, int(episode))
            rows[key] = (bool(z["success"]), share)  # a cell evaluated twice: the later folder wins
    index = pd.MultiIndex.from_tuples(rows, names=["seed", "checkpoint", "noise", "variant", "episode"])
    return pd.DataFrame(list(rows.values()), index=index, columns=["success", "imagined_share"]).reset_index()


EPISODE_KEY = ["seed", "checkpoint", "noise", "variant", "episode"]
EPISODE_COLUMNS = EPISODE_KEY + ["success", "imagined_share"]  # episodes.csv, load_records' columns


def read_episode_file(path: Path, columns: list[str], kind: str) -> pd.DataFrame:
    """One earlier report's episodes.csv, checked: ``columns`` there, seed and episode integers, success a
    boolean (``kind``: the report that writes such a file, for the error)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such episodes file; a {kind} report writes <out>/episodes.csv")
    df = pd.read_csv(path)
    if missing := [c for c in columns if c not in df.columns]:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; expected {', '.join(columns)}")
    try:
        return df.astype({"seed": int, "episode": int, "success": bool})
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: seed and episode must be integers, success a boolean ({e})") from None


def read_episodes(paths: list[Path]) -> pd.DataFrame:
    """Episodes from earlier reports' episodes.csv (records not on this disk), in load_records' columns."""
    frames = [read_episode_file(path, EPISODE_COLUMNS, "claims") for path in paths]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def episodes(evaluations: Path, earlier: list[Path] = ()) -> pd.DataFrame:
    """The records under ``evaluations`` and the episodes of earlier reports; an episode in both: the record."""
    df = pd.concat([read_episodes(list(earlier)), load_records(evaluations)], ignore_index=True)
    return df.drop_duplicates(EPISODE_KEY, keep="last").reset_index(drop=True) if len(df) else df


def _windows(noisy: np.ndarray) -> list[tuple[int, int]]:
    """The noise windows of one episode: [start, end) of each run of noisy steps."""
    edges = np.flatnonzero(np.diff(np.r_[0, noisy.astype(int), 0]))
    return list(zip(edges[::2], edges[1::2]))


LATE = 3  # a window counts as opened late when none of its first LATE steps was imagined


def _switching(imagined: np.ndarray, noisy: np.ndarray, kl: np.ndarray | None) -> dict:
    """How AdaMLI's switch behaved over one episode's windows: opened late, switched back before the window
    ended, and the KL it decided on (the jump into each window, the step-to-step change inside them)."""
    out = dict(windows=0, late=0, early=0, jump=0.0, jumps=0, swing=0.0, swings=0)
    for a, b in _windows(noisy):
        w = imagined[a:b]
        out["windows"] += 1
        out["late"] += int(not w[:LATE].any())
        out["early"] += int((w[:-1] & ~w[1:]).any())
        if kl is not None:
            if a > 0:
                out["jump"] += float(kl[a] - kl[a - 1])
                out["jumps"] += 1
            out["swing"] += float(np.abs(np.diff(kl[a:b])).sum())
            out["swings"] += b - a - 1
    return out


def episode_imagination(f: Path) -> dict[str, dict]:
    """One AdaMLI episode record's imagination counts per modality: steps in and outside the noise windows
    and how many of them it imagined (inside: split by the previous action's gripper command), and the
    window switching of ``_switching``."""
    with np.load(f) as z:
        if not any(k.startswith("imagined/") for k in z.files):
            return {}
        n = int(z["steps"])
        noisy = z["noise"][:n] if "noise" in z.files else np.zeros(n, bool)
        closed = np.r_[False, z["action"][: n - 1, -1] > 0] if "action" in z.files else np.zeros(n, bool)
        out = {}
        for k in (k for k in z.files if k.startswith("imagined/")):
            imagined = z[k][:n].astype(bool)
            m = len(imagined)
            kl = z[f"kl/{k[9:]}"][:m] if f"kl/{k[9:]}" in z.files else None
            noisy_m, closed_m = noisy[:m], closed[:m]
            out[k[9:]] = {"noisy": noisy_m.sum(), "hit": (imagined & noisy_m).sum(),
                          "noisy_open": (noisy_m & ~closed_m).sum(), "hit_open": (imagined & noisy_m & ~closed_m).sum(),
                          "noisy_closed": (noisy_m & closed_m).sum(), "hit_closed": (imagined & noisy_m & closed_m).sum(),
                          "clean": (~noisy_m).sum(), "false": (imagined & ~noisy_m).sum(),
                          **_switching(imagined, noisy_m, kl)}
    return out


def imagination_ratios(t: pd.DataFrame) -> pd.DataFrame:
    """Summed episode_imagination counts -> recall (inside the windows, gripper open / closed), imagination
    outside them, windows opened late and switched back inside, the KL jump in and step change inside."""
    ratio = lambda a, b: t[a] / t[b].where(t[b] > 0)  # noqa: E731
    return t.assign(recall=ratio("hit", "noisy"), recall_open=ratio("hit_open", "noisy_open"),
                    recall_closed=ratio("hit_closed", "noisy_closed"), outside=ratio("false", "clean"),
                    opened_late=ratio("late", "windows"), closed_early=ratio("early", "windows"),
                    kl_jump=ratio("jump", "jumps"), kl_swing=ratio("swing", "swings"))


def adamli_detection(evaluations: Path, seeds: list[int] | None = None) -> pd.DataFrame:
    """AdaMLI in closed loop, per (checkpoint, seed, noise, modality): the share of the noise windows' steps
    on which it imagined the modality (its recall), split by whether the previous action commanded the
    gripper closed (a zeroed gripper reading looks like a closed gripper), the share of steps outside
    the windows (every step of a clean episode) on which it imagined it anyway, and per window whether
    it opened late or switched back before the window ended, with the modality's KL jump into the
    window and its mean step-to-step change inside (a KL that swings as much as it jumps defeats the
    thresholds, which compare a change with the recent changes)."""
    counts = {}
    for f in sorted(evaluations.glob("s*/*/**/records/*/*/nostra_adamli_seed*.npz")):
        cell = cell_of(f, evaluations)
        if seeds is not None and cell[0] not in seeds:
            continue
        for modality, c in episode_imagination(f).items():  # a cell evaluated twice: the later wins
            counts[(*cell, modality, f.stem)] = c
    rows = [{"checkpoint": ck, "seed": sd, "noise": noise, "modality": modality, **c}
            for (seed, ck, noise, modality, _), c in counts.items() for sd in (str(seed), POOLED)]
    if not rows:
        return pd.DataFrame()
    return imagination_ratios(pd.DataFrame(rows).groupby(["checkpoint", "seed", "noise", "modality"]).sum().reset_index())


def nats_cell(x: float) -> str:
    return "–" if pd.isna(x) else f"{x:.0f}"


def detection_markdown(det: pd.DataFrame, checkpoint: str) -> list[str]:
    from nostra.noise import NoiseSchedule

    d = det[(det.checkpoint == checkpoint) & (det.seed == POOLED)] if len(det) else det
    if not len(d):
        return []
    order = {n: i for i, n in enumerate(NOISE_ORDER)}
    lines = ["| noise | modality | corrupted by it | imagined in the windows | gripper open | gripper closed "
             "| imagined outside them | windows opened late | switched back inside | KL jump in / step change "
             "inside (nats) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(d.itertuples(), key=lambda r: (order.get(r.noise, len(order)), r.noise, r.modality)):
        hit = r.modality in NoiseSchedule(r.noise, []).keys
        window = (f"{percent(r.opened_late)} | {percent(r.closed_early)} | {nats_cell(r.kl_jump)} / {nats_cell(r.kl_swing)}"
                  if hit else "– | – | –")
        lines.append(f"| {r.noise} | {r.modality} | {'yes' if hit else 'no'} | {percent(r.recall)} | {percent(r.recall_open)} "
                     f"| {percent(r.recall_closed)} | {percent(r.outside)} | {window} |")
    return lines


def _with_pooled(df: pd.DataFrame) -> pd.DataFrame:
    """Adds the pooled copy of every episode (seed 'pooled', episode = (training seed, episode seed))."""
    pooled = df.assign(episode=df.seed.astype(str) + ":" + df.episode.astype(str), seed=POOLED)
    return pd.concat([df.assign(seed=df.seed.astype(str), episode=df.episode.astype(str)), pooled])


def success_table(df: pd.DataFrame) -> pd.DataFrame:
    """Success per (checkpoint, seed, variant, noise): k, n, rate and its 95% Wilson interval, and the
    training seeds a cell holds (a pooled cell that only some seeds ran is marked in the tables)."""
    g = _with_pooled(df.assign(origin=df.seed)).groupby(["checkpoint", "seed", "variant", "noise"])
    t = g.agg(k=("success", "sum"), n=("success", "count"),
              seeds=("origin", lambda x: " ".join(map(str, sorted(set(x)))))).reset_index()
    t["rate"] = t.k / t.n
    t[["ci_low", "ci_high"]] = [wilson(int(k), int(n)) for k, n in zip(t.k, t.n)]
    return t


def paired(a: pd.Series, b: pd.Series, seed: int = 0) -> dict:
    """a - b over the episodes both have (indexed by episode): points, 95% bootstrap CI, McNemar exact p."""
    from scipy.stats import bootstrap
    from statsmodels.stats.contingency_tables import mcnemar

    common = a.index.intersection(b.index)
    x, y = a[common].to_numpy(bool), b[common].to_numpy(bool)
    d = x.astype(float) - y
    if len(d) == 0:
        return {"n": 0}
    if np.all(d == d[0]):  # no spread: the bootstrap interval is the point itself
        lo = hi = d[0]
    else:
        ci = bootstrap((d,), np.mean, confidence_level=0.95, n_resamples=10_000, method="percentile",
                       random_state=seed).confidence_interval
        lo, hi = ci.low, ci.high
    table = [[int(np.sum(x & y)), int(np.sum(x & ~y))], [int(np.sum(~x & y)), int(np.sum(~x & ~y))]]
    return {"n": len(d), "rate_a": x.mean(), "rate_b": y.mean(), "diff": d.mean(), "ci_low": lo, "ci_high": hi,
            "a_only": table[0][1], "b_only": table[1][0], "p": mcnemar(table, exact=True).pvalue}


def paired_cells(r) -> str:
    """A paired row's Markdown cells: difference in points [95% CI] | only a / only b | McNemar p."""
    return (f"{100 * r.diff:+.0f} [{100 * r.ci_low:+.0f}, {100 * r.ci_high:+.0f}] | {r.a_only} / {r.b_only} | "
            f"{r.p:.2g}")


def paired_table(df: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for (ck, seed), g in _with_pooled(df).groupby(["checkpoint", "seed"]):
        cells = {(v, n): c.set_index("episode")["success"] for (v, n), c in g.groupby(["variant", "noise"])}
        for a, b, noises in PAIRS:
            for noise in noises:
                if (a, noise) in cells and (b, noise) in cells:
                    rows.append({"checkpoint": ck, "seed": seed, "noise": noise, "a": a, "b": b,
                                 **paired(cells[a, noise], cells[b, noise])})
        # imagination's own cost: oracle MLI over mask's windows with nothing corrupted vs NOSTRA clean
        if ("nostra_mli", "clean_windows") in cells and ("nostra", "none") in cells:
            rows.append({"checkpoint": ck, "seed": seed, "noise": "clean_windows vs none", "a": "nostra_mli",
                         "b": "nostra", **paired(cells["nostra_mli", "clean_windows"], cells["nostra", "none"])})
    return pd.DataFrame(rows)


def false_imagination(df: pd.DataFrame) -> pd.DataFrame:
    """AdaMLI on clean episodes: the share of steps on which it imagined any modality."""
    clean = _with_pooled(df[(df.noise == "none") & (df.variant == "nostra_adamli")])
    return clean.groupby(["checkpoint", "seed"])["imagined_share"].agg(["mean", "count"]).reset_index()


def verdicts(success: pd.DataFrame, pairs: pd.DataFrame, checkpoint: str, seed: str = POOLED) -> list[str]:
    """The paper's claims, each shown / not shown / not testable, with the numbers that decided it.
    Table 1's claims are about mask; Table 2's (listed once one of its noises ran) about rgb, rgbd, all.
    A claim about a noise is testable where the clean and blind bars hold and that noise hurts."""
    s = success[(success.checkpoint == checkpoint) & (success.seed == seed)].set_index(["variant", "noise"])
    rate = lambda v, n: s.rate.get((v, n), np.nan)  # noqa: E731
    p = pairs[(pairs.checkpoint == checkpoint) & (pairs.seed == seed)] if len(pairs) else pairs

    def above(a: str, noise: str, b: str = "lstm") -> tuple[str, bool, list]:  # a above b under noise, paired
        row = p[(p.a == a) & (p.b == b) & (p.noise == noise)] if len(p) else p
        gain, pv = (row["diff"].iloc[0], row["p"].iloc[0]) if len(row) else (np.nan, np.nan)
        numbers = f"({gain * 100:+.0f} points, p = {pv:.2g})" if len(row) else "(–)"
        return (f"{LABELS[a]} above {LABELS[b]} under {noise} with McNemar p < 0.05 {numbers}",
                gain > 0 and pv < 0.05, [gain, pv])

    def within(a: str, noise: str) -> tuple[str, bool, list]:  # a under noise within 10 points of clean NOSTRA
        return (f"{LABELS[a]} under {noise} within {WITHIN:.0%} of its clean success "
                f"({percent(rate(a, noise))} vs {percent(rate('nostra', 'none'))})",
                rate("nostra", "none") - rate(a, noise) <= WITHIN, [rate("nostra", "none"), rate(a, noise)])

    def hurts(noise: str) -> tuple[str, bool, list]:
        return (f"{noise} hurts closed-loop BC-NOSTRA by >= {WITHIN:.0%} ({percent(rate('nostra', 'none'))} -> "
                f"{percent(rate('nostra', noise))})", rate("nostra", "none") - rate("nostra", noise) >= WITHIN,
                [rate("nostra", "none"), rate("nostra", noise)])

    def bar(text: str, values: list, test) -> tuple[str, bool, list]:  # over the models that ran (a NOSTRA-only run)
        ran = [v for v in values if not np.isnan(v)] or [np.nan]
        return text, test(ran), ran

    base = [bar(f"closed-loop clean >= {CLEAN_MIN:.0%} (BC-LSTM {percent(rate('lstm', 'none'))}, BC-NOSTRA "
                f"{percent(rate('nostra', 'none'))})", [rate("lstm", "none"), rate("nostra", "none")],
                lambda xs: min(xs) >= CLEAN_MIN),
            bar(f"blind control <= {BLIND_MAX:.0%} (BC-LSTM {percent(rate('lstm', 'blind'))}, MLI "
                f"{percent(rate('nostra_mli', 'blind'))})", [rate("lstm", "blind"), rate("nostra_mli", "blind")],
                lambda xs: max(xs) <= BLIND_MAX)]
    # (noise, its claims): Table 1's unless only Table 2 ran (OBS=rgbd), then Table 2's once any of its cells exist
    ran = set(s.index.get_level_values("noise"))
    has_dp = not np.isnan(rate("diffusion", "none"))
    # Diffusion Policy's claims have its own bars too: a baseline that did not learn tests nothing
    dp = [(f"Diffusion Policy clean >= {CLEAN_MIN:.0%} ({percent(rate('diffusion', 'none'))})",
           rate("diffusion", "none") >= CLEAN_MIN, [rate("diffusion", "none")]),
          (f"Diffusion Policy blind <= {BLIND_MAX:.0%} ({percent(rate('diffusion', 'blind'))})",
           rate("diffusion", "blind") <= BLIND_MAX, [rate("diffusion", "blind")])]
    claims = []
    if not ran & set(TABLE2_NOISES) or ran & set(TABLE1_NOISES[1:]):
        claims = [("mask", [within("nostra_mli", "mask"), above("nostra_mli", "mask"),
                            (f"AdaMLI within {WITHIN:.0%} of oracle MLI under mask ({percent(rate('nostra_adamli', 'mask'))} "
                             f"vs {percent(rate('nostra_mli', 'mask'))})",
                             abs(rate("nostra_adamli", "mask") - rate("nostra_mli", "mask")) <= WITHIN,
                             [rate("nostra_adamli", "mask"), rate("nostra_mli", "mask")])], [])]
        if has_dp:
            claims.append(("mask", [above("nostra_mli", "mask", "diffusion")], dp))
    if ran & set(TABLE2_NOISES):
        claims += [(n, [within("nostra_adamli", n), above("nostra_adamli", n)], []) for n in TABLE2_NOISES]
        if has_dp:
            claims += [(n, [above("nostra_adamli", n, "diffusion"), above("nostra_mli", n, "diffusion")], dp)
                       for n in TABLE2_NOISES]
    measured = lambda xs: not any(np.isnan(x) for x in xs)  # noqa: E731
    holds = lambda row: row[1] and measured(row[2])  # noqa: E731
    extras = {r[0]: r for _, _, extra in claims for r in extra}  # each bar once, however many claims it gates
    pre = base + [hurts(n) for n in dict.fromkeys(n for n, _, _ in claims)] + list(extras.values())
    lines = ["| Precondition | holds |", "|---|---|"] + [
        f"| {t} | {('yes' if ok else 'no') if measured(xs) else 'not measured'} |" for t, ok, xs in pre]
    lines += ["", "| Claim | verdict |", "|---|---|"]
    for noise, rows, extra in claims:
        testable = all(holds(r) for r in base + extra) and holds(hurts(noise))
        for text, ok, xs in rows:
            if not measured(xs):
                verdict = "not measured"
            else:
                seen = "shown" if ok else "not shown"
                verdict = seen if testable else f"not testable ({seen} as measured)"
            lines.append(f"| {text} | {verdict} |")
    return lines


def _cell(r, every: set[str] = frozenset()) -> str:
    """rate [CI]; a pooled cell that not every training seed ran names the seeds it holds."""
    held = set(str(getattr(r, "seeds", "")).split())
    only = f" (seed {', '.join(sorted(held, key=int))} only)" if every and held and held != every else ""
    return f"{100 * r.rate:.0f} [{100 * r.ci_low:.0f}, {100 * r.ci_high:.0f}]{only}"


def success_markdown(success: pd.DataFrame, checkpoint: str, seed: str) -> list[str]:
    s = success[(success.checkpoint == checkpoint) & (success.seed == seed)]
    every = set(success[success.checkpoint == checkpoint].seed.astype(str)) - {POOLED} if seed == POOLED else set()
    noises = [n for n in NOISE_ORDER if n in set(s.noise)]
    lines = ["| Method | " + " | ".join(noises) + " |", "|---" * (len(noises) + 1) + "|"]
    for v in [v for v in ROWS if v in set(s.variant)]:
        r = s[s.variant == v].set_index("noise")
        lines.append(f"| {LABELS.get(v, v)} | " + " | ".join(_cell(r.loc[n], every) if n in r.index else "–"
                                                             for n in noises) + " |")
    return lines


def paired_markdown(pairs: pd.DataFrame, checkpoint: str, seed: str) -> list[str]:
    p = pairs[(pairs.checkpoint == checkpoint) & (pairs.seed == seed)] if len(pairs) else pairs
    lines = ["| Comparison | noise | n | difference (points) [95% CI] | only a / only b | McNemar exact p |",
             "|---|---|---|---|---|---|"]
    for r in p.itertuples():
        lines.append(f"| {LABELS.get(r.a, r.a)} - {LABELS.get(r.b, r.b)} | {r.noise} | {r.n} | {paired_cells(r)} |")
    return lines


def write_report(evaluations: Path, out: Path, header: list[str] = (), earlier: list[Path] = (),
                 seeds: list[int] | None = None) -> str:
    """``seeds``: only these training seeds' episodes (a seed reported apart from its siblings on this disk)."""
    df = episodes(evaluations, earlier)
    if seeds is not None and len(df):
        df = df[df.seed.isin(seeds)].reset_index(drop=True)
    if df.empty:
        raise FileNotFoundError(f"no episode records under {evaluations}/s<seed>/<checkpoint>/**/records"
                                + (f" for training seeds {seeds}" if seeds is not None else ""))
    out.mkdir(parents=True, exist_ok=True)
    success, pairs, fir = success_table(df), paired_table(df), false_imagination(df)
    df.sort_values(EPISODE_KEY).to_csv(out / "episodes.csv", index=False)
    success.to_csv(out / "table1.csv", index=False)
    pairs.to_csv(out / "paired.csv", index=False)
    fir.to_csv(out / "false_imagination.csv", index=False)
    det, kept = adamli_detection(evaluations, seeds), out / "adamli_detection.csv"
    if len(det):
        det.to_csv(kept, index=False)
    elif kept.exists():  # no AdaMLI records on this disk (a model added later): the report's own table stays
        det = pd.read_csv(kept, dtype={"seed": str})
        det = det if seeds is None else det[det.seed.isin([*map(str, seeds), POOLED])]
    seeds = sorted(set(success.seed) - {POOLED}, key=str)
    seeds = seeds + [POOLED] if len(seeds) > 1 else seeds  # one training seed: pooled is the same table
    ran = set(success.noise)
    tables = " and ".join(t for t, noises in (("Table 1", TABLE1_NOISES[1:]), ("Table 2", TABLE2_NOISES))
                          if ran & set(noises)) or "Clean and controls"
    states = (f"- Initial states: environment seeds {df.episode.min()}-{df.episode.max()} ({df.episode.nunique()} "
              "distinct: each seed is one initial state, and every variant meets the same ones)")
    text = ["# The paper's claims at CPU scale", "", *[h for h in header if h], states, "",
            "Success in % over the episodes of each cell (95% Wilson interval); *clean_windows*: mask's windows with "
            "nothing corrupted (MLI imagines the cameras there: imagination's own cost); *blind*: no camera all "
            "episode (MLI: camera latents imagined from step 1). Pooled: every (training seed, episode) once.", ""]
    for ck in [c for c in ("best", "last") if c in set(success.checkpoint)] + sorted(set(success.checkpoint) - {"best", "last"}):
        text += [f"## Checkpoint: {ck}", ""]
        for seed in seeds:
            text += [f"### {tables}, training seed {seed}", "", *success_markdown(success, ck, seed), ""]
        table = paired_markdown(pairs, ck, POOLED)  # two header lines, then a row per comparison
        text += ["### Paired comparisons (pooled)", "", *(table if len(table) > 2 else
                 ["None yet: no cell at this checkpoint has two variants to pair (clean cells alone)."]), "",
                 "### Claims (pooled)", "", *verdicts(success, pairs, ck), ""]
        f = fir[(fir.checkpoint == ck) & (fir.seed == POOLED)]
        if len(f):
            text += [f"AdaMLI false imagination on clean episodes: {100 * f['mean'].iloc[0]:.0f}% of steps "
                     f"({int(f['count'].iloc[0])} episodes).", ""]
        if lines := detection_markdown(det, ck):
            text += ["### AdaMLI's imagination per modality in closed loop (pooled)", "",
                     "The share of the noise windows' steps on which AdaMLI imagined each modality (its recall where "
                     "the noise corrupts that modality), split by the gripper command of the previous action, and the "
                     "share of the other steps (every step of a clean episode) on which it imagined it anyway; where "
                     f"the noise corrupts the modality, the share of windows it did not imagine in their first {LATE} "
                     "steps (opened late) or stopped imagining before they ended (switched back inside), and its KL "
                     "jump into a window beside its mean step-to-step change inside one: AdaMLI switches back when "
                     "the KL drops by f_c times its recent changes, so a KL that swings as much as it jumps ends "
                     "imagination before the noise does.",
                     "", *lines, ""]
    (out / "claims.md").write_text("\n".join(text))
    return "\n".join(text)


def header_lines(evaluations: Path, command: str | None, wall_seconds: float | None, notes: list[str],
                 extra: list[str] = (), *, out: Path) -> list[str]:
    """A report's header: the command(s), the machine, the evaluations, ``extra`` lines, notes. The command
    joins the report folder's log (command_log) and the header names every command in it."""
    from nostra.workflows.command_log import command_header
    from nostra.workflows.cpu_report import machine

    return [*command_header(out, command, wall_seconds), f"- Machine: {machine()}", f"- Evaluations: `{evaluations}`",
            *extra, *[f"- {n}" for n in notes], ""]


def copied_variants(folder: Path, cell: Path | None = None) -> str:
    """The variants whose records a folder of copies holds (records/<task>/<noise>/<variant>_seed<n>.npz) that its
    cell (default: the folder's parent) holds no evaluated records of elsewhere (those win over copies)."""
    def variants(files) -> set[str]:
        return {p.name.rsplit("_seed", 1)[0] for p in files}

    pattern, cell = "records/*/*/*_seed*.npz", cell or folder.parent
    copies = [folder / "records"] + ([cell / "records"] if (cell / "SAME_AS_BEST.txt").exists() else [])  # make cpu's
    evaluated = [p for p in cell.glob(f"**/{pattern}") if not any(p.is_relative_to(c) for c in copies)]
    return ", ".join(sorted(variants(folder.glob(pattern)) - variants(evaluated)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--evaluations", required=True, type=Path, help="<runs>/evaluate/<task>")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--command", default=None, help="the command that made the evaluations (for the header)")
    ap.add_argument("--wall-seconds", type=float, default=None)
    ap.add_argument("--note", action="append", default=[], help="a line for the header (e.g. the matched widths)")
    ap.add_argument("--episodes", nargs="+", type=Path, default=[],
                    help="earlier reports' episodes.csv, read beside the records (seeds whose records are elsewhere)")
    ap.add_argument("--seeds", nargs="+", type=int, default=None,
                    help="only these training seeds (default: every s<seed> folder and earlier episode)")
    args = ap.parse_args(argv)
    copied = [c for c in sorted(p.relative_to(args.evaluations) for p in args.evaluations.glob(f"s*/last/*/{COPIED}"))
              if (args.seeds is None or int(c.parts[0][1:]) in args.seeds) and copied_variants(args.evaluations / c)]
    extra = ["- Last checkpoint = best checkpoint for the variants named (their final check was the best): those "
             "cells are the best cells' records, copied, not re-run: "
             + ", ".join(f"`{c}` ({copied_variants(args.evaluations / c)})" for c in copied)] if copied else []
    if args.episodes:
        extra.append(f"- Episodes read from earlier reports too: {', '.join(f'`{p}`' for p in args.episodes)}")
    if args.seeds is not None:
        extra.append(f"- Training seeds: {', '.join(map(str, args.seeds))} (the others on this disk left out)")
    header = header_lines(args.evaluations, args.command, args.wall_seconds, args.note, extra, out=args.out)
    print(write_report(args.evaluations, args.out, header, args.episodes, args.seeds))


if __name__ == "__main__":
    main()
