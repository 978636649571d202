"""The `nostra` command: stages listed, each a Hydra app printing its resolved config; unknown
stages, keys and values fail with a clear message before any work."""

import subprocess
import sys
from pathlib import Path

from pipeline.cli import STAGES

NOSTRA = str(Path(sys.executable).with_name("nostra"))


def _run(*args, cwd=None):
    return subprocess.run([NOSTRA, *args], capture_output=True, text=True, timeout=300, cwd=cwd)


def test_help_lists_every_stage():
    out = _run("--help")
    assert out.returncode == 0
    for stage in STAGES:
        assert f"  {stage} " in out.stdout
    assert "not implemented" not in out.stdout


def test_unknown_stage():
    out = _run("trian")
    assert out.returncode == 2 and "unknown stage 'trian'" in out.stderr and "train" in out.stderr


def test_cfg_job_and_bad_overrides(tmp_path):
    out = _run("train", "--cfg", "job", "model=rssm", cwd=tmp_path)
    assert out.returncode == 0 and "policy: rssm" in out.stdout and "latent_dim: 40" in out.stdout
    bad_key = _run("train", "train.nonsense=1", cwd=tmp_path)
    assert bad_key.returncode != 0 and "nonsense" in bad_key.stderr
    bad_value = _run("train", "model=transformer", cwd=tmp_path)
    assert bad_value.returncode != 0 and "transformer" in bad_value.stderr and "nostra" in bad_value.stderr
    assert not (tmp_path / "data").exists()  # nothing was done
