"""The index of every report under a reports folder: what each holds, the command that wrote it, its
wall time, its training seeds and the machine, read from each report's own header (the reports are
written by different commands, so this is the one page that lists them all).

    python -m nostra.workflows.reports_index reports
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

INDEX = "index.md"
COMMAND = re.compile(r"^(?:- Command: )?`([^`]+)`")
LOGGED = re.compile(r"^\s+\d+\. `([^`]+)`")  # one of several commands (a report's command log, command_log)
WALL = re.compile(r"^- Wall time[^:]*: (.+)$")
MACHINE = re.compile(r"^- Machine: (.+)$")
TRAINING_SEEDS = re.compile(r"^- Training seeds: ([0-9, ]*[0-9])")  # a report whose command names no SEEDS=
SEEDS = re.compile(r"\bSEEDS?=\"?([0-9 ]+)\"?")


def describe(path: Path) -> dict:
    """Title, command, wall time, machine and training seeds from a report's first lines."""
    lines = path.read_text().splitlines()
    if not lines or not lines[0].startswith("# "):
        raise ValueError(f"{path}: a report starts with a '# ' title line, found {lines[:1]!r}")
    info = {"title": lines[0][2:].strip(), "command": "", "wall": "", "machine": "", "listed": ""}
    logged = [m[1] for m in map(LOGGED.match, lines[1:60]) if m]
    if logged:
        info["command"] = "; then ".join(logged)
    for line in lines[1:40]:
        for key, pattern in (("command", COMMAND), ("wall", WALL), ("machine", MACHINE), ("listed", TRAINING_SEEDS)):
            m = pattern.match(line)
            if m and not info[key]:
                info[key] = m[1].strip()
    named = [m[1] for m in SEEDS.finditer(info["command"])] + [info.pop("listed").replace(",", " ")]
    seeds = sorted({s for m in named for s in m.split()}, key=int)
    info["seeds"] = ", ".join(seeds)
    return info


def reports(root: Path) -> list[Path]:
    """Every Markdown report under root but the index itself, profile by profile."""
    return sorted(p for p in root.rglob("*.md") if p != root / INDEX)


def render(root: Path) -> str:
    found = reports(root)
    if not found:
        raise FileNotFoundError(f"{root}: no Markdown reports (*.md) under it")
    rows = [(p, describe(p)) for p in found]
    machines = sorted({d["machine"] for _, d in rows if d["machine"]})
    out = ["# Reports", "",
           "Every report, the command that wrote it (as recorded in its header), its wall time and training "
           "seeds. Rollouts use episode seeds 1000-1049 for every variant unless a report says otherwise.", ""]
    out += [f"- Machine: {m}" for m in machines] + ([""] if machines else [])
    out += ["| Report | What | Command | Wall time | Training seeds |", "|---|---|---|---|---|"]
    for p, d in rows:
        command = f"`{d['command']}`" if d["command"] else "–"
        wall = d["wall"] or ("in the command" if re.search(r"\d+ min", d["command"]) else "–")
        out.append(f"| [{p.relative_to(root)}]({p.relative_to(root)}) | {d['title']} | {command} | {wall} | "
                   f"{d['seeds'] or '–'} |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the reports folder (e.g. reports)")
    args = ap.parse_args(argv)
    text = render(args.root)  # every report read before the index is touched: a bad one leaves the old index
    (args.root / INDEX).write_text(text)
    print(f"wrote {args.root / INDEX}")


if __name__ == "__main__":
    main()
