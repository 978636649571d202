"""Sweeps against a real Slurm controller: scripts/slurm_local.sh brings up a single-node cluster
(slurmctld + slurmd + munge, partition `cpu`) on this machine, `nostra sweep launcher=slurm` submits a
job array through submitit, the jobs train under Slurm and report to one MLflow parent run, and a job
requeued mid-run resumes from its last checkpoint. Where Slurm cannot be installed or started, these
tests fail with the reason (they never skip)."""

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest

from fixtures import write_robomimic
from nostra.data.store import Store

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "slurm_local.sh"
NOSTRA = str(Path(sys.executable).with_name("nostra"))
TINY = ["data.store=store.zarr", "data.collections=[t]", "data.batch_size=2", "data.seq_len=4", "data.workers=0",
        "data.obs_keys=[agentview_image,robot0_eef_pos]"]
SLURM = ["launcher=slurm", "launcher.partition=cpu", "launcher.gpus=0", "launcher.cpus_per_task=1",
         "launcher.mem_gb=2", "launcher.time_min=20"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A private single-node cluster (own state directory and ports, so a cluster someone started
    with the script's defaults is left alone); the environment that talks to it."""
    state = tmp_path_factory.mktemp("slurm")
    env = {**os.environ, "NOSTRA_SLURM_DIR": str(state), "NOSTRA_SLURM_PORT": os.environ.get("NOSTRA_TEST_SLURM_PORT",
                                                                                               "6917")}
    try:
        up = subprocess.run([str(SCRIPT), "start"], env=env, capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"scripts/slurm_local.sh start did not finish in {e.timeout} s: {e.stdout} {e.stderr}")
    if up.returncode != 0:
        logs = "".join(f"\n--- {p.name}\n{p.read_text()[-2000:]}" for p in sorted((state / "log").glob("*.log"))) \
            if (state / "log").is_dir() else ""
        subprocess.run([str(SCRIPT), "stop"], env=env, capture_output=True, timeout=120)
        pytest.fail(f"no Slurm cluster: scripts/slurm_local.sh start exited {up.returncode}\n{up.stdout}{up.stderr}{logs}")
    env.update(SLURM_CONF=str(state / "slurm.conf"), PATH=f"{state / 'bin'}:{env['PATH']}", MLFLOW_TRACKING_URI="",
               OMP_NUM_THREADS="1")
    try:
        yield env
    finally:
        down = subprocess.run([str(SCRIPT), "stop"], env=env, capture_output=True, text=True, timeout=120)
        assert down.returncode == 0, down.stdout + down.stderr


def _store(path: Path) -> None:
    Store(path / "store.zarr").ingest(write_robomimic(path / "t.hdf5", n=4, lengths=[10] * 4, image_size=40),
                                      name="t", progress=False)


def _slurm_jobs(env, array_id: str) -> dict[str, dict]:
    """The controller's record of each task of an array job: {"<array>_<task>": {field: value}}."""
    out = subprocess.run(["scontrol", "-o", "show", "job", array_id], env=env, capture_output=True, text=True,
                         check=True).stdout
    jobs = {}
    for line in out.splitlines():
        f = dict(kv.split("=", 1) for kv in line.split() if "=" in kv)
        jobs[f"{f['ArrayJobId']}_{f['ArrayTaskId']}"] = f
    return jobs


def _settled_jobs(env, array_id: str, timeout: float = 60) -> dict[str, dict]:
    """_slurm_jobs once no task is still running: a job writes its result (which ends the sweep)
    before its process exits, so the controller may mark it COMPLETED a moment after the sweep ends."""
    deadline = time.time() + timeout
    while True:
        jobs = _slurm_jobs(env, array_id)
        if time.time() > deadline or not {j["JobState"] for j in jobs.values()} & {"RUNNING", "COMPLETING"}:
            return jobs
        time.sleep(0.5)


def _children(tmp_path):
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = mlflow.search_runs(search_all_experiments=True)
    parent = runs[runs["tags.sweep"] == "true"]
    assert len(parent) == 1, parent
    return runs[runs["tags.mlflow.parentRunId"] == parent["run_id"].iloc[0]]


def test_sweep_runs_as_a_slurm_job_array(cluster, tmp_path):
    _store(tmp_path)
    extra = ["launcher.setup=['echo nostra setup ran']", "+launcher.additional_parameters={comment:nostra-sweep}"]
    cmd = [NOSTRA, "sweep", *SLURM, *extra, *TINY, "train.max_steps=2", "model=nostra,lstm"]
    done = subprocess.run(cmd, cwd=tmp_path, env=cluster, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]

    sweep = next((tmp_path / "data/runs/sweeps").iterdir())
    jobs = sorted(sweep.glob("[0-9]"))
    assert [j.name for j in jobs] == ["0", "1"] and all((j / "policy.ckpt").is_file() for j in jobs)
    assert all((j / "checkpoints" / "last.ckpt").is_file() for j in jobs)

    # one array job of two tasks, asked for the cpu partition and no GPU
    script = next((sweep / ".submitit").glob(".submission_file_*.sh")).read_text()
    assert "#SBATCH --array=0-1%2" in script and "#SBATCH --partition=cpu" in script
    assert "gpus" not in script and "gres" not in script and "#SBATCH --ntasks-per-node=1" in script
    assert "#SBATCH --comment=nostra-sweep" in script and "\necho nostra setup ran\n" in script
    folders = sorted(p.name for p in (sweep / ".submitit").iterdir() if re.fullmatch(r"\d+_\d+", p.name))
    array = folders[0].split("_")[0]
    assert folders == [f"{array}_0", f"{array}_1"], folders

    # the controller ran both tasks to completion on this node, in partition cpu
    records = _settled_jobs(cluster, array)
    assert sorted(records) == folders
    for rec in records.values():
        assert (rec["JobState"], rec["ExitCode"], rec["Partition"]) == ("COMPLETED", "0:0", "cpu"), rec
        assert rec["NodeList"] == os.uname().nodename.split(".")[0] and rec["Comment"] == "nostra-sweep", rec
    jobcomp = (Path(cluster["NOSTRA_SLURM_DIR"]) / "log" / "jobcomp.log").read_text()
    assert len(re.findall(rf"JobState=COMPLETED .*ArrayJobId={array} ArrayTaskId=[01] ", jobcomp)) == 2

    # inside each job: submitit's Slurm job environment, training on the CPU, a finished run
    for name in folders:
        log = (sweep / ".submitit" / name / f"{name}_0_log.out").read_text()
        assert log.startswith("nostra setup ran\n"), log  # the batch script's setup lines, before srun
        assert f"Starting with JobEnvironment(job_id={name}" in log and "Job completed successfully" in log, log
        err = (sweep / ".submitit" / name / f"{name}_0_log.err").read_text()
        assert "GPU available: False, used: False" in err and "max_steps=2` reached" in err, err

    children = _children(tmp_path)
    assert sorted(children["params.model"]) == ["lstm", "nostra"]
    assert set(children["status"]) == {"FINISHED"}


def test_requeued_job_resumes_from_its_last_checkpoint(cluster, tmp_path):
    """Job 0 of a two-seed sweep is requeued (`scontrol requeue`) once it has a checkpoint: it restarts,
    resumes from checkpoints/last.ckpt and ends at the same step as job 1, which ran uninterrupted."""
    _store(tmp_path)
    steps = 40
    cmd = [NOSTRA, "sweep", *SLURM, *TINY, "model=lstm", "model.net.rnn_hidden=64", "model.net.decoder_hidden=[64,64]",
           f"train.max_steps={steps}", "train.val_every=4", "seed=0,1"]  # last.ckpt every 4 steps
    log = open(tmp_path / "sweep.log", "w")
    sweep_proc = subprocess.Popen(cmd, cwd=tmp_path, env=cluster, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 300
        last = None
        while time.time() < deadline and sweep_proc.poll() is None:
            found = list((tmp_path / "data/runs/sweeps").glob("*/0/checkpoints/last.ckpt"))
            if found:
                last = found[0]
                break
            time.sleep(0.1)
        assert last is not None, f"job 0 wrote no checkpoint: {(tmp_path / 'sweep.log').read_text()[-3000:]}"
        sweep = last.parents[2]
        task0 = next(p.name for p in (sweep / ".submitit").iterdir() if re.fullmatch(r"\d+_0", p.name))
        subprocess.run(["scontrol", "requeue", task0], env=cluster, check=True, timeout=60)
        # Slurm holds a requeued job ~2 minutes (BeginTime) before it may start again; release it now
        for _ in range(100):
            rec = _slurm_jobs(cluster, task0)[task0]
            if rec["JobState"] == "PENDING":
                break
            time.sleep(0.2)
        subprocess.run(["scontrol", "update", f"jobid={task0}", "StartTime=now"], env=cluster, check=True, timeout=60)
        sweep_proc.wait(timeout=300)
    finally:
        if sweep_proc.poll() is None:
            sweep_proc.kill()
        log.close()
    assert sweep_proc.returncode == 0, (tmp_path / "sweep.log").read_text()[-3000:]

    array = task0.split("_")[0]
    records = _settled_jobs(cluster, array)
    assert records[task0]["Restarts"] == "1" and records[f"{array}_1"]["Restarts"] == "0", records
    assert {r["JobState"] for r in records.values()} == {"COMPLETED"}, records
    out = (sweep / ".submitit" / task0 / f"{task0}_0_log.out").read_text()
    err = (sweep / ".submitit" / task0 / f"{task0}_0_log.err").read_text()
    assert "DUE TO JOB REQUEUE" in err, err
    first, second = out.split(f"Starting with JobEnvironment(job_id={task0}")[1:]  # two attempts, one log
    assert "Job completed" not in first and "Job completed successfully" in second, out
    assert f"resuming from {sweep.relative_to(tmp_path)}/0/checkpoints/last.ckpt" in out, out
    ran = [json.loads((sweep / str(i) / "run.json").read_text())["steps"] for i in (0, 1)]
    assert ran == [steps, steps]
    uninterrupted = (sweep / ".submitit" / f"{array}_1" / f"{array}_1_0_log.out").read_text()
    assert "resuming from" not in uninterrupted

    # MLflow: the interrupted attempt is its own (failed) child run; each job has one finished run
    children = _children(tmp_path)
    finished = children[children["status"] == "FINISHED"]
    assert sorted(finished["params.seed"]) == ["0", "1"]
    assert sorted(children[children["status"] != "FINISHED"]["params.seed"]) == ["0"]
