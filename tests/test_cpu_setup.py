"""scripts/cpu_setup.sh, sourced by the CPU-profile scripts: where a study lives and which demos it trains on."""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def setup(env: dict, body: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """Source cpu_setup.sh with `env`, `collection` replaced by an echo (nothing generated), then run body
    in `cwd` (where its data/ is)."""
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"
    script = f'source {ROOT}/scripts/cpu_setup.sh; collection() {{ echo "collection $*"; }}; {body}'
    return subprocess.run(["bash", "-c", script], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PATH": path, **env})


def test_more_demos_add_a_collection_with_seeds_apart_and_a_study_of_their_own():
    r = setup({"DEMOS": "1000"}, 'demo_collections stack; echo "$DEMO_SEEDS"; echo "$COLLECTIONS $RUNS $REPORTS"')
    assert r.returncode == 0, r.stderr
    *made, seeds, last = r.stdout.splitlines()
    assert made == ["collection stack_cpu stack",
                    "collection stack_cpu_plus800 stack generate.episodes=800 generate.seed_offset=10000"]
    assert seeds == "1000 in all, expert seeds from 0 (stack_cpu) and from 10000 (stack_cpu_plus800)"
    assert last == "stack_cpu,stack_cpu_plus800 data/runs/cpu-d1000 reports/cpu-d1000"


def test_noisier_demos_are_collections_and_a_study_of_their_own_from_the_same_expert_seeds():
    env = {"DEMOS": "1000", "DEMO_NOISE": "0.2", "LR": "cosine", "STEPS": "10"}
    r = setup(env, 'demo_collections stack; echo "$DEMO_SEEDS"; echo "$COLLECTIONS $RUNS $REPORTS"; echo "$KNOBS"')
    assert r.returncode == 0, r.stderr
    *made, seeds, last, knobs = r.stdout.splitlines()
    assert made == ["collection stack_cpu_n0p2 stack generate.action_noise=0.2",
                    "collection stack_cpu_n0p2_plus800 stack generate.episodes=800 generate.seed_offset=10000 "
                    "generate.action_noise=0.2"]
    assert seeds == ("1000 in all, expert seeds from 0 (stack_cpu_n0p2) and from 10000 (stack_cpu_n0p2_plus800), "
                     "action noise 0.2")
    assert last == "stack_cpu_n0p2,stack_cpu_n0p2_plus800 data/runs/cpu-d1000-n0.2-cosine reports/cpu-d1000-n0.2-cosine"
    assert knobs == " DEMO_NOISE=0.2 LR=cosine"
    for bad in ("0", "0.0", "-0.1", "abc", "."):
        r = setup({"DEMO_NOISE": bad}, "echo reached")
        assert r.returncode == 2 and "reached" not in r.stdout, bad
        assert f"DEMO_NOISE={bad} must be a number above 0" in r.stderr


def test_the_profiles_demos_by_default():
    r = setup({"OBS": "rgbd"}, 'demo_collections lift; echo "$COLLECTIONS $RUNS"')
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["collection lift_cpu lift", "lift_cpu data/runs/cpu-rgbd"]


def test_a_demo_count_not_above_the_profiles_is_refused_naming_it():
    for bad in ("150", "200", "many"):
        r = setup({"DEMOS": bad}, "echo reached")
        assert r.returncode == 2 and "reached" not in r.stdout
        assert f"DEMOS={bad}" in r.stderr and "demos_per_task (200)" in r.stderr


def test_a_step_budget_that_is_not_a_whole_number_is_refused_naming_it():
    for bad in ("0", "3e3", "-5"):
        r = setup({"STEPS": bad}, "echo reached")
        assert r.returncode == 2 and "reached" not in r.stdout
        assert f"STEPS={bad}" in r.stderr
    assert setup({"STEPS": "3268"}, "echo reached").stdout == "reached\n"


def test_a_horizon_of_its_own_names_the_cells_apart_and_a_bad_one_is_refused():
    r = setup({"TASK": "stack", "HORIZON": "400"}, 'echo "$EVAL_NAME"')
    assert r.returncode == 0, r.stderr
    assert r.stdout == "stack-h400\n"
    assert setup({"TASK": "stack"}, 'echo "$EVAL_NAME"').stdout == "stack\n"  # the profile's horizon
    for bad in ("0", "4e2", "long"):
        r = setup({"TASK": "stack", "HORIZON": bad}, "echo reached")
        assert r.returncode == 2 and "reached" not in r.stdout and f"HORIZON={bad}" in r.stderr


def test_records_finds_a_variants_episodes_in_the_cell_or_a_runs_subfolder(tmp_path):
    cell = tmp_path / "s0/best/none"
    for where, variant in ((cell, "rssm"), (cell / "diffusion", "diffusion")):
        (where / "records/LiftD1/none").mkdir(parents=True)
        (where / f"records/LiftD1/none/{variant}_seed1000.npz").touch()
    r = setup({}, f'NAME=LiftD1; for v in rssm diffusion lstm; do records {cell} none $v || echo "$v: none"; done')
    assert r.stdout.splitlines() == [f"{cell}/records/LiftD1/none/rssm_seed1000.npz",
                                     f"{cell}/diffusion/records/LiftD1/none/diffusion_seed1000.npz", "lstm: none"]


def test_matched_capacity_links_the_configured_run_or_names_the_missing_one(tmp_path):
    body = 'NAME=LiftD1; link_configured nostra 2 && readlink -f "$RUNS/train/pretrain-nostra-LiftD1-s2"'
    r = setup({"CAPACITY": "matched", "OBS": "rgbd"}, body, cwd=tmp_path)
    assert r.returncode == 2 and "data/runs/cpu-rgbd/train/pretrain-nostra-LiftD1-s2" in r.stderr
    assert "CAPACITY=configured" in r.stderr and not (tmp_path / "data/runs/cpu-rgbd-matched").exists()
    configured = tmp_path / "data/runs/cpu-rgbd/train/pretrain-nostra-LiftD1-s2"
    configured.mkdir(parents=True)
    (configured / "run.json").write_text("{}")
    r = setup({"CAPACITY": "matched", "OBS": "rgbd"}, body, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == str(configured)  # data/runs/cpu-rgbd-matched/train/... points there


def test_a_decaying_rate_needs_a_step_budget_and_gets_a_study_of_its_own():
    r = setup({"LR": "cosine", "STEPS": "18000", "DEMOS": "1000"}, 'echo "$RUNS $REPORTS"')
    assert r.returncode == 0, r.stderr
    assert r.stdout == "data/runs/cpu-d1000-cosine reports/cpu-d1000-cosine\n"
    assert setup({}, 'echo "$LR $RUNS"').stdout == "constant data/runs/cpu\n"  # the paper's recipe
    r = setup({"LR": "cosine"}, "echo reached")
    assert r.returncode == 2 and "reached" not in r.stdout and "STEPS=<n>" in r.stderr
    r = setup({"LR": "cosin", "STEPS": "10"}, "echo reached")
    assert r.returncode == 2 and "LR=cosin" in r.stderr and "valid: constant, cosine" in r.stderr


def test_a_mixture_head_gets_a_study_of_its_own_and_a_bad_head_is_refused():
    r = setup({"HEAD": "gmm", "LR": "cosine", "STEPS": "10", "DEMOS": "1000"}, 'echo "$RUNS $REPORTS";echo "$KNOBS"')
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["data/runs/cpu-d1000-cosine-gmm reports/cpu-d1000-cosine-gmm", " LR=cosine HEAD=gmm"]
    r = setup({}, 'echo "$HEAD $RUNS [$RECIPE] [$KNOBS]"')
    assert r.stdout == "gaussian data/runs/cpu [] []\n"  # the paper's decoder, nothing to override
    r = setup({"HEAD": "mdn"}, "echo reached")
    assert r.returncode == 2 and "reached" not in r.stdout
    assert "HEAD=mdn" in r.stderr and "valid: gaussian, gmm" in r.stderr


def test_make_cpu_gives_the_recurrent_policies_the_rate_and_head_asked_for_and_diffusion_its_own(tmp_path):
    from script_stubs import run_stubbed

    (tmp_path / "data/raw").mkdir(parents=True)
    (tmp_path / "data/raw/liftd1_cpu.hdf5").touch()
    (tmp_path / "data/store.zarr/liftd1_cpu").mkdir(parents=True)
    env = {"LR": "cosine", "HEAD": "gmm", "STEPS": "900", "MODELS": "nostra diffusion"}
    r, calls = run_stubbed(tmp_path, "cpu.sh", env)
    trains = [c for c in calls if c.startswith("nostra train")]
    assert len(trains) == 2, (r.stderr, calls)
    nostra = trains[0].split()
    assert "model.optim.lr_scheduler=cosine" in nostra and "model.net.head=gmm" in nostra
    assert "train.max_steps=900" in nostra and "paths.runs=data/runs/cpu-cosine-gmm" in nostra
    assert "model=diffusion" in trains[1] and "lr_scheduler" not in trains[1] and "head" not in trains[1]


def test_matched_capacity_with_more_demos_links_the_configured_run_of_those_demos(tmp_path):
    body = 'NAME=LiftD1; link_configured nostra 0 && readlink -f "$RUNS/train/pretrain-nostra-LiftD1-s0"'
    configured = tmp_path / "data/runs/cpu-d1000-cosine/train/pretrain-nostra-LiftD1-s0"
    configured.mkdir(parents=True)
    (configured / "run.json").write_text("{}")
    r = setup({"CAPACITY": "matched", "DEMOS": "1000", "LR": "cosine", "STEPS": "10"}, body, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == str(configured)  # from data/runs/cpu-matched-d1000-cosine


def test_make_cpu_with_noisier_demos_generates_them_and_trains_on_them(tmp_path):
    from script_stubs import run_stubbed

    r, calls = run_stubbed(tmp_path, "cpu.sh", {"DEMO_NOISE": "0.1", "MODELS": "nostra"})
    generate = [c for c in calls if c.startswith("nostra generate")]
    assert generate == ["nostra generate profile=cpu task=liftd1 generate.collection=liftd1_cpu_n0p1 "
                        "generate.action_noise=0.1"], (r.stderr, calls)
    train = next(c for c in calls if c.startswith("nostra train")).split()
    assert "data.collections=[liftd1_cpu_n0p1]" in train and "paths.runs=data/runs/cpu-n0.1" in train


def test_noise_in_some_phases_only_is_a_collection_and_a_study_of_its_own():
    env = {"DEMOS": "1000", "DEMO_NOISE": "0.2", "DEMO_NOISE_PHASES": "approach,move", "LR": "cosine", "STEPS": "10"}
    r = setup(env, 'demo_collections stack; echo "$DEMO_SEEDS"; echo "$COLLECTIONS $RUNS"; echo "$KNOBS"')
    assert r.returncode == 0, r.stderr
    *made, seeds, last, knobs = r.stdout.splitlines()
    assert made == ["collection stack_cpu_n0p2_approach_move stack generate.action_noise=0.2 "
                    "generate.action_noise_phases=[approach,move]",
                    "collection stack_cpu_n0p2_approach_move_plus800 stack generate.episodes=800 "
                    "generate.seed_offset=10000 generate.action_noise=0.2 generate.action_noise_phases=[approach,move]"]
    assert seeds.endswith("action noise 0.2 (only in approach,move)")
    assert last == ("stack_cpu_n0p2_approach_move,stack_cpu_n0p2_approach_move_plus800 "
                    "data/runs/cpu-d1000-n0.2-approach-move-cosine")
    assert knobs == " DEMO_NOISE=0.2 DEMO_NOISE_PHASES=approach,move LR=cosine"
    r = setup({"DEMO_NOISE_PHASES": "approach"}, "echo reached")
    assert r.returncode == 2 and "reached" not in r.stdout and "needs DEMO_NOISE=<std> too" in r.stderr
    r = setup({"DEMO_NOISE": "0.2", "DEMO_NOISE_PHASES": "approach,hover"}, "echo reached")
    assert r.returncode == 2 and "reached" not in r.stdout
    assert "unknown phase 'hover'" in r.stderr and "approach descend grasp" in r.stderr


def test_make_cpu_with_noise_in_the_approach_only_generates_with_those_phases(tmp_path):
    from script_stubs import run_stubbed

    r, calls = run_stubbed(tmp_path, "cpu.sh", {"DEMO_NOISE": "0.2", "DEMO_NOISE_PHASES": "approach",
                                                "MODELS": "nostra"})
    generate = [c for c in calls if c.startswith("nostra generate")]
    assert generate == ["nostra generate profile=cpu task=liftd1 generate.collection=liftd1_cpu_n0p2_approach "
                        "generate.action_noise=0.2 generate.action_noise_phases=[approach]"], (r.stderr, calls)
    train = next(c for c in calls if c.startswith("nostra train")).split()
    assert "paths.runs=data/runs/cpu-n0.2-approach" in train
