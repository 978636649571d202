"""The training flows of the paper (section 4): pretrain on a collection, fine-tune a pretrained
checkpoint on a few target demos, co-train target demos with a retrieved manifest at a per-batch
mixture ratio. Lightning does the loop; every run is tracked (MLflow + local copy), checkpointed
and resumed from its last checkpoint when re-run."""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

from nostra.workflows import ddp
from nostra.data.dataset import SPLIT_FILE, make_loader, save_split, split_episodes
from nostra.data.store import Store
from nostra.modality import sim_observations
from nostra.policies import policy_module
from nostra.policies.checkpoint import load_net
from nostra.workflows.tracking import Tracker, TrackingLogger
from nostra.workflows.training_rollouts import RolloutCallback, RolloutConfig

STAGES = ("pretrain", "finetune", "cotrain")


@dataclass
class TrainSpec:
    policy: str
    store: str
    collections: list[str]
    keys: list[str] | None           # observation keys; None: every modality the simulator renders
    out_dir: str
    stage: str = "pretrain"
    net: dict = field(default_factory=dict)
    optim: dict = field(default_factory=dict)
    loss: dict = field(default_factory=dict)
    seq_len: int = 16
    batch_size: int = 32
    max_steps: int = 1000
    max_minutes: float | None = None  # wall-clock budget of the whole fit (Lightning's max_time); None: steps only
    keep_every: int | None = None    # keep checkpoints/step=<n>.ckpt every this many steps (None: last only)
    num_workers: int = 2
    val_fraction: float = 0.1
    val_every: int = 500
    ckpt_every: int = 500
    init_from: str | None = None     # finetune: the pretrained checkpoint
    num_demos: int | None = None     # finetune / cotrain: how many target demos to use
    manifest: str | None = None      # cotrain: retrieval manifest (JSON)
    cotrain_ratio: float = 0.5       # cotrain: share of each batch from the target demos
    seed: int = 0
    resume: bool = True
    progress: bool = True
    experiment: str = "nostra"
    run_name: str | None = None
    params: dict = field(default_factory=dict)  # extra MLflow params (task, profile, ...)
    parent_run_id: str | None = None
    trainer: dict = field(default_factory=dict)  # extra lightning.Trainer kwargs (devices, strategy, ...)
    dist_timeout_minutes: float = 360  # DDP process-group timeout: ranks wait this long for rank 0's rollouts
    rollout: RolloutConfig | None = None  # in-training rollouts and the best checkpoint (None: off)

    def __post_init__(self):
        if self.keys is None:
            self.keys = list(sim_observations().names)


