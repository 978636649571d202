"""Tables 4 and 5 from episode records: success per setting, paired comparisons on the same initial
states (NOSTRA vs BC-RSSM at each N, fine-tuned vs from scratch, retrieval vs target only), verdicts
that need significance, and a clear error for a folder that is no setting."""

import numpy as np
import pytest

from nostra.workflows.transfer_report import load_records, paired_table, success_table, verdicts, write_report


def _write(root, seed, setting, variant, successes, folder="cell"):
    rec = root / f"s{seed}" / setting / folder / "records" / "LiftD1" / "none"
    rec.mkdir(parents=True, exist_ok=True)
    for k, s in enumerate(successes):
        np.savez_compressed(rec / f"{variant}_seed{1000 + k}.npz", success=s, steps=10)


def _scenario(root):
    _write(root, 0, "finetune-n10", "nostra", [True] * 16 + [False] * 4)
    _write(root, 0, "finetune-n10", "rssm", [False] * 20)
    _write(root, 0, "finetune-n10", "lstm", [True] * 15 + [False] * 5)  # one episode apart from NOSTRA
    _write(root, 0, "finetune-n20", "nostra", [True] * 20)
    _write(root, 0, "cotrain-target_only", "nostra", [True] * 8 + [False] * 12)
    _write(root, 0, "cotrain-obj_skill", "nostra", [True] * 8 + [False] * 12)
    _write(root, 0, "cotrain-all", "nostra", [True] * 20)
    _write(root, 0, "cotrain-obj_skill", "rssm", [False] * 20, folder="rssm")  # a later evaluation, its own folder


def test_tables_pairs_and_verdicts(tmp_path):
    _scenario(tmp_path)
    df = load_records(tmp_path)
    s = success_table(df).set_index(["seed", "setting", "variant"])
    assert s.loc[("pooled", "finetune-n10", "nostra"), "rate"] == 0.8 and s.loc[("0", "cotrain-all", "nostra"), "n"] == 20
    pairs = paired_table(df, target_demos=10)
    p = pairs[pairs.seed == "pooled"].set_index(["a_setting", "a", "b_setting", "b"])
    r = p.loc[("finetune-n10", "nostra", "finetune-n10", "rssm")]
    assert r["diff"] == pytest.approx(0.8) and r.a_only == 16 and r.p == pytest.approx(2 * 0.5 ** 16)
    scratch = p.loc[("finetune-n10", "nostra", "cotrain-target_only", "nostra")]  # pretraining's gain at 10 demos
    assert scratch["diff"] == pytest.approx(0.4)
    assert ("finetune-n20", "nostra", "cotrain-target_only", "nostra") not in p.index  # 20 demos: no scratch run
    assert p.loc[("cotrain-all", "nostra", "cotrain-obj_skill", "nostra"), "diff"] == pytest.approx(0.6)  # +all's step
    lines = "\n".join(verdicts(pairs))
    assert "| BC-NOSTRA fine-tunes above BC-RSSM | finetune-n10 | +80" in lines and lines.count("| shown |") == 5
    assert "| BC-NOSTRA fine-tunes above BC-LSTM | finetune-n10 | +5 [+0, +15], p = 1 | not shown (higher, not significant) |" in lines
    assert "from scratch, as many demos | finetune-n10 | +40 [+20, +60], p = 0.0078 | shown |" in lines
    assert "obj_skill retrieval improves BC-NOSTRA over target only | cotrain-obj_skill | +0 [+0, +0], p = 1 | not shown |" in lines
    assert "| all retrieval improves BC-NOSTRA over obj_skill | cotrain-all | +60 [+40, +80], p = 0.00049 | shown |" in lines
    assert "| BC-NOSTRA co-trains above BC-RSSM | cotrain-obj_skill | +40 [+20, +60], p = 0.0078 | shown |" in lines
    assert "| BC-NOSTRA co-trains above BC-LSTM | cotrain-all | – | not measured |" in lines  # no BC-LSTM co-trained

    report = write_report(tmp_path, tmp_path / "out", target_demos=10)
    assert "| BC-NOSTRA | 80 [58, 92] | 100 [84, 100] |" in report  # Table 4's row: 10 and 20 demos
    assert (tmp_path / "out" / "transfer.png").stat().st_size > 10_000
    assert (tmp_path / "out" / "paired.csv").is_file()


