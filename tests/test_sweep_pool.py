"""nostra.workflows.sweep_pool: beta / gamma sweep reports of several training seeds pooled exactly from
their success cells and paired 2x2 tables; bad input refused by name."""
from pathlib import Path

import pandas as pd
import pytest

from nostra.workflows import sweep_pool
from nostra.workflows.sweep_report import CELLS


def sweep_report(folder: Path, settings: dict, pairs: list[dict]) -> Path:
    """A sweep report's two CSV files: settings maps (beta, gamma) to (rate of every cell, KL total)."""
    folder.mkdir(parents=True)
    rows = []
    for (beta, gamma), (rate, kl) in settings.items():
        row = {"setting": f"b{beta}_g{gamma}", "beta": beta, "gamma": gamma, "kl total": kl}
        for noise, v in CELLS:
            row |= {f"{v} {noise}": rate, f"{v} {noise} n": 50}
        rows.append(row)
    pd.DataFrame(rows).to_csv(folder / "sweep.csv", index=False)
    pd.DataFrame(pairs).to_csv(folder / "paired.csv", index=False)
    return folder


def pair(beta, a_only, b_only, rate_a=0.8):
    return {"beta": beta, "gamma": 0.1, "comparison": "BC-NOSTRA, none: this setting - the paper's", "n": 50,
            "rate_a": rate_a, "a_only": a_only, "b_only": b_only}


def test_pooled_cells_and_pairs_add_the_seeds_tables(tmp_path):
    s0 = sweep_report(tmp_path / "s0", {(1e-4, 0.1): (0.9, 110.0), (1e-2, 0.1): (0.8, 25.0), (1e-5, 0.1): (0.9, 140.0)},
                      [pair(1e-2, 1, 6), pair(1e-5, 0, 1)])
    s2 = sweep_report(tmp_path / "s2", {(1e-4, 0.1): (0.96, 100.0), (1e-2, 0.1): (0.7, 35.0)},
                      [pair(1e-2, 2, 8, rate_a=0.7)])
    text = sweep_pool.write_pooled([s0, s2], ["0", "2"], tmp_path / "out")
    cells = pd.read_csv(tmp_path / "out/success.csv", dtype={"seed": str})
    pooled = cells[(cells.seed == "pooled") & (cells.beta == 1e-2) & (cells.noise == "none")]
    assert pooled.k.item() == 40 + 35 and pooled.n.item() == 100 and pooled.kl_total.item() == 30.0
    assert not ((cells.seed == "pooled") & (cells.beta == 1e-5)).any()  # seed 2 never ran 1e-5
    pairs = pd.read_csv(tmp_path / "out/paired.csv", dtype={"seed": str})
    p = pairs[(pairs.seed == "pooled") & (pairs.beta == 1e-2)].iloc[0]
    assert (p.n, p.a_only, p.b_only) == (100, 3, 14) and p["diff"] == pytest.approx(-0.11) and p.p < 0.05
    assert not ((pairs.seed == "pooled") & (pairs.beta == 1e-5)).any()
    assert "| 0.01 | 0.1 | BC-NOSTRA, none: this setting - the paper's | pooled | 100 | -11 [" in text
    assert (tmp_path / "out/sweep_pooled.png").stat().st_size > 0 and "(sweep_pooled.png)" in text


def test_seeds_must_name_each_report_once(tmp_path):
    s0 = sweep_report(tmp_path / "s0", {(1e-4, 0.1): (0.9, 110.0)}, [pair(1e-4, 0, 0)])
    s2 = sweep_report(tmp_path / "s2", {(1e-4, 0.1): (0.9, 110.0)}, [pair(1e-4, 0, 0)])
    with pytest.raises(ValueError, match="1 training seed"):
        sweep_pool.write_pooled([s0, s2], ["0"], tmp_path / "out")
    with pytest.raises(ValueError, match="a training seed twice"):
        sweep_pool.write_pooled([s0, s2], ["0", "0"], tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_report_without_a_column_is_refused_by_file_and_column(tmp_path):
    s0 = sweep_report(tmp_path / "s0", {(1e-4, 0.1): (0.9, 110.0)}, [pair(1e-4, 0, 0)])
    s2 = sweep_report(tmp_path / "s2", {(1e-4, 0.1): (0.9, 110.0)}, [pair(1e-4, 0, 0)])
    pd.read_csv(s2 / "paired.csv").drop(columns="b_only").to_csv(s2 / "paired.csv", index=False)
    with pytest.raises(ValueError, match=r"s2/paired.csv: missing column\(s\) b_only"):
        sweep_pool.write_pooled([s0, s2], ["0", "2"], tmp_path / "out")
    (s2 / "sweep.csv").unlink()
    with pytest.raises(FileNotFoundError, match="s2/sweep.csv: missing"):
        sweep_pool.write_pooled([s0, s2], ["0", "2"], tmp_path / "out")
    assert not (tmp_path / "out").exists()