def read_manifest(path: str | os.PathLike, store: Store) -> tuple[list[tuple[str, int]], str]:
    """Episodes of a retrieval manifest, checked against the store, and the manifest's hash."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"manifest {path} does not exist")
    raw = path.read_bytes()
    try:
        manifest = json.loads(raw)
        pairs = [(str(e["collection"]), int(e["episode"])) for e in manifest["episodes"]]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"manifest {path}: expected {{'episodes': [{{'collection', 'episode', ...}}]}} ({e})") from e
    have = set(store.collections())
    for c, ep in pairs:
        if c not in have:
            raise ValueError(f"manifest {path} names collection {c!r}, which the store {store.path} lacks; "
                             f"it has {sorted(have)}")
        n = len(store.episode_ends(c))
        if not 0 <= ep < n:
            raise ValueError(f"manifest {path} names episode {ep} of {c!r}, which has episodes 0..{n - 1}")
    return pairs, manifest.get("hash") or hashlib.sha256(raw).hexdigest()[:16]


def _episodes(spec: TrainSpec, store: Store):
    """(train pairs, val pairs, mixture weights or None, manifest hash)."""
    train, val = split_episodes(store, spec.collections, spec.val_fraction, spec.seed)
    if spec.num_demos is not None:
        if spec.num_demos < 1 or spec.num_demos > len(train):
            raise ValueError(f"num_demos={spec.num_demos}, but {spec.collections} have {len(train)} training demos")
        train = sorted(train)[: spec.num_demos]
    if spec.stage != "cotrain":
        return train, val, None, None
    if not spec.manifest:
        raise ValueError("stage=cotrain needs a retrieval manifest (train.manifest=<path>)")
    extra, digest = read_manifest(spec.manifest, store)
    overlap = sorted({c for c, _ in extra} & set(spec.collections))
    if overlap:
        raise ValueError(f"manifest {spec.manifest} draws from the target collections {overlap}; "
                         "co-training mixes target and retrieved collections, so they must differ")
    if not 0 < spec.cotrain_ratio < 1:
        raise ValueError(f"cotrain_ratio must be in (0, 1), got {spec.cotrain_ratio}")
    counts = {}
    for c, _ in extra:
        counts[c] = counts.get(c, 0) + 1
    weights = {c: spec.cotrain_ratio / len(spec.collections) for c in spec.collections}
    weights.update({c: (1 - spec.cotrain_ratio) * n / len(extra) for c, n in counts.items()})
    return train + extra, val, weights, digest


def _module(spec: TrainSpec, modalities, action_dim: int, stats: dict):
    module = policy_module(spec.policy)(modalities, action_dim, net=spec.net, optim=spec.optim, loss=spec.loss)
    if spec.init_from:
        # checks policy and modality set before any training; keeps the pretrained normalisation
        pretrained = load_net(spec.init_from, expected_policy=spec.policy, expected_modalities=spec.keys)
        try:
            module.net.load_state_dict(pretrained.state_dict())
        except RuntimeError as e:
            raise ValueError(f"{spec.init_from}: its network does not match this config's {spec.policy} "
                             f"network (net={spec.net}): {e}") from e
    else:
        module.set_normalization(stats)
    return module


class _ResumedStream(L.Callback):
    """A resumed run continues its epoch from a fresh loader iterator: the sampler's stream is
    seeded by the step it resumes at too, so it does not replay the windows the epoch began with
    (the same on every rank, so the ranks' shards still interleave)."""

    def __init__(self, sampler):
        self.sampler = sampler

    def on_train_start(self, trainer, pl_module) -> None:
        if hasattr(self.sampler, "resumed_at"):
            self.sampler.resumed_at = int(trainer.global_step)


def train(spec: TrainSpec) -> dict:
    """Run one training flow; returns paths and the tracking summary."""
    if spec.stage not in STAGES:
        raise ValueError(f"unknown training stage {spec.stage!r}; valid: {', '.join(STAGES)}")
    if spec.stage == "finetune" and not spec.init_from:
        raise ValueError("stage=finetune needs a pretrained checkpoint (train.init_from=<path>)")
    start = time.time()
    L.seed_everything(spec.seed, workers=True, verbose=False)
    store = Store(spec.store)
    train_eps, val_eps, weights, manifest_hash = _episodes(spec, store)
    collections = weights if weights is not None else spec.collections
    loader = make_loader(store, collections, spec.keys, spec.seq_len, spec.batch_size, spec.num_workers,
                         episodes=train_eps, num_samples=spec.max_steps * spec.batch_size, seed=spec.seed)
    ds = loader.dataset
    module = _module(spec, ds.modalities(), ds.action_dim, ds.stats())
    val_loader = None
    if val_eps:
        val_loader = make_loader(store, sorted({c for c, _ in val_eps}), spec.keys, spec.seq_len, spec.batch_size,
                                 0, episodes=val_eps, shuffle=False)

    out = Path(spec.out_dir)
    callbacks = [ModelCheckpoint(dirpath=out / "checkpoints", save_last=True, every_n_train_steps=spec.ckpt_every,
                                 save_top_k=0)]
    if spec.keep_every:
        callbacks.append(ModelCheckpoint(dirpath=out / "checkpoints", filename="step={step}", auto_insert_metric_name=False,
                                         every_n_train_steps=spec.keep_every, save_top_k=-1))
    rollouts = None
    if spec.rollout is not None and (spec.rollout.every or spec.rollout.final_episodes):
        from nostra.policies import runner_class

        rollouts = RolloutCallback(spec.rollout, spec.policy, out, runner_class(spec.policy).can_imagine)
        callbacks.append(rollouts)
    callbacks.append(_ResumedStream(loader.sampler))
    replicas = ddp.ReplicaCheck()  # under DDP: ranks draw different windows and end with the same weights
    callbacks.append(replicas)
    max_time = {"minutes": spec.max_minutes} if spec.max_minutes else None
    logger = TrackingLogger()
    kwargs = dict(max_steps=spec.max_steps, max_time=max_time, logger=logger, callbacks=callbacks,
                  enable_progress_bar=spec.progress, enable_model_summary=False,
                  log_every_n_steps=max(1, min(10, spec.max_steps // 3)),
                  val_check_interval=min(spec.val_every, spec.max_steps) if val_loader else None,
                  limit_val_batches=4, num_sanity_val_steps=0)
    trainer = ddp.make_trainer({**kwargs, **spec.trainer}, asdict(spec), out / "ddp_spec.json",
                               spec.dist_timeout_minutes)
    # built on every rank (a distributed run starts its other ranks in trainer.fit); only global rank 0 tracks
    zero = trainer.is_global_zero
    if zero:  # evaluation's offline analysis reads the held-out episodes from here
        out.mkdir(parents=True, exist_ok=True)
        save_split(out / SPLIT_FILE, train_eps, val_eps)
    params = {"model": spec.policy, "stage": spec.stage, "seed": spec.seed, "collections": ",".join(spec.collections),
              "num_demos": spec.num_demos, "manifest_hash": manifest_hash, "max_steps": spec.max_steps,
              "init_from": spec.init_from, "world_size": trainer.world_size, **spec.params}
    tracker = Tracker(spec.experiment, spec.run_name or f"{spec.stage}-{spec.policy}", out, params,
                      tags={"stage": spec.stage}, parent_run_id=spec.parent_run_id, rank=trainer.global_rank)
    logger.tracker = tracker
    last = out / "checkpoints" / "last.ckpt"
    resume = str(last) if spec.resume and last.is_file() else None
    if resume and zero:
        print(f"resuming from {resume}")
    status, final = "FAILED", out / "policy.ckpt"
    with ddp.session():
        try:
            trainer.fit(module, loader, val_loader, ckpt_path=resume)
            trainer.save_checkpoint(final)  # collective under DDP: every rank calls it, rank 0 writes
            status = "FINISHED"
        finally:
            tracker.log_artifact(out / "metrics.jsonl")
            summary = tracker.finish(status)
    result = {"checkpoint": str(final), "run_id": tracker.run_id, "tracking": summary, "manifest_hash": manifest_hash,
              "steps": int(trainer.global_step), "train_episodes": len(train_eps), "val_episodes": len(val_eps),
              "wall_seconds": round(time.time() - start, 1)}
    if replicas.report:
        result["ddp"] = replicas.report
    if rollouts is not None:
        result["rollouts"] = rollouts.summary()
        result["best_checkpoint"] = str(out / "checkpoints" / "best.ckpt")
    if zero:
        (out / "run.json").write_text(json.dumps(result, indent=2))
        print(summary)
    return result
