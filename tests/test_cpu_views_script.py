"""scripts/cpu_views.sh (Table 3's views) run against stand-in `nostra` and `python` commands that log their
arguments: where the report goes (OUT) and which earlier reports' runs it pools (EPISODES)."""
import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUB = """#!/usr/bin/env bash
echo "$(basename "$0") $*" >> "$(dirname "$0")/../../calls.log"
case "$*" in *get_task*) echo LiftD1 ;; esac
"""


def run_script(tmp_path: Path, env: dict) -> tuple[subprocess.CompletedProcess, list[str]]:
    (tmp_path / "scripts").mkdir()
    for name in ("cpu_views.sh", "cpu_setup.sh"):
        shutil.copy(ROOT / "scripts" / name, tmp_path / "scripts" / name)
    bin_dir = tmp_path / ".venv/bin"
    bin_dir.mkdir(parents=True)
    for name in ("nostra", "python"):
        (bin_dir / name).write_text(STUB)
        (bin_dir / name).chmod(0o755)
    (tmp_path / "data/runs/cpu/offline/liftd1-views/b1e-4-s3").mkdir(parents=True)  # what the analyses write
    r = subprocess.run(["bash", "scripts/cpu_views.sh"], cwd=tmp_path, capture_output=True, text=True,
                       env={**os.environ, "SEED": "3", "BETAS": "1e-4", "SPLITS": "held_out", **env})
    log = tmp_path / "calls.log"
    return r, log.read_text().splitlines() if log.exists() else []


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
