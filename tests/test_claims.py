"""The claims report: Table 1 per seed and pooled from episode records, paired comparisons on the
same initial states (McNemar exact, bootstrap interval), AdaMLI's false imagination, and verdicts
that are 'not testable' unless the preconditions hold."""

import shutil

import numpy as np
import pandas as pd
import pytest

from nostra.workflows.claims import load_records, paired_table, success_table, verdicts, write_report
from nostra.noise import NoiseSchedule


def _write(root, seed, ck, noise, variant, successes, imagined=None, folder="cell"):
    rec = root / f"s{seed}" / ck / noise / folder / "records" / "LiftD1" / noise
    rec.mkdir(parents=True, exist_ok=True)
    for k, s in enumerate(successes):
        extra = {} if imagined is None else {"imagined/agentview_image": np.asarray(imagined[k], bool)}
        np.savez_compressed(rec / f"{variant}_seed{1000 + k}.npz", success=s, steps=10, **extra)


def _scenario(root, mli_mask, lstm_mask):
    for seed in (0, 1):
        _write(root, seed, "best", "none", "lstm", [True] * 10)
        _write(root, seed, "best", "none", "nostra", [True] * 10)
        _write(root, seed, "best", "blind", "lstm", [False] * 10)
        _write(root, seed, "best", "blind", "nostra_mli", [False] * 10)
        _write(root, seed, "best", "mask", "nostra", [True] * 5 + [False] * 5)
        _write(root, seed, "best", "mask", "nostra_mli", mli_mask)
        _write(root, seed, "best", "mask", "lstm", lstm_mask)
        _write(root, seed, "best", "mask", "nostra_adamli", mli_mask[:-1] + [False])
        _write(root, seed, "best", "none", "nostra_adamli", [True] * 10, imagined=[[True, False, False, False]] * 10)


def test_pooled_table_paired_test_and_verdicts(tmp_path):
    _scenario(tmp_path, mli_mask=[True] * 10, lstm_mask=[False] * 10)
    df = load_records(tmp_path)
    success = success_table(df)
    pooled = success[(success.seed == "pooled") & (success.checkpoint == "best")].set_index(["variant", "noise"])
    assert pooled.loc[("nostra", "mask"), "n"] == 20 and pooled.loc[("nostra", "mask"), "rate"] == 0.5
    pairs = paired_table(df)
    r = pairs[(pairs.seed == "pooled") & (pairs.a == "nostra_mli") & (pairs.b == "lstm") & (pairs.noise == "mask")].iloc[0]
    assert r.n == 20 and r["diff"] == 1.0 and r.a_only == 20 and r.b_only == 0
    assert r.p == pytest.approx(2 * 0.5 ** 20)
    lines = "\n".join(verdicts(success, pairs, "best"))
    assert "| BC-NOSTRA + MLI above BC-LSTM under mask with McNemar p < 0.05 (+100 points" in lines
    assert lines.count("| shown |") == 3

    report = write_report(tmp_path, tmp_path / "out")
    assert "false imagination on clean episodes: 25% of steps (20 episodes)" in report
    assert (tmp_path / "out" / "paired.csv").is_file() and (tmp_path / "out" / "table1.csv").is_file()


def test_claims_are_not_testable_when_blind_control_succeeds(tmp_path):
    _scenario(tmp_path, mli_mask=[True] * 10, lstm_mask=[True] * 9 + [False])
    for seed in (0, 1):  # the task does not need the cameras: the claims cannot be tested on it
        _write(tmp_path, seed, "best", "blind", "nostra_mli", [True] * 10)
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| blind control <= 20% (BC-LSTM 0%, MLI 100%) | no |" in lines
    assert "| shown |" not in lines and "not testable (not shown as measured)" in lines


def test_paired_interval_is_over_the_same_episodes(tmp_path):
    # MLI wins on seeds 0-4, loses on 5-9 of the same initial states: no difference, p = 1
    _scenario(tmp_path, mli_mask=[True] * 5 + [False] * 5, lstm_mask=[False] * 5 + [True] * 5)
    pairs = paired_table(load_records(tmp_path))
    r = pairs[(pairs.seed == "0") & (pairs.a == "nostra_mli") & (pairs.b == "lstm") & (pairs.noise == "mask")].iloc[0]
    assert r["diff"] == 0 and r.p == 1.0 and r.ci_low < 0 < r.ci_high


