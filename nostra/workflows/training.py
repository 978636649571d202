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
from lightning.pytorch.callbacks import ModelCheckpoint, Timer

from nostra.configs import ModelConfig, TrainConfig, from_dict, model_config
from nostra.workflows import ddp
from nostra.data.dataset import SPLIT_FILE, make_loader, save_split, split_episodes
from nostra.data.store import Store
from nostra.modality import sim_observations
from nostra.policies.modules import policy_module
from nostra.policies.checkpoint import load_net
from nostra.workflows.tracking import Tracker, TrackingLogger
from nostra.workflows.training_rollouts import RolloutCallback, RolloutEnv

STAGES = ("pretrain", "finetune", "cotrain")


@dataclass
class TrainSpec:
    """One training run: the typed model and train configs (nostra.configs: conf/model, conf/train)
    and what the data and task configs add."""
    model: ModelConfig               # policy, net, optim (, loss)
    train: TrainConfig               # collections, steps, stage, checkpoints, tracking, trainer, rollouts
    store: str
    seq_len: int = 16
    batch_size: int = 32
    num_workers: int = 2
    val_fraction: float = 0.1
    seed: int = 0
    params: dict = field(default_factory=dict)  # extra MLflow params (task, profile, ...)
    rollout_env: RolloutEnv | None = None        # where train.rollout runs; needed when its every > 0

    @classmethod
    def from_dict(cls, d: dict) -> "TrainSpec":
        """The inverse of dataclasses.asdict (DDP ranks read the spec from JSON)."""
        env = d.get("rollout_env")
        return cls(**{**d, "model": model_config(**d["model"]), "train": from_dict(TrainConfig, d["train"]),
                      "rollout_env": env and RolloutEnv(**env)})

    def __post_init__(self):
        # data.weights=null reaches the typed config as None (an interpolation is not validated);
        # {} keeps the spec's JSON (DDP ranks) within TrainConfig's types
        self.train.weights = dict(self.train.weights or {})
        if self.train.obs_keys is None:  # every modality the simulator renders
            self.train.obs_keys = list(sim_observations().names)


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
    t = spec.train
    train, val = split_episodes(store, t.collections, spec.val_fraction, spec.seed)
    if t.num_demos is not None:
        if t.num_demos < 1 or t.num_demos > len(train):
            raise ValueError(f"num_demos={t.num_demos}, but {t.collections} have {len(train)} training demos")
        train = sorted(train)[: t.num_demos]
    if t.stage != "cotrain":
        return train, val, _mixture(t), None
    if t.weights:
        raise ValueError("stage=cotrain mixes target and retrieved demos by train.cotrain_ratio; "
                         f"data.weights={t.weights} is for the other stages")
    if not t.manifest:
        raise ValueError("stage=cotrain needs a retrieval manifest (train.manifest=<path>)")
    extra, digest = read_manifest(t.manifest, store)
    overlap = sorted({c for c, _ in extra} & set(t.collections))
    if overlap:
        raise ValueError(f"manifest {t.manifest} draws from the target collections {overlap}; "
                         "co-training mixes target and retrieved collections, so they must differ")
    if not 0 < t.cotrain_ratio < 1:
        raise ValueError(f"cotrain_ratio must be in (0, 1), got {t.cotrain_ratio}")
    counts = {}
    for c, _ in extra:
        counts[c] = counts.get(c, 0) + 1
    weights = {c: t.cotrain_ratio / len(t.collections) for c in t.collections}
    weights.update({c: (1 - t.cotrain_ratio) * n / len(extra) for c, n in counts.items()})
    return train + extra, val, weights, digest


def _mixture(t: TrainConfig) -> dict[str, float] | None:
    """data.weights, checked against the collections trained on."""
    if not t.weights:
        return None
    if set(t.weights) != set(t.collections):
        raise ValueError(f"data.weights={t.weights} must give one weight per collection of "
                         f"data.collections={t.collections}")
    return dict(t.weights)


def _module(spec: TrainSpec, modalities, action_dim: int, stats: dict):
    model, init_from = asdict(spec.model), spec.train.init_from
    policy = model.pop("policy")
    module = policy_module(policy)(modalities, action_dim, **model)
    if init_from:
        # checks policy and modality set before any training; keeps the pretrained normalisation
        pretrained = load_net(init_from, expected_policy=policy, expected_modalities=spec.train.obs_keys)
        try:
            module.net.load_state_dict(pretrained.state_dict())
        except RuntimeError as e:
            raise ValueError(f"{init_from}: its network does not match this config's {policy} "
                             f"network (net={model['net']}): {e}") from e
    else:
        module.set_normalization(stats)
    return module


def _rollouts(spec: TrainSpec, out: Path):
    """The in-training rollouts' callback (train.rollout.every > 0), else None."""
    from nostra.policies import runner_class

    if spec.train.rollout.every <= 0:
        return None
    if spec.rollout_env is None:
        raise ValueError("train.rollout.every > 0: the rollouts need TrainSpec.rollout_env (the task and its noise)")
    policy = spec.model.policy
    return RolloutCallback(spec.train.rollout, spec.rollout_env, policy, out, runner_class(policy).can_imagine)


class _ResumedStream(L.Callback):
    """A resumed run continues its epoch from a fresh loader iterator: the sampler's stream is
    seeded by the step it resumes at too, so it does not replay the windows the epoch began with
    (the same on every rank, so the ranks' shards still interleave)."""

    def __init__(self, sampler):
        self.sampler = sampler

    def on_train_start(self, trainer, pl_module) -> None:
        if hasattr(self.sampler, "resumed_at"):
            self.sampler.resumed_at = int(trainer.global_step)


