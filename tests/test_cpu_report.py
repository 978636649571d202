"""The CPU profile's report and recipe table are built from what the runs wrote: success cells
with intervals for best/last and clean/blind, training cost, learning curves, and the recipe's
differences (independent trainings: Newcombe interval; same checkpoint: McNemar)."""

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from nostra.workflows import cpu_report


def _success(path, rows):
    path.mkdir(parents=True, exist_ok=True)
    pd.DataFrame([{"task": "LiftD1", "noise": n, "variant": v, "label": v, "episodes": 10, "successes": k,
                   "success_rate": k / 10, "ci_low": 0.1, "ci_high": 0.9, "errors": 0} for n, v, k in rows]
                 ).to_csv(path / "success.csv", index=False)


def test_cpu_report(tmp_path):
    runs = tmp_path / "runs"
    _success(runs / "evaluate/liftd1/s0/best", [("none", "lstm", 9), ("blind", "lstm", 1), ("none", "nostra_mli", 8)])
    _success(runs / "evaluate/liftd1/s0/last", [("none", "lstm", 7)])
    run = runs / "train/pretrain-lstm-LiftD1-s0"
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"steps": 3000, "wall_seconds": 1800, "train_episodes": 180,
                                              "val_episodes": 20}))
    (run / "rollouts.json").write_text(json.dumps([
        {"step": 1000, "episodes": 10, "score": 0.6, "seconds": 60},
        {"step": 2000, "episodes": 10, "score": 0.9, "seconds": 60},
        {"step": 3000, "episodes": 50, "score": 0.7, "seconds": 180}]))
    out = tmp_path / "report"
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--out", str(out), "--wall-seconds", "3600",
                     "--command", "TASK=liftd1 make cpu"])
    text = (out / "index.md").read_text()
    assert "| 0 | BC-LSTM | 90 [10, 90] | 70 [10, 90] | 10 [10, 90] |" in text
    assert "cameras imagined" in text and "| 0 | BC-NOSTRA | – | – | – | – | – | not trained |" in text
    assert "| 0 | BC-LSTM | 180 + 20 | 3000 | 30.0 | 5.0 (17%) | 3 | 2000 (90%, 10) |" in text
    assert "demos: expert seeds from 0;" in text
    assert (out / "learning_curves.png").stat().st_size > 0
    assert "copies the best cell" not in text

    (runs / "evaluate/liftd1/s0/last/none").mkdir(parents=True)  # scripts/cpu.sh's copy when last = best
    (runs / "evaluate/liftd1/s0/last/none/SAME_AS_BEST.txt").write_text("a copy")
    (runs / "evaluate/liftd1/s0/last/none/records/LiftD1/none").mkdir(parents=True)
    (runs / "evaluate/liftd1/s0/last/none/records/LiftD1/none/lstm_seed1000.npz").write_bytes(b"")
    (runs / "evaluate/liftd1/s0/last/none/rssm/records/LiftD1/none").mkdir(parents=True)  # a later model's own run
    (runs / "evaluate/liftd1/s0/last/none/rssm/records/LiftD1/none/rssm_seed1000.npz").write_bytes(b"")
    (runs / "evaluate/liftd1/s1/last/none").mkdir(parents=True)  # a seed this report does not cover
    (runs / "evaluate/liftd1/s1/last/none/SAME_AS_BEST.txt").write_text("a copy")
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--out", str(out), "--demos", "seeds from 0 and 10000"])
    text = (out / "index.md").read_text()
    assert "copies of the best cells, not a second run: `s0/last/none` (lstm)\n" in text
    assert "s1/last" not in text and "demos: seeds from 0 and 10000;" in text
    # rewritten without --command (by hand): the log's one command stays the header's, nothing added
    assert "- Command: `TASK=liftd1 make cpu`" in text and "Commands, in the order" not in text

    # HORIZON=<n>: the cells live in their own folder, never mixed with the profile horizon's
    _success(runs / "evaluate/liftd1-h400/s0/best", [("none", "lstm", 10)])
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--out", str(tmp_path / "h400"), "--horizon", "400"])
    text = (tmp_path / "h400" / "index.md").read_text()
    assert "| 0 | BC-LSTM | 100 [10, 90] | – | – |" in text and "Rollout horizon: 400 steps" in text


