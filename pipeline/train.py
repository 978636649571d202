"""`nostra train stage=pretrain|finetune|cotrain [overrides]`."""

from __future__ import annotations

from omegaconf import OmegaConf

from pipeline._hydra import run


def _app(cfg) -> None:
    from nostra.configs import typed
    from nostra.workflows.training import TrainSpec, train
    from nostra.workflows.training_rollouts import RolloutEnv
    from pipeline.evaluate import noise_windows

    t = typed(cfg.train, "train")  # nostra.configs.TrainConfig
    # data.collections may be one name (an interpolated list is not type-checked)
    t.collections = [t.collections] if isinstance(t.collections, str) else list(t.collections)
    if not t.collections:
        raise SystemExit("nostra train: no collections to train on; set data.collections=[<name>,...] "
                         "(`nostra ingest` prints the names in the store)")
    # the rollouts during training use the evaluation's windows and noise (`nostra evaluate`)
    # (no image size: rollouts render the checkpoint's)
    env = RolloutEnv(task=cfg.task.name, windows=noise_windows(cfg),
                     noise_params=OmegaConf.to_container(cfg.noise, resolve=True))
    spec = TrainSpec(model=typed(cfg.model, "model"), train=t, store=cfg.data.store, seq_len=cfg.data.seq_len,
                     batch_size=cfg.data.batch_size, num_workers=cfg.data.workers, val_fraction=cfg.data.val_fraction,
                     seed=cfg.seed, params={"task": cfg.task.name, "profile": cfg.profile.name}, rollout_env=env)
    train(spec)


def main(argv: list[str]) -> int:
    return run("train", argv, _app)
