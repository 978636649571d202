"""scripts/cpu_views.sh (Table 3's views) run against stand-in `nostra` and `python` commands that log their
arguments: where the report goes (OUT) and which earlier reports' runs it pools (EPISODES)."""
from pathlib import Path

from script_stubs import run_stubbed


def run_script(tmp_path: Path, env: dict):
    (tmp_path / "data/runs/cpu/offline/liftd1-views/b1e-4-s3").mkdir(parents=True)  # what the analyses write
    return run_stubbed(tmp_path, "cpu_views.sh", {"SEED": "3", "BETAS": "1e-4", "SPLITS": "held_out", **env})


def test_out_and_episodes_reach_the_report_and_its_logged_command(tmp_path):
    earlier = tmp_path / "views_episodes.csv"
    earlier.write_text("run,episode,steps,modality,kl_nats\n")
    r, calls = run_script(tmp_path, {"OUT": "reports/cpu/liftd1/views-s3", "EPISODES": str(earlier)})
    assert r.returncode == 0, r.stderr
    runs = [c.split("train.run_name=")[1].split()[0] for c in calls if "train.run_name=" in c]
    assert runs == ["views-nostra-LiftD1-b1e-4-s3", "views-nostra-LiftD1-b1e-4-s3-occluded"]
    report = [c for c in calls if "offline_report" in c]
    assert len(report) == 1 and "--out reports/cpu/liftd1/views-s3 " in report[0]
    assert f"--views-episodes {earlier} " in report[0]
    assert f'OUT=reports/cpu/liftd1/views-s3 EPISODES="{earlier}"' in report[0]


def test_the_default_report_folder_is_the_tasks_views(tmp_path):
    r, calls = run_script(tmp_path, {})
    assert r.returncode == 0, r.stderr
    report = [c for c in calls if "offline_report" in c][0]
    assert "--out reports/cpu/liftd1/views " in report and "--views-episodes" not in report


def test_a_missing_episodes_file_is_refused_by_name_before_any_work(tmp_path):
    r, calls = run_script(tmp_path, {"EPISODES": "reports/gone/views_episodes.csv"})
    assert r.returncode == 2 and "EPISODES: no such file reports/gone/views_episodes.csv" in r.stderr
    assert calls == []
