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