def test_clean_windows_imagines_without_corrupting():
    s = NoiseSchedule("clean_windows", [[5, 10]])
    obs = {"agentview_image": np.full((4, 4, 3), 7, np.uint8), "robot0_eef_pos": np.ones(3)}
    assert s.active(5) and not s.active(10) and "agentview_image" in s.keys
    assert all(np.array_equal(s.corrupt(obs, 6)[k], obs[k]) for k in obs)


def test_cells_not_run_yet_are_not_measured_not_failed(tmp_path):
    """A run stopped before its mask cells: the verdicts say so instead of "no" / "not shown"."""
    for variant, ok in (("lstm", True), ("nostra", True)):
        _write(tmp_path, 0, "best", "none", variant, [ok] * 10)
    _write(tmp_path, 0, "best", "blind", "lstm", [False] * 10)
    _write(tmp_path, 0, "best", "blind", "nostra_mli", [False] * 10)
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| mask hurts closed-loop BC-NOSTRA by >= 10% (100% -> –) | not measured |" in lines
    assert "| blind control <= 20% (BC-LSTM 0%, MLI 0%) | yes |" in lines
    assert lines.count("| not measured |") == 4 and "shown" not in lines


def test_a_nostra_only_run_is_tested_on_the_bars_of_the_models_it_ran(tmp_path):
    """A training seed with BC-NOSTRA alone (no BC-LSTM records): the clean and blind bars read NOSTRA's
    cells, and a failing NOSTRA still fails them."""
    _write(tmp_path, 1, "best", "none", "nostra", [True] * 10)
    _write(tmp_path, 1, "best", "blind", "nostra_mli", [False] * 10)
    for variant, ok in (("nostra", [False] * 10), ("nostra_adamli", [True] * 10)):
        _write(tmp_path, 1, "best", "rgb", variant, ok)
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| closed-loop clean >= 85% (BC-LSTM –, BC-NOSTRA 100%) | yes |" in lines
    assert "| blind control <= 20% (BC-LSTM –, MLI 0%) | yes |" in lines
    assert "| BC-NOSTRA + AdaMLI under rgb within 10% of its clean success (100% vs 100%) | shown |" in lines
    assert "| BC-NOSTRA + AdaMLI above BC-LSTM under rgb with McNemar p < 0.05 (–) | not measured |" in lines
    _write(tmp_path, 1, "best", "blind", "nostra_mli", [True] * 10)  # imagining blind succeeds: vision not needed
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| blind control <= 20% (BC-LSTM –, MLI 100%) | no |" in lines
    assert "under rgb within 10% of its clean success (100% vs 100%) | not testable (shown as measured) |" in lines


def test_table2_noises_get_their_columns_pairs_and_claims(tmp_path):
    """OBS=rgbd's cells (rgb, rgbd, all): AdaMLI against the others, paired, and its claims gated by
    whether each noise hurts the closed-loop policy; Table 1's mask claims are left out (not run)."""
    for seed in (0, 1):
        _write(tmp_path, seed, "best", "none", "lstm", [True] * 10)
        _write(tmp_path, seed, "best", "none", "nostra", [True] * 10)
        _write(tmp_path, seed, "best", "blind", "lstm", [False] * 10)
        _write(tmp_path, seed, "best", "blind", "nostra_mli", [False] * 10)
        for noise in ("rgb", "rgbd", "all"):
            _write(tmp_path, seed, "best", noise, "nostra", [True] * 4 + [False] * 6)
            _write(tmp_path, seed, "best", noise, "lstm", [False] * 10)
            _write(tmp_path, seed, "best", noise, "nostra_adamli", [True] * 10 if noise != "all" else [True] * 5 + [False] * 5)
    df = load_records(tmp_path)
    pairs = paired_table(df)
    r = pairs[(pairs.seed == "pooled") & (pairs.a == "nostra_adamli") & (pairs.b == "lstm") & (pairs.noise == "rgbd")]
    assert len(r) == 1 and r["diff"].iloc[0] == 1.0
    lines = "\n".join(verdicts(success_table(df), pairs, "best"))
    assert "| rgb hurts closed-loop BC-NOSTRA by >= 10% (100% -> 40%) | yes |" in lines
    assert "| BC-NOSTRA + AdaMLI under rgbd within 10% of its clean success (100% vs 100%) | shown |" in lines
    assert "| BC-NOSTRA + AdaMLI under all within 10% of its clean success (50% vs 100%) | not shown |" in lines
    assert "mask" not in lines and "| not measured |" not in lines
    report = write_report(tmp_path, tmp_path / "out")
    assert "### Table 2, training seed pooled" in report and "| none | rgb | rgbd | all | blind |" in report


