"""One normalisation statistic: streamed (ingest) and whole-array (fit_stats) give the same numbers."""

import numpy as np

from nostra.data.stats import RunningStats, combine, fit_stats


def test_fit_stats_matches_numpy_and_the_streamed_combination():
    x = np.random.default_rng(0).normal(3.0, 2.0, size=(4, 25, 3))
    s = fit_stats({"a": x})["a"]
    flat = x.reshape(-1, 3)
    assert np.allclose(s["mean"], flat.mean(0)) and np.allclose(s["std"], flat.std(0), atol=1e-5)
    assert np.allclose(s["min"], flat.min(0)) and np.allclose(s["max"], flat.max(0)) and s["count"] == 100
    parts = []
    for chunk in np.array_split(flat, 3):  # as ingest streams it, collection by collection
        acc = RunningStats()
        acc.update(chunk)
        parts.append(acc.to_dict())
    streamed = combine(parts)
    assert all(np.allclose(streamed[k], s[k], atol=1e-5) for k in ("mean", "std", "min", "max"))
