"""The beta/gamma sensitivity report (scripts/cpu_sweep.sh): one row per setting with its rollout
success cells, KL and AdaMLI detection; settings are parsed from their folder names."""

import json

import numpy as np
import pytest

from nostra.workflows.sweep_report import main, paired_table, parse, sweep_table


def _records(root, setting, noise, variant, wins, n=4):
    rec = root / setting / noise / "cell" / "records" / "LiftD1" / noise
    rec.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        np.savez(rec / f"{variant}_seed{1000 + k}.npz", success=k < wins)


def _offline(root, setting, kl):
    d = root / setting / "mask" / "offline"
    d.mkdir(parents=True)
    d.joinpath("offline.json").write_text(json.dumps({
        "kl_nats": kl, "detect": {"all": {"precision": 0.8, "recall": 0.6}}, "false_imagination": {"all": 0.05}}))


def test_one_row_per_setting_with_success_kl_and_detection(tmp_path):
    ev, off = tmp_path / "ev", tmp_path / "off"
    for setting, wins in (("b1e-4_g0.1", 4), ("b1e-2_g0.1", 1), ("b1e-4_g0.9", 2)):
        _records(ev, setting, "none", "nostra", wins)
        _records(ev, setting, "mask", "nostra_mli", wins - 1 if wins else 0)
    _offline(off, "b1e-4_g0.1", {"cam": 10.0, "pos": 5.0})
    _offline(off, "b1e-2_g0.1", {"cam": 1.0, "pos": 0.5})
    table = sweep_table(ev, off)
    assert list(zip(table.beta, table.gamma)) == [(1e-4, 0.1), (1e-2, 0.1), (1e-4, 0.9)]  # gamma, then beta
    row = table.set_index("setting").loc["b1e-2_g0.1"]
    assert row["nostra none"] == 0.25 and row["nostra none n"] == 4 and row["kl total"] == 1.5
    assert np.isnan(table.set_index("setting").loc["b1e-4_g0.9", "kl total"])  # its analysis did not run
    main(["--evaluations", str(ev), "--offline", str(off), "--out", str(tmp_path / "out"), "--command", "c"])
    text = (tmp_path / "out/sweep.md").read_text()
    assert "| **0.0001** | **0.1** | 100 [51, 100] | – | 75 [30, 95] | – | 15.0 | 10.0 | 5.0 | 0.80 / 0.60 | 5.0% |" in text
    assert "| 0.01 | 0.1 | 25 [5, 70] | – | 0 [0, 49] | – | 1.5 |" in text
    assert (tmp_path / "out/sweep.png").stat().st_size > 1000
    assert "- Episodes: 4 per cell, initial-state seeds 1000-1003" in text
    assert "| 0.01 | 0.1 | BC-NOSTRA, none: this setting - the paper's | 4 | -75 [" in text


def test_paired_rows_compare_each_setting_to_the_papers_on_the_same_episodes(tmp_path):
    ev = tmp_path / "ev"
    _records(ev, "b1e-4_g0.1", "mask", "nostra", 1)        # episodes 1000-1003: T F F F
    _records(ev, "b1e-4_g0.1", "mask", "nostra_mli", 3)    # T T T F
    _records(ev, "b1e-3_g0.1", "mask", "nostra_mli", 4)    # T T T T
    pairs = paired_table(ev).set_index("comparison")
    mli = pairs.loc["BC-NOSTRA + MLI - BC-NOSTRA, mask"]
    assert (mli.beta, mli.n, mli["diff"], mli.a_only, mli.b_only) == (1e-4, 4, 0.5, 2, 0)
    vs_paper = pairs.loc["BC-NOSTRA + MLI, mask: this setting - the paper's"]
    assert (vs_paper.beta, vs_paper["diff"], vs_paper.a_only, vs_paper.b_only) == (1e-3, 0.25, 1, 0)
    assert vs_paper.p == 1.0  # one discordant episode: McNemar's exact test cannot reject
    assert len(pairs) == 2  # no AdaMLI cells, and no comparison of the paper's setting with itself


def test_bad_setting_folder_and_empty_sweep_say_what_is_expected(tmp_path):
    with pytest.raises(ValueError, match=r"'beta0.1': expected b<beta>_g<gamma>"):
        parse("beta0.1")
    with pytest.raises(FileNotFoundError, match="no sweep setting under .*cpu_sweep.sh"):
        sweep_table(tmp_path / "ev", tmp_path / "off")
