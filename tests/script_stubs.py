"""Run a scripts/*.sh study against stand-in `nostra` and `python` commands that log their arguments
(calls.log) and print LiftD1 for the task-name lookup (and three phases for the experts' phase list): what the
script would run, without running it."""
import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUB = """#!/usr/bin/env bash
echo "$(basename "$0") $*" >> "$(dirname "$0")/../../calls.log"
case "$*" in *get_task*) echo LiftD1 ;; *PHASES*) echo approach descend grasp ;; esac
"""


def run_stubbed(tmp_path: Path, script: str, env: dict, scripts: dict | None = None
                ) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run scripts/<script> (with cpu_setup.sh beside it) in ``tmp_path``: its result and the logged calls.
    ``scripts``: other scripts/<name> it calls, as stand-in text."""
    (tmp_path / "scripts").mkdir()
    for name in (script, "cpu_setup.sh"):
        shutil.copy(ROOT / "scripts" / name, tmp_path / "scripts" / name)
    for name, text in (scripts or {}).items():
        (tmp_path / "scripts" / name).write_text(text)
    bin_dir = tmp_path / ".venv/bin"
    bin_dir.mkdir(parents=True)
    for name in ("nostra", "python"):
        (bin_dir / name).write_text(STUB)
        (bin_dir / name).chmod(0o755)
    r = subprocess.run(["bash", f"scripts/{script}"], cwd=tmp_path, capture_output=True, text=True,
                       env={**os.environ, **env})
    log = tmp_path / "calls.log"
    return r, log.read_text().splitlines() if log.exists() else []
