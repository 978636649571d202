"""The offline report gathers every analysis: KL per checkpoint once, detection per noise."""

import json

import pandas as pd
import pytest

from nostra.workflows.offline_report import main


def _analysis(root, name, noise, ckpt, kl, **extra):
    d = root / name / "offline"
    d.mkdir(parents=True)
    d.joinpath("offline.json").write_text(json.dumps({**extra,
        "noise": noise, "checkpoint": ckpt, "episodes": [["c", 0], ["c", 1], ["c", 2]],
        "kl_nats": kl, "kl_nats_ci": {m: [v - 1, v + 1] for m, v in kl.items()},
        "detect": {"agentview_image": {"precision": 0.9, "recall": 0.5}, "robot0_eef_pos": {"precision": 0.0, "recall": 1.0},
                   "all": {"precision": 0.8, "recall": 0.4}},
        "false_imagination": {"agentview_image": 0.05, "robot0_eef_pos": 0.01, "all": 0.02}, "action_mse": {}}))


def test_report_lists_kl_once_per_checkpoint_and_detection_per_noise(tmp_path):
    _analysis(tmp_path / "runs", "s0/mask", "mask", "a.ckpt", {"cam": 3.0, "pos": 1.0})
    _analysis(tmp_path / "runs", "s0/proprio_stuck", "proprio_stuck", "a.ckpt", {"cam": 3.0, "pos": 1.0})
    (tmp_path / "runs/s0/mask/offline/kl_episode.png").write_bytes(b"png")  # only the mask analysis drew one
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
    text = (tmp_path / "out/offline.md").read_text()
    assert text.count("`a.ckpt` (3 episodes)") == 1
    assert "| cam | 3.00 | [2.00, 4.00] | 75% |" in text and "| pos | 1.00 | [0.00, 2.00] | 25% |" in text
    assert "`s0/mask`: noise `mask`" in text and "`s0/proprio_stuck`: noise `proprio_stuck`" in text
    assert text.count("| agentview_image | 0.90 | 0.50 | 5.0% |") == 1  # mask: the cameras are noised
    assert "| robot0_eef_pos | – (not noised) | – (not noised) | 1.0% |" in text  # nothing to detect under mask
    assert "| robot0_eef_pos | 0.00 | 1.00 | 1.0% |" in text  # proprio_stuck corrupts it
    assert (tmp_path / "out/kl_episode-s0-mask.png").read_bytes() == b"png"
    assert "![s0/mask](kl_episode-s0-mask.png)" in text and "proprio_stuck.png" not in text


def test_no_analysis_fails_saying_how_to_make_one(tmp_path):
    with pytest.raises(FileNotFoundError, match="no offline.json under .*evaluate.rollouts=false"):
        main(["--analyses", str(tmp_path), "--out", str(tmp_path / "out")])


def test_two_runs_show_each_modalitys_share_side_by_side(tmp_path):
    _analysis(tmp_path / "runs", "s0/mask", "mask", "good.ckpt", {"agentview_image": 3.0, "pos": 1.0})
    _analysis(tmp_path / "runs", "s0-occluded/mask", "mask", "occluded.ckpt", {"agentview_image": 1.0, "pos": 1.0})
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
    text = (tmp_path / "out/offline.md").read_text()
    assert "| modality | s0 | s0-occluded |" in text
    assert "| agentview_image | 75% | 50% |" in text and "| pos | 25% | 50% |" in text


def test_analyses_that_differ_in_thresholds_make_a_sensitivity_table_and_figure(tmp_path):
    for f_o in (5.0, 20.0):
        _analysis(tmp_path / "runs", f"s0-fo{f_o:g}/mask", "mask", "a.ckpt", {"cam": 1.0},
                  adamli={"f_o": f_o, "k_o": 10, "f_c": 3.0})
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures"])
    text = (tmp_path / "out/offline.md").read_text()
    assert "| noise | f_o | precision | recall | false imagination |" in text  # only the varied threshold
    assert "| mask | 5 | 0.80 | 0.40 | 2.0% |" in text and "| mask | 20 | 0.80 | 0.40 | 2.0% |" in text
    assert (tmp_path / "out/adamli_sweep.png").stat().st_size > 1000 and "Figure 5" not in text


def test_threshold_sweep_adds_closed_loop_success_per_setting(tmp_path):
    import numpy as np

    for f_o in (5.0, 20.0):
        _analysis(tmp_path / "runs", f"s0-fo{f_o:g}/mask", "mask", "a.ckpt", {"cam": 1.0}, adamli={"f_o": f_o, "f_c": 3.0})
        for noise, wins in (("none", 4 if f_o == 5 else 3), ("mask", 1)):
            rec = tmp_path / "rollouts" / f"s0-fo{f_o:g}" / noise / "records" / "LiftD1" / noise
            rec.mkdir(parents=True)
            for k in range(4):
                np.savez(rec / f"nostra_adamli_seed{1000 + k}.npz", success=k < wins)
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures",
          "--rollouts", str(tmp_path / "rollouts")])
    text = (tmp_path / "out/offline.md").read_text()
    assert "| noise | f_o | precision | recall | false imagination | closed-loop success, none | closed-loop success, mask |" in text
    assert "| mask | 5 | 0.80 | 0.40 | 2.0% | 100 [51, 100] | 25 [5, 70] |" in text
    assert "| mask | 20 | 0.80 | 0.40 | 2.0% | 75 [30, 95] | 25 [5, 70] |" in text
    csv = (tmp_path / "out/adamli_sweep.csv").read_text().splitlines()[0]
    assert "success_none,success_none_low,success_none_high" in csv
    # f_o = 5 against the paper's 20 on the same four initial states: one more success clean, none masked
    assert "| 5 | none | 4 | +25 [+0, +75] | 1 / 0 | 1 |" in text and "| 5 | mask | 4 | +0 [+0, +0] | 0 / 0 | 1 |" in text
    pairs = pd.read_csv(tmp_path / "out/adamli_paired.csv")
    assert list(pairs.f_o) == [5, 5] and set(pairs.noise) == {"none", "mask"}
