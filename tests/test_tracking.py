"""Tracking against a real MLflow server on localhost (MLFLOW_TRACKING_URI), and the local copy
that keeps every metric when the backend goes away mid-run."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from nostra.workflows.tracking import Tracker, search_runs, tracking_uri


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def server(tmp_path):
    port = _free_port()
    mlflow = str(Path(sys.executable).with_name("mlflow"))
    proc = subprocess.Popen([mlflow, "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
                             "--backend-store-uri", f"sqlite:///{tmp_path / 'server.db'}",
                             "--default-artifact-root", str(tmp_path / "artifacts")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    for _ in range(120):
        try:
            urllib.request.urlopen(f"{url}/health", timeout=1)
            break
        except OSError:
            time.sleep(0.5)
    else:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("mlflow server did not start")
    yield url, proc
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_logs_to_a_server_then_survives_its_death(server, tmp_path, monkeypatch):
    url, proc = server
    monkeypatch.setenv("MLFLOW_TRACKING_URI", url)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "15")  # a loaded machine answers slowly; a dead server is refused at once
    assert tracking_uri() == url
    t = Tracker("srv", "run", tmp_path / "run", {"model": "nostra"})
    t.log_metrics({"train/loss": 1.5}, step=1)
    runs = search_runs("srv")
    assert runs["metrics.train/loss"].tolist() == [1.5] and runs["params.model"].tolist() == ["nostra"]

    os.killpg(proc.pid, signal.SIGKILL)  # the backend dies mid-run
    proc.wait()
    t.log_metrics({"train/loss": 0.5}, step=2)
    summary = t.finish()
    assert "MLflow tracking failed" in summary and str(tmp_path / "run" / "metrics.jsonl") in summary
    local = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert [r["metrics"]["train/loss"] for r in local if "metrics" in r] == [1.5, 0.5]


def test_default_is_an_embedded_sqlite_file(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert tracking_uri() == f"sqlite:///{tmp_path / 'mlflow.db'}"
    Tracker("local", "run", tmp_path / "r", {"seed": 0}).finish()
    assert (tmp_path / "mlflow.db").is_file() and len(search_runs("local")) == 1
