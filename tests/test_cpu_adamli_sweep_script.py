"""scripts/cpu_adamli_sweep.sh: which checkpoint, demos and horizon AdaMLI's threshold settings are tried on."""
from script_stubs import run_stubbed


def test_the_best_checkpoint_of_the_profiles_study_by_default(tmp_path):
    r, calls = run_stubbed(tmp_path, "cpu_adamli_sweep.sh", {"F_O": "20", "F_C": "12", "ROLLOUT_NOISES": "mask"})
    assert r.returncode == 0, r.stderr
    offline, rollout = [c.split() for c in calls if c.startswith("nostra evaluate")]
    assert "evaluate.offline.checkpoint=data/runs/cpu/train/pretrain-nostra-LiftD1-s0/checkpoints/best.ckpt" in offline
    assert "evaluate.offline.collections=[liftd1_cpu]" in offline
    assert "evaluate.checkpoint=best" in rollout and not any(a.startswith("profile.eval_horizon") for a in rollout)
    assert "evaluate.out_dir=data/runs/cpu/evaluate/liftd1-adamli/s0-fo20-fc12/mask" in rollout


def test_a_studys_last_checkpoint_its_demos_and_horizon(tmp_path):
    env = {"TASK": "stack", "DEMO_NOISE": "0.2", "DEMO_NOISE_PHASES": "approach", "LR": "cosine",
           "STEPS": "18000", "HORIZON": "600", "CHECKPOINT": "last", "F_O": "20", "F_C": "12",
           "ROLLOUT_NOISES": "none"}
    r, calls = run_stubbed(tmp_path, "cpu_adamli_sweep.sh", env)
    assert r.returncode == 0, r.stderr
    runs = "data/runs/cpu-n0.2-approach-cosine"
    offline, rollout = [c.split() for c in calls if c.startswith("nostra evaluate")]
    assert f"evaluate.offline.checkpoint={runs}/train/pretrain-nostra-LiftD1-s0/checkpoints/last.ckpt" in offline
    assert "evaluate.offline.collections=[stack_cpu_n0p2_approach]" in offline
    assert f"evaluate.out_dir={runs}/offline/stack-adamli-last/s0-fo20-fc12/mask" in offline
    assert "evaluate.checkpoint=last" in rollout and "profile.eval_horizon=600" in rollout
    assert f"evaluate.out_dir={runs}/evaluate/stack-h600-adamli-last/s0-fo20-fc12/none" in rollout
    report = next(c for c in calls if "offline_report" in c)
    assert "CHECKPOINT=last" in report and "HORIZON=600" in report and "DEMO_NOISE_PHASES=approach" in report


def test_an_unknown_checkpoint_is_refused_naming_the_valid_ones(tmp_path):
    r, calls = run_stubbed(tmp_path, "cpu_adamli_sweep.sh", {"CHECKPOINT": "step=3000"})
    assert r.returncode == 2 and "CHECKPOINT=step=3000" in r.stderr and "valid: best, last" in r.stderr
    assert not [c for c in calls if c.startswith("nostra")]
