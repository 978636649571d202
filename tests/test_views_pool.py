"""Table 3 pooled over seeds from the views reports' per-seed changes (views.csv) alone."""
import pandas as pd
import pytest
from scipy import stats

from nostra.workflows.views_pool import main


def _report(folder, rows):
    folder.mkdir(parents=True)
    pd.DataFrame(rows, columns=["run", "view", "episodes", "modality", "kl_change_pct", "share_change_pts"]).to_csv(
        folder / "views.csv", index=False)


def test_seeds_from_several_reports_are_pooled_with_a_t_interval_over_the_seeds(tmp_path):
    _report(tmp_path / "a", [("b1e-4-s0", "occluded", 20, "agentview_image", 3.0, -0.1),
                             ("b1e-4-s1", "occluded", 20, "agentview_image", -41.0, -4.3),
                             ("b1e-4-s0", "blind", 20, "agentview_image", -66.0, -7.5),  # one seed: not pooled
                             ("b1e-2-s0", "occluded", 20, "agentview_image", 67.0, 3.2)])
    # seed 1 again in a later report: the first report's value is kept
    _report(tmp_path / "b", [("b1e-4-s1", "occluded", 20, "agentview_image", 99.0, 9.9),
                             ("b1e-4-s3", "occluded", 20, "agentview_image", -40.0, -5.0)])
    main(["--reports", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "out")])
    pooled = pd.read_csv(tmp_path / "out/views_pooled.csv")
    assert len(pooled) == 1
    r = pooled.iloc[0]
    assert (r.run, r.view, r.seeds, r.kl_change_pct_per_seed) == ("b1e-4", "occluded", "0 1 3", "+3 -41 -40")
    x = [3.0, -41.0, -40.0]
    low, high = stats.t.interval(0.95, 2, loc=sum(x) / 3, scale=stats.sem(x))
    assert r.kl_change_pct == pytest.approx(-26) and (r.kl_change_pct_low, r.kl_change_pct_high) == pytest.approx((low, high))
    text = (tmp_path / "out/views_pooled.md").read_text()
    assert "| b1e-4-s* | occluded | 0 1 3 | agentview_image | +3 -41 -40% | -26% [" in text
    assert "python -m nostra.workflows.views_pool --reports" in text


def test_a_bad_views_csv_is_refused_naming_it(tmp_path):
    _report(tmp_path / "a", [("b1e-4", "occluded", 20, "agentview_image", 3.0, -0.1)])
    with pytest.raises(ValueError, match="a/views.csv: run 'b1e-4' does not end in -s<training seed>"):
        main(["--reports", str(tmp_path / "a"), "--out", str(tmp_path / "out")])
    (tmp_path / "b").mkdir()
    (tmp_path / "b/views.csv").write_text("run,view,modality\nb1e-4-s0,occluded,agentview_image\n")
    with pytest.raises(ValueError, match=r"b/views.csv: missing column\(s\) kl_change_pct, share_change_pts"):
        main(["--reports", str(tmp_path / "b"), "--out", str(tmp_path / "out")])
    with pytest.raises(FileNotFoundError, match="gone/views.csv: no views.csv"):
        main(["--reports", str(tmp_path / "gone"), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()


def test_nothing_to_pool_is_said_and_nothing_written(tmp_path):
    _report(tmp_path / "a", [("b1e-4-s0", "occluded", 20, "agentview_image", 3.0, -0.1)])
    with pytest.raises(ValueError, match="no run, view and modality has two training seeds"):
        main(["--reports", str(tmp_path / "a"), "--out", str(tmp_path / "out")])
    assert not (tmp_path / "out").exists()
