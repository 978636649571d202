"""scripts/cpu_claims.sh run against stand-in commands: a last cell whose model's final check was the best gets
the best cell's records copied (same-as-best), unless the last checkpoint was evaluated there itself."""
from script_stubs import run_stubbed

CELLS = "data/runs/cpu/evaluate/liftd1/s0"


def _records(tmp_path, cell: str, noise: str, folder: str = "lstm"):
    rec = tmp_path / CELLS / cell / noise / folder / "records/LiftD1" / noise
    rec.mkdir(parents=True)
    (rec / "lstm_seed1000.npz").write_bytes(b"")


def test_a_last_cell_evaluated_itself_gets_no_copy_of_the_best(tmp_path):
    for noise in ("none", "blind"):
        _records(tmp_path, "best", noise)
    _records(tmp_path, "last", "none")  # evaluated on the last checkpoint (make cpu's clean cell)
    # the stand-in python says yes to same_as_best: the final check was the best
    r, calls = run_stubbed(tmp_path, "cpu_claims.sh", {"SEEDS": "0", "MODELS": "lstm", "NOISES": "none blind",
                                                       "CHECKPOINTS": "last"}, scripts={"cpu.sh": "exit 0\n"})
    assert r.returncode == 0, r.stderr
    assert not (tmp_path / CELLS / "last/none/same-as-best").exists()
    assert (tmp_path / CELLS / "last/blind/same-as-best/records/LiftD1/blind/lstm_seed1000.npz").is_file()
    assert not [c for c in calls if c.startswith("nostra evaluate")]  # both cells have their records
    assert [c for c in calls if "nostra.workflows.claims" in c]
