"""Imagination over longer windows from episode records: success and the paired MLI - LI difference
per window setting, each imagined path's drift from its own model's clean path, the task's windows
read from the claims cells, and clear errors for a folder that is no window setting."""

import numpy as np
import pandas as pd
import pytest

from nostra.workflows.horizon_report import drift_cm, load, parse_setting, summary, write_report


def _write(folder, noise, variant, successes, windows=(), offset=0.0, steps=20):
    rec = folder / "cell" / "records" / "LiftD1" / noise
    rec.mkdir(parents=True, exist_ok=True)
    noisy = np.zeros(steps, bool)
    for a, b in windows:
        noisy[a:b] = True
    for k, s in enumerate(successes):
        eef = np.zeros((steps, 3), np.float32)
        eef[noisy, 0] = offset  # metres away from the clean path on the imagined steps
        np.savez_compressed(rec / f"{variant}_seed{1000 + k}.npz", success=s, steps=steps, eef_pos=eef, noise=noisy)


def _scenario(tmp_path):
    ev, ref = tmp_path / "horizon", tmp_path / "claims"
    for v in ("nostra", "rssm"):
        _write(ref / "none", "none", v, [True] * 20)
    _write(ref / "mask", "mask", "nostra_mli", [True] * 18 + [False] * 2, [(5, 10)], 0.01)
    _write(ref / "mask", "mask", "rssm_li", [True] * 18 + [False] * 2, [(5, 10)], 0.01)
    _write(ev / "5-20", "mask", "nostra_mli", [True] * 16 + [False] * 4, [(5, 20)], 0.02)
    _write(ev / "5-20", "mask", "rssm_li", [True] * 4 + [False] * 16, [(5, 20)], 0.05)
    return ev, ref


