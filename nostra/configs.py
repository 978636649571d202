"""The typed configs (LeRobot keeps one beside each model): a dataclass per policy (network,
optimiser, loss) and one for a training run. They hold the defaults: conf/model/*.yaml and
conf/train/default.yaml extend them as Hydra structured-config schemas (registered by
pipeline/_hydra.py), so an unknown key or a value of the wrong type fails when the config is
composed; the policies read their settings from them and checkpoints store them.

Plain dataclasses, no torch: every `nostra` stage imports this module to compose its config (it
lives here, not in nostra.policies, whose package imports torch and diffusers)."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException


class ConfigError(ValueError):
    pass


# ---- policies ------------------------------------------------------------------------------------

@dataclass
class EncoderConfig:
    """The per-modality encoders every policy network has (nostra.policies.base.PolicyNet)."""
    embed_dim: int = 128
    encoder_hidden: list[int] = field(default_factory=lambda: [256])
    image_encoder: str = "light"     # light | spatial | resnet18 (nostra.models.encoders)
    image_norm: str = "group"
    image_aug: str = "none"          # training-only crop | shift | none (encoders.ImageAug)
    aug_pixels: int = 8
    keypoints: int = 32

    def min_window(self) -> int:
        """The shortest training window (steps) the policy's loss accepts."""
        return 1


@dataclass
class LSTMNetConfig(EncoderConfig):
    """BC-LSTM (robomimic BC-RNN): 2-layer LSTM, MLP or GMM head."""
    rnn_hidden: int = 400
    rnn_layers: int = 2
    decoder_hidden: list[int] = field(default_factory=lambda: [400, 400])
    head: str = "gaussian"           # gaussian | gmm
    action_std: float = 1.0
    gmm_modes: int = 5
    rnn_horizon: int = 0             # rollouts reset the LSTM state this often (0: never)


@dataclass
class StateSpaceNetConfig(EncoderConfig):
    """BC-NOSTRA and BC-RSSM (nostra.policies.state_space), paper Table 7."""
    latent_dim: int = 40
    deter: int = 256
    hidden: int = 256
    min_std: float = 0.1
    fusion_embed: int = 256
    fusion_heads: int = 2
    fusion_blocks: int = 1
    fusion_out: int = 256
    decoder_hidden: list[int] = field(default_factory=lambda: [400, 400])
    head: str = "gaussian"           # gaussian | gmm
    action_std: float = 1.0
    gmm_modes: int = 5
    rnn_horizon: int = 0             # rollouts restart the filter this often (0: never)


@dataclass
class DiffusionNetConfig(EncoderConfig):
    """Diffusion Policy, CNN variant, paper Table 8: observation horizon 2, action horizon 8,
    prediction horizon 16 (train with data.seq_len >= 16), DDPM with 100 squared-cosine steps."""
    horizon: int = 16
    n_obs_steps: int = 2
    n_action_steps: int = 8
    down_dims: list[int] = field(default_factory=lambda: [256, 512, 1024])  # 83.6M parameters
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 256
    train_steps: int = 100
    sampler: str = "ddpm"            # ddpm | ddim; the runner may override (e.g. ddim with 10 steps)
    inference_steps: int | None = None   # None: train_steps

    def min_window(self) -> int:
        return self.horizon  # the loss denoises a whole horizon of actions


@dataclass
class OptimConfig:
    """Adam with the paper's constant learning rate (Table 7). ``lr_scheduler`` (a diffusers schedule
    name: cosine, linear, ...) decays it over ``total_steps`` instead, after ``warmup_steps``: not the
    paper's recipe, for a short CPU budget whose last checkpoint should not land on a swing."""
    lr: float = 1e-4
    lr_scheduler: str = "constant"
    warmup_steps: int = 0
    total_steps: int | None = None   # the schedule's length; None: the trainer's (max_steps)


@dataclass
class DiffusionOptimConfig(OptimConfig):
    """AdamW with warm-up and half-cycle cosine decay; EMA weights deployed."""
    betas: list[float] = field(default_factory=lambda: [0.95, 0.999])
    eps: float = 1e-8
    weight_decay: float = 1e-6
    lr_scheduler: str = "cosine"
    warmup_steps: int = 500
    ema_power: float = 0.75
    ema_max_decay: float = 0.9999