def test_cpu_report_best_is_the_runs_own_pick_at_its_horizon(tmp_path):
    """A run resumed at a longer horizon: the table's best step is the one run.json names (picked among
    the checks at that horizon), not the highest score at another horizon; the curve draws both."""
    run = tmp_path / "runs/train/pretrain-nostra-Stack-s0"
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"steps": 3000, "wall_seconds": 1800, "rollouts": {
        "best": {"step": 3000, "score": 0.7, "episodes": 10}}}))
    (run / "rollouts.json").write_text(json.dumps([
        {"step": 2000, "episodes": 10, "horizon": 200, "score": 0.9, "seconds": 60},
        {"step": 3000, "episodes": 10, "horizon": 400, "score": 0.7, "seconds": 60}]))
    lines, curves, _ = cpu_report.training_rows(tmp_path / "runs", "Stack", [0], ["nostra"])
    assert lines[-1].endswith("| 2 | 3000 (70%, 10) |")
    # resumed across sittings: the wall is the fit's over every sitting (train_seconds), not this process's
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**info, "train_seconds": 7200, "resumed": True}))
    lines, _, _ = cpu_report.training_rows(tmp_path / "runs", "Stack", [0], ["nostra"])
    assert "| 3000 | 120.0, resumed | 2.0 (2%) | 2 |" in lines[-1]
    cpu_report.curve_figure(curves, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 0


def test_cpu_report_keeps_rows_whose_runs_are_gone(tmp_path):
    """The report rewritten on a disk that has only a later model's run (another VM, MODELS=diffusion):
    the earlier BC-LSTM cells and training row stay, marked, and the new model's are added; a cell
    evaluated again on this disk replaces the kept one; another task's folder is refused."""
    runs, out = tmp_path / "runs", tmp_path / "report"
    _success(runs / "evaluate/liftd1/s2/best", [("none", "lstm", 9), ("blind", "lstm", 1)])
    run = runs / "train/pretrain-lstm-LiftD1-s2"
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"steps": 4929, "wall_seconds": 1896, "train_episodes": 180,
                                              "val_episodes": 20}))
    (run / "rollouts.json").write_text(json.dumps([{"step": 4000, "episodes": 10, "score": 0.9, "seconds": 200}]))
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--seeds", "2", "--models", "lstm", "--out", str(out)])
    lstm_row = "| 2 | BC-LSTM | 180 + 20 | 4929 | 31.6 | 3.3 (11%) | 1 | 4000 (90%, 10) |"
    assert lstm_row in (out / "index.md").read_text() and "†" not in (out / "index.md").read_text()

    shutil.rmtree(runs)  # a fresh machine: only the Diffusion Policy run
    _success(runs / "evaluate/liftd1/s2/best", [("none", "diffusion", 8), ("blind", "lstm", 3)])
    run = runs / "train/pretrain-diffusion-LiftD1-s2"
    run.mkdir(parents=True)
    (run / "run.json").write_text(json.dumps({"steps": 16349, "wall_seconds": 5400}))
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--seeds", "2", "--models", "diffusion",
                     "--out", str(out)])
    text = (out / "index.md").read_text()
    assert "| 2 | BC-LSTM | 90 [10, 90] † | – | 30 [10, 90] |" in text  # blind re-evaluated here: not kept
    assert "| 2 | Diffusion Policy | 80 [10, 90] | – | – |" in text
    assert lstm_row[:-2] + " † |" in text and "| 2 | Diffusion Policy | – | 16349 | 90.0 |" in text
    assert "kept from this folder's earlier report" in text
    cells = pd.read_csv(out / "success.csv")
    assert len(cells) == 3 and "kept" not in cells.columns

    # a report written before training.json: the kept training rows come from its index.md
    (out / "training.json").unlink()
    shutil.rmtree(runs)
    cpu_report.main(["--task", "liftd1", "--runs", str(runs), "--seeds", "2", "--models", "lstm", "--out", str(out)])
    text = (out / "index.md").read_text()
    assert lstm_row[:-2] + " † |" in text and "| 2 | Diffusion Policy | – | 16349 |" in text
    assert "not trained" not in text

    before = (out / "index.md").read_text()
    with pytest.raises(ValueError, match="success.csv holds cells of task 'LiftD1'"):
        cpu_report.main(["--task", "stack", "--runs", str(runs), "--out", str(out)])
    assert (out / "index.md").read_text() == before  # nothing rewritten


def _records(folder, successes):
    rec = folder / "records/LiftD1/none"
    rec.mkdir(parents=True)
    for seed, ok in enumerate(successes):
        np.savez(rec / f"lstm_seed{1000 + seed}.npz", success=ok, steps=10)


def test_recipe_table(tmp_path):
    ev = tmp_path / "ev"
    _records(ev / "base", [True] * 9 + [False])
    _records(ev / "noaug", [True] * 5 + [False] * 5)
    _records(ev / "reset10", [True] * 10)
    _records(ev / "carry", [False] * 8 + [True] * 2)
    out = tmp_path / "recipe.md"
    cpu_report.main(["recipe", "--evaluations", str(ev), "--task", "liftd1", "--out", str(out)])
    text = out.read_text()
    assert "| BC-LSTM, image augmentation off | 50 [24, 76] (n=10) | -40 [" in text
    assert "state carried all episode | 20 [" in text and "-80 (McNemar exact p = 0.0078)" in text
    assert "noise-free demos | – (not run)" in text
