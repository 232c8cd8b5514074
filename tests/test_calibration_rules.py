"""Calibration rules: the stride mix percentiles aim at, the mix a rollout executed, and the success-constrained
choice among a ladder of percentiles."""

from __future__ import annotations

import numpy as np
import pytest

from hipolicy_jax.evaluation import calibration


def test_intended_mix_is_the_gaps_between_percentiles():
    assert calibration.intended_mix((10, 70), (1, 2, 3)) == {"1": 0.1, "2": 0.6, "3": 0.3}
    assert calibration.intended_mix((25,), (1, 4)) == {"1": 0.25, "4": 0.75}
    with pytest.raises(ValueError, match="percentiles: need M-1=2 values"):
        calibration.intended_mix((10,), (1, 2, 3))


def test_thresholds_at_percentiles_send_the_intended_mix_on_their_own_entropies():
    from hipolicy_jax.sampling import select_frequency

    h = np.random.default_rng(0).normal(size=1000)
    th = calibration.calibrate_thresholds(h, 3, (10, 70))
    k = np.asarray(select_frequency(h.astype(np.float32), th, 3))  # index 0 = stride 1
    strides = np.asarray([1, 2, 3])[k]
    mix = calibration.achieved_mix(strides[None], np.ones((1, h.size), bool), (1, 2, 3))
    for s, want in calibration.intended_mix((10, 70), (1, 2, 3)).items():
        assert abs(mix[s] - want) <= 0.002


def test_achieved_mix_counts_valid_decisions_only():
    strides = np.array([[1, 3, 3, 2], [2, 2, 0, 0]])
    valid = np.array([[True, True, True, True], [True, True, False, False]])
    assert calibration.achieved_mix(strides, valid, (1, 2, 3)) == {"1": 1 / 6, "2": 3 / 6, "3": 2 / 6}


def test_ladder_runs_from_cautious_to_aggressive():
    for m in (2, 3, 4):
        ladder = calibration.percentile_ladder(m)
        assert len(ladder) >= 6 and all(len(q) == m - 1 for q in ladder)
        stride1 = [q[0] for q in ladder]  # the share of decisions at stride 1 falls along the ladder
        assert all(a > b for a, b in zip(stride1, stride1[1:]))
        for q in ladder:
            calibration.effective_percentiles(m, q)  # valid percentiles
    assert (10.0, 70.0) in calibration.percentile_ladder(3)  # the paper's
    assert calibration.percentile_ladder(1) == ()


def test_success_constrained_choice():
    cands = [{"success_rate": r} for r in (0.9, 0.88, 0.86, 0.8, 0.85, 0.6)]
    # the most aggressive within the margin, even past a candidate that falls outside it
    assert calibration.choose_success_constrained(cands, 0.9, 0.05) == 4
    assert calibration.choose_success_constrained(cands, 0.9, 0.0) == 0
    assert calibration.choose_success_constrained(cands, 0.9, 0.3) == 5
    # none within the margin: the most cautious
    assert calibration.choose_success_constrained(cands, 1.0, 0.05) == 0
    with pytest.raises(ValueError, match="margin: a success-rate difference in"):
        calibration.choose_success_constrained(cands, 0.9, -0.1)
    with pytest.raises(ValueError, match="candidates"):
        calibration.choose_success_constrained([], 0.9, 0.05)
