"""The reports index: one row per report with the command, wall time and seeds of its header, and a
clear error (the old index kept) for a file that is no report."""

import pytest

from nostra.workflows.reports_index import main


def _report(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_index_lists_every_report(tmp_path):
    _report(tmp_path / "cpu/liftd1/index.md", "# CPU profile: LiftD1\n\n- Command: `SEEDS=\"0 1\" make cpu`\n"
            "- Machine: 2 cores\n- Wall time of the command: 90 min\n")
    _report(tmp_path / "cpu/liftd1/offline/offline.md", "# Where the nats go\n\n`SEED=0 bash scripts/cpu_views.sh (50 min)`\n")
    _report(tmp_path / "cpu/liftd1/pooled/claims.md", "# Pooled\n\n- Command: `python -m pool a b`\n"
            "- Training seeds: 0, 2 (each report names its runs)\n")
    main([str(tmp_path)])
    text = (tmp_path / "index.md").read_text()
    assert "| [cpu/liftd1/index.md](cpu/liftd1/index.md) | CPU profile: LiftD1 | `SEEDS=\"0 1\" make cpu` | 90 min | 0, 1 |" in text
    assert "| Where the nats go | `SEED=0 bash scripts/cpu_views.sh (50 min)` | in the command | 0 |" in text
    assert "| Pooled | `python -m pool a b` | – | 0, 2 |" in text  # seeds its header lists, not its command
    assert "- Machine: 2 cores" in text
    main([str(tmp_path)])  # the index itself is not listed when it is rebuilt
    assert "](index.md)" not in (tmp_path / "index.md").read_text()


def test_malformed_report_keeps_the_old_index(tmp_path):
    _report(tmp_path / "cpu/a.md", "# A\n")
    main([str(tmp_path)])
    before = (tmp_path / "index.md").read_text()
    _report(tmp_path / "cpu/b.md", "no title here\n")
    with pytest.raises(ValueError, match=r"b\.md: a report starts with a '# ' title line"):
        main([str(tmp_path)])
    assert (tmp_path / "index.md").read_text() == before
    with pytest.raises(FileNotFoundError, match="no Markdown reports"):
        main([str(tmp_path / "empty")])
