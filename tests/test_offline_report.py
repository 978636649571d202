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
    assert "| seed | f_o | rollout noise | minus | n |" in text
    assert "| 0 | 5 | none | paper's thresholds | 4 | +25 [+0, +75] | 1 / 0 | 1 |" in text
    assert "| 0 | 5 | mask | paper's thresholds | 4 | +0 [+0, +0] | 0 / 0 | 1 |" in text
    pairs = pd.read_csv(tmp_path / "out/adamli_paired.csv")
    assert list(pairs.f_o) == [5, 5] and set(pairs.noise) == {"none", "mask"}


def _records(folder, variant, wins, n=4):
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        np.savez(folder / f"{variant}_seed{1000 + k}.npz", success=k < wins)


def test_a_sweep_without_the_papers_setting_is_paired_with_make_cpu_claims_cells(tmp_path):
    """f_c = 6 alone in the sweep: its cell under `all` is paired with the claims' AdaMLI (the paper's
    f_c = 3), oracle MLI and clean closed-loop cells of the same checkpoint, on the same episode seeds."""
    for f_c in (3.0, 6.0):  # the offline analyses vary f_c; the rollouts ran f_c = 6 only
        _analysis(tmp_path / "runs", f"s1-fo20-fc{f_c:g}/all", "all", "a.ckpt", {"cam": 1.0},
                  adamli={"f_o": 20.0, "f_c": f_c})
    _records(tmp_path / "rollouts/s1-fo20-fc6/all/records/LiftD1/all", "nostra_adamli", wins=4)
    # another training seed's setting: nothing of its own seed to be paired with (not seed 1's cells)
    _analysis(tmp_path / "runs", "s0-fo20-fc6/all", "all", "b.ckpt", {"cam": 1.0}, adamli={"f_o": 20.0, "f_c": 6.0})
    _records(tmp_path / "rollouts/s0-fo20-fc6/all/records/LiftD1/all", "nostra_adamli", wins=2)
    claims = tmp_path / "evaluate/liftd1/s1/best"
    _records(claims / "all/nostra+nostra_mli+nostra_adamli/records/LiftD1/all", "nostra_adamli", wins=1)
    _records(claims / "all/nostra+nostra_mli+nostra_adamli/records/LiftD1/all", "nostra_mli", wins=3)
    _records(claims / "all/nostra+nostra_mli+nostra_adamli/records/LiftD1/all", "nostra", wins=0)
    _records(claims / "none/records/LiftD1/none", "nostra", wins=4)
    _records(claims / "all/lstm/records/LiftD1/all", "lstm", wins=0)
    _records(claims / "none/records/LiftD1/none", "lstm", wins=2)  # another noise: not paired with `all`
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures",
          "--rollouts", str(tmp_path / "rollouts"), "--reference", str(claims)])
    pairs = pd.read_csv(tmp_path / "out/adamli_paired.csv")
    assert set(pairs.seed) == {1} and list(pairs.against) == ["paper's thresholds", "oracle MLI", "clean, closed loop", "BC-LSTM"]
    assert list(pairs["diff"]) == [0.75, 0.25, 0.0, 1.0] and list(pairs.a_only) == [3, 1, 0, 4]
    text = (tmp_path / "out/offline.md").read_text()
    assert "| 1 | 6 | all | paper's thresholds | 4 | +75 [+25, +100] | 3 / 0 | 0.25 |" in text
    sweep = pd.read_csv(tmp_path / "out/adamli_sweep.csv").set_index("analysis")  # the paper's row: the claims' cell
    assert sweep.loc["s1-fo20-fc3/all", "success_all"] == 0.25 and sweep.loc["s1-fo20-fc6/all", "success_all"] == 1.0
    assert sweep.loc["s0-fo20-fc6/all", "success_all"] == 0.5  # seed 0 has no reference: its own cell only
    with pytest.raises(FileNotFoundError, match="--reference .*nowhere: no such folder"):
        main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out2"), "--no-figures",
              "--rollouts", str(tmp_path / "rollouts"), "--reference", str(tmp_path / "nowhere")])
    assert not (tmp_path / "out2").exists()  # checked before anything is written


