"""AdaMLI on synthetic KL traces with known noise windows (paper section 3.2, appendix F)."""

import numpy as np
import pytest

from nostra.policies.imagination import AdaMLI, AdaMLIConfig, KLSwitch, adamli_flags, detection_scores, window_mask
from nostra.sim.synthetic import kl_trace

PAPER_WINDOWS = {"stack": [(25, 75), (100, 150)], "other": [(75, 100), (125, 150)]}


@pytest.mark.parametrize("task", sorted(PAPER_WINDOWS))
def test_detection_precision_and_recall(task):
    flags, truth = [], []
    for seed in range(20):
        kl, mask = kl_trace(200, PAPER_WINDOWS[task], seed=seed)
        flags.append(adamli_flags(kl)), truth.append(mask)
    scores = detection_scores(np.concatenate(flags), np.concatenate(truth))
    assert scores["precision"] >= 0.9, scores
    assert scores["recall"] >= 0.9, scores


def test_no_detection_without_noise():
    for seed in range(10):
        kl, _ = kl_trace(300, [], seed=seed)
        assert not adamli_flags(kl).any()


def test_switches_on_jump_and_back_on_drop():
    kl = np.full(60, 2.0) + 0.01 * np.sin(np.arange(60))
    kl[30:40] += 3.0
    flags = adamli_flags(kl)
    assert flags[30:40].all() and not flags[:30].any() and not flags[40:].any()


def test_thresholds_are_the_papers_defaults_and_configurable():
    cfg = AdaMLIConfig()
    assert (cfg.f_o, cfg.k_o, cfg.f_c, cfg.k_c) == (20.0, 10, 3.0, 2)
    kl = np.full(60, 2.0) + 0.05 * np.sin(np.arange(60) * 1.3)
    kl[30:40] += 0.6  # a jump of about 10x the typical change: below f_o = 20, above f_o = 5
    assert not adamli_flags(kl).any()
    assert adamli_flags(kl, AdaMLIConfig(f_o=5.0))[30:40].all()


def test_per_modality_state_machines_are_independent():
    det = AdaMLI(["rgb", "depth"])
    out = []
    for t in range(40):
        out.append(det.update({"rgb": 1.0 + 0.01 * (t % 3) + (2.0 if 20 <= t < 30 else 0.0),
                               "depth": 1.0 + 0.01 * (t % 2)}))
    assert all(o["rgb"] for o in out[20:30]) and not any(o["depth"] for o in out)
    det.reset()
    assert all(not s.imagining for s in det.switches.values())


def test_window_mask_and_scores():
    mask = window_mask(10, [(2, 4), (8, 20)])
    assert mask.tolist() == [False, False, True, True, False, False, False, False, True, True]
    s = detection_scores(np.array([1, 1, 0, 0], bool), np.array([1, 0, 1, 0], bool))
    assert s == {"precision": 0.5, "recall": 0.5}
    assert KLSwitch().update(5.0) is False  # first value: nothing to compare with


def test_thresholds_from_a_config_dict_are_cast_and_checked():
    cfg = AdaMLIConfig.from_dict({"f_o": 10, "k_o": 4.0})
    assert (cfg.f_o, cfg.k_o, cfg.f_c) == (10.0, 4, 3.0) and isinstance(cfg.k_o, int)
    assert AdaMLIConfig.from_dict(None) == AdaMLIConfig() == AdaMLIConfig.from_dict({})
    with pytest.raises(ValueError, match=r"unknown AdaMLI parameter\(s\) \['f0'\]; valid: f_o, k_o, f_c"):
        AdaMLIConfig.from_dict({"f0": 1})
