"""Table 3's paired comparison: the occluded (or blind) arm against the good arm over the episodes both analysed."""

import json

import pytest

from nostra.workflows.offline_report import main
from nostra.workflows.views import markdown, pooled_changes, view_changes


def _arm(episodes, agent, pos, steps):
    return {"episodes": [["c", e] for e in episodes], "episode_steps": steps,
            "kl_nats_episodes": {"agentview_image": agent, "pos": pos}}


GOOD = _arm([0, 1, 2, 3], [4.0, 5.0, 3.0, 4.0], [1.0] * 4, [10, 10, 20, 10])
# listed in another order, with an episode the good arm never analysed (left out of the pairing)
OCCLUDED = _arm([3, 7, 2, 1, 0], [2.0, 99.0, 1.0, 3.0, 2.0], [2.0, 99.0, 2.0, 2.0, 2.0], [10, 10, 20, 10, 10])


def test_occluded_arm_is_compared_on_the_common_episodes_step_weighted():
    changes = view_changes([{"name": "b1e-2-s0/mask", **GOOD}, {"name": "b1e-2-s0-occluded/mask", **OCCLUDED}])
    agent = changes.set_index("modality").loc["agentview_image"]
    assert agent.episodes == 4 and agent.view == "occluded"
    assert agent.kl_good == pytest.approx(190 / 50) and agent.kl_view == pytest.approx(90 / 50)
    assert agent.kl_change_pct == pytest.approx(100 * (90 / 190 - 1))
    assert agent.share_change_pts == pytest.approx(100 * (90 / 190 - 190 / 240))
    assert agent.kl_change_pct_low <= agent.kl_change_pct <= agent.kl_change_pct_high < 0
    pos = changes.set_index("modality").loc["pos"]
    assert pos.kl_change_pct == pytest.approx(100) and pos.share_change_pts > 0


def test_occluded_and_blind_arms_are_each_paired_with_the_good_arm():
    changes = view_changes([{"name": "s0/mask", **GOOD}, {"name": "s0-occluded/mask", **OCCLUDED},
                            {"name": "s0-blind/mask", **OCCLUDED}, {"name": "s1-blind/mask", **OCCLUDED}])
    assert sorted(set(zip(changes.run, changes.view))) == [("s0", "blind"), ("s0", "occluded")]


def test_seeds_are_pooled_alike_and_their_spread_widens_the_interval():
    # seed 0: the agent view's KL falls 53% (GOOD vs OCCLUDED); seed 1: it doubles (+100%)
    doubled = _arm([0, 1, 2, 3], [8.0, 10.0, 6.0, 8.0], [1.0] * 4, [10, 10, 20, 10])
    arms = [{"name": "b1e-4-s0/mask", **GOOD}, {"name": "b1e-4-s0-occluded/mask", **OCCLUDED},
            {"name": "b1e-4-s1/mask", **GOOD}, {"name": "b1e-4-s1-occluded/mask", **doubled},
            {"name": "b1e-2-s0/mask", **GOOD}, {"name": "b1e-2-s0-occluded/mask", **OCCLUDED}]  # one seed: not pooled
    pooled = pooled_changes(arms, n_resamples=2000)
    assert set(pooled.run) == {"b1e-4"} and set(pooled.seeds) == {"0 1"}
    agent = pooled.set_index("modality").loc["agentview_image"]
    assert agent.kl_change_pct == pytest.approx((100 * (90 / 190 - 1) + 100) / 2)
    assert agent.kl_change_pct_per_seed == "-53 +100"
    # resampling the seeds reaches both seeds' values: the interval spans the disagreement
    assert agent.kl_change_pct_low < -40 and agent.kl_change_pct_high > 90
    text = "\n".join(markdown(view_changes(arms), pooled=pooled))
    assert f"| b1e-4-s* | occluded | 0 1 | agentview_image | -53 +100% | {agent.kl_change_pct:+.0f}% [" in text


def test_a_run_without_its_other_arm_or_per_episode_kl_is_not_compared():
    assert not len(view_changes([{"name": "s0-occluded/mask", **OCCLUDED}]))
    old = {k: v for k, v in GOOD.items() if k != "kl_nats_episodes"}  # an analysis from before it was stored
    assert not len(view_changes([{"name": "s0/mask", **old}, {"name": "s0-occluded/mask", **OCCLUDED}]))