def test_one_setting_apart_from_the_papers_is_paired_with_make_cpu_claims_cells(tmp_path):
    """f_c = 12 the sweep's only analysis (nothing varies among its rows, but it is not the paper's f_c):
    still a sensitivity row, and its rollouts paired with the claims' AdaMLI (f_c = 3) and MLI cells."""
    _analysis(tmp_path / "runs", "s4-fo20-fc12/mask", "mask", "a.ckpt", {"cam": 1.0}, adamli={"f_o": 20.0, "f_c": 12.0})
    _records(tmp_path / "rollouts/s4-fo20-fc12/mask/records/LiftD1/mask", "nostra_adamli", wins=4)
    claims = tmp_path / "evaluate/liftd1/s4/best"
    _records(claims / "mask/nostra+nostra_mli+nostra_adamli/records/LiftD1/mask", "nostra_adamli", wins=1)
    _records(claims / "mask/nostra+nostra_mli+nostra_adamli/records/LiftD1/mask", "nostra_mli", wins=4)
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures",
          "--rollouts", str(tmp_path / "rollouts"), "--reference", str(claims)])
    pairs = pd.read_csv(tmp_path / "out/adamli_paired.csv")
    assert list(pairs.against) == ["paper's thresholds", "oracle MLI"] and list(pairs["diff"]) == [0.75, 0.0]
    assert "| 4 | 12 | mask | paper's thresholds | 4 | +75 [+25, +100] | 3 / 0 | 0.25 |" in (tmp_path / "out/offline.md").read_text()


def test_analyses_at_the_papers_thresholds_make_no_sensitivity_table(tmp_path):
    _analysis(tmp_path / "runs", "s4-fo20-fc3/mask", "mask", "a.ckpt", {"cam": 1.0}, adamli={"f_o": 20, "f_c": 3.0})
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures"])
    assert "sensitivity" not in (tmp_path / "out/offline.md").read_text()
    assert not (tmp_path / "out/adamli_sweep.csv").exists()


def test_sweep_rollouts_say_how_adamli_switched_beside_the_papers_cells(tmp_path):
    """Per setting and rollout noise, the windows AdaMLI switched back inside; the paper's setting comes
    from make cpu-claims' AdaMLI records of the same checkpoint (named s<seed>-fo20-fc3)."""
    import numpy as np

    _analysis(tmp_path / "runs", "s2-fo20-fc6/mask", "mask", "a.ckpt", {"cam": 1.0}, adamli={"f_o": 20.0, "f_c": 6.0})
    noise = np.array([False, False, True, True, True, True, False])
    kl = np.array([1.0, 1.0, 30.0, 10.0, 30.0, 10.0, 1.0])  # the KL swings inside the window as much as it jumps
    def record(folder, k, imagined):
        folder.mkdir(parents=True, exist_ok=True)
        np.savez(folder / f"nostra_adamli_seed{1000 + k}.npz", success=True, steps=7, noise=noise,
                 action=np.zeros((7, 7)), **{"imagined/agentview_image": np.array(imagined, bool),
                                             "kl/agentview_image": kl})
    for k in range(2):
        record(tmp_path / "rollouts/s2-fo20-fc6/cam_jitter/records/LiftD1/cam_jitter", k, [0, 0, 1, 1, 1, 1, 1])
        record(tmp_path / "evaluate/liftd1/s2/best/cam_jitter/cell/records/LiftD1/cam_jitter", k, [0, 0, 1, 0, 0, 0, 0])
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures",
          "--rollouts", str(tmp_path / "rollouts"), "--reference", str(tmp_path / "evaluate/liftd1/s2/best")])
    sw = pd.read_csv(tmp_path / "out/adamli_switching.csv").set_index("setting")
    assert sw.loc["s2-fo20-fc3", "closed_early"] == 1.0 and sw.loc["s2-fo20-fc6", "closed_early"] == 0.0
    assert sw.loc["s2-fo20-fc6", "outside"] == 1 / 3 and sw.loc["s2-fo20-fc6", "kl_swing"] == 20.0
    text = (tmp_path / "out/offline.md").read_text()
    assert "| s2-fo20-fc3 | cam_jitter | agentview_image | 25% | 0% | 0% | 100% | 29 / 20 |" in text
