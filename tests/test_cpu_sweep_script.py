"""scripts/cpu_sweep.sh (NOSTRA's beta / gamma sensitivity) run against stand-in `nostra` and `python`
commands that log their arguments: a training seed's own cells, where its report goes (OUT), and the
paper's setting trained with make cpu's command when its run is missing."""
from pathlib import Path

from script_stubs import run_stubbed


def run_script(tmp_path: Path, env: dict):
    (tmp_path / "data/raw").mkdir(parents=True)
    (tmp_path / "data/raw/liftd1_cpu.hdf5").write_text("")  # the demos: generated before
    (tmp_path / "data/store.zarr/liftd1_cpu").mkdir(parents=True)
    return run_stubbed(tmp_path, "cpu_sweep.sh", {"SEED": "2", "BETAS": "1e-2", "GAMMAS": " ", **env})


def test_a_second_seed_gets_its_own_cells_and_report(tmp_path):
    r, calls = run_script(tmp_path, {"OUT": "reports/cpu/liftd1/sweep-s2"})
    assert r.returncode == 0, r.stderr
    evaluations = [c for c in calls if c.startswith("nostra evaluate")]
    assert len(evaluations) == 6  # two settings x (none, mask, offline)
    assert all("evaluate.out_dir=data/runs/cpu/evaluate/liftd1-sweep-s2/" in c
               or "evaluate.out_dir=data/runs/cpu/offline/liftd1-sweep-s2/" in c for c in evaluations)
    report = [c for c in calls if "sweep_report" in c]
    assert len(report) == 1 and "--out reports/cpu/liftd1/sweep-s2 " in report[0]
    assert "--evaluations data/runs/cpu/evaluate/liftd1-sweep-s2 " in report[0]
    assert "OUT=reports/cpu/liftd1/sweep-s2 bash scripts/cpu_sweep.sh" in report[0]


def test_the_papers_setting_is_trained_with_make_cpus_command_only_when_missing(tmp_path):
    r, calls = run_script(tmp_path, {})
    assert r.returncode == 0, r.stderr
    trains = [c for c in calls if c.startswith("nostra train")]
    assert len(trains) == 1 and "seed=2" in trains[0] and "train.max_minutes=30" in trains[0]
    assert "train.run_name" not in trains[0]  # make cpu's name: pretrain-nostra-<task>-s<seed>
    sweep = [c for c in calls if c.startswith("nostra sweep")]
    assert len(sweep) == 1 and "model.loss={beta:1e-2}" in sweep[0]
    assert "--out reports/cpu/liftd1/sweep " in [c for c in calls if "sweep_report" in c][0]



def test_a_finished_papers_run_is_kept(tmp_path):
    run = tmp_path / "data/runs/cpu/train/pretrain-nostra-LiftD1-s2"
    run.mkdir(parents=True)
    (run / "run.json").write_text("{}")
    r, calls = run_script(tmp_path, {})
    assert r.returncode == 0, r.stderr
    assert not [c for c in calls if c.startswith("nostra train")]
    assert len([c for c in calls if c.startswith("nostra sweep")]) == 1