def test_report_shows_the_paired_table_and_writes_views_csv(tmp_path):
    for name, arm in (("b1e-2-s0", GOOD), ("b1e-2-s0-occluded", OCCLUDED)):
        d = tmp_path / "runs" / name / "mask" / "offline"
        d.mkdir(parents=True)
        kl = {m: sum(v) / len(v) for m, v in arm["kl_nats_episodes"].items()}
        d.joinpath("offline.json").write_text(json.dumps({
            **arm, "noise": "mask", "checkpoint": f"{name}.ckpt", "kl_nats": kl,
            "kl_nats_ci": {m: [v - 1, v + 1] for m, v in kl.items()}, "action_mse": {}}))
    main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--no-figures"])
    text = (tmp_path / "out/offline.md").read_text()
    assert "`b1e-2-s0` vs `b1e-2-s0-occluded` (4 episodes)" in text
    assert "| agentview_image | 3.80 | 1.80 | -53% [" in text and "| 79.2% | 47.4% | -31.8 [" in text
    assert (tmp_path / "out/views.csv").read_text().startswith("run,view,episodes,modality,")
    assert (tmp_path / "out/views.png").read_bytes().startswith(b"\x89PNG") and "![views](views.png)" in text
    assert not (tmp_path / "out/views_pooled.csv").exists() and "Pooled over training seeds" not in text  # one seed


def test_training_kl_traces_are_read_beside_the_checkpoint(tmp_path):
    from nostra.workflows.views import training_changes, training_kl, traces_figure

    analyses = []
    for name, arm, kl in (("s0", GOOD, [3.0, 2.0]), ("s0-blind", OCCLUDED, [1.0, 0.5])):
        run = tmp_path / name
        run.mkdir()
        lines = [{"params": {"model": "nostra"}}, {"step": 5, "metrics": {"train/loss": 1.0}}]
        lines += [{"step": 10 * (i + 1), "metrics": {"kl_nats/agentview_image": v}} for i, v in enumerate(kl)]
        (run / "metrics.jsonl").write_text("\n".join(json.dumps(x) for x in lines) + "\n")
        analyses.append({"name": f"{name}/mask", "checkpoint": str(run / "policy.ckpt"), **arm})
    assert training_kl(analyses[1]["checkpoint"], "agentview_image").to_dict() == {10: 1.0, 20: 0.5}
    assert traces_figure(analyses, tmp_path / "t.png") and (tmp_path / "t.png").stat().st_size > 1000
    assert not traces_figure([{**a, "checkpoint": str(tmp_path / "gone/policy.ckpt")} for a in analyses],
                             tmp_path / "none.png")
    # the training log's reading: the mean over each run's last steps (here the last 10: one logged step)
    batches = training_changes(analyses, last=10).set_index("modality").loc["agentview_image"]
    assert (batches.kl_good, batches.kl_view, batches.kl_change_pct) == (2.0, 0.5, -75.0)


def test_the_report_names_the_demos_the_analyses_replayed():
    from nostra.workflows.offline_report import demos_word

    assert demos_word([{"name": "a"}]) == "held-out"  # offline.json from before the split was recorded
    assert demos_word([{"split": "train"}, {"split": "train"}]) == "training"
    assert demos_word([{"split": "train"}, {"split": "held_out"}]) == "held-out and training"


def _write_analyses(root, arms):
    for name, arm in arms:
        d = root / name / "mask" / "offline"
        d.mkdir(parents=True)
        kl = {m: sum(v) / len(v) for m, v in arm["kl_nats_episodes"].items()}
        d.joinpath("offline.json").write_text(json.dumps({
            **arm, "noise": "mask", "checkpoint": f"{name}.ckpt", "kl_nats": kl,
            "kl_nats_ci": {m: [v - 1, v + 1] for m, v in kl.items()}, "action_mse": {}}))


DOUBLED = _arm([0, 1, 2, 3], [8.0, 10.0, 6.0, 8.0], [1.0] * 4, [10, 10, 20, 10])


