"""`nostra train stage=pretrain|finetune|cotrain [overrides]`."""

from __future__ import annotations

from omegaconf import OmegaConf

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.workflows.training import TrainSpec, train
    from nostra.workflows.training_rollouts import RolloutConfig

    t = cfg.train
    collections = OmegaConf.to_container(t.collections, resolve=True)
    if isinstance(collections, str):
        collections = [collections]
    if not collections:
        raise SystemExit("nostra train: no collections to train on; set data.collections=[<name>,...] "
                         "(`nostra ingest` prints the names in the store)")
    model = OmegaConf.to_container(cfg.model, resolve=True)
    spec = TrainSpec(
        policy=model["policy"], store=cfg.data.store, collections=list(collections),
        keys=list(t.obs_keys) if t.obs_keys else None, out_dir=t.out_dir, stage=t.stage, net=model.get("net", {}), optim=model.get("optim", {}),
        loss=model.get("loss", {}), seq_len=cfg.data.seq_len, batch_size=cfg.data.batch_size, max_steps=t.max_steps,
        max_minutes=t.max_minutes, keep_every=t.keep_every,
        num_workers=cfg.data.workers, val_fraction=cfg.data.val_fraction, val_every=t.val_every,
        ckpt_every=t.ckpt_every, init_from=t.init_from, num_demos=t.num_demos, manifest=t.manifest,
        cotrain_ratio=t.cotrain_ratio, seed=cfg.seed, resume=t.resume, progress=t.progress,
        experiment=t.experiment, run_name=t.run_name, parent_run_id=t.parent_run_id,
        params={"task": cfg.task.name, "profile": cfg.profile.name},
        trainer=OmegaConf.to_container(t.trainer, resolve=True),
        dist_timeout_minutes=t.dist_timeout_minutes, rollout=_rollout(cfg, RolloutConfig))
    train(spec)


def _rollout(cfg, config_cls):
    """train.rollout -> the in-training rollout config (windows and noise as `nostra evaluate` uses)."""
    from pipeline.evaluate import noise_windows

    r = OmegaConf.to_container(cfg.train.rollout, resolve=True)
    if not r.pop("enabled"):
        return None
    return config_cls(task=cfg.task.name, windows=noise_windows(cfg), noise_params=OmegaConf.to_container(cfg.noise, resolve=True),
                      **r)  # no image size: rollouts render the checkpoint's


def main(argv: list[str]) -> int:
    return run("train", argv, _app)