@dataclass
class KLLossConfig:
    """L = NLL + beta * [gamma KL(q || sg(p)) + (1 - gamma) KL(sg(q) || p)] (state_space.loss)."""
    beta: float = 1e-4
    gamma: float = 0.1


@dataclass
class ModelConfig:
    """conf/model: the policy's name; each policy's config adds net, optim (and loss)."""
    policy: str = ""


@dataclass
class LSTMConfig(ModelConfig):
    policy: str = "lstm"
    net: LSTMNetConfig = field(default_factory=LSTMNetConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)


@dataclass
class NostraConfig(ModelConfig):
    policy: str = "nostra"
    net: StateSpaceNetConfig = field(default_factory=StateSpaceNetConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    loss: KLLossConfig = field(default_factory=KLLossConfig)


@dataclass
class RSSMConfig(NostraConfig):
    policy: str = "rssm"


@dataclass
class DiffusionConfig(ModelConfig):
    policy: str = "diffusion"
    net: DiffusionNetConfig = field(default_factory=DiffusionNetConfig)
    optim: DiffusionOptimConfig = field(default_factory=DiffusionOptimConfig)


MODEL_CONFIGS: dict[str, type[ModelConfig]] = {
    "nostra": NostraConfig, "rssm": RSSMConfig, "lstm": LSTMConfig, "diffusion": DiffusionConfig}


def model_config(policy: str, **sections: dict | None) -> ModelConfig:
    """The typed config of ``policy`` from plain dicts (``net={...}, optim={...}, loss={...}``);
    keys left out take the defaults, an empty or None section is left out."""
    if policy not in MODEL_CONFIGS:
        raise ConfigError(f"unknown policy {policy!r}; valid: {', '.join(MODEL_CONFIGS)}")
    return from_dict(MODEL_CONFIGS[policy], {k: v for k, v in sections.items() if v})


# ---- training ------------------------------------------------------------------------------------

@dataclass
class RolloutConfig:
    """train.rollout: rollouts during training (nostra.workflows.training_rollouts), on when every > 0."""
    every: int = 0                   # steps between checks; 0: no in-training rollouts
    episodes: int = 10               # per cell at each check
    final_episodes: int = 50         # per cell at the end of training
    noises: list[str] = field(default_factory=lambda: ["none"])
    modes: list[str] = field(default_factory=lambda: ["closed"])   # closed | oracle (MLI) | adaptive (AdaMLI)
    seed: int = 1000                 # episode i has seed seed + i at every check: demos use seeds from 0
    horizon: int | None = None       # None: the task's
    workers: int = 2


@dataclass
class TrainConfig:
    """conf/train: one training flow of the paper (nostra.workflows.training.train)."""
    collections: list[str]           # target collection(s)
    obs_keys: list[str] | None       # None: every modality the simulator renders (nostra.modality)
    out_dir: str
    # {collection: weight}: a mixture of `collections` (not cotrain: its mixture is cotrain_ratio); empty or
    # None: windows uniformly. Not `| None`: OmegaConf resolves an Optional dict's interpolation too early
    weights: dict[str, float] = field(default_factory=dict)
    stage: str = "pretrain"          # pretrain | finetune | cotrain
    max_steps: int = 1000
    max_minutes: float | None = None   # wall-clock budget of the whole fit, rollouts included; None: steps only
    val_every: int = 500             # validate and save checkpoints/last.ckpt every this many steps
    keep_every: int | None = None    # also keep checkpoints/step=<n>.ckpt every this many steps
    init_from: str | None = None     # finetune: the pretrained checkpoint (same policy and modalities)
    num_demos: int | None = None     # finetune / cotrain: the first N training episodes of the target
    manifest: str | None = None      # cotrain: retrieval manifest JSON (nostra retrieve)
    cotrain_ratio: float = 0.5       # cotrain: share of each batch drawn from the target demos
    resume: bool = True              # continue from out_dir/checkpoints/last.ckpt when it exists
    skip_finished: bool = False      # out_dir/run.json exists (the run ended): keep it, train nothing (`nostra sweep`)
    experiment: str = "nostra"       # MLflow experiment
    run_name: str | None = None
    parent_run_id: str | None = None   # MLflow parent run (set by `nostra sweep`)
    progress: bool = True
    # lightning.Trainer kwargs (Lightning's defaults); others with +train.trainer.<key>=<value>
    trainer: dict[str, Any] = field(default_factory=lambda: {"accelerator": "auto", "devices": "auto",
                                                             "strategy": "auto"})
    dist_timeout_minutes: float = 360  # DDP process-group timeout: ranks wait this long for rank 0's rollouts
    rollout: RolloutConfig = field(default_factory=RolloutConfig)


@dataclass
class VariantConfig:
    """evaluate.variants.<id>: one row of the tables (a null entry leaves the row out)."""
    checkpoint: str                  # the training run's policy.ckpt (evaluate.checkpoint picks best/last/step)
    mode: str = "closed"             # closed | oracle (MLI, LI) | adaptive (AdaMLI)
    rnn_horizon: int | None = None   # reset the recurrent state every this many steps; None: the policy's
    # mode=adaptive: AdaMLI's thresholds, e.g. `...adamli={f_o: 10, k_o: 4}` (f_o, k_o, f_c, k_c, min_changes,
    # warmup); None: the paper's. Any, not a dict: Hydra refuses new keys merged into a typed dict
    adamli: Any = None


@dataclass
class OfflineConfig:
    """evaluate.offline: per-modality KL and AdaMLI detection on held-out demos (nostra.workflows.analysis)."""
    enabled: bool = True
    checkpoint: str = ""
    collections: list[str] = field(default_factory=list)
    noise: str = "rgb"               # mask | wrist_mask | agentview_mask | depth_mask | proprio_zero | proprio_stuck | rgb | rgbd | all
    episodes: int = 8                # demos of the training run's split (below), the first ones
    split: str = "held_out"          # held_out (never trained on) | train (the demos it trained on)
    windows: list[list[int]] | None = None   # None: the middle third of each demo
    setting: str = "default"         # Table 3 column: the data the policy was trained on
    adamli: Any = None               # AdaMLI's thresholds, as in VariantConfig; None: the paper's


@dataclass
class EvaluateConfig:
    """conf/evaluate: rollouts under the noise suite (nostra.workflows.evaluation) and offline analyses."""
    tasks: list[str]
    noises: list[str]
    out_dir: str
    ckpt_dir: str = "data/runs/train"
    variants: dict[str, VariantConfig | None] = field(default_factory=dict)
    checkpoint: str = "last"         # best (in-training rollouts) | last | step=<n>
    episodes: int = 10               # per task x noise x variant; episode i has seed `seed + i` for all
    seed: int = 1000
    horizon: int | None = None       # None: the task's
    # task -> [[start, end], ...]; None: the task's noise_windows. Any, not a dict: Hydra merges an
    # override into a typed dict and refuses its new keys (`evaluate.windows={Lift: [[30, 60]]}`)
    windows: Any = None
    noise_params: dict[str, Any] = field(default_factory=dict)
    workers: int = 2
    image_size: int | None = None    # None: each checkpoint's; a value that disagrees is refused
    videos_per_cell: int = 2
    rollouts: bool = True
    experiment: str = "nostra"       # MLflow experiment
    table: str = "robustness"        # which report table these runs feed: robustness | finetune | cotrain
    setting: str = ""                # the column within it
    offline: OfflineConfig = field(default_factory=OfflineConfig)


# ---- from plain dicts ----------------------------------------------------------------------------

def from_dict(cls: type, data: dict):
    """``cls`` (a config dataclass) from a plain, possibly partial dict: unknown keys fail with
    the valid ones, values are checked and converted to the fields' types (by OmegaConf)."""
    check_keys(cls, data)
    try:
        return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(cls), data))
    except OmegaConfBaseException as e:
        raise ConfigError(f"{cls.__name__}: {e}") from e


def check_keys(cls: type, data: dict, prefix: str = "") -> None:
    """Every key of ``data`` (recursively, through nested configs) is a field of ``cls``."""
    types = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    for key, value in data.items():
        if key not in names:
            raise ConfigError(f"unknown key '{prefix}{key}' in a {cls.__name__}; valid keys: {', '.join(names)}")
        if dataclasses.is_dataclass(types[key]) and isinstance(value, dict):
            check_keys(types[key], value, f"{prefix}{key}.")


def typed(node, name: str):
    """A composed config node with a schema (``cfg.model``, ``cfg.train``) as its dataclass.
    OmegaConf would drop the keys that a `+key=value` override added to it; they fail here."""
    check_keys(OmegaConf.get_type(node), OmegaConf.to_container(node), f"{name}.")
    return OmegaConf.to_object(node)
