"""In-training rollouts pick the best checkpoint among checks at one horizon: a run resumed at a
longer horizon keeps its earlier checks in rollouts.json but does not compare scores across horizons."""

import json

from nostra.configs import RolloutConfig
from nostra.workflows.training_rollouts import RolloutCallback, RolloutEnv


def _callback(out, horizon):
    return RolloutCallback(RolloutConfig(every=1000, horizon=horizon), RolloutEnv(task="stack"), "nostra", out,
                           can_imagine=True)


def test_best_and_done_only_among_checks_at_the_runs_horizon(tmp_path):
    (tmp_path / "rollouts.json").write_text(json.dumps([
        {"step": 1000, "episodes": 10, "score": 0.4},                    # logged before horizons were
        {"step": 2000, "episodes": 10, "horizon": 200, "score": 0.9},
        {"step": 3000, "episodes": 10, "horizon": 400, "score": 0.7},
        {"step": 4000, "episodes": 10, "horizon": 400, "score": 0.7}]))
    at400 = _callback(tmp_path, 400)
    assert at400.best == 0.7 and at400.summary()["best"] == {"step": 4000, "score": 0.7, "episodes": 10}
    assert at400.summary()["checks"] == 4 and at400.summary()["horizon"] == 400
    assert at400._done(3000) and not at400._done(2000)   # step 2000 was checked at 200 steps only

    at200 = _callback(tmp_path, 200)
    assert at200.best == 0.9 and at200.summary()["best"]["step"] == 2000
    assert at200._done(1000) and at200._done(2000) and not at200._done(3000)

    # the task's own horizon when train.rollout.horizon is unset (Stack's, from the task registry)
    default = _callback(tmp_path, None)
    assert default.horizon == default.task.horizon
