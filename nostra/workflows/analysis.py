"""Offline analyses on held-out demos from the store (no simulator, fast): observation noise is
injected into stored episodes and each policy variant is stepped through them.

* action error inside the noise windows, per variant (paper Figure 4 in numbers);
* AdaMLI detection precision / recall against the true windows, per modality, and its false
  imagination rate on the clean episodes (share of steps it imagines where nothing is wrong);
* mean per-modality KL in nats over the clean episodes (Table 3), logged as `kl_nats/<modality>`,
  with a 95% interval over the held-out episodes;
* a Figure-5-style plot of per-modality KL over one noisy episode with AdaMLI's decisions.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from nostra import episode
from nostra.episode import Episode, RecordedSource, oracle_keys
from nostra.modality import render_size
from nostra.policies.imagination import AdaMLIConfig, detection_scores
from nostra.noise import NoiseSchedule, check_noise

# noises that act on stored observations (camera jitter and texture swaps need the simulator)
OFFLINE_NOISES = ("mask", "depth_mask", "proprio_zero", "proprio_stuck", "rgb", "rgbd", "all")
SPLIT_WORDS = {"held_out": "held-out", "train": "training"}  # how reports name the demos a split replays


@dataclass
class OfflineSpec:
    checkpoint: str
    store: str
    episodes: list            # (collection, episode) pairs, held out from training (or trained on: split)
    split: str = "held_out"   # which of the training run's episodes they are (recorded in offline.json)
    noise: str = "mask"
    windows: list | None = None   # None: one window over the middle third of each episode
    out_dir: str = "offline"
    seed: int = 0
    progress: bool = True
    noise_params: dict = field(default_factory=dict)
    adamli: dict = field(default_factory=dict)   # AdaMLI's thresholds (empty: the paper's)


def _windows(spec: OfflineSpec, length: int) -> list[tuple[int, int]]:
    if spec.windows:
        return [(int(a), int(b)) for a, b in spec.windows if a < length]
    return [(max(1, length // 3), max(2, 2 * length // 3))]


def _replay(runner, obs: dict, horizon: int, schedule: NoiseSchedule, mode: str, image_size: int,
            seed: int) -> Episode:
    """Step a runner through a stored episode (the episode engine, recorded observations)."""
    return episode.run(RecordedSource(obs, image_size), runner, schedule, mode, horizon,
                       np.random.default_rng([seed, 7]))


def analyse(spec: OfflineSpec) -> dict:
    """Run the analyses; writes offline.md, kl_episode.png and returns the numbers."""
    from nostra.data.store import Store
    from nostra.workflows.figures import kl_figure
    from nostra.policies.checkpoint import load_runner

    if spec.noise not in OFFLINE_NOISES:
        check_noise(spec.noise)
        raise ValueError(f"noise {spec.noise!r} needs the simulator; offline noises: {', '.join(OFFLINE_NOISES)}")
    if not spec.episodes:
        raise ValueError("no held-out episodes to analyse")
    store, out = Store(spec.store), Path(spec.out_dir)
    lengths = [_length(store, c, e) for c, e in spec.episodes]
    if not any(NoiseSchedule(spec.noise, _windows(spec, n), spec.noise_params).mask(n).any() for n in lengths):
        raise ValueError(f"noise windows {spec.windows or 'middle third'} cover no step of the episodes "
                         f"(lengths {min(lengths)}-{max(lengths)}): nothing would be corrupted")
    out.mkdir(parents=True, exist_ok=True)
    closed = load_runner(spec.checkpoint)
    names = closed.modality_names
    image_size = render_size(closed.net.modalities)  # the stored images are the size the policy trained on
    variants = {"closed": closed}
    if closed.can_imagine:
        variants["oracle"] = closed
        variants["adaptive"] = load_runner(spec.checkpoint, adaptive=True, adamli=spec.adamli)
    errors = {v: [] for v in ["clean", *variants]}
    kl_clean = {m: [] for m in closed.net.groups} if closed.can_imagine else {}
    kl_episodes = {m: [] for m in kl_clean}           # each held-out episode's mean: the intervals' samples
    clean_flags = {m: [] for m in names}              # AdaMLI on the clean episodes: false imagination
    steps = []                                        # each held-out episode's step count (KL-weighted shares)
    flags, truth = {m: [] for m in names}, {m: [] for m in names}
    figure_done = False
    for ep_i, (coll, ep) in enumerate(tqdm(spec.episodes, desc="offline", disable=not spec.progress)):
        data = store.episode(coll, ep, [*names, "actions"])
        obs, target, length = {k: data[k] for k in names}, data["actions"], len(data["actions"])
        schedule = NoiseSchedule(spec.noise, _windows(spec, length), spec.noise_params)
        inside = schedule.mask(length)
        noised = oracle_keys(schedule, names)
        seed = spec.seed + ep_i
        run = _replay(closed, obs, length, NoiseSchedule("none", []), "closed", image_size, seed)
        errors["clean"].append(_err(np.asarray(run.action), target, inside))
        steps.append(len(run.kl))
        for g in kl_clean:
            kl_clean[g] += [i[g] for i in run.kl]
            kl_episodes[g].append(float(np.mean([i[g] for i in run.kl])))
        if "adaptive" in variants:
            run = _replay(variants["adaptive"], obs, length, NoiseSchedule("none", []), "adaptive", image_size, seed)
            for m in names:
                clean_flags[m] += [i[m] for i in run.imagined]
        for v, runner in variants.items():
            run = _replay(runner, obs, length, schedule, v, image_size, seed)
            errors[v].append(_err(np.asarray(run.action), target, inside))
            if v == "adaptive":
                for m in names:
                    flags[m] += [i[m] for i in run.imagined]
                    truth[m] += list(inside & (m in noised))
                if not figure_done:
                    kl_figure({g: np.array([i[g] for i in run.kl]) for g in closed.net.groups}, schedule.windows,
                              out / "kl_episode.png", {m: np.array([i[m] for i in run.imagined])
                                                       for m in names if m in noised},
                              title=f"{coll} episode {ep}, noise {spec.noise}")
                    figure_done = True
    result = {"action_mse": {v: float(np.nanmean(e)) for v, e in errors.items()},
              "kl_nats": {g: float(np.mean(v)) for g, v in kl_clean.items()},
              "kl_nats_ci": {g: mean_interval(v) for g, v in kl_episodes.items()},
              # per held-out episode, so two runs on the same initial states can be compared paired
              "kl_nats_episodes": kl_episodes, "episode_steps": steps}
    if clean_flags[names[0]]:
        result["false_imagination"] = {m: float(np.mean(f)) for m, f in clean_flags.items()}
        result["false_imagination"]["all"] = float(np.mean(np.concatenate([clean_flags[m] for m in names])))
    if flags[names[0]]:
        result["detect"] = {m: detection_scores(np.array(flags[m]), np.array(truth[m])) for m in names}
        result["detect"]["all"] = detection_scores(np.concatenate([flags[m] for m in names]),
                                                   np.concatenate([truth[m] for m in names]))
    (out / "offline.md").write_text(markdown(result, spec))
    (out / "offline.json").write_text(json.dumps({"noise": spec.noise, "checkpoint": spec.checkpoint,
                                                  "split": spec.split,
                                                  "episodes": [list(e) for e in spec.episodes],
                                                  "adamli": dataclasses.asdict(AdaMLIConfig.from_dict(spec.adamli)), **result}, indent=1))
    return result


def _length(store, collection: str, episode: int) -> int:
    """Steps of an episode, from the store's episode ends (no data read)."""
    ends = store.episode_ends(collection)
    return int(ends[episode] - (ends[episode - 1] if episode else 0))