def test_success_pairs_and_drift(tmp_path):
    ev, ref = _scenario(tmp_path)
    df = load(ev, ref, "5-10", "mask")
    s = summary(df, horizon=20).set_index("setting")
    assert list(s.index) == ["5-10", "5-20"]  # sorted by imagined steps: 5, 15
    long = s.loc["5-20"]
    assert long.nostra_mli_rate == 0.8 and long.rssm_li_rate == 0.2 and long.steps == 15
    assert long.pair_diff == pytest.approx(0.6) and long.pair_a_only == 12 and long.pair_p == pytest.approx(2 * 0.5 ** 12)
    assert long.nostra_mli_drift_cm == pytest.approx(2.0) and long.rssm_li_drift_cm == pytest.approx(5.0)
    assert long.drift_diff_cm == pytest.approx(3.0)
    assert s.loc["5-10"].pair_diff == 0

    report = write_report(ev, tmp_path / "out", "mask", ref, "5-10", horizon=20)
    assert "| [5, 20) | 15 | 80 [58, 92] | 20 [8, 42] | +60 [+40, +80] | 12 / 0 | 0.00049 | 2.0 | 5.0 |" in report
    assert "by >= 10 points with p < 0.05: [5, 20)." in report
    assert "The row [5, 10) is the task's windows" in report
    assert "- Initial states: environment seeds 1000-1019 (20 distinct, the same in every cell)" in report
    assert (tmp_path / "out" / "horizon.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "horizon.csv").is_file() and (tmp_path / "out" / "episodes.csv").is_file()


def test_drift_only_over_steps_both_reach(tmp_path):
    _write(tmp_path / "a", "mask", "nostra_mli", [True], [(5, 20)], 0.03, steps=20)
    _write(tmp_path / "b", "none", "nostra", [True], steps=8)  # the clean run ended (succeeded) at step 8
    a = next((tmp_path / "a").glob("**/*.npz"))
    b = next((tmp_path / "b").glob("**/*.npz"))
    assert drift_cm(a, b) == pytest.approx(3.0)  # steps 5-7 only
    assert np.isnan(drift_cm(a, None))


def test_bad_settings(tmp_path):
    with pytest.raises(ValueError, match="'15to65': expected start-end"):
        parse_setting("15to65")
    with pytest.raises(ValueError, match=r"\[\(65, 15\)\] must satisfy 0 < start < end"):
        parse_setting("65-15")
    ev, ref = _scenario(tmp_path)
    with pytest.raises(FileNotFoundError, match="no records of nostra_mli, rssm_li, nostra_adamli, nostra, rssm under 'cam_jitter'"):
        load(ev, None, None, "cam_jitter")
    with pytest.raises(ValueError, match="--reference needs --reference-windows"):
        load(ev, ref, None, "mask")
    (ev / "long").mkdir()
    with pytest.raises(ValueError, match="'long': expected start-end"):
        load(ev, ref, "5-10", "mask")


def test_a_setting_run_here_wins_over_the_claims_cell(tmp_path):
    ev, ref = _scenario(tmp_path)
    _write(ev / "5-10", "mask", "nostra_mli", [False] * 20, [(5, 10)], 0.01)  # the task's windows, rerun here
    df = load(ev, ref, "5-10", "mask")
    mli = df[(df.setting == "5-10") & (df.variant == "nostra_mli")]
    assert len(mli) == 20 and not mli.success.any()
    assert not len(df[(df.setting == "5-10") & (df.variant == "rssm_li")])  # not mixed with the claims cell's


def test_a_changed_adamli_is_not_read_from_the_claims_cell(tmp_path):
    """AdaMLI run here with other settings: the claims cell's (the paper's) AdaMLI is left out at the
    task's windows, its MLI kept; an unknown variant names the valid ones."""
    ev, ref = _scenario(tmp_path)
    _write(ref / "mask", "mask", "nostra_adamli", [True] * 20, [(5, 10)], 0.01)
    assert len(load(ev, ref, "5-10", "mask").query("variant == 'nostra_adamli'")) == 20
    df = load(ev, ref, "5-10", "mask", ("nostra_adamli",))
    assert "nostra_adamli" not in set(df.variant) and len(df.query("setting == '5-10' and variant == 'nostra_mli'")) == 20
    with pytest.raises(ValueError, match="--reference-excludes adamli: unknown variant; valid: nostra_mli, rssm_li"):
        load(ev, ref, "5-10", "mask", ("adamli",))


def test_pool_over_seeds_pairs_by_seed_and_episode(tmp_path):
    from nostra.workflows.horizon_pool import write_pool

    ev, ref = _scenario(tmp_path)
    a, b = tmp_path / "s2", tmp_path / "s3"
    write_report(ev, a, "mask", ref, "5-10", horizon=20)
    (ev / "5-15").mkdir()  # a setting only the second seed has: left out of the pool, named
    _write(ev / "5-15", "mask", "nostra_mli", [True] * 20, [(5, 15)])
    _write(ev / "5-15", "mask", "rssm_li", [True] * 20, [(5, 15)])
    write_report(ev, b, "mask", ref, "5-10", horizon=20)
    report = write_pool([a, b], [2, 3], tmp_path / "pooled", "mask", horizon=20, reference_windows="5-10")
    s = pd.read_csv(tmp_path / "pooled" / "horizon.csv").set_index("setting")
    assert list(s.index) == ["5-10", "5-20"]
    long = s.loc["5-20"]  # the same episodes twice: 40 paired units, 24 discordant, all for MLI
    assert long.nostra_mli_n == 40 and long.pair_n == 40 and long.pair_a_only == 24
    assert long.pair_p == pytest.approx(2 * 0.5 ** 24) and long.drift_n == 40
    assert "Not in every seed's report, so not pooled: [5, 15)" in report
    assert "Pooled over training seeds 2, 3" in report


def test_pool_errors_name_the_file_and_value(tmp_path):
    from nostra.workflows.horizon_pool import write_pool

    ev, ref = _scenario(tmp_path)
    a = tmp_path / "s2"
    write_report(ev, a, "mask", ref, "5-10", horizon=20)
    with pytest.raises(FileNotFoundError, match="nope/episodes.csv"):
        write_pool([a, tmp_path / "nope"], [2, 3], tmp_path / "out")
    with pytest.raises(ValueError, match="one distinct training seed per report"):
        write_pool([a, a], [2, 2], tmp_path / "out")
    with pytest.raises(ValueError, match=r"ran under 'mask', not --noise 'wrist_mask'"):
        write_pool([a], [2], tmp_path / "out", noise="wrist_mask")
    assert not (tmp_path / "out").exists()  # nothing written on bad input


def test_adamli_paired_with_the_oracle_where_it_ran(tmp_path):
    ev, ref = _scenario(tmp_path)
    _write(ev / "5-20", "mask", "nostra_adamli", [True] * 10 + [False] * 10, [(5, 20)], 0.03)
    report = write_report(ev, tmp_path / "out", "mask", ref, "5-10", horizon=20)
    s = summary(load(ev, ref, "5-10", "mask"), horizon=20).set_index("setting")
    assert s.loc["5-20"].ada_diff == pytest.approx(-0.3) and s.loc["5-20"].ada_b_only == 6
    assert pd.isna(s.loc["5-10"].ada_diff)  # AdaMLI not run at the task's windows: no row for it
    assert "| [5, 20) | 50 [30, 70] | 80 [58, 92] | -30 [-50, -10] | 0 / 6 | 0.031 | 3.0 |" in report
    assert "AdaMLI - MLI | only AdaMLI / only MLI" in report and "MLI - NOSTRA" not in report  # closed loop not run


def test_closed_loop_control_pairs_with_mli(tmp_path):
    ev, ref = _scenario(tmp_path)
    _write(ev / "5-20", "mask", "nostra", [True] * 2 + [False] * 18, [(5, 20)], 0.08)
    report = write_report(ev, tmp_path / "out", "mask", ref, "5-10", horizon=20)
    s = summary(load(ev, ref, "5-10", "mask"), horizon=20).set_index("setting")
    assert s.loc["5-20"].closed_diff == pytest.approx(0.7) and s.loc["5-20"].closed_a_only == 14
    assert "| [5, 20) | 80 [58, 92] | 10 [3, 30] | +70 [+50, +90] | 14 / 0 | 0.00012 | 2.0 |" in report


def test_adamli_imagination_of_the_corrupted_modality(tmp_path):
    """AdaMLI's switch read from its records: of wrist_mask's noisy steps, the share imagined on the wrist
    camera only (the agent view it should keep observing does not count), windows switched back, other steps."""
    ev, ref = tmp_path / "horizon", tmp_path / "claims"
    _write(ref / "none", "none", "nostra", [True] * 4)
    rec = ev / "5-20" / "cell" / "records" / "LiftD1" / "wrist_mask"
    rec.mkdir(parents=True)
    noisy = np.zeros(20, bool)
    noisy[5:20] = True
    for k, start in enumerate((12, 12, 5, 20)):  # opens late (step 12) twice, on time once, never once
        wrist = np.zeros(20, bool)
        wrist[start:] = True
        if k == 2:
            wrist[15:] = False  # switched back before the window's end
        np.savez_compressed(rec / f"nostra_adamli_seed{1000 + k}.npz", success=k < 2, steps=20, noise=noisy,
                            eef_pos=np.zeros((20, 3), np.float32), **{"imagined/robot0_eye_in_hand_image": wrist,
                            "imagined/agentview_image": np.ones(20, bool)})
    s = summary(load(ev, ref, "5-10", "wrist_mask"), horizon=20).set_index("setting").loc["5-20"]
    assert s.ada_recall == pytest.approx((8 + 8 + 10) / 60)  # not the agent view's 100%
    assert s.ada_back == pytest.approx(1 / 4) and s.ada_outside == 0
    report = write_report(ev, tmp_path / "out", "wrist_mask", ref, "5-10", horizon=20)
    assert "| [5, 20) | 43.3% | 25.0% | 0.0% |" in report and "(`robot0_eye_in_hand_image`)" in report
    assert "BC-RSSM + LI did not run here" in report and "MLI - LI" not in report  # no empty LI table
