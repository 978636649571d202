"""Robustness evaluation (paper Tables 1 and 2): every variant meets the same initial states under
every noise, episodes spread over worker processes; success rates with 95% Wilson intervals go to
MLflow (`success/<task>/<noise>/<variant>`), a Markdown/CSV table and figures."""

from __future__ import annotations

import math
import os
import warnings
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, fields
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from nostra.modality import as_modalities, render_size, sim_observations
from nostra.noise import NoiseSchedule
from nostra.sim.rollout import EpisodeJob, EpisodeResult, init_worker, work
from nostra.workflows.variants import LABELS, MODES


@dataclass
class Variant:
    name: str          # an id used in metric names, e.g. nostra_mli
    checkpoint: str
    mode: str = "closed"  # closed | oracle (MLI / LI knowing the window) | adaptive (AdaMLI)
    rnn_horizon: int | None = None  # override the checkpoint's state reset period at rollout (0: never)
    adamli: dict = field(default_factory=dict)  # mode=adaptive: AdaMLI's thresholds (empty: the paper's)

    @property
    def label(self) -> str:
        return LABELS.get(self.name, self.name)


@dataclass
class EvalSpec:
    tasks: list[str]
    noises: list[str]
    variants: list[Variant]
    out_dir: str
    episodes: int = 10
    seed: int = 1000
    horizon: int | None = None                 # None: the task's horizon
    windows: dict = field(default_factory=dict)  # task -> [[start, end], ...] overriding the task's
    noise_params: dict = field(default_factory=dict)
    workers: int = 2
    image_size: int | None = None  # None: each checkpoint's; a value that disagrees with one is refused
    videos_per_cell: int = 1
    progress: bool = True
    experiment: str = "nostra"
    run_name: str = "evaluate"
    params: dict = field(default_factory=dict)
    checkpoint: str = "last"   # which checkpoint of each run the variants use (the tables say it)

    @classmethod
    def from_config(cls, config, **extra) -> "EvalSpec":
        """From the typed evaluate config (nostra.configs.EvaluateConfig): every field the two share
        by name, then ``extra`` (what the stage resolves: variants, windows, run name, MLflow params)."""
        shared = {f.name for f in fields(cls)} & {f.name for f in fields(config)}
        return cls(**{**{n: getattr(config, n) for n in shared}, **extra})