def test_header_states_the_command_and_notes(tmp_path, capsys):
    from nostra.workflows.claims import main

    _scenario(tmp_path / "ev", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out"), "--command", "CAPACITY=matched make cpu-claims",
          "--note", "Capacity-matched: model.net.rnn_hidden=457"])
    text = (tmp_path / "out/claims.md").read_text()
    assert "- Command: `CAPACITY=matched make cpu-claims`" in text and "- Capacity-matched: model.net.rnn_hidden=457" in text
    assert "- Initial states: environment seeds 1000-1009 (10 distinct:" in text  # from the records' names
    main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out"), "--command", "NOISES=mask make cpu-claims",
          "--wall-seconds", "300"])  # a second piece: the header names both commands
    text = (tmp_path / "out/claims.md").read_text()
    assert "  1. `CAPACITY=matched make cpu-claims` (finished " in text and "- Command:" not in text
    assert "  2. `NOISES=mask make cpu-claims` (finished " in text and "- Wall time of the commands: 5 min (1 of 2 timed)" in text


def test_adamli_detection_per_modality_and_gripper_phase(tmp_path):
    """AdaMLI's closed-loop imagination per modality: recall inside the windows, split by the previous
    action's gripper command, and imagination outside them; a diagnostic noise gets its column."""
    rec = tmp_path / "s0" / "best" / "proprio_zero" / "cell" / "records" / "LiftD1" / "proprio_zero"
    rec.mkdir(parents=True)
    noise = np.array([False, True, True, True, True, False])
    grip = np.array([-1, -1, 1, 1, 1, 1.0])  # closed from step 3 on (the command of step 2)
    action = np.zeros((6, 7), np.float32)
    action[:, -1] = grip
    gripper = np.array([False, True, True, False, False, True])  # misses while closed, one false imagination
    kl = np.array([1.0, 9.0, 7.0, 9.0, 7.0, 1.0])  # jumps by 8 into the window, then changes by 2 a step
    for k in range(2):
        np.savez_compressed(rec / f"nostra_adamli_seed{1000 + k}.npz", success=k == 0, steps=6, noise=noise,
                            action=action, **{"imagined/robot0_gripper_qpos": gripper, "kl/robot0_gripper_qpos": kl,
                                              "imagined/robot0_eef_pos": noise,
                                              "imagined/robot0_eef_quat": np.arange(6) == 4})  # opens late
        np.savez_compressed(rec / f"nostra_mli_seed{1000 + k}.npz", success=True, steps=6)
    from nostra.workflows.claims import adamli_detection

    det = adamli_detection(tmp_path).set_index(["seed", "modality"])
    g = det.loc[("pooled", "robot0_gripper_qpos")]
    assert g.recall == 0.5 and g.recall_open == 1.0 and g.recall_closed == 0.0
    assert g.outside == 0.5 and det.loc[("0", "robot0_eef_pos")].recall == 1.0
    assert g.opened_late == 0.0 and g.closed_early == 1.0 and g.kl_jump == 8.0 and g.kl_swing == 2.0
    e = det.loc[("pooled", "robot0_eef_pos")]  # imagined over the whole window, no KL recorded
    assert e.opened_late == 0.0 and e.closed_early == 0.0 and np.isnan(e.kl_jump)
    assert det.loc[("pooled", "robot0_eef_quat")].opened_late == 1.0
    report = write_report(tmp_path, tmp_path / "out")
    assert "| proprio_zero | robot0_gripper_qpos | yes | 50% | 100% | 0% | 50% | 0% | 100% | 8 / 2 |" in report
    assert "| BC-NOSTRA + AdaMLI | 50 [" in report and "| proprio_zero |" in report.split("### Paired")[1]
    assert (tmp_path / "out" / "adamli_detection.csv").is_file()

    # a model added later on a disk without AdaMLI's records: the report keeps its own per-modality table
    kept = (tmp_path / "out" / "adamli_detection.csv").read_text()
    _write(tmp_path / "later", 0, "best", "proprio_zero", "lstm", [False, True])
    report = write_report(tmp_path / "later", tmp_path / "out", earlier=[tmp_path / "out" / "episodes.csv"])
    assert "| proprio_zero | robot0_gripper_qpos | yes | 50% | 100% | 0% | 50% | 0% | 100% | 8 / 2 |" in report
    assert "| BC-LSTM | 50 [" in report and (tmp_path / "out" / "adamli_detection.csv").read_text() == kept


