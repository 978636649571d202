"""`nostra evaluate [overrides]`: robustness rollouts and offline analyses of trained policies."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from pipeline._hydra import run


def _rollouts(cfg, e) -> None:
    """e: the typed evaluate config (nostra.configs.EvaluateConfig)."""
    from nostra.workflows.evaluation import EvalSpec, Variant, evaluate
    from nostra.policies.checkpoint import select_checkpoint

    variants = [Variant(name, select_checkpoint(v.checkpoint, e.checkpoint), v.mode, v.rnn_horizon, dict(v.adamli or {}))
                for name, v in e.variants.items() if v]  # null: left out
    spec = EvalSpec.from_config(e, variants=variants, windows=noise_windows(cfg), run_name=f"evaluate-{'-'.join(e.tasks)}",
                                params={"profile": cfg.profile.name, "seed": cfg.seed, "task": ",".join(e.tasks),
                                        "table": e.table, "setting": e.setting, "checkpoint": e.checkpoint})
    table = evaluate(spec)
    print((Path(e.out_dir) / "success.md").read_text())
    print(f"{len(table)} cells; results in {e.out_dir}")


def noise_windows(cfg) -> dict:
    """evaluate.windows, else the task config's noise_windows, else the registry's (paper) ones
    (also what the rollouts during training use)."""
    windows = OmegaConf.to_container(cfg.evaluate.windows, resolve=True) if cfg.evaluate.windows else {}
    if not isinstance(windows, dict):
        raise SystemExit(f"evaluate.windows={windows!r}: expected task -> [[start, end], ...], "
                         f"e.g. 'evaluate.windows={{{cfg.task.name}: [[30, 60]]}}'")
    if cfg.task.name not in windows and cfg.task.get("noise_windows"):
        windows[cfg.task.name] = OmegaConf.to_container(cfg.task.noise_windows, resolve=True)
    return windows


def _run_dir(checkpoint: str) -> Path:
    """The training run a checkpoint belongs to (policy.ckpt in it, the others in its checkpoints/)."""
    p = Path(checkpoint).parent
    return p.parent if p.name == "checkpoints" else p


def _offline(cfg, e) -> None:
    from nostra.workflows.analysis import OfflineSpec, analyse
    from nostra.data.dataset import run_episodes
    from nostra.workflows.tracking import Tracker

    o = e.offline
    collections = o.collections
    episodes = run_episodes(_run_dir(o.checkpoint), collections, o.split)  # the training run's own split
    if not episodes:
        raise ValueError(f"{o.checkpoint}: its training run's {o.split} split has no episode of {collections}")
    spec = OfflineSpec(checkpoint=o.checkpoint, store=cfg.data.store, episodes=episodes[: o.episodes],
                       split=o.split, noise=o.noise, windows=o.windows,
                       out_dir=str(Path(e.out_dir) / "offline"), seed=cfg.seed,
                       noise_params=e.noise_params, adamli=dict(o.adamli or {}))
    result = analyse(spec)
    tracker = Tracker(e.experiment, f"offline-{'-'.join(e.tasks)}", spec.out_dir,
                      {"checkpoint": o.checkpoint, "noise": o.noise, "episodes": len(spec.episodes), "split": o.split,
                       "profile": cfg.profile.name, "task": ",".join(e.tasks), "seed": cfg.seed, "model": "nostra",
                       "setting": o.setting})
    metrics = {f"kl_nats/{m}": v for m, v in result["kl_nats"].items()}
    metrics.update({f"action_mse/{v}": x for v, x in result["action_mse"].items()})
    if "detect" in result:
        metrics.update({"detect/precision": result["detect"]["all"]["precision"],
                        "detect/recall": result["detect"]["all"]["recall"]})
        metrics.update({f"detect/{k}/{m}": s[k] for m, s in result["detect"].items() for k in ("precision", "recall")})
    metrics.update({f"false_imagination/{m}": v for m, v in result.get("false_imagination", {}).items()})
    tracker.log_metrics(metrics)
    for name in ("offline.md", "kl_episode.png"):
        if (Path(spec.out_dir) / name).is_file():
            tracker.log_artifact(Path(spec.out_dir) / name)
    print((Path(spec.out_dir) / "offline.md").read_text())
    print(tracker.finish())


def _app(cfg) -> None:
    from nostra.configs import typed

    e = typed(cfg.evaluate, "evaluate")  # nostra.configs.EvaluateConfig
    # data.collections may be one name (an interpolated list is not type-checked)
    if isinstance(e.offline.collections, str):
        e.offline.collections = [e.offline.collections]
    if e.rollouts:
        _rollouts(cfg, e)
    if e.offline.enabled:
        _offline(cfg, e)


def main(argv: list[str]) -> int:
    return run("evaluate", argv, _app)