def mean_interval(samples, level: float = 0.95) -> list[float]:
    """Student-t interval of the mean of per-episode values (one value: no interval)."""
    from scipy import stats

    x = np.asarray(samples, float)
    if len(x) < 2:
        return [float("nan"), float("nan")]
    lo, hi = stats.t.interval(level, len(x) - 1, loc=x.mean(), scale=stats.sem(x))
    return [float(lo), float(hi)]


def _err(actions: np.ndarray, target: np.ndarray, inside: np.ndarray) -> float:
    if not inside.any():
        return float("nan")
    return float(np.mean(np.sum((actions[inside] - target[inside]) ** 2, -1)))


def markdown(result: dict, spec: OfflineSpec) -> str:
    lines = [f"## Offline analysis: noise `{spec.noise}` on {len(spec.episodes)} {SPLIT_WORDS[spec.split]} demos", "",
             "| variant | action MSE inside the windows |", "|---|---|"]
    lines += [f"| {v} | {e:.4f} |" for v, e in result["action_mse"].items()]
    if result["kl_nats"]:
        total = sum(result["kl_nats"].values())
        lines += ["", "| modality | mean KL on clean demos (nats per step) | 95% CI over episodes | share |",
                  "|---|---|---|---|"]
        lines += [f"| {m} | {v:.3f} | [{result['kl_nats_ci'][m][0]:.3f}, {result['kl_nats_ci'][m][1]:.3f}] | "
                  f"{100 * v / total:.0f}% |" for m, v in result["kl_nats"].items()]
    if "detect" in result:
        lines += ["", f"| modality | AdaMLI precision ({spec.noise}) | AdaMLI recall | false imagination on clean demos |",
                  "|---|---|---|---|"]
        false = result.get("false_imagination", {})
        lines += [f"| {m} | {s['precision']:.2f} | {s['recall']:.2f} | {100 * false.get(m, float('nan')):.1f}% |"
                  for m, s in result["detect"].items()]
    return "\n".join(lines) + "\n"
