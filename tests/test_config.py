"""The stage configs hold no dead keys (every key of conf/data/default.yaml is read by the code or
interpolated by another config), and the documented noise-window override works from the command
line (once: "Key 'Lift' is not in struct")."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[1]


def leaf_keys(node, prefix: str = "") -> list[str]:
    """Dotted paths of a config's leaves (a dict's keys, recursively; lists are leaves)."""
    if not isinstance(node, DictConfig):
        return [prefix]
    out = []
    for k in node.keys():
        out += leaf_keys(node._get_node(k), f"{prefix}.{k}" if prefix else str(k))
    return out


def reference_pattern(group: str, key: str) -> re.Pattern:
    """How code or another config reads ``<group>.<key>``: ``cfg.data.key``, ``cfg["data"]["key"]``,
    an interpolation ``${data.key}`` / ``${oc.select:data.key,...}``, an OmegaConf.select string
    ``"data.key"``."""
    dotted = re.escape(f"{group}.{key}")
    parts = key.split(".")
    item = r"\[['\"]" + re.escape(group) + r"['\"]\]" + "".join(r"\[['\"]" + re.escape(p) + r"['\"]\]" for p in parts)
    return re.compile(rf"(?:cfg\.{dotted}|\$\{{{dotted}|select:{dotted}|['\"]{dotted}['\"]|{item})(?![\w])")


def sources() -> dict[Path, str]:
    """The code that reads configs and the configs that interpolate one another."""
    files = [*ROOT.glob("nostra/**/*.py"), *ROOT.glob("pipeline/**/*.py"), *ROOT.glob("retrieval/**/*.py"),
             *ROOT.glob("conf/**/*.yaml"), ROOT / "dvc.yaml", ROOT / "params.yaml"]
    return {p: p.read_text() for p in files if p.is_file()}


def unreferenced(group: str, keys: list[str], texts: dict[Path, str]) -> list[str]:
    return [k for k in keys if not any(reference_pattern(group, k).search(t) for t in texts.values())]


def test_every_data_key_is_read():
    keys = leaf_keys(OmegaConf.load(ROOT / "conf" / "data" / "default.yaml"))
    assert {"store", "collections", "obs_keys", "seq_len", "batch_size", "workers", "val_fraction"} <= set(keys)
    assert unreferenced("data", keys, sources()) == []


def test_an_unread_key_is_caught():
    """The check is precise enough to fail: the removed keys (data.pad, data.cache_mb) and a made-up
    one are unread, although `pad` and `cache_mb` are argument names in nostra.data.dataset."""
    texts = sources()
    assert unreferenced("data", ["pad", "cache_mb", "no_such_key"], texts) == ["pad", "cache_mb", "no_such_key"]
    assert unreferenced("data", ["seq_len", "obs_keys"], texts) == []  # code / an interpolation


def _evaluate_cfg(monkeypatch, *overrides: str):
    """The config `nostra evaluate <overrides>` hands its app (the `nostra` entry point, Hydra's
    command-line parsing), the app itself replaced so that nothing runs."""
    import pipeline.evaluate as ev
    from pipeline.cli import main

    seen = []
    monkeypatch.setattr(ev, "_app", seen.append)
    assert main(["evaluate", *overrides]) == 0
    return seen[0]


def test_windows_override_from_the_command_line(monkeypatch):
    """The override documented in conf/evaluate/default.yaml, as a shell passes it."""
    from pipeline.evaluate import noise_windows

    cfg = _evaluate_cfg(monkeypatch, "task=lift", "evaluate.windows={Lift: [[30, 60]]}")
    assert noise_windows(cfg) == {"Lift": [[30, 60]]}
    default = _evaluate_cfg(monkeypatch, "task=lift")
    assert noise_windows(default) == {"Lift": [[15, 35], [45, 60]]}  # conf/task/lift.yaml
    other = _evaluate_cfg(monkeypatch, "task=lift", "evaluate.windows={Stack: [[10, 20], [40, 50]]}")
    assert noise_windows(other) == {"Stack": [[10, 20], [40, 50]], "Lift": [[15, 35], [45, 60]]}


def test_windows_override_with_the_compose_api():
    from hydra import compose, initialize_config_dir

    from pipeline._hydra import CONF_DIR
    from pipeline.evaluate import noise_windows

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose("config", overrides=["evaluate.windows={Lift: [[30, 60]]}"])
    assert cfg.task.name == "Lift"
    assert noise_windows(cfg) == {"Lift": [[30, 60]]}


def test_windows_override_of_one_task_with_a_plus(monkeypatch):
    """The dotted form adds a key, so it needs Hydra's `+` (conf/evaluate/default.yaml says so)."""
    from pipeline.evaluate import noise_windows

    cfg = _evaluate_cfg(monkeypatch, "task=lift", "+evaluate.windows.Lift=[[30,60]]")
    assert noise_windows(cfg) == {"Lift": [[30, 60]]}


@pytest.mark.parametrize("bad, message", [("evaluate.window={Lift: [[30, 60]]}", "window"),
                                          ("evaluate.windows.Lift=[[30, 60]]", "+evaluate.windows.Lift")])
def test_a_wrong_windows_override_fails_with_a_hint(monkeypatch, capsys, bad, message):
    """A misspelt key fails (struct); the dotted form without `+` fails with Hydra's hint to add it."""
    with pytest.raises(SystemExit):
        _evaluate_cfg(monkeypatch, bad)
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("path", sorted((ROOT / "conf/task").glob("*.yaml")), ids=lambda p: p.stem)
def test_task_configs_name_registered_tasks_with_their_windows(path):
    """A task config's noise_windows are its registry entry's, which the offline analysis and the
    in-training rollouts read: two different values once gave windows past LiftD1's episodes."""
    from nostra.sim.tasks import get_task

    cfg = OmegaConf.load(path)
    spec = get_task(cfg.name)
    if "noise_windows" in cfg:
        assert [tuple(w) for w in cfg.noise_windows] == [tuple(w) for w in spec.noise_windows], path
