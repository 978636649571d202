"""nostra.workflows.grasp_labels: what the demos' gripper labels say at the point where the expert closes."""
import numpy as np
import pandas as pd
import pytest

import fixtures as F
from nostra.data import CollectionError, Store
from nostra.workflows.grasp_labels import EEF, grasp_labels, main


def _demo(hover: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Descend to (0, 0, 0.82) by step 9, stay there open for `hover` steps (pushed 3 cm off in x at the
    fourth), closed for 5 steps, then lift 3 cm a step, still closed."""
    z = list(1.0 - 0.02 * np.arange(9)) + [0.82] * (hover + 5) + list(0.82 + 0.03 * np.arange(1, 10))
    pos = np.column_stack([np.zeros(len(z)), np.zeros(len(z)), z])
    pos[12, 0] = 0.03
    grip = -np.ones(len(z))
    grip[9 + hover:] = 1.0
    return grip, pos


def test_the_open_run_and_share_count_only_the_steps_at_the_grasp_point():
    run, share = grasp_labels(*_demo())
    # near: steps 9-11 and 13-14 open (12 pushed off, 8 still 2 cm above), 15-19 closed; 20 has left
    assert run == 2 and share == pytest.approx(5 / 10)
    assert grasp_labels(-np.ones(20), np.zeros((20, 3))) is None  # never closes


def _collection(tmp_path, store, name, hovers):
    eps = F.make_episodes(len(hovers), lengths=[len(_demo(h)[0]) for h in hovers], seed=len(hovers))
    for ep, h in zip(eps, hovers):
        grip, pos = _demo(h)
        ep.actions[:, -1] = grip
        ep.obs[EEF] = pos.astype(np.float32)
    store.ingest(F.robomimic_hdf5.write(tmp_path / f"{name}.hdf5", eps, F.ENV_ARGS, total=len(eps),
                                        progress=False), name=name, progress=False)


def test_report_per_label_over_its_collections(tmp_path):
    store = Store(tmp_path / "store.zarr")
    _collection(tmp_path, store, "few", [4, 4])     # hover 4: open there 9-11 (3 of 8), none just before
    _collection(tmp_path, store, "many", [12])      # hover 12: open there 9-11, 13-20 (11 of 16), 8 just before
    out = tmp_path / "report"
    main(["--store", str(store.path), "--collections", "short=few", "long=few,many", "--out", str(out)])
    demos = pd.read_csv(out / "demos.csv")
    assert list(demos["label"]) == ["short", "short", "long", "long", "long"]
    assert demos["open_share"].round(4).tolist() == [round(3 / 8, 4)] * 4 + [round(11 / 16, 4)]
    df = pd.read_csv(out / "grasp_labels.csv").set_index("label")
    assert df.loc["short", "half_or_more_open"] == 0 and df.loc["long", "half_or_more_open"] == 1
    assert df.loc["long", "open_run_p90"] == pytest.approx(np.quantile([0, 0, 8], 0.9))
    assert (out / "grasp_labels.png").stat().st_size > 0 and "| long | 3 (3) |" in (out / "index.md").read_text()


def test_an_unknown_collection_is_refused_naming_the_ones_there(tmp_path):
    store = Store(tmp_path / "store.zarr")
    _collection(tmp_path, store, "few", [4])
    with pytest.raises(CollectionError, match="no collection 'nope'.*few"):
        main(["--store", str(store.path), "--collections", "x=nope", "--out", str(tmp_path / "r")])
    assert not (tmp_path / "r").exists()  # nothing written before the collections were read
