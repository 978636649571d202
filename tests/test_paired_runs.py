"""Two studies compared cell by cell on the initial states both met (nostra.workflows.paired_runs)."""
import numpy as np
import pytest

from nostra.workflows import paired_runs


def _records(root, cell, successes):
    """Episode records of one cell: root/s<seed>/<checkpoint>/records/Stack/<noise>/<variant>_seed<n>.npz."""
    seed, checkpoint, noise, variant = cell
    folder = root / f"s{seed}" / checkpoint / "records" / "Stack" / noise
    folder.mkdir(parents=True, exist_ok=True)
    for i, ok in enumerate(successes):
        np.savez(folder / f"{variant}_seed{1000 + i}.npz", success=ok, steps=10)


def test_cells_both_hold_are_paired_episode_by_episode(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    _records(a, (0, "best", "none", "nostra"), [True] * 18 + [False] * 2)
    _records(b, (0, "best", "none", "nostra"), [True] * 2 + [False] * 18)
    _records(a, (0, "best", "blind", "nostra_mli"), [False] * 20)  # b has no blind cell: left out
    out = tmp_path / "report"
    paired_runs.main(["--a", f"more={a}", "--b", f"fewer={b}", "--out", str(out), "--command", "cmd"])
    text = (out / "index.md").read_text()
    assert "# more vs fewer" in text and "- Command: `cmd`" in text and "- Training seeds: 0" in text
    row = next(line for line in text.splitlines() if line.startswith("| 0 | best | none |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[4].startswith("90 [") and cells[5].startswith("10 [") and cells[6].startswith("+80 [")
    assert cells[7] == "16 / 0" and float(cells[8]) < 1e-3 and cells[9] == "20"
    assert "blind" not in text.split("McNemar p | episodes |")[1]


def test_a_folder_without_records_or_a_missing_label_is_named(tmp_path, capsys):
    good = tmp_path / "a"
    _records(good, (0, "best", "none", "nostra"), [True])
    for bad, said in ((str(good), "expected LABEL="), (f"x={tmp_path / 'empty'}", "empty: no episode records")):
        with pytest.raises(SystemExit):
            paired_runs.main(["--a", bad, "--b", f"b={good}", "--out", str(tmp_path / "o")])
        assert said in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_no_cell_in_common_is_an_error_and_writes_nothing(tmp_path):
    _records(tmp_path / "a", (0, "best", "none", "nostra"), [True])
    _records(tmp_path / "b", (1, "best", "none", "nostra"), [True])
    with pytest.raises(SystemExit, match="no cell in common"):
        paired_runs.main(["--a", f"a={tmp_path / 'a'}", "--b", f"b={tmp_path / 'b'}", "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()
