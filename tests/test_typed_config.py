"""The typed configs (nostra.configs): the dataclasses are the networks' arguments and the yaml
files' schemas, so composing a config gives their defaults; a misspelt key or a value of the wrong
type fails at start, naming the key (and the valid ones); the dropped keys (train.ckpt_every,
train.rollout.enabled) are gone; every field of a training run is read; checkpoints keep the
whole config and refuse one that does not fit."""

from __future__ import annotations

import inspect
import re
from dataclasses import asdict, fields
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from conftest import lr_trace, small_net
from nostra.configs import (MODEL_CONFIGS, ConfigError, EncoderConfig, EvaluateConfig, RolloutConfig, TrainConfig,
                            VariantConfig, model_config, typed)
from pipeline._hydra import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]
MODS = [{"name": "pos", "kind": "lowdim", "shape": [2]}]


def _compose(*overrides: str):
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _yaml_keys(path: Path) -> dict:
    """The keys a conf file sets itself (its defaults list aside), with their raw values."""
    raw = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    raw.pop("defaults")
    return _flat(raw)


# ---- the dataclasses are the networks' arguments -------------------------------------------------

def _arguments(fn, skip=("self", "modalities", "action_dim", "encoder_kwargs")) -> dict:
    return {n: p.default for n, p in inspect.signature(fn).parameters.items() if n not in skip}


@pytest.mark.parametrize("policy", list(MODEL_CONFIGS))
def test_net_config_fields_are_the_network_arguments_with_the_same_defaults(policy):
    from nostra.policies.modules import policy_module
    from nostra.policies.base import PolicyNet

    net_cls = policy_module(policy).net_cls
    expected = {**_arguments(PolicyNet.__init__), **_arguments(net_cls.__init__)}
    expected = {k: list(v) if isinstance(v, tuple) else v for k, v in expected.items()}
    assert asdict(MODEL_CONFIGS[policy]().net) == expected
    assert {f.name for f in fields(EncoderConfig)} == set(_arguments(PolicyNet.__init__))


# ---- composing gives the dataclass defaults ------------------------------------------------------

@pytest.mark.parametrize("policy", list(MODEL_CONFIGS))
def test_composed_model_config_is_the_dataclass_defaults_plus_what_the_profile_sets(policy):
    """conf/model/<policy>.yaml sets only interpolated values (the profile's, the data's): every
    literal default lives in the dataclass."""
    own = _yaml_keys(ROOT / "conf" / "model" / f"{policy}.yaml")
    assert own and all(isinstance(v, str) and v.startswith("${") for v in own.values()), own
    for profile in ("tiny", "paper"):
        cfg = _compose(f"model={policy}", f"profile={profile}")
        model = typed(cfg.model, "model")
        assert type(model) is MODEL_CONFIGS[policy] and model.policy == policy
        composed, default = _flat(asdict(model)), _flat(asdict(MODEL_CONFIGS[policy]()))
        assert {k: v for k, v in composed.items() if k not in own} == {k: v for k, v in default.items() if k not in own}
        assert {k: composed[k] for k in own} == {k: OmegaConf.select(cfg.model, k) for k in own}


def test_composed_train_config_is_typed_with_the_dropped_keys_gone():
    own = _yaml_keys(ROOT / "conf" / "train" / "default.yaml")
    assert all(isinstance(v, str) and v.startswith("${") for v in own.values()), own
    cfg = _compose("profile=cpu")
    t = typed(cfg.train, "train")
    assert type(t) is TrainConfig and type(t.rollout) is RolloutConfig
    assert (t.val_every, t.rollout.every, t.max_minutes, t.stage, t.resume) == (500, 1000, 30.0, "pretrain", True)
    assert "ckpt_every" not in cfg.train and "enabled" not in cfg.train.rollout
    assert _compose().train.rollout.every == 0  # tiny: no in-training rollouts


def test_the_documented_overrides_still_compose():
    """The model.* and train.* overrides that scripts, the README, dvc.yaml and the tests use."""
    cfg = _compose("model=nostra", "model.loss.beta=1e-3", "model.net.rnn_horizon=0", "model.optim.lr=3e-4",
                   "train.rollout.every=0", "train.rollout.final_episodes=0", "train.rollout.modes=[closed]",
                   "train.max_minutes=null", "+train.trainer.num_nodes=2", "train.num_demos=10",
                   "train.stage=finetune", "train.init_from=x.ckpt", "train.val_every=3", "train.progress=false")
    model, t = typed(cfg.model, "model"), typed(cfg.train, "train")
    assert (model.loss.beta, model.optim.lr, t.num_demos, t.max_minutes) == (1e-3, 3e-4, 10, None)
    assert t.trainer == {"accelerator": "auto", "devices": "auto", "strategy": "auto", "num_nodes": 2}
    cfg = _compose("model=lstm", "model.net.image_aug=crop", "model.net.rnn_hidden=64",
                   "model.net.decoder_hidden=[64,64]", "train.trainer={accelerator: cpu, devices: 2, strategy: ddp}")
    assert typed(cfg.model, "model").net.decoder_hidden == [64, 64]
    assert typed(cfg.train, "train").trainer == {"accelerator": "cpu", "devices": 2, "strategy": "ddp"}