def test_pooling_seed_reports_equals_pooling_their_records(tmp_path):
    """Seeds reported apart (records on different disks) pool to the numbers the records give together."""
    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "both", mli_mask=[True] * 8 + [False] * 2, lstm_mask=[False] * 7 + [True] * 3)
    _write(tmp_path / "both", 1, "best", "mask", "lstm", [True] * 6 + [False] * 4)  # seeds differ
    for seed in (0, 1):  # each seed's records alone, as on its own machine
        shutil.copytree(tmp_path / "both" / f"s{seed}", tmp_path / f"alone{seed}" / f"s{seed}")
        write_report(tmp_path / f"alone{seed}", tmp_path / f"report{seed}")
    write_report(tmp_path / "both", tmp_path / "together")
    text = write_pooled([tmp_path / "report0", tmp_path / "report1"], tmp_path / "pooled")

    key = ["checkpoint", "seed", "noise", "a", "b"]
    want = pd.read_csv(tmp_path / "together" / "paired.csv", dtype={"seed": str}).set_index(key).sort_index()
    got = pd.read_csv(tmp_path / "pooled" / "paired.csv", dtype={"seed": str}).set_index(key).sort_index()
    assert list(got.index) == list(want.index)
    exact = ["n", "rate_a", "rate_b", "diff", "a_only", "b_only", "p"]
    pd.testing.assert_frame_equal(got[exact], want[exact], check_dtype=False)
    assert (got.ci_low - want.ci_low).abs().max() <= 0.05  # the bootstrap draws over another episode order
    s_want = pd.read_csv(tmp_path / "together" / "table1.csv", dtype={"seed": str}).set_index(key[:2] + ["variant", "noise"])
    s_got = pd.read_csv(tmp_path / "pooled" / "table1.csv", dtype={"seed": str}).set_index(key[:2] + ["variant", "noise"])
    pd.testing.assert_frame_equal(s_got.sort_index()[["k", "n", "rate"]], s_want.sort_index()[["k", "n", "rate"]],
                                  check_dtype=False)
    assert "false imagination on clean episodes: 25% of steps (20 episodes)" in text
    assert "### Claims (pooled)" in text


