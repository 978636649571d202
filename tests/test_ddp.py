"""Data-parallel training on CPU (gloo): the samplers shard by rank so that two ranks with batch B
draw exactly what one process draws with batch 2B; `nostra train` with two DDP processes tracks one
MLflow run, matches the single-process run with the doubled batch and resumes; the in-training
rollouts run on rank 0 while the other rank waits, and the Diffusion Policy's EMA copy stays the
same on both ranks."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from conftest import small_net, train_spec
from nostra.data.dataset import MixtureSampler, WindowSampler, make_loader
from fixtures import write_robomimic
from nostra.data.store import Store
from nostra.policies.checkpoint import load_net
from nostra.workflows.tracking import search_runs
from nostra.configs import RolloutConfig
from nostra.workflows.training import train
from nostra.workflows.training_rollouts import RolloutEnv

ROOT = Path(__file__).resolve().parents[1]
NOSTRA = str(Path(sys.executable).with_name("nostra"))
KEYS = ["agentview_image", "robot0_eef_pos", "robot0_gripper_qpos"]
DDP = {"accelerator": "cpu", "devices": 2, "strategy": "ddp"}
# Two DDP ranks with batch 2 against one process with batch 4: the gradients differ only in the
# order of float additions (DDP averages two half-batch mean gradients across the ranks, one
# process takes one mean), about 1e-7 relative per step; after six Adam steps the weights agree to
# ~1e-6. A loss on different windows (a sampler that does not shard, or shards differently) moves
# by 1e-3..1e-2 relative, so these bounds separate the two by an order of magnitude or more.
LOSS_RTOL, WEIGHT_ATOL = 1e-4, 1e-4


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    s = Store(root / "store.zarr")
    s.ingest(write_robomimic(root / "target.hdf5", n=6, lengths=[12] * 6, image_size=40, seed=0), name="target",
             progress=False)
    return s


@pytest.fixture(autouse=True)
def _sqlite_tracking(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the embedded mlflow.db lands in the working directory
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    torch.manual_seed(0)


# ---- samplers ---------------------------------------------------------------------------------
def _samplers(world: int, rank: int | None):
    """Each kind of sampler make_loader builds, for one rank of `world` (rank None: read it from
    torch.distributed). With world 1 the per-rank count is doubled: the same global batch."""
    kw = {} if rank is None else {"rank": rank, "world_size": world}
    n = 40 // world
    return {"mixture": MixtureSampler({"a": (0, 30), "b": (30, 37)}, {"a": 1.0, "b": 3.0}, n, seed=3, **kw),
            "random": WindowSampler(37, replacement=True, num_samples=n, seed=3, **kw),
            "shuffled pass": WindowSampler(37, seed=3, **kw),
            "ordered pass": WindowSampler(37, shuffle=False, **kw)}


def test_samplers_shard_by_rank_into_the_single_process_stream(monkeypatch):
    single = {k: list(s) for k, s in _samplers(1, 0).items()}
    r0, r1 = ({k: list(s) for k, s in _samplers(2, r).items()} for r in (0, 1))
    for kind in single:
        # rank r takes every second element starting at r: batch k of the two ranks together (batch
        # 2 each) is batch k of one process with batch 4
        n = len(single[kind]) // 2  # a pass's 37th window: rank 1 pads with the stream's first
        assert len(r0[kind]) == len(r1[kind]) == -(-len(single[kind]) // 2), kind
        assert r0[kind][:n] == single[kind][0::2][:n] and r1[kind][:n] == single[kind][1::2][:n], kind
        assert r0[kind][:2] != r1[kind][:2], kind
    # a pass over all windows is split, padded by wrapping so both ranks get 19 of the 37
    assert sorted(set(r0["shuffled pass"]) | set(r1["shuffled pass"])) == list(range(37))
    assert len(r0["ordered pass"]) == 19 and r1["ordered pass"][-1] == 0

    # the stream is a function of (seed, epoch): each pass a new one, set_epoch replays it
    s = _samplers(1, 0)["mixture"]
    first, second = list(s), list(s)
    assert first != second
    s.set_epoch(0)
    assert list(s) == first and list(s) == second
    s.set_epoch(0)
    s.resumed_at = 6  # a run resumed mid-epoch at step 6 does not replay the epoch's first windows
    assert list(s) != first

    # rank and world size are read from torch.distributed when iterating, not when building
    lazy = _samplers(2, None)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_rank", lambda *a: 1)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda *a: 2)
    for kind, sampler in lazy.items():
        assert list(sampler) == r1[kind], kind


def test_ddp_strategies_get_the_long_timeout_and_nostras_launcher(tmp_path):
    from datetime import timedelta

    from lightning.pytorch.strategies import DDPStrategy

    from nostra.workflows.ddp import NostraDDP, trainer_kwargs

    def strategy(name):
        kw = trainer_kwargs({"strategy": name}, {}, tmp_path / "spec.json", timeout_minutes=90)
        assert kw["use_distributed_sampler"] is False  # the loaders' samplers shard themselves
        return kw["strategy"]

    for name in ("ddp", "ddp_find_unused_parameters_true"):
        assert isinstance(strategy(name), NostraDDP) and strategy(name)._timeout == timedelta(minutes=90)
    assert strategy("ddp_find_unused_parameters_true")._ddp_kwargs == {"find_unused_parameters": True}
    spawn = strategy("ddp_spawn")  # not re-launched from a command line: Lightning's launcher, our timeout
    assert type(spawn) is DDPStrategy and spawn._timeout == timedelta(minutes=90)
    assert strategy("auto") == "auto"


# ---- training ---------------------------------------------------------------------------------
LSTM_NET = {**small_net("lstm"), "image_aug": "none"}  # deterministic: no augmentation, no sampling


def _cli(*overrides, cwd):
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    out = subprocess.run([NOSTRA, "train", *overrides], capture_output=True, text=True, timeout=300, cwd=cwd, env=env)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


def _losses(run_dir: Path) -> dict[int, float]:
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["metrics"]["train/loss"] for r in records if "train/loss" in r.get("metrics", {})}


def test_cli_ddp_matches_the_doubled_batch_tracks_once_and_resumes(store, tmp_path, capsys):
    ddp_out, single_out = tmp_path / "ddp", tmp_path / "single"
    args = [f"data.store={store.path}", "data.collections=[target]", f"data.obs_keys=[{','.join(KEYS)}]",
            "model=lstm", "model.net.rnn_hidden=64", "model.net.decoder_hidden=[64,64]", "model.net.embed_dim=32",
            "model.net.encoder_hidden=[64]", "data.seq_len=8", "data.workers=0", "train.val_every=3",
            "train.progress=false", "train.experiment=ddp", f"train.out_dir={ddp_out}",
            "model.optim.lr=1e-3", "seed=0", "train.trainer={accelerator: cpu, devices: 2, strategy: ddp}"]
    _cli(*args, "data.batch_size=2", "train.max_steps=6", cwd=tmp_path)
    result = json.loads((ddp_out / "run.json").read_text())
    assert result["steps"] == 6
    assert result["ddp"]["world_size"] == 2 and result["ddp"]["distinct_first_batches"]
    assert result["ddp"]["replicas_identical"]
    runs = search_runs("ddp")
    assert len(runs) == 1 and runs["params.world_size"][0] == "2"  # one MLflow run, not one per rank

    # one process, batch 4 = 2 ranks x 2, same seed: the same windows in every step
    def spec(**kw):  # what the command line above asks for
        return train_spec(**{**dict(policy="lstm", store=str(store.path), collections=["target"], obs_keys=KEYS,
                                    net={**LSTM_NET, "rnn_horizon": 8}, optim={"lr": 1e-3}, seq_len=8, num_workers=0,
                                    val_every=3, progress=False), **kw})

    single = train(spec(out_dir=str(single_out), batch_size=4, max_steps=6, experiment="single"))
    assert "ddp" not in single
    ddp_losses, single_losses = _losses(ddp_out), _losses(single_out)
    assert ddp_losses.keys() == single_losses.keys() and len(ddp_losses) >= 3
    for step, loss in single_losses.items():  # the ranks' logged losses are averaged (sync_dist)
        assert ddp_losses[step] == pytest.approx(loss, rel=LOSS_RTOL), step
    a, b = load_net(ddp_out / "policy.ckpt"), load_net(single_out / "policy.ckpt")
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.allclose(x.float(), y.float(), rtol=0, atol=WEIGHT_ATOL), name
    batch = next(iter(make_loader(store, ["target"], KEYS, seq_len=8, batch_size=8, num_workers=0, shuffle=False)))
    with torch.no_grad():
        assert float(a.loss(batch)["loss"]) == pytest.approx(float(b.loss(batch)["loss"]), rel=LOSS_RTOL)

    # re-run with more steps under DDP (from Python this time, this process rank 0): continues from last.ckpt
    again = train(spec(out_dir=str(ddp_out), batch_size=2, max_steps=8, experiment="ddp", trainer=DDP))
    assert "resuming from" in capsys.readouterr().out
    assert again["steps"] == 8 and json.loads((ddp_out / "run.json").read_text())["steps"] == 8
    assert max(_losses(ddp_out)) > 6
    assert len(search_runs("ddp")) == 2  # one more training, one more run


@pytest.mark.sim
def test_diffusion_ddp_rollouts_on_rank_zero_keep_the_ema_in_sync(tmp_path):
    keys = ["agentview_image", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
    s = Store(tmp_path / "store.zarr")
    s.ingest(write_robomimic(tmp_path / "t.hdf5", n=4, lengths=[12] * 4, image_size=40), name="t", progress=False)
    rollout = RolloutConfig(every=2, episodes=2, final_episodes=2, horizon=5, workers=1)
    net = dict(embed_dim=16, encoder_hidden=[32], down_dims=[16, 32], step_embed_dim=16, horizon=8, n_obs_steps=2,
               n_action_steps=4, train_steps=10, sampler="ddim", inference_steps=3)
    out = tmp_path / "run"
    result = train(train_spec("diffusion", store=str(s.path), collections=["t"], obs_keys=keys, out_dir=str(out),
                              net=net, optim={"warmup_steps": 1}, seq_len=8, batch_size=2, max_steps=4, num_workers=0,
                              progress=False, val_fraction=0, experiment="t", rollout=rollout, trainer=DDP,
                              rollout_env=RolloutEnv("Lift")))
    assert result["steps"] == 4
    assert result["ddp"]["replicas_identical"] and "ema_net" in result["ddp"]["compared"]
    checks = json.loads((out / "rollouts.json").read_text())
    assert [(c["step"], c["episodes"]) for c in checks] == [(2, 2), (4, 2)]
    assert all((out / "checkpoints" / f"step={n}.ckpt").is_file() for n in (2, 4))
    assert (out / "checkpoints/best.ckpt").is_file() and result["rollouts"]["checks"] == 2
    logged = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [m["step"] for m in logged if "rollout/Lift/none/diffusion" in m.get("metrics", {})] == [2, 4]
    assert len(search_runs("t")) == 1
    # this process was rank 0: it is left as it was (no process group, no DDP environment)
    assert not torch.distributed.is_initialized()
    assert not {"LOCAL_RANK", "WORLD_SIZE", "MASTER_PORT"} & set(os.environ)