def task_windows(windows: dict, name: str, task) -> list[list[int]]:
    """The noise windows of ``task`` (a registry Task, asked for as ``name``): those ``windows``
    (task -> [[start, end], ...]) gives under either name, else the task's own."""
    return windows.get(name) or windows.get(task.name) or [list(w) for w in task.noise_windows]


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate (written out: one formula, no statsmodels)."""
    if n == 0:
        return math.nan, math.nan
    p, z2 = k / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def validate(spec: EvalSpec) -> None:
    """Fail before any rollout: unknown task / noise / mode, bad windows, noise parameters or AdaMLI
    thresholds, or a policy the env cannot feed."""
    from nostra.policies import runner_class
    from nostra.policies.checkpoint import read_meta
    from nostra.policies.imagination import AdaMLIConfig
    from nostra.sim.tasks import get_task

    for task in spec.tasks:
        t = get_task(task)
        windows, horizon = task_windows(spec.windows, task, t), spec.horizon or t.horizon
        late = [w for w in windows if w[0] >= horizon]
        if late and any(n != "none" for n in spec.noises):  # a warning: micro profiles (ci) roll out a few steps on purpose
            warnings.warn(f"task {t.name}: noise windows {late} start at or after the rollout horizon {horizon}: "
                          "never applied, so those cells are noise-free there", stacklevel=2)
        for noise in spec.noises:
            try:
                NoiseSchedule(noise, windows, spec.noise_params)
            except (ValueError, TypeError) as e:
                raise ValueError(f"task {t.name}, noise {noise!r}, windows {windows}: {e}") from e
    if not spec.variants:
        raise ValueError("no variants to evaluate")
    for v in spec.variants:
        if v.mode not in MODES:
            raise ValueError(f"variant {v.name!r}: unknown mode {v.mode!r}; valid modes: {', '.join(MODES)}")
        try:
            AdaMLIConfig.from_dict(v.adamli)
        except ValueError as e:
            raise ValueError(f"variant {v.name!r}: {e}") from None
        meta, _ = read_meta(v.checkpoint)
        runner = runner_class(meta["policy"])
        if v.mode != "closed" and not runner.can_imagine:
            raise ValueError(f"variant {v.name!r}: a '{meta['policy']}' policy cannot imagine (mode {v.mode!r})")
        try:
            check_renderable(as_modalities(meta["modalities"]), spec.image_size)
        except ValueError as e:
            raise ValueError(f"variant {v.name!r} ({v.checkpoint}): {e}") from None


def check_renderable(modalities, image_size: int | None = None) -> None:
    """The simulator can feed a policy trained on ``modalities``: it renders each of them, at the
    checkpoint's image size (``image_size``, a config's, must agree)."""
    size = render_size(modalities, image_size)
    rendered = sim_observations(size).select(m.name for m in modalities)
    for m, r in zip(modalities, rendered):
        if m != r:
            raise ValueError(f"the policy was trained on {m.name} as {m.kind} {m.shape}; the simulator renders "
                             f"{r.kind} {r.shape}")


def jobs_of(spec: EvalSpec) -> list[EpisodeJob]:
    from nostra.sim.tasks import get_task

    jobs, out = [], Path(spec.out_dir)
    for task in spec.tasks:
        t = get_task(task)
        windows = task_windows(spec.windows, task, t)
        for i in range(spec.episodes):
            for noise in spec.noises:
                for v in spec.variants:
                    video = (str(out / "videos" / t.name / noise / f"{v.name}_ep{i}.mp4")
                             if i < spec.videos_per_cell else None)
                    jobs.append(EpisodeJob(t.name, noise, v.name, v.checkpoint, v.mode, spec.seed + i,
                                           spec.horizon or t.horizon, windows, dict(spec.noise_params),
                                           spec.image_size, video, v.rnn_horizon, tuple(sorted(v.adamli.items()))))
    return jobs


def run_jobs(jobs: list[EpisodeJob], workers: int, progress: bool = True) -> list[EpisodeResult]:
    """Episodes over worker processes (one env + runners each). A crashed worker's episodes are
    retried once in a fresh pool, then count as failed with the reason; nothing aborts the run."""
    bar = tqdm(total=len(jobs), desc="rollouts", disable=not progress)
    results: dict[int, EpisodeResult] = {}
    # batch-1 inference needs one thread; more threads spin (OpenMP) and starve the CPU renderer
    threads = max(1, (os.cpu_count() or 1) // (2 * max(1, workers)))
    if workers <= 1:
        init_worker(threads)
        for i, job in enumerate(jobs):
            results[i] = work(job)
            bar.update()
        bar.close()
        return [results[i] for i in range(len(jobs))]
    pending, crashes = dict(enumerate(jobs)), Counter()
    while pending:
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=init_worker,
                                 initargs=(threads, max(1, (os.cpu_count() or 1) // workers))) as pool:
            futures = {pool.submit(work, job): i for i, job in pending.items()}
            for f in as_completed(futures):
                i = futures[f]
                try:
                    results[i] = f.result()
                except BrokenProcessPool:
                    crashes[i] += 1
                    if crashes[i] < 2:
                        continue
                    results[i] = EpisodeResult(pending[i], False, 0, reason="worker process crashed")
                pending.pop(i)
                bar.update()
    bar.close()
    return [results[i] for i in range(len(jobs))]


def summarize(results: list[EpisodeResult], spec: EvalSpec) -> pd.DataFrame:
    rows = []
    for task in dict.fromkeys(r.job.task for r in results):
        for noise in spec.noises:
            for v in spec.variants:
                cell = [r for r in results if (r.job.task, r.job.noise, r.job.variant) == (task, noise, v.name)]
                k, n = sum(r.success for r in cell), len(cell)
                lo, hi = wilson(k, n)
                rows.append({"task": task, "noise": noise, "variant": v.name, "label": v.label, "episodes": n,
                             "successes": k, "success_rate": k / n if n else math.nan, "ci_low": lo, "ci_high": hi,
                             "errors": sum(bool(r.reason) for r in cell)})
    return pd.DataFrame(rows)


def markdown_table(table: pd.DataFrame, checkpoint: str = "last") -> str:
    """Paper Table 1 layout: one row per method, one column per task x noise; success % [95% CI]."""
    lines = [f"Checkpoint: **{checkpoint}** of each training run "
             + ("(the best by in-training rollout success)." if checkpoint == "best" else
                "(the end of training)." if checkpoint == "last" else "."), ""]
    for task, t in table.groupby("task", sort=False):
        noises = list(dict.fromkeys(t["noise"]))
        lines += [f"### {task}", "", "| Method | " + " | ".join(noises) + " |", "|---" * (len(noises) + 1) + "|"]
        for label, r in t.groupby("label", sort=False):
            cells = [f"{100 * x.success_rate:.0f} [{100 * x.ci_low:.0f}, {100 * x.ci_high:.0f}]"
                     + (f" ({x.errors} err)" if x.errors else "") for x in r.itertuples()]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        n = int(t["episodes"].max())
        lines += ["", f"Success rate in % over {n} episodes per cell, 95% Wilson interval in brackets.", ""]
    return "\n".join(lines)


def save_records(results: list[EpisodeResult], out: Path) -> None:
    failures = []
    for r in results:
        j = r.job
        path = out / "records" / j.task / j.noise / f"{j.variant}_seed{j.seed}.npz"
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {k: v for k, v in r.record.items() if isinstance(v, np.ndarray)}
        np.savez_compressed(path, success=r.success, steps=r.steps, **arrays)
        if r.reason:
            failures.append(f"{j.task}/{j.noise}/{j.variant} seed {j.seed}: {r.reason}")
    (out / "failures.log").write_text("\n".join(failures) + ("\n" if failures else ""))


def evaluate(spec: EvalSpec) -> pd.DataFrame:
    from nostra.workflows.figures import trajectory_figure
    from nostra.workflows.tracking import Tracker

    validate(spec)
    out = Path(spec.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = run_jobs(jobs_of(spec), spec.workers, spec.progress)
    save_records(results, out)
    table = summarize(results, spec)
    table.to_csv(out / "success.csv", index=False)
    (out / "success.md").write_text(markdown_table(table, spec.checkpoint))
    trajectory_figure(results, spec, out / "trajectories.png")
    tracker = Tracker(spec.experiment, spec.run_name, out,
                      {"tasks": ",".join(spec.tasks), "noises": ",".join(spec.noises), "episodes": spec.episodes,
                       "variants": ",".join(v.name for v in spec.variants), **spec.params})
    tracker.log_metrics({f"success/{r.task}/{r.noise}/{r.variant}": r.success_rate for r in table.itertuples()})
    for name in ("success.md", "success.csv", "trajectories.png"):
        if (out / name).is_file():
            tracker.log_artifact(out / name)
    print(tracker.finish())
    return table
