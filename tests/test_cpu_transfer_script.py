"""scripts/cpu_transfer.sh (`make cpu-transfer`) run against stand-in `nostra` and `python` commands that
log their arguments: which runs Table 4 trains for the DEMOS it is given."""
from pathlib import Path

from script_stubs import run_stubbed


def run_script(tmp_path: Path, env: dict):
    return run_stubbed(tmp_path, "cpu_transfer.sh", {"TABLES": "4", "SEEDS": "1", "MODELS": "nostra", **env})


def test_demos_names_table_4s_columns_not_the_training_collections_size(tmp_path):
    # DEMOS is also cpu_setup.sh's collection size (refused at or under 200): the script must not pass it on
    r, calls = run_script(tmp_path, {"DEMOS": "10 20"})
    assert r.returncode == 0, r.stderr
    finetunes = [c for c in calls if "train.stage=finetune" in c]
    assert [c.split("train.num_demos=")[1].split()[0] for c in finetunes] == ["10", "20"]
    assert all(" paths.runs=data/runs/cpu " in c for c in finetunes)  # the profile's study, not cpu-d<n>
    report = [c for c in calls if "transfer_report" in c]
    assert len(report) == 1 and 'DEMOS="10 20"' in report[0]


def test_the_default_columns_are_10_and_20_demos(tmp_path):
    r, calls = run_script(tmp_path, {"DEMOS": ""})
    assert r.returncode == 0, r.stderr
    assert sum("train.num_demos=" in c and "finetune" in c for c in calls) == 2


def test_settings_picks_table_5s_columns(tmp_path):
    r, calls = run_script(tmp_path, {"TABLES": "5", "COTRAIN_MODELS": "rssm nostra",
                                     "SETTINGS": "target_only obj_skill"})
    assert r.returncode == 0, r.stderr
    runs = [c.split("train.run_name=")[1].split()[0] for c in calls if "train.run_name=" in c]
    assert runs == ["cotrain-rssm-LiftD1-target_only-s1", "cotrain-nostra-LiftD1-target_only-s1",
                    "cotrain-rssm-LiftD1-obj_skill-s1", "cotrain-nostra-LiftD1-obj_skill-s1"]
    retrieved = [c.split("retrieval.mode=")[1].split()[0] for c in calls if "retrieval.mode=" in c]
    assert retrieved == ["obj_skill"]  # no manifest for a column that does not run
    assert 'SETTINGS="target_only obj_skill"' in [c for c in calls if "transfer_report" in c][0]


def test_an_unknown_setting_is_refused_by_name_before_any_work(tmp_path):
    r, calls = run_script(tmp_path, {"TABLES": "5", "SETTINGS": "target_only obj-skill"})
    assert r.returncode == 2
    assert "obj-skill" in r.stderr and "target_only obj_skill all" in r.stderr
    assert not [c for c in calls if c.startswith("nostra ")]


def test_episodes_reach_the_report_and_its_command(tmp_path):
    r, calls = run_script(tmp_path, {"TABLES": "5", "SETTINGS": "target_only",
                                     "EPISODES": "reports/a/episodes.csv reports/b/episodes.csv"})
    assert r.returncode == 0, r.stderr
    report = [c for c in calls if "transfer_report" in c][0]
    assert "--seeds 1 --episodes reports/a/episodes.csv reports/b/episodes.csv --command" in report  # SEEDS' only
    assert 'EPISODES="reports/a/episodes.csv reports/b/episodes.csv" make cpu-transfer' in report
    (tmp_path / "none").mkdir()
    _, calls = run_script(tmp_path / "none", {"TABLES": "5", "SETTINGS": "target_only"})  # none given: none passed
    assert "--episodes" not in [c for c in calls if "transfer_report" in c][0]
