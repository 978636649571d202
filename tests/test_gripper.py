"""nostra.workflows.gripper: open-to-closed switches of the gripper command per episode, per cell."""
import numpy as np
import pytest

from nostra.workflows.gripper import closings, main


def _episode(switches: int, steps: int = 120) -> np.ndarray:
    """Actions (steps x 7) whose gripper command closes once, then opens and closes `switches` - 1 times more."""
    grip = -np.ones(steps)
    for k in range(switches):
        grip[10 + 4 * k: 12 + 4 * k] = 1.0  # closed for two steps, open for two
    if switches == 1:
        grip[10:] = 1.0  # one grasp, held
    return np.column_stack([np.zeros((steps, 6)), grip]).astype(np.float32)


def _records(root, cell, episodes, key="action", offsets=None):
    """Records of a cell; with `offsets` (m, one per episode) the red cube sits that far in x from the end
    effector and the green cube 0.1 m beyond it, at every step."""
    folder = root / cell / "records/Stack/none"
    folder.mkdir(parents=True)
    for i, (ok, switches) in enumerate(episodes):
        arrays = {key: _episode(switches)}
        if offsets is not None:
            eef = np.tile([0.1, 0.2, 0.9], (len(arrays[key]), 1)).astype(np.float32)
            arrays.update({"eef_pos": eef, "object/red_cube": eef + [offsets[i], 0, -0.05],
                           "object/green_cube": eef + [offsets[i] + 0.1, 0, -0.05]})
        np.savez(folder / f"nostra_seed{1000 + i}.npz", success=ok, **arrays)


def test_closings_count_only_switches_from_open_to_closed():
    assert closings(_episode(1)) == 1 and closings(_episode(12)) == 12
    assert closings(np.zeros((5, 7))) == 0  # never closed
    assert closings(np.column_stack([np.zeros((4, 6)), [-0.1, 0.3, -0.1, 0.2]])) == 2  # a swing around 0 counts


def test_cells_count_dithering_episodes_and_which_failures_dither(tmp_path):
    gaussian, gmm = tmp_path / "gaussian", tmp_path / "gmm"
    _records(gaussian, "s0/best/none", [(True, 1), (True, 2), (False, 30), (False, 12), (False, 1)])
    _records(gmm, "s0/best/none", [(True, 1), (True, 1), (True, 2), (False, 9), (False, 2)])
    out = tmp_path / "report"
    main(["--runs", f"Gaussian={gaussian}", f"GMM={gmm}", "--out", str(out)])
    rows = (out / "index.md").read_text()
    assert "| Gaussian | 0 | best | none | BC-NOSTRA | 2 / 5 | 2 | 2 of 3 | 1.5 / 12 | – | – / – |" in rows
    assert "| GMM | 0 | best | none | BC-NOSTRA | 3 / 5 | 0 | 0 of 2 | 1 / 5.5 | – | – / – |" in rows  # 9: not 10
    assert (out / "gripper.png").stat().st_size > 0 and (out / "gripper.csv").read_text().count("\n") == 3


def test_a_record_without_actions_is_named_and_nothing_is_written(tmp_path):
    _records(tmp_path / "runs", "s0/best/none", [(True, 1)], key="eef_pos")
    with pytest.raises(ValueError, match=r"nostra_seed1000\.npz: no 'action' array \(keys: success, eef_pos\)"):
        main(["--runs", f"old={tmp_path / 'runs'}", "--out", str(tmp_path / "report")])
    assert not (tmp_path / "report").exists()


def test_failures_that_closed_beside_every_object_are_counted_from_the_recorded_positions(tmp_path):
    runs = tmp_path / "runs"
    # successes close 0.5 and 1 cm from the red cube; failures 3 cm (beside it), 1.5 cm (on it) and never
    episodes = [(True, 1), (True, 1), (False, 30), (False, 1), (False, 0)]
    _records(runs, "s0/last/none", episodes, offsets=[0.005, -0.01, 0.03, 0.015, 0.0])
    out = tmp_path / "report"
    main(["--runs", f"Gaussian={runs}", "--out", str(out)])
    assert "| Gaussian | 0 | last | none | BC-NOSTRA | 2 / 5 | 1 | 1 of 3 | 1 / 1 | 1 of 3 | 0.8 / 2.2 |" in \
        (out / "index.md").read_text()