def test_unknown_setting_folder(tmp_path):
    _write(tmp_path, 0, "finetune-ten", "nostra", [True])
    with pytest.raises(ValueError, match="'finetune-ten': expected finetune-n<N>.*cotrain-target_only"):
        load_records(tmp_path)
    with pytest.raises(FileNotFoundError, match="no episode records"):
        load_records(tmp_path / "empty")


def test_pooling_seed_reports_equals_pooling_their_records(tmp_path):
    """Tables 4 and 5 of seeds reported apart pool to the numbers their records give together."""
    import shutil

    import pandas as pd

    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "both")
    _write(tmp_path / "both", 1, "finetune-n10", "nostra", [True] * 12 + [False] * 8)
    _write(tmp_path / "both", 1, "finetune-n10", "rssm", [True] * 14 + [False] * 6)
    _write(tmp_path / "both", 1, "cotrain-target_only", "nostra", [False] * 10 + [True] * 10)
    for seed in (0, 1):
        shutil.copytree(tmp_path / "both" / f"s{seed}", tmp_path / f"alone{seed}" / f"s{seed}")
        write_report(tmp_path / f"alone{seed}", tmp_path / f"report{seed}", target_demos=10)
    write_report(tmp_path / "both", tmp_path / "together", target_demos=10)
    text = write_pooled([tmp_path / "report0", tmp_path / "report1"], tmp_path / "pooled")

    key = ["seed", "table", "a_setting", "a", "b_setting", "b"]
    want = pd.read_csv(tmp_path / "together" / "paired.csv", dtype={"seed": str}).set_index(key).sort_index()
    got = pd.read_csv(tmp_path / "pooled" / "paired.csv", dtype={"seed": str}).set_index(key).sort_index()
    assert set(got.index) <= set(want.index)
    assert ("pooled", "Table 4", "finetune-n10", "nostra", "finetune-n10", "rssm") in got.index
    # seed 1 has no cotrain-all run: the records' report pools seed 0 alone there, the pool leaves it out
    assert ("pooled", "Table 5", "cotrain-all", "nostra", "cotrain-target_only", "nostra") not in got.index
    exact = ["n", "rate_a", "rate_b", "diff", "a_only", "b_only", "p"]
    pd.testing.assert_frame_equal(got[exact], want.loc[got.index, exact], check_dtype=False)
    s = pd.read_csv(tmp_path / "pooled" / "success.csv", dtype={"seed": str}).set_index(["seed", "setting", "variant"])
    assert s.loc[("pooled", "finetune-n10", "nostra"), "k"] == 28 and ("pooled", "cotrain-all", "nostra") not in s.index
    assert "## Claims (pooled)" in text and (tmp_path / "pooled" / "transfer.png").is_file()