@pytest.mark.parametrize("experiment, noises, rows", [
    ("robustness", ["none", "mask", "cam_jitter", "table_tex"], 7),
    ("adamli", ["rgb", "rgbd", "all"], 5),
    ("finetune", ["none"], 3),
    ("cotrain", ["none"], 1),
])
def test_composed_evaluate_config_is_typed_for_every_experiment(experiment, noises, rows):
    e = typed(_compose(f"+experiment={experiment}").evaluate, "evaluate")
    assert type(e) is EvaluateConfig and e.noises == noises
    assert len([v for v in e.variants.values() if v]) == rows
    assert all(type(v) is VariantConfig for v in e.variants.values() if v)


def test_the_documented_evaluate_overrides_compose():
    e = typed(_compose("evaluate.windows={Lift: [[30, 60]]}", "evaluate.variants.lstm=null",
                       "evaluate.checkpoint=best", "evaluate.variants.nostra.rnn_horizon=10").evaluate, "evaluate")
    assert e.windows == {"Lift": [[30, 60]]} and e.variants["lstm"] is None and e.checkpoint == "best"
    assert e.variants["nostra"].rnn_horizon == 10 and e.variants["nostra_mli"].mode == "oracle"
    e = typed(_compose("evaluate.variants.nostra_adamli.adamli={f_o: 10, k_o: 4}", "evaluate.offline.adamli={f_c: 1.5}"
                       ).evaluate, "evaluate")
    assert e.variants["nostra_adamli"].adamli == {"f_o": 10, "k_o": 4} and e.offline.adamli == {"f_c": 1.5}


def _evaluate_cli(monkeypatch, capsys, *overrides: str) -> str:
    import pipeline.evaluate as ev
    from pipeline.cli import main

    seen = []
    monkeypatch.setattr(ev, "_rollouts", lambda *a: seen.append(a))
    monkeypatch.setattr(ev, "_offline", lambda *a: seen.append(a))
    with pytest.raises((SystemExit, ConfigError)):
        main(["evaluate", *overrides])
    assert not seen
    return capsys.readouterr().err


@pytest.mark.parametrize("override, node, valid", [
    ("evaluate.episods=3", "evaluate", "episodes"),
    ("evaluate.variants.nostra.mod=oracle", "evaluate.variants.nostra", "mode"),
    ("evaluate.offline.nose=mask", "evaluate.offline", "noise"),
])
def test_an_unknown_evaluate_key_fails_naming_the_valid_ones(monkeypatch, capsys, override, node, valid):
    key = override.split("=")[0].rpartition(".")[2]
    err = _evaluate_cli(monkeypatch, capsys, override)
    assert f"{node} has no key '{key}'; valid keys: " in err and re.search(rf"valid keys: .*\b{valid}\b", err), err


def test_evaluate_windows_that_are_not_per_task_fail_with_an_example(monkeypatch, capsys):
    import pipeline.evaluate as ev
    from pipeline.cli import main

    monkeypatch.setattr(ev, "_offline", lambda *a: None)
    with pytest.raises(SystemExit, match=r"evaluate.windows=\[\[30, 60\]\]: expected task -> .*\{Lift: \[\[30, 60\]\]\}"):
        main(["evaluate", "evaluate.windows=[[30,60]]"])


# ---- bad keys and values fail at start -----------------------------------------------------------

def _train_cli(monkeypatch, capsys, *overrides: str) -> str:
    """`nostra train <overrides>` with the app replaced (nothing trains); its stderr."""
    import pipeline.train as tr
    from pipeline.cli import main

    seen = []
    monkeypatch.setattr(tr, "_app", seen.append)
    with pytest.raises(SystemExit):
        main(["train", *overrides])
    assert not seen
    return capsys.readouterr().err


@pytest.mark.parametrize("override, node, valid", [
    ("model.net.rnn_hiden=3", "model.net", "rnn_hidden"),
    ("model.optim.learning_rate=3", "model.optim", "lr"),
    ("train.ckpt_every=3", "train", "val_every"),          # dropped: checkpoints/last.ckpt every val_every
    ("train.rollout.enabled=true", "train.rollout", "every"),  # dropped: on when every > 0
])
def test_an_unknown_key_fails_naming_it_and_the_valid_keys(monkeypatch, capsys, override, node, valid):
    key = override.split("=")[0].rpartition(".")[2]
    err = _train_cli(monkeypatch, capsys, "model=lstm", override)
    assert f"{node} has no key '{key}'; valid keys: " in err
    assert re.search(rf"valid keys: .*\b{valid}\b", err), err


