"""Running a stage as a Hydra app from `nostra <stage> [overrides]`."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

import hydra
from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from nostra.configs import MODEL_CONFIGS, EvaluateConfig, TrainConfig

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")


def _if_gpus(gpus, with_gpus, without):
    """${nostra.if_gpus:<gpus>,<value with GPUs>,<value without>} (conf/launcher/slurm.yaml)."""
    return with_gpus if int(gpus or 0) > 0 else without


def _gpus_per_node(gpus, gres):
    """--gpus-per-node: none for a CPU job, nor when a gpu --gres already asks for the GPUs."""
    return None if int(gpus or 0) <= 0 or "gpu" in str(gres or "") else int(gpus)


OmegaConf.register_new_resolver("nostra.if_gpus", _if_gpus, replace=True)
OmegaConf.register_new_resolver("nostra.gpus_per_node", _gpus_per_node, replace=True)


def register_schemas() -> None:
    """The typed configs (nostra.configs) as structured-config schemas that conf/model/<policy>.yaml
    conf/train/default.yaml and conf/evaluate/default.yaml extend (`defaults: [<policy>_schema, _self_]`)."""
    store = ConfigStore.instance()
    for policy, schema in MODEL_CONFIGS.items():
        store.store(group="model", name=f"{policy}_schema", node=schema)
    store.store(group="train", name="train_schema", node=TrainConfig)
    store.store(group="evaluate", name="evaluate_schema", node=EvaluateConfig)


register_schemas()  # on import, like the resolvers: hydra.main and the compose API both need them


def run(stage: str, argv: list[str], fn: Callable, config_name: str = "config") -> int:
    """Hydra reads sys.argv, so the stage's own arguments are put there (this keeps --cfg job,
    --help and --multirun working exactly as for any Hydra app)."""
    saved = sys.argv
    sys.argv = [f"nostra {stage}", *argv]
    try:
        hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)(fn)()
    except SystemExit as e:
        hint = unknown_key_hint(argv, config_name) if e.code == 1 else None  # Hydra printed its error
        if hint:
            print(f"nostra {stage}: {hint}", file=sys.stderr)
        raise
    finally:
        sys.argv = saved
    return 0


def unknown_key_hint(argv: list[str], config_name: str = "config") -> str | None:
    """For an override of a key that the composed config lacks (a typo): the keys its node has.
    Hydra's error names the key but not the valid ones, and suggests `+key=value`, which adds a
    key that no code reads (a typed node refuses it later, nostra.configs.typed)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser, overrides = OverridesParser.create(), []
    for arg in argv:
        try:
            overrides += parser.parse_overrides([arg])
        except Exception:  # flags such as --multirun, --cfg job
            continue
    choices = [o.input_line for o in overrides if "." not in o.key_or_group and not o.is_sweep_override()]
    try:
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            cfg = compose(config_name, overrides=choices)
    except Exception:  # the choices themselves fail: Hydra's error says why
        return None
    keys = [o.key_or_group.split(".") for o in overrides
            if "." in o.key_or_group and not (o.is_add() or o.is_delete())]
    return next(filter(None, (_missing_key(cfg, path) for path in keys)), None)


def _missing_key(cfg, path: list[str]) -> str | None:
    """'<node> has no key <k>; valid keys: ...' for the first key of ``path`` the config lacks."""
    node = cfg
    for i, key in enumerate(path):
        if not OmegaConf.is_dict(node) or not len(node):  # a value or an open (empty) dict: anything goes
            return None
        if key not in node:
            return f"{'.'.join(path[:i]) or 'the config'} has no key {key!r}; valid keys: {', '.join(map(str, node))}"
        node = node._get_node(key)  # not node[key]: no interpolation is resolved
    return None
