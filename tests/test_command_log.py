"""A report's command log: a report written in pieces names every command that wrote into it, with its
wall time, and a malformed log fails naming the file and line before anything is appended."""

import pytest

from nostra.workflows import command_log
from nostra.workflows.reports_index import describe


def test_one_command_then_several(tmp_path):
    assert command_log.command_header(tmp_path, "A=1 make cpu", 600) == [
        "- Command: `A=1 make cpu`", "- Wall time of the command: 10 min"]
    assert command_log.command_header(tmp_path, None) == [  # a rewrite without a command records nothing
        "- Command: `A=1 make cpu`", "- Wall time of the command: 10 min"]
    lines = command_log.command_header(tmp_path, "A=1 NOISES=mask make cpu", 120)
    assert lines[0].startswith("- Commands, in the order they ran")
    assert lines[1].startswith("  1. `A=1 make cpu` (finished ") and lines[1].endswith(" UTC, 10 min)")
    assert lines[2].startswith("  2. `A=1 NOISES=mask make cpu` (finished ") and lines[2].endswith(", 2 min)")
    assert lines[3] == "- Wall time of the commands: 12 min"
    report = tmp_path / "r.md"
    report.write_text("# R\n\n" + "\n".join(lines) + "\n")
    info = describe(report)  # the reports index lists both commands and their summed wall time
    assert info["command"] == "A=1 make cpu; then A=1 NOISES=mask make cpu" and info["wall"] == "12 min"


def test_untimed_entries_are_counted(tmp_path):
    command_log.record(tmp_path, "a", 60)
    lines = command_log.command_header(tmp_path, "python -m pool", None)
    assert lines[-1] == "- Wall time of the commands: 1 min (1 of 2 timed)"


def test_a_named_log_file(tmp_path):
    command_log.record(tmp_path / "recipe.commands.jsonl", "make cpu-recipe", 60)
    assert (tmp_path / "recipe.commands.jsonl").is_file() and not (tmp_path / command_log.LOG).exists()


@pytest.mark.parametrize("line, match", [("not json", r"commands\.jsonl:2: not a JSON line"),
                                         ('{"wall_seconds": 3}', r"commands\.jsonl:2: an entry needs a 'command'")])
def test_malformed_log_is_named_and_kept(tmp_path, line, match):
    log = tmp_path / command_log.LOG
    log.write_text('{"command": "a"}\n' + line + "\n")
    before = log.read_text()
    with pytest.raises(ValueError, match=match):
        command_log.record(tmp_path, "b", 1)
    assert log.read_text() == before
