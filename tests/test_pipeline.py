"""The dvc pipeline end to end on the micro `ci` profile, in a git checkout of the tracked files:
`dvc repro` runs every stage, writes the report and leaves `git status` clean; a second `dvc repro`
with nothing changed does nothing; a changed parameter marks exactly the stages that read it."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
BIN = str(Path(sys.executable).parent)
pytestmark = [pytest.mark.sim, pytest.mark.slow]


def _dvc(cwd, *args, timeout=1500):
    env = {**os.environ, "PATH": f"{BIN}:{os.environ['PATH']}", "MLFLOW_TRACKING_URI": ""}
    return subprocess.run([f"{BIN}/dvc", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    for d in ("nostra", "retrieval", "pipeline", "conf"):
        shutil.copytree(ROOT / d, root / d, ignore=shutil.ignore_patterns("__pycache__"))
    for f in ("dvc.yaml", ".gitignore", ".dvcignore", ".dvc/config", ".dvc/.gitignore"):
        (root / f).parent.mkdir(exist_ok=True)
        shutil.copy(ROOT / f, root / f)
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    params.update(profile="ci", num_demos=2, budget=2, library_demos={"lift": 3, "stack": 2, "pickplacecan": 2})
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    _git(root, "init", "-q")
    _git(root, "add", "-A")
    _git(root, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "tracked files")
    return root


def _git(cwd, *args) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout


# ~30 stage processes, each paying ~8 s of imports (lightning pulls torchmetrics and transformers):
# ~11 min on the 2-core machine, over the suite's default per-test limit
@pytest.mark.timeout(1500)
def test_repro_then_nothing_then_only_what_changed(project):
    first = _dvc(project, "repro")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    index = (project / "reports/ci/index.md").read_text()
    assert "Table 1" in index and "Table 5" in index
    assert (project / "data/runs/evaluate/robustness/success.md").is_file()
    assert (project / "data/runs/manifests/all.json").is_file()
    assert _git(project, "status", "--porcelain") == "", "dvc repro left files git would track"

    again = _dvc(project, "repro")
    assert again.returncode == 0 and "Running stage" not in again.stdout, again.stdout[-2000:]

    params = yaml.safe_load((project / "params.yaml").read_text())
    (project / "params.yaml").write_text(yaml.safe_dump({**params, "budget": 3}))
    status = _dvc(project, "status").stdout
    changed = {line.rstrip(":").strip() for line in status.splitlines() if line.endswith(":")
               and not line.startswith("\t")}
    assert changed == {"retrieve@obj_skill", "retrieve@all"}, status
