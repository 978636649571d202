"""Reports come from MLflow alone: logged success and KL metrics land in the right cells, the
newest run wins, and missing runs show as a dash with the reason instead of a crash."""

import pandas as pd
import pytest

from nostra.workflows.report import write_report
from nostra.workflows.tracking import Tracker


@pytest.fixture(autouse=True)
def _cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


def _log(name, params, metrics, tmp_path):
    t = Tracker("rep", name, tmp_path / name, params)
    t.log_metrics(metrics)
    t.finish()


def test_tables_from_mlflow(tmp_path):
    _log("evaluate-old", {"table": "robustness"}, {"success/Lift/mask/nostra_mli": 0.1}, tmp_path)
    _log("evaluate", {"table": "robustness"}, {"success/Lift/none/nostra": 1.0, "success/Lift/mask/nostra": 0.25,
                                               "success/Lift/mask/nostra_mli": 0.75}, tmp_path)
    for setting, v in (("target_only", 0.4), ("obj_skill", 0.5), ("all", 0.7)):
        _log("evaluate-co", {"table": "cotrain", "setting": setting}, {"success/Lift/none/nostra": v}, tmp_path)
    _log("offline-Lift", {"setting": "good view"}, {"kl_nats/agentview_image": 3.0, "kl_nats/robot0_eef_pos": 0.5},
         tmp_path)
    index = write_report(tmp_path / "report", "rep")
    t1 = pd.read_csv(tmp_path / "report/table1_robustness.csv").set_index("Method")
    assert t1.loc["BC-NOSTRA", "Lift none"] == "100" and t1.loc["BC-NOSTRA", "Lift mask"] == "25"
    assert t1.loc["BC-NOSTRA + MLI", "Lift mask"] == "75"  # the newer run wins
    assert t1.loc["BC-LSTM", "Lift mask"] == "–"
    t1_md = (tmp_path / "report/table1_robustness.md").read_text()
    assert "no evaluation run logged" in t1_md and "Lift/mask/lstm" in t1_md
    t5 = pd.read_csv(tmp_path / "report/table5_cotrain.csv").set_index("Method")
    assert t5.loc["BC-NOSTRA", "Lift all"] == "70 (+30)" and t5.loc["BC-NOSTRA", "Lift target_only"] == "40"
    t3 = pd.read_csv(tmp_path / "report/table3_kl.csv").set_index("Input")
    assert t3.loc["agentview_image", "good view"] == 3.0 and t3.loc["Total", "good view"] == 3.5
    text = index.read_text()
    assert "Table 4" in text and "no evaluation run with params.table=finetune" in text


def test_empty_experiment_gives_dashes(tmp_path):
    index = write_report(tmp_path / "r", "nothing-here")
    assert "0 runs" in index.read_text()
    assert (tmp_path / "r/table2_adamli.md").read_text().count("–") > 5


def test_peak_and_final_checkpoints_get_their_own_tables(tmp_path):
    _log("evaluate-last", {"table": "robustness"}, {"success/Lift/none/lstm": 0.6}, tmp_path)
    _log("evaluate-best", {"table": "robustness", "checkpoint": "best"}, {"success/Lift/none/lstm": 0.9}, tmp_path)
    write_report(tmp_path / "report", "rep")
    final = pd.read_csv(tmp_path / "report/table1_robustness.csv").set_index("Method")
    peak = pd.read_csv(tmp_path / "report/table1_robustness_best.csv").set_index("Method")
    assert final.loc["BC-LSTM", "Lift none"] == "60" and peak.loc["BC-LSTM", "Lift none"] == "90"
    assert "peak over checkpoints" in (tmp_path / "report/table1_robustness_best.md").read_text()
    assert "final checkpoint" in (tmp_path / "report/table1_robustness.md").read_text()
