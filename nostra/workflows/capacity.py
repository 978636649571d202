"""Capacity matching (issue 11, what the paper's reviewers asked for): the parameter count of each
policy's network at a profile, and the width of BC-LSTM's LSTM (``rnn_hidden``) and of BC-RSSM's
joint latent (``latent_dim``, per modality) that give NOSTRA's count, so a comparison can rule out
"NOSTRA wins because it is bigger". Counts come from building the networks (no training).

    python -m nostra.workflows.capacity --profile cpu --task liftd1 --out reports/cpu/liftd1/capacity.md

The matched widths are overrides for `nostra train` (e.g. `model.net.rnn_hidden=<n>`); the file
lists them with the counts, and `--override lstm` prints just one (what `CAPACITY=matched make cpu` trains with)."""

from __future__ import annotations

import argparse
import functools
from dataclasses import asdict
from pathlib import Path

from nostra.configs import ModelConfig, typed
from nostra.modality import sim_observations
from nostra.workflows.variants import LABELS

# policy -> the net key whose width is matched to NOSTRA's parameter count
KNOBS = {"lstm": "rnn_hidden", "rssm": "latent_dim"}


def count(policy: str, net: dict, modalities) -> int:
    """Parameters of ``policy``'s network with ``net`` (a full net config dict)."""
    from nostra.policies import net_class

    return sum(p.numel() for p in net_class(policy)(modalities, 7, **net).parameters())


def match(config: ModelConfig, target: int, modalities, knob: str, hi: int = 4096) -> tuple[int, int]:
    """(width, parameter count): the value of ``net.<knob>`` whose count is closest to ``target``
    (counts grow with the width, so a bisection finds it)."""
    net = asdict(config.net)

    @functools.cache  # each count builds a network
    def at(width: int) -> int:
        return count(config.policy, {**net, knob: width}, modalities)

    lo_w, hi_w = 1, hi
    if at(hi_w) < target:
        raise ValueError(f"{config.policy}: net.{knob}={hi_w} gives {at(hi_w)} parameters, fewer than {target}")
    while hi_w - lo_w > 1:
        mid = (lo_w + hi_w) // 2
        lo_w, hi_w = (mid, hi_w) if at(mid) < target else (lo_w, mid)
    best = min((lo_w, hi_w), key=lambda w: abs(at(w) - target))
    return best, at(best)


def table(configs: dict[str, ModelConfig], modalities) -> list[dict]:
    """One row per policy: its parameter count as configured, and where it has a knob, the width
    matching NOSTRA's count and the count at that width."""
    counts = {p: count(p, asdict(c.net), modalities) for p, c in configs.items()}
    target = counts["nostra"]
    rows = []
    for policy, c in configs.items():
        row = {"policy": policy, "params": counts[policy], "vs_nostra": counts[policy] / target}
        if policy in KNOBS:
            knob = KNOBS[policy]
            width, n = match(c, target, modalities, knob)
            row.update(knob=knob, configured=getattr(c.net, knob), matched=width, matched_params=n)
        rows.append(row)
    return rows


def markdown(rows: list[dict], command: str) -> str:
    target = next(r["params"] for r in rows if r["policy"] == "nostra")
    lines = ["# Parameter counts and capacity matching", "",
             f"`{command}` (networks built, not trained).", "",
             "| Policy | parameters | vs NOSTRA | matched to NOSTRA's count |", "|---|---|---|---|"]
    for r in rows:
        matched = (f"`model.net.{r['knob']}={r['matched']}` (configured {r['configured']}): "
                   f"{r['matched_params']:,} ({r['matched_params'] / target:.2f}x)" if "knob" in r else "")
        lines.append(f"| {LABELS[r['policy']]} | {r['params']:,} | {r['vs_nostra']:.2f}x | {matched} |")
    return "\n".join(lines) + "\n"


def configs_for(profile: str, task: str, policies: list[str]) -> tuple[dict[str, ModelConfig], list]:
    """The typed model configs and the modalities a profile trains with (composed as `nostra train`)."""
    from hydra import compose, initialize_config_dir

    from pipeline._hydra import CONF_DIR

    configs, modalities = {}, None
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        for policy in policies:
            cfg = compose("config", overrides=[f"profile={profile}", f"task={task}", f"model={policy}"])
            configs[policy] = typed(cfg.model, "model")
            sim = sim_observations(cfg.profile.image_size)
            keys = cfg.data.obs_keys
            modalities = [m for m in sim.modalities if keys is None or m.name in keys]
    return configs, modalities


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="cpu")
    ap.add_argument("--task", default="liftd1")
    ap.add_argument("--policies", nargs="+", default=["nostra", "rssm", "lstm", "diffusion"])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--override", choices=sorted(KNOBS), default=None,
                    help="print only this policy's matching `nostra train` override (for scripts)")
    args = ap.parse_args(argv)
    if args.override:
        configs, modalities = configs_for(args.profile, args.task, ["nostra", args.override])
        target = count("nostra", asdict(configs["nostra"].net), modalities)
        width, _ = match(configs[args.override], target, modalities, KNOBS[args.override])
        print(f"model.net.{KNOBS[args.override]}={width}")
        return
    if "nostra" not in args.policies:
        ap.error("--policies must include nostra: the counts are matched to it")
    configs, modalities = configs_for(args.profile, args.task, args.policies)
    command = (f"python -m nostra.workflows.capacity --profile {args.profile} --task {args.task} "
               f"--policies {' '.join(args.policies)}")
    text = markdown(table(configs, modalities), command)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)


if __name__ == "__main__":
    main()
