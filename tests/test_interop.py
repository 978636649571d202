"""Files as other tools write them (nostra.data.fixtures_external says which tool and version each
mimics): LeRobot v3.0 task layouts and shared mp4s, LeRobot v2.1, round trips."""

import numpy as np
import pytest

from nostra.data import DataError, Store
from nostra.data import fixtures as F
from nostra.data import fixtures_external as X

LENGTHS = [12, 7, 9]
VIDEO_TOL = 4.0  # mean absolute error (0..255) of AV1 (crf 30) frames against the originals


@pytest.fixture(scope="module")
def eps():
    out = F.make_episodes(3, LENGTHS, image_size=16, keys=(*F.RGB_KEYS, *F.LOWDIM))
    out[1].meta["language"] = "push the red cube"  # two tasks: index 0 and 1
    return out


def check_lerobot_collection(s, name, eps):
    np.testing.assert_array_equal(s.episode_ends(name), np.cumsum(LENGTHS))
    for i, ep in enumerate(eps):
        got = s.episode(name, i)
        np.testing.assert_array_equal(got["actions"], ep.actions)
        for k in F.LOWDIM:
            np.testing.assert_array_equal(got[k], ep.obs[k])
        for k in F.RGB_KEYS:  # each episode's own frames out of the shared file
            err = np.abs(got[k].astype(float) - ep.obs[k]).mean()
            assert err < VIDEO_TOL, (i, k, err)
    assert s.episodes(name)["language"].tolist() == [e.meta["language"] for e in eps]


@pytest.mark.parametrize("layout", X.TASK_LAYOUTS)
def test_lerobot_v30_task_layouts_and_shared_mp4(tmp_path, eps, layout):
    root = X.write_lerobot_v30(tmp_path / "lr", eps, state_keys=list(F.LOWDIM), task_layout=layout)
    assert sorted(p.name for p in (root / "videos/observation.images.agentview").rglob("*.mp4")) == ["file-000.mp4"]
    s = Store(tmp_path / "store.zarr")
    name = s.ingest(root, key_map=F.LEROBOT_KEY_MAP, progress=False)
    check_lerobot_collection(s, name, eps)


def test_lerobot_v30_task_index_missing_from_tasks(tmp_path, eps):
    import pandas as pd
    root = X.write_lerobot_v30(tmp_path / "lr", eps, state_keys=list(F.LOWDIM), task_layout="frames_only")
    pd.DataFrame({"task_index": [0]}, index=["lift the red cube"]).to_parquet(root / "meta/tasks.parquet")
    with pytest.raises(DataError, match=r"tasks.parquet: episode_1: key 'task_index': has no task_index 1"):
        Store(tmp_path / "store.zarr").ingest(root, key_map=F.LEROBOT_KEY_MAP, progress=False)