def test_a_seed_split_over_two_reports_pools_once_per_cell(tmp_path):
    """Seed 1's Table 4 from one sitting and its Table 5 from another pool with seed 0; a cell of a seed in two
    reports is refused, unless --seeds leaves that seed out."""
    import shutil

    import pandas as pd

    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "ev0")
    write_report(tmp_path / "ev0", tmp_path / "report0", target_demos=10)
    _write(tmp_path / "ev4", 1, "finetune-n10", "nostra", [True] * 12 + [False] * 8)
    _write(tmp_path / "ev4", 1, "finetune-n10", "rssm", [True] * 14 + [False] * 6)
    write_report(tmp_path / "ev4", tmp_path / "table4", target_demos=10)
    _write(tmp_path / "ev5", 1, "cotrain-target_only", "nostra", [False] * 10 + [True] * 10)
    _write(tmp_path / "ev5", 2, "finetune-n10", "nostra", [True] * 20)  # a third seed, in this report only
    _write(tmp_path / "ev5", 2, "finetune-n10", "rssm", [True] * 20)
    write_report(tmp_path / "ev5", tmp_path / "table5", target_demos=10)
    write_pooled([tmp_path / "report0", tmp_path / "table4", tmp_path / "table5"], tmp_path / "pooled")
    pairs = pd.read_csv(tmp_path / "pooled" / "paired.csv", dtype={"seed": str})
    pooled = pairs[pairs.seed == "pooled"].set_index(["a_setting", "a", "b_setting", "b"])
    r = pooled.loc[("finetune-n10", "nostra", "finetune-n10", "rssm")]  # seeds 0, 1 and 2: 60 episodes
    assert r.n == 60 and r.a_only == 16 + 0 + 0 and r.b_only == 0 + 2 + 0
    # seed 1's fine-tuned and from-scratch runs sit in different reports: no pair, so no pool of it
    assert ("finetune-n10", "nostra", "cotrain-target_only", "nostra") not in pooled.index

    shutil.copytree(tmp_path / "table5", tmp_path / "table5-again")
    with pytest.raises(ValueError, match="training seed 1's cell cotrain-target_only / nostra is in both"):
        write_pooled([tmp_path / "table5", tmp_path / "table5-again"], tmp_path / "out")
    with pytest.raises(ValueError, match="training seed 2's cell finetune-n10 / nostra is in both"):
        write_pooled([tmp_path / "report0", tmp_path / "table5", tmp_path / "table5-again"], tmp_path / "out",
                     only=["0", "2"])
    write_pooled([tmp_path / "report0", tmp_path / "table4", tmp_path / "table5"], tmp_path / "out", only=["0", "1"])
    s = pd.read_csv(tmp_path / "out" / "success.csv", dtype={"seed": str})
    assert set(s.seed) == {"0", "1", "pooled"}
    with pytest.raises(ValueError, match="training seed.s. 7 in none of the reports; they hold 0, 1, 2"):
        write_pooled([tmp_path / "report0", tmp_path / "table4", tmp_path / "table5"], tmp_path / "out", only=["7"])


def test_pooling_refuses_reports_of_two_kinds(tmp_path):
    from nostra.workflows.claims_pool import write_pooled

    _scenario(tmp_path / "ev")
    write_report(tmp_path / "ev", tmp_path / "transfer")
    (tmp_path / "claims").mkdir()
    (tmp_path / "claims" / "table1.csv").write_text("checkpoint,seed,variant,noise,k,n\n")
    with pytest.raises(ValueError, match=r"different kinds: .*transfer \(transfer\), .*claims \(claims\)"):
        write_pooled([tmp_path / "transfer", tmp_path / "claims"], tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="neither table1.csv"):
        write_pooled([tmp_path / "transfer", tmp_path / "ev"], tmp_path / "out")


