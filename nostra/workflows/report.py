"""The paper's tables and figures rebuilt from MLflow alone (no other files are read).

Evaluation runs log `success/<task>/<noise>/<variant>` with params `table` (robustness, finetune,
cotrain) and `setting` (e.g. `10 demos`, `target only`); offline runs log `kl_nats/<modality>`
with `setting` (the data the policy was trained on). The newest run wins for each cell; a cell
without a run shows a dash and the reason is listed under the table."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from nostra.workflows.variants import LABELS

ROBUSTNESS_NOISES = ["none", "mask", "cam_jitter", "table_tex"]
ADAMLI_NOISES = ["rgb", "rgbd", "all"]
ROWS_T1 = ["lstm", "diffusion", "rssm", "rssm_li", "nostra", "nostra_mli", "nostra_adamli"]
ROWS_T2 = ["lstm", "diffusion", "rssm", "nostra", "nostra_adamli"]
ROWS_T4 = ["lstm", "rssm", "nostra"]  # the paper fine-tunes the recurrent policies only
ROWS_T5 = ["lstm", "diffusion", "rssm", "nostra"]
SUCCESS = re.compile(r"^metrics\.success/(?P<task>[^/]+)/(?P<noise>[^/]+)/(?P<variant>[^/]+)$")
DASH = "–"
CELL_COLUMNS = ("task", "noise", "variant", "value", "table", "setting", "run_id", "checkpoint")
# evaluate.checkpoint -> how the tables name it: the final checkpoint, or the peak over checkpoints
CHECKPOINT_TITLES = {"last": "final checkpoint", "best": "peak over checkpoints (best in-training rollouts)"}


def runs(experiment: str, uri: str | None = None) -> pd.DataFrame:
    from nostra.workflows.tracking import search_runs

    df = search_runs(experiment, uri)
    return df.sort_values("start_time") if len(df) else df


def success_cells(df: pd.DataFrame) -> pd.DataFrame:
    """Long table (task, noise, variant, value, table, setting, run_id) of every success metric;
    later runs override earlier ones."""
    metrics = {c: SUCCESS.match(c).groupdict() for c in df.columns if SUCCESS.match(c)}
    rows = []
    for rec in df.to_dict("records"):
        for col, key in metrics.items():
            if _present(rec.get(col)):
                rows.append({**key, "value": float(rec[col]), "table": _param(rec, "table", "robustness"),
                             "setting": _param(rec, "setting", ""), "run_id": rec["run_id"],
                             "checkpoint": _param(rec, "checkpoint", "last")})
    out = pd.DataFrame(rows, columns=[*CELL_COLUMNS])
    return out.drop_duplicates(["table", "setting", "task", "noise", "variant", "checkpoint"], keep="last")


def _present(v) -> bool:
    return v is not None and not (isinstance(v, float) and np.isnan(v))


def _param(rec: dict, name: str, default: str) -> str:
    v = rec.get(f"params.{name}")
    return str(v) if _present(v) else default


def _fmt(v) -> str:
    return f"{100 * v:.0f}" if _present(v) else DASH


def _lookup(cells, **where):
    sel = cells
    for k, v in where.items():
        sel = sel[sel[k] == v]
    return float(sel["value"].iloc[-1]) if len(sel) else None


def table_noise(cells: pd.DataFrame, table: str, noises: list[str], rows: list[str], title: str,
                checkpoint: str = "last"):
    """Tables 1 and 2: methods x (task, noise), for the runs evaluated with one checkpoint choice."""
    cells = cells[(cells["table"] == table) & (cells["checkpoint"] == checkpoint)]
    tasks = list(dict.fromkeys(cells["task"])) or ["(no task evaluated)"]
    header = ["Method"] + [f"{t} {n}" for t in tasks for n in noises]
    body, missing = [], []
    for v in rows:
        row = [LABELS.get(v, v)]
        for t in tasks:
            for n in noises:
                x = _lookup(cells, task=t, noise=n, variant=v)
                row.append(_fmt(x))
                if x is None:
                    missing.append(f"{t}/{n}/{v}")
        body.append(row)
    note = (f"{DASH}: no evaluation run logged success/<task>/<noise>/<variant> for "
            f"{', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''}" if missing else "")
    return title, pd.DataFrame(body, columns=header), note


def table_settings(cells: pd.DataFrame, table: str, rows: list[str], title: str, baseline: str | None = None):
    """Tables 4 and 5: methods x settings (demos, retrieval mode), success without noise, with
    deltas against the baseline setting where given."""
    cells = cells[(cells["table"] == table) & (cells["noise"] == "none")]
    settings = list(dict.fromkeys(cells["setting"]))
    tasks = list(dict.fromkeys(cells["task"]))
    header = ["Method"] + [f"{t} {s}" for t in tasks for s in settings] if settings else ["Method", "(no runs)"]
    body, missing = [], []
    for v in rows:
        row = [LABELS.get(v, v)]
        for t in tasks:
            base = _lookup(cells, task=t, variant=v, setting=baseline) if baseline else None
            for s in settings:
                x = _lookup(cells, task=t, variant=v, setting=s)
                cell = _fmt(x)
                if x is not None and base is not None and s != baseline:
                    cell += f" ({100 * (x - base):+.0f})"
                row.append(cell)
                if x is None:
                    missing.append(f"{t}/{s}/{v}")
        if not settings:
            row.append(DASH)
        body.append(row)
    note = f"{DASH}: no `{table}` evaluation run for {', '.join(missing[:12])}" if missing else ""
    if not settings:
        note = f"{DASH}: no evaluation run with params.table={table} in MLflow yet"
    return title, pd.DataFrame(body, columns=header), note


def table_kl(df: pd.DataFrame, title: str):
    """Table 3: mean per-modality KL (nats) by training data (offline runs' `setting`)."""
    recs = [r for r in df.to_dict("records") if str(r.get("tags.mlflow.runName", "")).startswith("offline")]
    cols = [c for c in df.columns if c.startswith("metrics.kl_nats/") and any(_present(r.get(c)) for r in recs)]
    if not cols or not recs:
        return title, pd.DataFrame([[DASH, DASH]], columns=["Input", "(no runs)"]), \
            f"{DASH}: no offline analysis run logged kl_nats/<modality>"
    by_setting = {_param(r, "setting", "default"): r for r in recs}  # newest wins
    body = [[c.split("/", 1)[1]] + [_num(r.get(c)) for r in by_setting.values()] for c in cols]
    totals = [sum(r[c] for c in cols if _present(r.get(c))) for r in by_setting.values()]
    body.append(["Total"] + [_num(t) for t in totals])
    return title, pd.DataFrame(body, columns=["Input", *by_setting]), ""


def _num(v) -> str:
    return f"{v:.3f}" if _present(v) else DASH


def to_markdown(title: str, table: pd.DataFrame, note: str) -> str:
    lines = [f"## {title}", "", "| " + " | ".join(table.columns) + " |", "|---" * len(table.columns) + "|"]
    lines += ["| " + " | ".join(str(x) for x in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join(lines + (["", note] if note else []) + [""])


def tables(df: pd.DataFrame) -> dict[str, tuple]:
    cells = success_cells(df) if len(df) else pd.DataFrame(columns=[*CELL_COLUMNS])
    out = {}
    # the final checkpoint always; the peak too where runs were evaluated with checkpoint=best
    for ck in ["last"] + (["best"] if (cells["checkpoint"] == "best").any() else []):
        suffix, what = ("" if ck == "last" else f"_{ck}"), CHECKPOINT_TITLES[ck]
        out[f"table1_robustness{suffix}"] = table_noise(
            cells, "robustness", ROBUSTNESS_NOISES, ROWS_T1,
            f"Table 1: success (%) under visual noise (MLI / LI use an oracle), {what}", ck)
        out[f"table2_adamli{suffix}"] = table_noise(
            cells, "robustness", ADAMLI_NOISES, ROWS_T2,
            f"Table 2: success (%) under multimodal noise with AdaMLI, {what}", ck)
    return {
        **out,
        "table3_kl": table_kl(df, "Table 3: information per modality (KL, nats) by training data"),
        "table4_finetune": table_settings(cells, "finetune", ROWS_T4,
                                          "Table 4: success (%) after fine-tuning a pretrained policy"),
        "table5_cotrain": table_settings(cells, "cotrain", ROWS_T5,
                                         "Table 5: success (%) when co-training with retrieved data",
                                         baseline="target_only"),
    }


def write_report(out_dir: str | Path, experiment: str = "nostra", uri: str | None = None,
                 only: list[str] | None = None) -> Path:
    """Write every table as Markdown and CSV, the logged figures as PNG, and an index.md."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df = runs(experiment, uri)
    index = ["# Report", "", f"Built from MLflow experiment `{experiment}` ({len(df)} runs).", ""]
    for name, (title, table, note) in tables(df).items():
        if only and name not in only:
            continue
        md = to_markdown(title, table, note)
        (out / f"{name}.md").write_text(md)
        table.to_csv(out / f"{name}.csv", index=False)
        index.append(md)
    figures = _figures(df, out / "figures", uri)
    if figures:
        index += ["## Figures", ""] + [f"![{p.stem}](figures/{p.name})" for p in figures] + [""]
    (out / "index.md").write_text("\n".join(index))
    return out / "index.md"


def _figures(df: pd.DataFrame, folder: Path, uri: str | None) -> list[Path]:
    """PNG artifacts of the newest evaluation / offline runs, downloaded from MLflow."""
    if not len(df):
        return []
    from mlflow.tracking import MlflowClient

    from nostra.workflows.tracking import tracking_uri

    client, found = MlflowClient(uri or tracking_uri()), []
    folder.mkdir(parents=True, exist_ok=True)
    seen = set()
    for r in df.iloc[::-1].to_dict("records"):  # newest first: one figure per run name and file
        try:
            arts = [a.path for a in client.list_artifacts(r["run_id"]) if a.path.endswith(".png")]
        except Exception:  # an unreachable artifact store: the tables are still written
            continue
        for a in arts:
            name = f"{r.get('tags.mlflow.runName') or r['run_id']}_{a}".replace("/", "_")
            if name in seen:
                continue
            seen.add(name)
            local = client.download_artifacts(r["run_id"], a, str(folder / ".tmp"))
            shutil.move(local, folder / name)
            found.append(folder / name)
    shutil.rmtree(folder / ".tmp", ignore_errors=True)
    return found
