"""`nostra ingest` and `nostra export` as Hydra apps."""

import h5py
import numpy as np
import pytest

from nostra.data import Store
import fixtures as F
from pipeline.cli import main


def test_ingest_then_export(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    F.write_robomimic(tmp_path / "lift.hdf5", lengths=[6, 4], image_size=8)
    F.write_lerobot(tmp_path / "so100", n=2, image_size=8, video=False)
    assert main(["ingest", "ingest.sources=[lift.hdf5,so100]", "ingest.progress=false",
                 "ingest.metadata.task=Lift", "paths.data=d"]) == 0
    out = capsys.readouterr().out
    assert "lift: 2 episodes, 10 steps" in out and "so100: 2 episodes" in out
    s = Store(tmp_path / "d/store.zarr")
    assert s.collections() == ["lift", "so100"] and set(s.episodes("so100")["task"]) == {"Lift"}
    assert main(["export", "export.collection=lift", "export.progress=false", "paths.data=d"]) == 0
    with h5py.File(tmp_path / "d/export/lift.hdf5", "r") as f:
        np.testing.assert_array_equal(f["data/demo_1/actions"][:], s.episode("lift", 1)["actions"])
    assert main(["export", "export.collection=lift", "export.format=lerobot", "export.progress=false",
                 "paths.data=d"]) == 0
    assert (tmp_path / "d/export/lift_lerobot/meta/info.json").is_file()


def test_several_sources_into_one_collection(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    F.write_robomimic(tmp_path / "s0.hdf5", lengths=[6, 4], image_size=8)
    F.write_robomimic(tmp_path / "s1.hdf5", lengths=[5], seed=2, image_size=8)
    assert main(["ingest", "ingest.sources=[s0.hdf5,s1.hdf5]", "ingest.name=lift", "ingest.progress=false",
                 "paths.data=d"]) == 0
    df = Store(tmp_path / "d/store.zarr").episodes("lift")
    assert list(df["length"]) == [6, 4, 5] and df["source"].str.endswith("s1.hdf5").tolist() == [False, False, True]


def test_bad_input_exits_with_a_message(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "junk.txt").write_text("junk")
    with pytest.raises(SystemExit) as e:
        main(["ingest", "ingest.sources=[junk.txt]", "paths.data=d"])
    assert e.value.code == 1 and "junk.txt: unknown format" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["export", "paths.data=d"])
    assert e.value.code == 2 and "export.collection=<name>" in capsys.readouterr().err
    assert not (tmp_path / "d/store.zarr").exists() or Store(tmp_path / "d/store.zarr").collections() == []