def window_length(spec: TrainSpec) -> int:
    """data.seq_len, raised to the policy's shortest window (Diffusion Policy: its prediction horizon,
    as diffusion_policy sizes its windows) so one profile serves every policy."""
    need = spec.model.net.min_window()
    if spec.seq_len < need:
        print(f"training windows of {need} steps (data.seq_len={spec.seq_len} is shorter than "
              f"{spec.model.policy}'s horizon)")
    return max(spec.seq_len, need)


def train(spec: TrainSpec) -> dict:
    """Run one training flow; returns paths and the tracking summary."""
    t, policy = spec.train, spec.model.policy
    if t.stage not in STAGES:
        raise ValueError(f"unknown training stage {t.stage!r}; valid: {', '.join(STAGES)}")
    if t.stage == "finetune" and not t.init_from:
        raise ValueError("stage=finetune needs a pretrained checkpoint (train.init_from=<path>)")
    start = time.time()
    out = Path(t.out_dir)
    if t.skip_finished and (out / "run.json").is_file():
        print(f"nostra train: {out} finished before (run.json), kept")
        return json.loads((out / "run.json").read_text())
    rollouts = _rollouts(spec, out)
    L.seed_everything(spec.seed, workers=True, verbose=False)
    store = Store(spec.store)
    train_eps, val_eps, weights, manifest_hash = _episodes(spec, store)
    collections = weights if weights is not None else t.collections
    seq_len = window_length(spec)
    loader = make_loader(store, collections, t.obs_keys, seq_len, spec.batch_size, spec.num_workers,
                         episodes=train_eps, num_samples=t.max_steps * spec.batch_size, seed=spec.seed)
    ds = loader.dataset
    module = _module(spec, ds.modalities(), ds.action_dim, ds.stats())
    val_loader = None
    if val_eps:
        val_loader = make_loader(store, sorted({c for c, _ in val_eps}), t.obs_keys, seq_len, spec.batch_size,
                                 0, episodes=val_eps, shuffle=False)

    callbacks = [ModelCheckpoint(dirpath=out / "checkpoints", save_last=True, every_n_train_steps=t.val_every,
                                 save_top_k=0)]
    if t.keep_every:
        callbacks.append(ModelCheckpoint(dirpath=out / "checkpoints", filename="step={step}", auto_insert_metric_name=False,
                                         every_n_train_steps=t.keep_every, save_top_k=-1))
    if rollouts is not None:
        callbacks.append(rollouts)
    callbacks.append(_ResumedStream(loader.sampler))
    replicas = ddp.ReplicaCheck()  # under DDP: ranks draw different windows and end with the same weights
    callbacks.append(replicas)
    max_time = {"minutes": t.max_minutes} if t.max_minutes else None
    if max_time is None:  # Lightning adds its own Timer for max_time; either one keeps the time across resumes
        callbacks.append(Timer(verbose=False))
    logger = TrackingLogger()
    kwargs = dict(max_steps=t.max_steps, max_time=max_time, logger=logger, callbacks=callbacks,
                  enable_progress_bar=t.progress, enable_model_summary=False,
                  log_every_n_steps=max(1, min(10, t.max_steps // 3)),
                  val_check_interval=min(t.val_every, t.max_steps) if val_loader else None,
                  limit_val_batches=4, num_sanity_val_steps=0)
    trainer = ddp.make_trainer({**kwargs, **t.trainer}, asdict(spec), out / "ddp_spec.json", t.dist_timeout_minutes)
    # built on every rank (a distributed run starts its other ranks in trainer.fit); only global rank 0 tracks
    zero = trainer.is_global_zero
    if zero:  # evaluation's offline analysis reads the held-out episodes from here
        out.mkdir(parents=True, exist_ok=True)
        save_split(out / SPLIT_FILE, train_eps, val_eps)
    params = {"model": policy, "stage": t.stage, "seed": spec.seed, "collections": ",".join(t.collections),
              "num_demos": t.num_demos, "manifest_hash": manifest_hash, "max_steps": t.max_steps,
              "init_from": t.init_from, "world_size": trainer.world_size, **spec.params}
    tracker = Tracker(t.experiment, t.run_name or f"{t.stage}-{policy}", out, params,
                      tags={"stage": t.stage}, parent_run_id=t.parent_run_id, rank=trainer.global_rank)
    logger.tracker = tracker
    last = out / "checkpoints" / "last.ckpt"
    resume = str(last) if t.resume and last.is_file() else None
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
              "wall_seconds": round(time.time() - start, 1), "resumed": resume is not None,
              "train_seconds": round(_train_seconds(trainer), 1)}
    if replicas.report:
        result["ddp"] = replicas.report
    if rollouts is not None:
        result["rollouts"] = rollouts.summary()
        result["best_checkpoint"] = str(out / "checkpoints" / "best.ckpt")
    if zero:
        (out / "run.json").write_text(json.dumps(result, indent=2))
        print(summary)
    return result


def _train_seconds(trainer) -> float:
    """The fit's time over every sitting: the Timer's state travels in last.ckpt, so a resumed run counts the
    time its earlier sittings spent up to that checkpoint (wall_seconds counts this process only)."""
    timer = next(c for c in trainer.callbacks if isinstance(c, Timer))
    return timer.time_elapsed("train")
