"""A report folder's command log, ``commands.jsonl``: every command that wrote into the report, in order.

The report scripts resume: a study is often run in pieces (the same script with other cells, another
model, a second checkpoint), and each piece rewrites the report from every record on the disk. Its
header must then name every piece, not only the last one, with the wall time of each. Each report
writer appends the command it was given (one JSON line: the command, when it finished, its wall
time) and renders the header from the whole log; a report rewritten without ``--command`` (e.g. by
hand, after a code change) keeps the log's history.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

LOG = "commands.jsonl"


def log_path(where: Path) -> Path:
    """The log of a report folder (its commands.jsonl), or ``where`` itself when it names a .jsonl file
    (a folder holding several reports gives each its own, e.g. recipe.commands.jsonl)."""
    where = Path(where)
    return where if where.suffix == ".jsonl" else where / LOG


def read(where: Path) -> list[dict]:
    """The log's entries, oldest first ([] when there is no log yet)."""
    path = log_path(where)
    if not path.is_file():
        return []
    entries = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            entry = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}:{n}: not a JSON line ({exc.msg}); each line is an object with "
                             "'command', 'finished' and 'wall_seconds'") from None
        if not isinstance(entry, dict) or not isinstance(entry.get("command"), str):
            raise ValueError(f"{path}:{n}: an entry needs a 'command' string, found {line[:80]!r}")
        entries.append(entry)
    return entries


def record(where: Path, command: str | None, wall_seconds: float | None = None) -> list[dict]:
    """Append this run's command to the log (when there is one to record); every entry."""
    entries = read(where)  # a malformed log fails here, before anything is appended to it
    if command:
        entry = {"command": command, "finished": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
                 "wall_seconds": None if wall_seconds is None else round(float(wall_seconds), 1)}
        path = log_path(where)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a") as f:
            f.write(json.dumps(entry) + "\n")
        entries.append(entry)
    return entries


def _minutes(seconds: float | None) -> str:
    return "" if seconds is None else f"{seconds / 60:.0f} min"


def header(entries: list[dict]) -> list[str]:
    """Header lines naming the commands: one as ``- Command:`` and its wall time, several as a numbered list
    (when each finished, UTC, and its wall time) and their summed wall time."""
    if not entries:
        return []
    if len(entries) == 1:
        wall = _minutes(entries[0].get("wall_seconds"))
        return [f"- Command: `{entries[0]['command']}`"] + ([f"- Wall time of the command: {wall}"] if wall else [])
    lines = ["- Commands, in the order they ran (each added to this report; the log beside it):"]
    for i, e in enumerate(entries, start=1):
        when = [f"finished {e['finished']} UTC"] if e.get("finished") else []
        when += [_minutes(e.get("wall_seconds"))] if e.get("wall_seconds") is not None else []
        lines.append(f"  {i}. `{e['command']}`" + (f" ({', '.join(when)})" if when else ""))
    walls = [e["wall_seconds"] for e in entries if e.get("wall_seconds") is not None]
    if walls:
        lines.append(f"- Wall time of the commands: {_minutes(sum(walls))}"
                     + (f" ({len(walls)} of {len(entries)} timed)" if len(walls) < len(entries) else ""))
    return lines


def command_header(where: Path, command: str | None, wall_seconds: float | None = None) -> list[str]:
    """Record this run in the log, then the header lines naming every command in it."""
    return header(record(where, command, wall_seconds))
