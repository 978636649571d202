"""Generation and ingest are bit-reproducible: the same seeds, code and machine give the same bytes,
so `dvc repro` of the same seeds and code reproduces the md5s its dvc.lock records (no creation times, no wall-clock
values, no absolute install paths in the outputs)."""

import hashlib
import os
import re
from pathlib import Path

import h5py
import pytest

from fixtures import write_robomimic
from nostra.data.store import Store


def md5(path: Path) -> str:
    return hashlib.md5(Path(path).read_bytes()).hexdigest()


def tree_md5(root: Path) -> dict[str, str]:
    """relative path -> md5 of every file under root."""
    return {p.relative_to(root).as_posix(): md5(p) for p in sorted(Path(root).rglob("*")) if p.is_file()}


def _ingest_twice(tmp_path: Path, source: str) -> tuple[dict, dict]:
    """The same source (a relative path, as dvc.yaml passes them) into two fresh stores."""
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        for store in ("a.zarr", "b.zarr"):
            Store(store).ingest([source], progress=False)
    finally:
        os.chdir(cwd)
    return tree_md5(tmp_path / "a.zarr"), tree_md5(tmp_path / "b.zarr")


def test_ingest_and_export_twice_give_the_same_bytes(tmp_path):
    write_robomimic(tmp_path / "raw" / "demo.hdf5", n=3, image_size=16, seed=0)
    a, b = _ingest_twice(tmp_path, "raw/demo.hdf5")
    assert any(k.endswith("zarr.json") for k in a) and any("/data/" in k for k in a)
    assert a == b, sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))

    store = Store(tmp_path / "a.zarr")
    (name,) = store.collections()
    first = store.export(name, tmp_path / "x.hdf5", progress=False)
    second = store.export(name, tmp_path / "y.hdf5", progress=False)
    assert md5(first) == md5(second)


@pytest.mark.sim
def test_generate_twice_gives_the_same_bytes(tmp_path):
    """Two demos of Lift with tiny images, once in this process and once by two spawned workers
    (other interpreters, other hash seeds): the same file; ingested, the same store."""
    import robosuite

    from nostra.sim.generate import GenerateConfig, generate

    outs = []
    for i, workers in enumerate((1, 2)):
        cfg = GenerateConfig(task="lift", out=str(tmp_path / "raw" / f"lift{i}.hdf5"), episodes=2, workers=workers,
                             image_size=16, max_steps=120, steps_after_success=0)
        assert generate(cfg, progress=False)["demos"] == 2
        outs.append(Path(cfg.out))
    assert md5(outs[0]) == md5(outs[1])

    # no path of this installation: robosuite's assets are named from the package on, and resolve
    # against the local install as robosuite's edit_model_xml does
    root = os.path.dirname(os.path.abspath(robosuite.__file__))
    with h5py.File(outs[0]) as f:
        model = f["data/demo_0"].attrs["model_file"]
    assert root not in model and 'file="robosuite/models/assets/' in model
    files = re.findall(r'file="robosuite/([^"]+)"', model)
    assert files and all(os.path.isfile(os.path.join(root, p)) for p in files)

    a, b = _ingest_twice(tmp_path, "raw/lift0.hdf5")
    assert a == b, sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