def test_a_state_space_key_on_another_policy_fails(monkeypatch, capsys):
    err = _train_cli(monkeypatch, capsys, "model=lstm", "model.loss.beta=1e-3")
    assert "model has no key 'loss'; valid keys: policy, net, optim" in err


@pytest.mark.parametrize("override", ["model.net.rnn_hidden=abc", "train.max_steps=ten", "train.resume=maybe"])
def test_a_value_of_the_wrong_type_fails_naming_the_key(monkeypatch, capsys, override):
    err = _train_cli(monkeypatch, capsys, "model=lstm", override)
    assert f"Error merging override {override}" in err and f"full_key: {override.split('=')[0]}" in err, err
    assert re.search(r"could not be converted|is not a valid", err) and "has no key" not in err, err


def test_a_key_added_with_plus_fails_instead_of_being_dropped():
    """Hydra's `+key=value` adds a key even to a typed node, and OmegaConf.to_object would drop it."""
    cfg = _compose("model=lstm", "+model.net.rnn_hiden=3")
    with pytest.raises(ConfigError, match=r"unknown key 'model\.net\.rnn_hiden' in a LSTMNetConfig; "
                                          r"valid keys: .*rnn_hidden"):
        typed(cfg.model, "model")


def test_a_policy_module_refuses_unknown_keys_and_takes_the_dataclass_defaults():
    from nostra.policies.modules import policy_module

    with pytest.raises(ConfigError, match="unknown key 'net.rnn_hiden'"):
        policy_module("lstm")(MODS, 2, net={"rnn_hiden": 3})
    with pytest.raises(ConfigError, match="unknown key 'loss'"):
        policy_module("lstm")(MODS, 2, loss={"beta": 1.0})
    module = policy_module("nostra")(MODS, 2, net=small_net("nostra"), loss={"beta": 1e-3})
    assert module.loss_cfg == {"beta": 1e-3, "gamma": 0.1}
    assert module.configure_optimizers().param_groups[0]["lr"] == 1e-4
    diffusion = policy_module("diffusion")(MODS, 2, net={"down_dims": [8, 16]}, optim={"warmup_steps": 1})
    assert (diffusion.config.optim.warmup_steps, diffusion.config.optim.betas) == (1, [0.95, 0.999])


@pytest.mark.parametrize("policy", ["nostra", "rssm", "lstm"])
def test_a_recurrent_policy_keeps_the_papers_constant_rate_unless_a_schedule_is_named(policy):
    """Adam at a constant 1e-4 by default (paper Table 7); optim.lr_scheduler=cosine decays it to 0 at
    total_steps and holds it there; constant with a warm-up ramps then stays; an unknown name is
    refused with the valid ones."""
    from nostra.policies.modules import policy_module

    make = policy_module(policy)
    opt = make(MODS, 2, net=small_net(policy)).configure_optimizers()
    assert isinstance(opt, torch.optim.Adam) and opt.param_groups[0]["lr"] == 1e-4
    cosine = make(MODS, 2, net=small_net(policy), optim={"lr": 1.0, "lr_scheduler": "cosine", "total_steps": 10})
    lrs = lr_trace(cosine.configure_optimizers()["lr_scheduler"]["scheduler"], 20)
    assert lrs[0] == pytest.approx(1.0) and lrs[5] == pytest.approx(0.5) and lrs[4] > lrs[5] > lrs[6]
    assert max(lrs[10:]) == pytest.approx(0.0, abs=1e-9)
    warm = make(MODS, 2, net=small_net(policy), optim={"lr": 1.0, "warmup_steps": 4, "total_steps": 10})
    assert lr_trace(warm.configure_optimizers()["lr_scheduler"]["scheduler"], 12)[2:] == pytest.approx(
        [0.5, 0.75] + [1.0] * 8)
    with pytest.raises(ValueError, match=r"unknown optim.lr_scheduler 'cosin'; valid: linear, cosine, "):
        make(MODS, 2, net=small_net(policy), optim={"lr_scheduler": "cosin"}).configure_optimizers()


def test_the_schedule_composes_from_the_command_line():
    cfg = _compose("model=nostra", "model.optim.lr_scheduler=cosine", "model.optim.total_steps=18000")
    optim = typed(cfg.model, "model").optim
    assert (optim.lr, optim.lr_scheduler, optim.warmup_steps, optim.total_steps) == (1e-4, "cosine", 0, 18000)


