"""Loading a trained policy from a Lightning checkpoint with no training code, with clear errors
for a file that is not a policy checkpoint, another policy, or another modality set.

The metadata is written here too (``write_meta``, which ``PolicyModule.on_save_checkpoint`` calls;
CHECKPOINT_FORMAT is in nostra.policies.base). Imports go one way: this module imports base and the policy registry
(nostra.policies); neither imports this module (tests/test_imports.py checks it)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Iterable

import torch

from nostra.configs import ConfigError, ModelConfig, model_config
from nostra.modality import as_modalities
from nostra.policies import POLICIES, net_class, runner_class
from nostra.policies.base import CHECKPOINT_FORMAT


class CheckpointError(ValueError):
    pass


def write_meta(checkpoint: dict, config: ModelConfig, modalities: list[dict], action_dim: int) -> None:
    """Store the policy's metadata in a Lightning checkpoint dict: the format, the observation
    contract (the modalities, plain), the action size and the whole typed config (policy, net,
    optim, loss), from which ``load_net`` rebuilds the network."""
    checkpoint["nostra"] = {"format": CHECKPOINT_FORMAT, "modalities": modalities, "action_dim": action_dim,
                            **asdict(config)}


def read_meta(path) -> tuple[dict, dict]:
    """(meta, state_dict) of a policy checkpoint (its metadata written by ``write_meta``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for a non-checkpoint file
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({type(e).__name__}: {e})") from e
    meta = ckpt.get("nostra") if isinstance(ckpt, dict) else None
    if not isinstance(meta, dict) or "policy" not in meta or "state_dict" not in ckpt:
        raise CheckpointError(f"{path}: not a nostra policy checkpoint (no 'nostra' metadata or 'state_dict')")
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')} is not the supported {CHECKPOINT_FORMAT}")
    return meta, ckpt["state_dict"]


def load_net(path, expected_policy: str | None = None, expected_modalities: Iterable[str] | None = None):
    """Build the policy network stored in ``path`` and load its weights (eval mode)."""
    meta, state = read_meta(path)
    policy = meta["policy"]
    if policy not in POLICIES:
        raise CheckpointError(f"{path}: unknown policy {policy!r}; valid: {', '.join(POLICIES)}")
    if expected_policy is not None and policy != expected_policy:
        raise CheckpointError(f"{path} holds a '{policy}' policy, not '{expected_policy}'")
    modalities = as_modalities(meta["modalities"])
    names = [m.name for m in modalities]
    if expected_modalities is not None and sorted(expected_modalities) != sorted(names):
        raise CheckpointError(f"{path} was trained on modalities {sorted(names)}, "
                              f"but {sorted(expected_modalities)} were given")
    net = net_class(policy)(modalities, meta["action_dim"], **asdict(stored_config(path, meta).net))
    # a policy that trains with an EMA copy (diffusion's AveragedModel ``ema_net``) deploys the averaged weights
    prefix = "ema_net.module." if any(k.startswith("ema_net.module.") for k in state) else "net."
    weights = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    try:
        net.load_state_dict(weights)
    except RuntimeError as e:
        raise CheckpointError(f"{path}: weights do not fit a '{policy}' network with its stored config: {e}") from e
    return net.eval()


def stored_config(path, meta: dict) -> ModelConfig:
    """The typed model config a checkpoint's metadata holds. One written before the whole config was
    stored has only ``net`` (the defaults complete it as they did in training); its optim and
    loss show the defaults, not necessarily what it was trained with."""
    try:
        return model_config(meta["policy"], **{k: meta.get(k) for k in ("net", "optim", "loss")})
    except ConfigError as e:
        raise CheckpointError(f"{path}: its stored config does not fit this code's '{meta['policy']}' "
                              f"policy: {e}") from e


def load_runner(path, modalities: Iterable[str] | None = None, expected_policy: str | None = None,
                **runner_kwargs):
    """The runner of whatever policy ``path`` holds (refused unless it is ``expected_policy``, when given)."""
    net = load_net(path, expected_policy=expected_policy, expected_modalities=modalities)
    return runner_class(net.policy)(net, **runner_kwargs)


CHOICES = "best | last | step=<n>"


def select_checkpoint(path, which: str = "last") -> str:
    """The checkpoint of a training run that ``which`` names: ``last`` is ``path`` itself (the run's
    final ``policy.ckpt``); ``best`` the run's ``checkpoints/best.ckpt`` (best in-training rollout
    success); ``step=<n>`` the ``checkpoints/step=<n>.ckpt`` kept at that step."""
    path, which = Path(path), str(which)
    run = path if path.is_dir() else path.parent
    if which == "last":
        return str(run / "policy.ckpt" if path.is_dir() else path)
    if which == "best":
        best = run / "checkpoints" / "best.ckpt"
        if not best.is_file():
            raise FileNotFoundError(f"checkpoint=best: {best} does not exist; the run in {run} was trained without "
                                    "in-training rollouts (train.rollout); use checkpoint=last or a step")
        return str(best)
    if which.startswith("step=") and which[5:].isdigit():
        step = run / "checkpoints" / f"{which}.ckpt"
        if not step.is_file():
            kept = sorted(p.stem for p in (run / "checkpoints").glob("step=*.ckpt"))
            raise FileNotFoundError(f"checkpoint={which}: {step} does not exist; {run} keeps {kept or 'no step checkpoints'}")
        return str(step)
    raise ValueError(f"unknown checkpoint choice {which!r}; valid: {CHOICES}")