def test_a_later_baseline_pairs_with_cells_whose_records_are_gone(tmp_path):
    """episodes.csv keeps every outcome: a run evaluated later, on a disk without the earlier records,
    pairs with them as if they were on disk, and a record wins over an earlier episode."""
    import shutil

    import pandas as pd

    _scenario(tmp_path / "all")
    write_report(tmp_path / "all", tmp_path / "together", target_demos=10)
    shutil.copytree(tmp_path / "all", tmp_path / "first")  # the earlier sitting: every cell but BC-RSSM's at 10 demos
    for f in (tmp_path / "first" / "s0" / "finetune-n10").glob("**/rssm_seed*.npz"):
        f.unlink()
    write_report(tmp_path / "first", tmp_path / "early", target_demos=10)
    later = tmp_path / "later"  # a new disk: the baseline's records alone, plus one record that overrides
    _write(later, 0, "finetune-n10", "rssm", [False] * 20)
    _write(later, 0, "cotrain-all", "nostra", [False], folder="again")  # episode 1000 again: the record wins
    write_report(later, tmp_path / "joined", target_demos=10, earlier=[tmp_path / "early" / "episodes.csv"])

    key = ["seed", "table", "a_setting", "a", "b_setting", "b"]
    want = pd.read_csv(tmp_path / "together" / "paired.csv", dtype={"seed": str}).set_index(key)
    got = pd.read_csv(tmp_path / "joined" / "paired.csv", dtype={"seed": str}).set_index(key)
    row = ("0", "Table 4", "finetune-n10", "nostra", "finetune-n10", "rssm")
    assert row in got.index and got.loc[row, "a_only"] == 16
    pd.testing.assert_series_equal(got.loc[row], want.loc[row])
    ep = pd.read_csv(tmp_path / "joined" / "episodes.csv")
    cell = ep[(ep.setting == "cotrain-all") & (ep.variant == "nostra")]
    assert len(cell) == 20 and not cell[cell.episode == 1000].success.iloc[0] and cell.success.sum() == 19


def test_a_bad_episodes_file_names_the_file_and_what_is_wrong(tmp_path):
    _scenario(tmp_path / "ev")
    bad = tmp_path / "episodes.csv"
    bad.write_text("seed,setting,variant,success\n0,finetune-n10,nostra,True\n")
    with pytest.raises(ValueError, match=r"episodes.csv: missing column\(s\) episode; expected seed, setting"):
        write_report(tmp_path / "ev", tmp_path / "out", earlier=[bad])
    bad.write_text("seed,setting,variant,episode,success\n0,finetune-10,nostra,1000,True\n")
    with pytest.raises(ValueError, match=r"episodes.csv: transfer setting folder 'finetune-10'"):
        write_report(tmp_path / "ev", tmp_path / "out", earlier=[bad])
    with pytest.raises(FileNotFoundError, match="nope.csv: no such episodes file"):
        write_report(tmp_path / "ev", tmp_path / "out", earlier=[tmp_path / "nope.csv"])
    assert not (tmp_path / "out").exists()  # nothing written for a refused input


def test_the_command_refuses_a_bad_episodes_file_before_logging_itself(tmp_path):
    from nostra.workflows.transfer_report import main

    _scenario(tmp_path / "ev")
    with pytest.raises(FileNotFoundError, match="nope.csv"):
        main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "out"), "--command", "x",
              "--episodes", str(tmp_path / "nope.csv")])
    assert not (tmp_path / "out").exists()  # no commands.jsonl entry for a run that did not happen


def test_seeds_keeps_only_the_chosen_training_seeds(tmp_path):
    """A seed reported apart from a sibling whose records sit on the same disk: its pooled tables are its own."""
    import pandas as pd

    from nostra.workflows.transfer_report import main

    _scenario(tmp_path / "ev")
    _write(tmp_path / "ev", 1, "cotrain-target_only", "nostra", [False] * 20)  # another seed on this disk
    write_report(tmp_path / "ev", tmp_path / "both", target_demos=10)
    assert "## Training seed 1" in (tmp_path / "both" / "transfer.md").read_text()
    report = write_report(tmp_path / "ev", tmp_path / "s0", target_demos=10, seeds=[0])
    assert "## Training seed 1" not in report and "## Training seed pooled" not in report
    ep = pd.read_csv(tmp_path / "s0" / "episodes.csv")
    assert set(ep.seed) == {0} and len(ep) == 20 * 8
    with pytest.raises(FileNotFoundError, match=r"no episodes of training seeds \[2\] under .*ev/s<seed>"):
        main(["--evaluations", str(tmp_path / "ev"), "--out", str(tmp_path / "s2"), "--command", "x", "--seeds", "2"])
    assert not (tmp_path / "s2").exists()  # refused before its command is logged beside the report