# ---- every field of a training run is read -------------------------------------------------------

def _unread(names, pattern: str, text: str) -> list[str]:
    return [n for n in names if not re.search(pattern.format(re.escape(n)), text)]


def test_every_train_field_is_read():
    from nostra.workflows.training import TrainSpec

    training = (ROOT / "nostra/workflows/training.py").read_text()
    rollouts = (ROOT / "nostra/workflows/training_rollouts.py").read_text()
    train_fields = [f.name for f in fields(TrainConfig)]
    assert _unread(train_fields, r"\b(?:t|spec\.train)\.{}\b", training) == []
    assert _unread([f.name for f in fields(TrainSpec)], r"\bspec\.{}\b", training) == []
    assert _unread([f.name for f in fields(RolloutConfig)], r"\bcfg\.{}\b", rollouts) == []
    # the check can fail: a name nothing reads, and the dropped one
    assert _unread(["ckpt_every", "no_such_field"], r"\b(?:t|spec\.train)\.{}\b", training) == ["ckpt_every",
                                                                                             "no_such_field"]


def test_a_train_spec_survives_json_as_ddp_ranks_read_it():
    import json

    from conftest import train_spec
    from nostra.workflows.training import TrainSpec
    from nostra.workflows.training_rollouts import RolloutEnv

    spec = train_spec("diffusion", net={"down_dims": [8, 16]}, optim={"warmup_steps": 1}, store="s.zarr",
                      collections=["t"], obs_keys=["pos"], out_dir="out", max_minutes=1.5,
                      trainer={"accelerator": "cpu", "devices": 2, "strategy": "ddp"},
                      rollout=RolloutConfig(every=2, horizon=5), rollout_env=RolloutEnv("Lift", {"Lift": [[1, 2]]}))
    again = TrainSpec.from_dict(json.loads(json.dumps(asdict(spec))))
    assert again == spec and type(again.model.optim) is type(spec.model.optim)


# ---- checkpoints keep the config -----------------------------------------------------------------

def _save(tmp_path, module, name: str = "m.ckpt", edit=None) -> Path:
    """A checkpoint as Lightning writes it (state dict + on_save_checkpoint's metadata)."""
    ckpt = {"state_dict": module.state_dict()}
    module.on_save_checkpoint(ckpt)
    if edit:
        edit(ckpt["nostra"])
    torch.save(ckpt, tmp_path / name)
    return tmp_path / name


def test_a_checkpoint_keeps_the_whole_config(tmp_path):
    from nostra.policies.modules import policy_module
    from nostra.policies.checkpoint import load_net, read_meta, stored_config

    module = policy_module("rssm")(MODS, 2, net={**small_net("rssm"), "rnn_horizon": 7}, optim={"lr": 3e-4},
                                   loss={"beta": 1e-3})
    path = _save(tmp_path, module)
    meta, _ = read_meta(path)
    assert {k: meta[k] for k in ("policy", "net", "optim", "loss")} == asdict(module.config)
    assert stored_config(path, meta) == module.config == model_config(
        "rssm", net={**small_net("rssm"), "rnn_horizon": 7}, optim={"lr": 3e-4}, loss={"beta": 1e-3})
    net = load_net(path)
    assert net.rnn_horizon == 7
    torch.testing.assert_close(net.state_dict(), module.net.state_dict())


def test_an_older_checkpoint_with_only_its_net_keys_still_loads(tmp_path):
    from nostra.policies.modules import policy_module
    from nostra.policies.checkpoint import load_net, read_meta, stored_config

    module = policy_module("lstm")(MODS, 2, net=small_net("lstm"))

    def as_before(meta):  # what on_save_checkpoint wrote before: the net keys given, no optim / loss
        meta["net"] = small_net("lstm")
        del meta["optim"]

    path = _save(tmp_path, module, edit=as_before)
    assert stored_config(path, read_meta(path)[0]) == module.config
    torch.testing.assert_close(load_net(path).state_dict(), module.net.state_dict())


def test_a_checkpoint_with_an_unknown_net_key_fails_naming_the_file_and_key(tmp_path):
    from nostra.policies.modules import policy_module
    from nostra.policies.checkpoint import CheckpointError, load_net

    module = policy_module("lstm")(MODS, 2, net=small_net("lstm"))
    path = _save(tmp_path, module, "foreign.ckpt", edit=lambda meta: meta["net"].update(rnn_cell="gru"))
    with pytest.raises(CheckpointError, match=r"foreign\.ckpt: .*unknown key 'net\.rnn_cell'.*"
                                              r"valid keys: .*rnn_hidden"):
        load_net(path)
