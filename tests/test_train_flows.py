"""The training flows end to end on a tiny store: pretrain -> resume -> finetune -> cotrain, tracked
in MLflow (embedded sqlite) with a local copy, and the clear errors before any training."""

import json

import pytest
import torch

from conftest import small_net, train_spec
from nostra.data.dataset import held_out_episodes, run_episodes, split_episodes
from fixtures import write_robomimic
from nostra.data.store import Store
from nostra.policies.checkpoint import CheckpointError, load_runner
from nostra.workflows.tracking import search_runs
from nostra.workflows.training import TrainSpec, train

KEYS = ["agentview_image", "robot0_eef_pos", "robot0_gripper_qpos"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("flows")
    s = Store(root / "store.zarr")
    for name, seed in (("target", 0), ("library", 1)):
        s.ingest(write_robomimic(root / f"{name}.hdf5", n=6, lengths=[12] * 6, image_size=40, seed=seed),
                 name=name, progress=False)
    return s


def spec(store, tmp, **kw) -> TrainSpec:
    base = dict(policy="nostra", store=str(store.path), collections=["target"], obs_keys=KEYS, out_dir=str(tmp),
                net=small_net("nostra"), optim={"lr": 1e-3}, seq_len=8, batch_size=4, max_steps=6,
                num_workers=0, val_every=3, progress=False, experiment="test")
    return train_spec(**{**base, **kw})


@pytest.fixture(autouse=True)
def _sqlite_tracking(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the embedded mlflow.db lands in the working directory
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    torch.manual_seed(0)


def test_pretrain_tracks_checkpoints_and_resumes(store, tmp_path):
    out = tmp_path / "pre"
    result = train(spec(store, out, run_name="pre"))
    assert result["steps"] == 6 and (out / "policy.ckpt").is_file() and (out / "checkpoints/last.ckpt").is_file()
    runner = load_runner(out / "policy.ckpt")
    assert runner.modality_names == KEYS
    runs = search_runs("test")
    assert len(runs) == 1 and runs["params.model"][0] == "nostra"
    assert "metrics.train/loss" in runs and "metrics.kl_nats/agentview_image" in runs
    local = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert any("train/loss" in r.get("metrics", {}) for r in local)
    # the run's own split, which evaluation's offline analysis reads instead of recomputing it
    assert held_out_episodes(out) == split_episodes(store, ["target"], 0.1, 0)[1] != []
    assert held_out_episodes(out, ["library"]) == []
    assert run_episodes(out, ["target"], "train") == split_episodes(store, ["target"], 0.1, 0)[0] != []
    assert result["resumed"] is False and 0 < result["train_seconds"]
    # a re-run with more steps continues from last.ckpt instead of starting over, and counts the time its
    # earlier sittings spent (the Timer's state in last.ckpt: set to a day here so that it cannot be missed)
    last = torch.load(out / "checkpoints/last.ckpt", map_location="cpu", weights_only=False)
    last["callbacks"]["Timer"]["time_elapsed"]["train"] = 86400.0
    torch.save(last, out / "checkpoints/last.ckpt")
    again = train(spec(store, out, run_name="pre", max_steps=9))
    assert again["steps"] == 9 and again["resumed"] is True
    assert 86400 < again["train_seconds"] < 86400 + again["wall_seconds"]


def test_held_out_episodes_of_a_run_without_a_split(tmp_path):
    with pytest.raises(FileNotFoundError, match="episodes.json: no episode split"):
        held_out_episodes(tmp_path)
    (tmp_path / "episodes.json").write_text('{"train": []}')
    with pytest.raises(ValueError, match="episodes.json: not an episode split"):
        held_out_episodes(tmp_path)
    assert run_episodes(tmp_path, part="train") == []
    with pytest.raises(ValueError, match="'valid' unknown; valid: held_out, train"):
        run_episodes(tmp_path, part="valid")


def test_finetune_and_cotrain(store, tmp_path):
    pre = train(spec(store, tmp_path / "pre", collections=["library"]))["checkpoint"]
    fine = train(spec(store, tmp_path / "fine", stage="finetune", init_from=pre, num_demos=2))
    assert fine["train_episodes"] == 2
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"episodes": [{"collection": "library", "episode": e, "score": 1.0}
                                                 for e in range(4)]}))
    co = train(spec(store, tmp_path / "co", stage="cotrain", manifest=str(manifest), num_demos=2))
    assert co["manifest_hash"] and co["train_episodes"] == 6
    runs = search_runs("test")
    assert co["manifest_hash"] in set(runs["params.manifest_hash"])


def test_a_mixture_of_collections_by_weight(store, tmp_path):
    """data.weights draws windows by collection (MixtureSampler): a collection with weight 0 gives none."""
    from nostra.data.dataset import MixtureSampler
    from nostra.workflows.training import _episodes

    mixed = spec(store, tmp_path / "m", collections=["target", "library"], weights={"target": 1.0, "library": 0.0})
    train_eps, _, weights, _ = _episodes(mixed, store)
    assert weights == {"target": 1.0, "library": 0.0} and {c for c, _ in train_eps} == {"target", "library"}
    sampler = MixtureSampler({"target": (0, 10), "library": (10, 20)}, weights, 50, seed=0)
    assert all(i < 10 for i in sampler)
    assert train(mixed)["steps"] == 6
    with pytest.raises(ValueError, match=r"one weight per collection of data.collections=\['target', 'library'\]"):
        train(spec(store, tmp_path / "m2", collections=["target", "library"], weights={"target": 1.0}))
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"episodes": [{"collection": "library", "episode": 0}]}))
    with pytest.raises(ValueError, match="cotrain_ratio"):
        train(spec(store, tmp_path / "m3", stage="cotrain", manifest=str(manifest), weights={"target": 1.0}))
    assert not (tmp_path / "m2").exists() and not (tmp_path / "m3").exists()


def test_bad_inputs_fail_before_training(store, tmp_path):
    pre = train(spec(store, tmp_path / "pre"))["checkpoint"]
    with pytest.raises(CheckpointError, match="trained on modalities"):
        train(spec(store, tmp_path / "f1", stage="finetune", init_from=pre, obs_keys=KEYS[:2]))
    with pytest.raises(CheckpointError, match="holds a 'nostra' policy, not 'lstm'"):
        train(spec(store, tmp_path / "f2", stage="finetune", init_from=pre, policy="lstm", net=small_net("lstm")))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"episodes": [{"collection": "library", "episode": 99}]}))
    with pytest.raises(ValueError, match="episode 99 of 'library'"):
        train(spec(store, tmp_path / "c1", stage="cotrain", manifest=str(bad)))
    bad.write_text(json.dumps({"episodes": [{"collection": "nowhere", "episode": 0}]}))
    with pytest.raises(ValueError, match="collection 'nowhere'"):
        train(spec(store, tmp_path / "c2", stage="cotrain", manifest=str(bad)))
    with pytest.raises(ValueError, match="unknown training stage 'distill'"):
        train(spec(store, tmp_path / "x", stage="distill"))
    assert not (tmp_path / "f1").exists() and not (tmp_path / "c1").exists()


def test_tracking_failure_keeps_training(store, tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")  # nothing listens there
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "2")
    out = tmp_path / "offline"
    result = train(spec(store, out))
    assert result["steps"] == 6 and (out / "policy.ckpt").is_file()
    assert "MLflow tracking failed" in result["tracking"] and "metrics.jsonl" in result["tracking"]
    assert "train/loss" in (out / "metrics.jsonl").read_text()