def test_pooling_refuses_a_seed_twice_and_a_missing_file(tmp_path):
    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "ev", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    write_report(tmp_path / "ev", tmp_path / "both")
    with pytest.raises(ValueError, match="training seed 0.s cell best / .* is in both"):
        write_pooled([tmp_path / "both", tmp_path / "both"], tmp_path / "out")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "table1.csv").write_text("checkpoint,seed\nbest,3\n")
    with pytest.raises(ValueError, match=r"broken/table1.csv: missing column\(s\) variant, noise, k, n"):
        write_pooled([tmp_path / "both", tmp_path / "broken"], tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="nowhere: neither table1.csv"):
        write_pooled([tmp_path / "both", tmp_path / "nowhere"], tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_pooled_cell_that_some_seeds_ran_says_so(tmp_path):
    _scenario(tmp_path, mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path, 0, "best", "none", "rssm", [True] * 10)  # BC-RSSM trained on seed 0 alone
    report = write_report(tmp_path, tmp_path / "out")
    pooled = report.split("### Table 1, training seed pooled")[1].split("###")[0]
    assert "| BC-RSSM | 100 [72, 100] (seed 0 only) |" in pooled
    assert "| BC-LSTM | 100 [84, 100] |" in pooled  # both seeds: nothing added
    assert "(seed 0 only)" not in report.split("### Table 1, training seed pooled")[0]  # per-seed tables


def test_episodes_of_an_earlier_report_pair_with_new_records(tmp_path):
    """A seed whose records are gone is read back from its report's episodes.csv: with another seed's records
    the report is the one the records give together, and a variant run later pairs with the earlier episodes."""
    _scenario(tmp_path / "both", mli_mask=[True] * 8 + [False] * 2, lstm_mask=[False] * 7 + [True] * 3)
    shutil.copytree(tmp_path / "both" / "s0", tmp_path / "alone0" / "s0")
    write_report(tmp_path / "alone0", tmp_path / "report0")
    shutil.copytree(tmp_path / "both" / "s1", tmp_path / "later" / "s1")
    _write(tmp_path / "later", 0, "best", "mask", "rssm_li", [True] * 4 + [False] * 6)  # seed 0, run later
    _write(tmp_path / "both", 0, "best", "mask", "rssm_li", [True] * 4 + [False] * 6)
    earlier = [tmp_path / "report0" / "episodes.csv"]
    write_report(tmp_path / "later", tmp_path / "merged", earlier=earlier)
    write_report(tmp_path / "both", tmp_path / "together")
    for name in ("table1.csv", "paired.csv", "episodes.csv"):
        got, want = (pd.read_csv(tmp_path / d / name) for d in ("merged", "together"))
        pd.testing.assert_frame_equal(got, want)
    pairs = pd.read_csv(tmp_path / "merged" / "paired.csv", dtype={"seed": str})
    r = pairs[(pairs.seed == "0") & (pairs.a == "nostra_mli") & (pairs.b == "rssm_li")].iloc[0]
    assert r.n == 10 and r["diff"] == pytest.approx(0.4) and r.a_only == 4 and r.b_only == 0

    # a record evaluated again wins over the earlier report's episode
    _write(tmp_path / "later", 0, "best", "none", "lstm", [False] * 10)
    write_report(tmp_path / "later", tmp_path / "again", earlier=earlier)
    df = pd.read_csv(tmp_path / "again" / "episodes.csv")
    assert not df[(df.seed == 0) & (df.variant == "lstm") & (df.noise == "none")].success.any()

    (tmp_path / "bad.csv").write_text("seed,checkpoint,noise\n0,best,none\n")
    with pytest.raises(ValueError, match=r"bad.csv: missing column\(s\) variant, episode, success, imagined_share"):
        write_report(tmp_path / "later", tmp_path / "out", earlier=[tmp_path / "bad.csv"])
    (tmp_path / "words.csv").write_text("seed,checkpoint,noise,variant,episode,success,imagined_share\n"
                                        "zero,best,none,lstm,1000,True,\n")
    with pytest.raises(ValueError, match="words.csv: seed and episode must be integers"):
        write_report(tmp_path / "later", tmp_path / "out", earlier=[tmp_path / "words.csv"])
    with pytest.raises(FileNotFoundError, match="nowhere.csv: no such episodes file"):
        write_report(tmp_path / "later", tmp_path / "out", earlier=[tmp_path / "nowhere.csv"])
    assert not (tmp_path / "out").exists()


def test_pooling_only_some_seeds_of_the_reports(tmp_path):
    """--seeds pools the seeds that ran a model the others did not (a report holding seeds 0 and 1, BC-RSSM
    on seed 0 only, and one holding seed 2): the comparison is pooled over seeds 0 and 2, seed 1 left out."""
    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "ev01", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path / "ev01", 0, "best", "mask", "rssm_li", [True] * 5 + [False] * 5)
    _scenario(tmp_path / "ev2", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    shutil.rmtree(tmp_path / "ev2" / "s0")
    shutil.move(tmp_path / "ev2" / "s1", tmp_path / "ev2" / "s2")
    _write(tmp_path / "ev2", 2, "best", "mask", "rssm_li", [True] * 8 + [False] * 2)
    write_report(tmp_path / "ev01", tmp_path / "r01")
    write_report(tmp_path / "ev2", tmp_path / "r2")
    text = write_pooled([tmp_path / "r01", tmp_path / "r2"], tmp_path / "p02", only=["0", "2"])
    assert "- Training seeds: 0, 2" in text and "### Training seed 1" not in text
    pairs = pd.read_csv(tmp_path / "p02" / "paired.csv", dtype={"seed": str})
    r = pairs[(pairs.seed == "pooled") & (pairs.b == "rssm_li")].iloc[0]
    assert r.n == 20 and r.a_only == 7 and r.b_only == 0
    everything = write_pooled([tmp_path / "r01", tmp_path / "r2"], tmp_path / "p012")
    assert "BC-RSSM + LI | mask | 20" not in everything  # seed 1 lacks the pair: not pooled over all three
    with pytest.raises(ValueError, match="training seed.s. 5 in none of the reports; they hold 0, 1, 2"):
        write_pooled([tmp_path / "r01", tmp_path / "r2"], tmp_path / "out", only=["0", "5"])
    with pytest.raises(ValueError, match="1 training seed.s.; pooling needs two or more"):
        write_pooled([tmp_path / "r01", tmp_path / "r2"], tmp_path / "out", only=["2"])
    assert not (tmp_path / "out").exists()


def test_a_checkpoint_with_clean_cells_alone_says_there_is_nothing_to_pair(tmp_path):
    _scenario(tmp_path, mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path, 0, "last", "none", "nostra", [True] * 10)
    last = write_report(tmp_path, tmp_path / "out").split("## Checkpoint: last")[1]
    assert "None yet: no cell at this checkpoint has two variants to pair" in last
    assert "| Comparison |" not in last and "| not measured |" in last


def test_seeds_report_one_training_seed_apart_from_the_others_on_disk(tmp_path):
    from nostra.workflows.claims import main

    _scenario(tmp_path / "ev", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path / "ev", 1, "best", "mask", "nostra_mli", [False] * 10)  # seed 1 differs: it must not enter
    main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out"), "--seeds", "0"])
    episodes = pd.read_csv(tmp_path / "out" / "episodes.csv")
    assert set(episodes.seed) == {0}
    table = pd.read_csv(tmp_path / "out" / "table1.csv")
    mli = table[(table.variant == "nostra_mli") & (table.noise == "mask")]
    assert set(mli.seed.astype(str)) == {"0", "pooled"} and list(mli.rate) == [1.0, 1.0] and list(mli.n) == [10, 10]
    assert set(pd.read_csv(tmp_path / "out" / "adamli_detection.csv").seed.astype(str)) <= {"0", "pooled"}
    assert "- Training seeds: 0 (the others on this disk left out)" in (tmp_path / "out/claims.md").read_text()
    with pytest.raises(FileNotFoundError, match=r"for training seeds \[7\]"):
        write_report(tmp_path / "ev", tmp_path / "out7", seeds=[7])


def test_diffusion_claim_has_its_own_bars(tmp_path):
    _scenario(tmp_path, mli_mask=[True] * 10, lstm_mask=[False] * 10)
    for seed in (0, 1):
        _write(tmp_path, seed, "best", "none", "diffusion", [True] * 9 + [False])
        _write(tmp_path, seed, "best", "mask", "diffusion", [False] * 10)
        _write(tmp_path, seed, "best", "blind", "diffusion", [False] * 10)
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| Diffusion Policy clean >= 85% (90%) | yes |" in lines
    assert "| BC-NOSTRA + MLI above Diffusion Policy under mask with McNemar p < 0.05 (+100 points" in lines
    assert lines.count("| shown |") == 4
    for seed in (0, 1):  # a Diffusion Policy that did not learn: its claim alone is not testable
        _write(tmp_path, seed, "best", "none", "diffusion", [True] * 3 + [False] * 7)
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| Diffusion Policy clean >= 85% (30%) | no |" in lines and lines.count("| shown |") == 3
    assert "above Diffusion Policy under mask with McNemar p < 0.05 (+100 points, p = 1.9e-06) | not testable (shown" in lines


def test_table2_diffusion_rows_are_paired_and_gated_by_its_bars(tmp_path):
    """OBS=rgbd with a Diffusion Policy: AdaMLI and oracle MLI above it under rgb, rgbd, all, paired, each gated
    by Diffusion Policy's own clean and blind bars (listed once)."""
    for noise in ("none", "blind", "rgb", "rgbd", "all"):
        _write(tmp_path, 0, "best", noise, "lstm", [noise == "none"] * 10)
        _write(tmp_path, 0, "best", noise, "diffusion", [noise == "none"] * 10)
        nostra = [True] * 10 if noise == "none" else [True] * 2 + [False] * 8
        if noise != "blind":
            _write(tmp_path, 0, "best", noise, "nostra", nostra)
            _write(tmp_path, 0, "best", noise, "nostra_adamli", [True] * 10 if noise != "all" else [True] * 3 + [False] * 7)
        if noise != "none":
            _write(tmp_path, 0, "best", noise, "nostra_mli", [noise != "blind"] * 10)
    df = load_records(tmp_path)
    pairs = paired_table(df)
    r = pairs[(pairs.seed == "pooled") & (pairs.a == "nostra_mli") & (pairs.b == "diffusion") & (pairs.noise == "all")]
    assert len(r) == 1 and r["diff"].iloc[0] == 1.0
    lines = "\n".join(verdicts(success_table(df), pairs, "best"))
    assert lines.count("| Diffusion Policy clean >= 85% (100%) | yes |") == 1
    assert "| BC-NOSTRA + AdaMLI above Diffusion Policy under rgb with McNemar p < 0.05 (+100 points" in lines
    assert "| BC-NOSTRA + AdaMLI above Diffusion Policy under all with McNemar p < 0.05 (+30 points, p = 0.25) | not shown |" in lines
    assert "| BC-NOSTRA + MLI above Diffusion Policy under rgbd with McNemar p < 0.05 (+100 points" in lines
    _write(tmp_path, 0, "best", "none", "diffusion", [True] * 5 + [False] * 5)  # under the bar: not testable
    df = load_records(tmp_path)
    lines = "\n".join(verdicts(success_table(df), paired_table(df), "best"))
    assert "| Diffusion Policy clean >= 85% (50%) | no |" in lines
    assert "above Diffusion Policy under rgb with McNemar p < 0.05 (+100 points, p = 0.002) | not testable (shown" in lines
    assert "| BC-NOSTRA + AdaMLI above BC-LSTM under rgb with McNemar p < 0.05 (+100 points, p = 0.002) | shown |" in lines


def test_header_names_the_variants_whose_last_cells_copy_the_best(tmp_path):
    from nostra.workflows.claims import main

    _scenario(tmp_path / "ev", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path / "ev", 0, "last", "none", "nostra", [True] * 10)  # run on its own last checkpoint
    _write(tmp_path / "ev", 0, "last", "none", "lstm", [True] * 10, folder="same-as-best")
    main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out")])
    line = next(l for l in (tmp_path / "out/claims.md").read_text().splitlines() if l.startswith("- Last checkpoint"))
    assert line.endswith("`s0/last/none/same-as-best` (lstm)")


def test_an_evaluated_last_cell_wins_over_its_same_as_best_copy(tmp_path):
    """Best and last one EMA update apart (Diffusion Policy): both evaluated, the last's own records count, and
    the header does not call them copies."""
    from nostra.workflows.claims import load_records, main

    _scenario(tmp_path / "ev", mli_mask=[True] * 10, lstm_mask=[False] * 10)
    _write(tmp_path / "ev", 0, "last", "none", "lstm", [False] * 10, folder="lstm")           # evaluated
    _write(tmp_path / "ev", 0, "last", "none", "lstm", [True] * 10, folder="same-as-best")    # copied from best
    _write(tmp_path / "ev", 0, "last", "none", "nostra", [True] * 10, folder="same-as-best")  # copied only
    df = load_records(tmp_path / "ev").set_index(["seed", "checkpoint", "noise", "variant"]).sort_index()
    assert not df.loc[(0, "last", "none", "lstm"), "success"].any()
    assert df.loc[(0, "last", "none", "nostra"), "success"].all()
    main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out")])
    line = next(l for l in (tmp_path / "out/claims.md").read_text().splitlines() if l.startswith("- Last checkpoint"))
    assert line.endswith("`s0/last/none/same-as-best` (nostra)")