def test_a_later_sitting_pools_with_the_runs_an_earlier_report_kept(tmp_path):
    import pandas as pd

    _write_analyses(tmp_path / "s0", [("b1e-4-s0", GOOD), ("b1e-4-s0-occluded", OCCLUDED)])
    main(["--analyses", str(tmp_path / "s0"), "--out", str(tmp_path / "r0"), "--no-figures"])
    kept = pd.read_csv(tmp_path / "r0/views_episodes.csv")
    assert set(kept.run) == {"b1e-4-s0", "b1e-4-s0-occluded"} and len(kept) == 2 * 4 + 5 * 2
    # seed 0's runs are gone from the disk; seed 1 is analysed in a later sitting
    _write_analyses(tmp_path / "s1", [("b1e-4-s1", GOOD), ("b1e-4-s1-occluded", DOUBLED)])
    main(["--analyses", str(tmp_path / "s1"), "--out", str(tmp_path / "r1"), "--no-figures",
          "--views-episodes", str(tmp_path / "r0/views_episodes.csv")])
    before, after = pd.read_csv(tmp_path / "r0/views.csv"), pd.read_csv(tmp_path / "r1/views.csv")
    pd.testing.assert_frame_equal(before, after[after.run == "b1e-4-s0"].reset_index(drop=True))
    pooled = pd.read_csv(tmp_path / "r1/views_pooled.csv").set_index("modality").loc["agentview_image"]
    assert pooled.seeds == "0 1" and pooled.kl_change_pct_per_seed == "-53 +100"
    # both sittings' runs are kept again, so a third sitting pools all of them
    assert set(pd.read_csv(tmp_path / "r1/views_episodes.csv").run) == {
        "b1e-4-s0", "b1e-4-s0-occluded", "b1e-4-s1", "b1e-4-s1-occluded"}


def test_a_run_on_the_disk_wins_over_the_same_run_read_back(tmp_path):
    from nostra.workflows.views import episode_frame, with_earlier

    earlier = [{"name": "b1e-4-s0/mask", **DOUBLED}, {"name": "b1e-4-s0-occluded/mask", **OCCLUDED}]
    episode_frame(earlier).to_csv(tmp_path / "views_episodes.csv", index=False)
    merged = with_earlier([{"name": "b1e-4-s0/mask", **GOOD}], [tmp_path / "views_episodes.csv"])
    assert [a["name"] for a in merged] == ["b1e-4-s0-occluded", "b1e-4-s0/mask"]
    assert merged[1]["kl_nats_episodes"] == GOOD["kl_nats_episodes"]  # the disk's, not the file's DOUBLED
    assert merged[0]["kl_nats_episodes"]["agentview_image"] == [2.0, 3.0, 1.0, 2.0, 99.0]  # by episode 0, 1, 2, 3, 7


@pytest.mark.parametrize("content, message", [
    ("run,episode,steps,modality\nb-s0,0,10,pos\n", "missing column(s) kl_nats"),
    ("run,episode,steps,modality,kl_nats\nb-s0,zero,10,pos,1.0\n", "episode and steps must be integers"),
    ("run,episode,steps,modality,kl_nats\nb-s0,0,0,pos,1.0\n", "steps must be positive (run b-s0)"),
    ("run,episode,steps,modality,kl_nats\nb-s0,0,10,pos,1.0\nb-s0,1,10,agentview_image,1.0\n",
     "run b-s0 lacks some modality's KL"),
])
def test_a_bad_views_episodes_file_is_refused_naming_it_before_anything_is_written(tmp_path, content, message):
    _write_analyses(tmp_path / "runs", [("b1e-4-s1", GOOD), ("b1e-4-s1-occluded", DOUBLED)])
    bad = tmp_path / "views_episodes.csv"
    bad.write_text(content)
    with pytest.raises(ValueError) as e:
        main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--views-episodes", str(bad)])
    assert str(bad) in str(e.value) and message in str(e.value)
    assert not (tmp_path / "out").exists()
    with pytest.raises(FileNotFoundError, match="gone.csv: no such file"):
        main(["--analyses", str(tmp_path / "runs"), "--out", str(tmp_path / "out"),
              "--views-episodes", str(tmp_path / "gone.csv")])
