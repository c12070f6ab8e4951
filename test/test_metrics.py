"""Tests of vehicle_estimation.evaluation.metrics on hand-computed arrays."""

import math

import numpy as np
import pytest

from vehicle_estimation.evaluation import metrics as m


def test_basic_errors_hand_computed():
    est = [1.0, 2.0, 4.0, math.nan]
    true = [1.0, 1.0, 2.0, 5.0]
    # errors 0, 1, 2 (NaN pair ignored)
    assert m.mae(est, true) == pytest.approx(1.0)
    assert m.rmse(est, true) == pytest.approx(math.sqrt(5.0 / 3.0))
    assert m.max_abs_error(est, true) == 2.0
    assert m.bias(est, true) == pytest.approx(1.0)
    assert m.mape(est, true) == pytest.approx((0 + 100 + 100) / 3)
    assert m.mape([110.0, 95.0], 100.0) == pytest.approx(7.5)        # scalar truth broadcast
    assert m.share_within([101.0, 104.0, 110.0], 100.0, 3.0) == pytest.approx(1 / 3)
    assert math.isnan(m.rmse([], []))
    s = m.summary([1.0, 3.0], [2.0, 2.0])
    assert s == {"n": 2, "mae": 1.0, "rmse": 1.0, "bias": 0.0, "max_abs_error": 1.0}


def test_rolling_cv_and_convergence_rate_hand_computed():
    cv = m.rolling_cv([1.0, 3.0, 3.0, 3.0], window=2)
    assert math.isnan(cv[0])
    assert cv[1] == pytest.approx(1.0 / 2.0)    # std([1,3]) = 1, mean 2
    assert cv[2] == 0.0 and cv[3] == 0.0
    # converged from index 2 on: CR = 3 steps
    assert m.convergence_rate([1.0, 3.0, 3.0, 3.0], 3.0, window=2) == 3
    assert m.convergence_rate([3.0, 3.0, 3.0, 1.0], 3.0, window=2) is None   # leaves at the end


def test_convergence_rate_on_synthetic_converging_signal():
    n = 2000
    k = np.arange(n)
    true = 10000.0
    est = true + 4000.0 * np.exp(-k / 100.0)       # first-order convergence from 14 t
    window = 50
    cr = m.convergence_rate(est, true, window=window)
    # Error < 2 % needs 4000 exp(-k/100) < 200 -> k > 100 ln 20 = 299.6 -> k >= 300.
    # c_v of the window [k-49, k] is far below 2 % by then, so CR = 300 + 1.
    assert cr == 301
    t = 0.1 * k
    assert m.convergence_time(t, est, true, window=window) == pytest.approx(30.0)
    # a signal that oscillates by +-5 % never satisfies c_v < 0.02
    osc = true * (1 + 0.05 * np.sin(k))
    assert m.convergence_rate(osc, true, window=window) is None


def test_align_linear_previous_and_overlap():
    t_true = [0.0, 1.0, 2.0]
    y_true = [0.0, 10.0, 20.0]
    t, e, tr = m.align([-0.5, 0.5, 1.5, 2.5], [1, 2, 3, 4], t_true, y_true)
    np.testing.assert_allclose(t, [0.5, 1.5])
    np.testing.assert_allclose(e, [2, 3])
    np.testing.assert_allclose(tr, [5.0, 15.0])
    t, e, tr = m.align([0.5, 1.5, 2.5], [1, 2, 3], t_true, y_true, mode="previous", hold_last=True)
    np.testing.assert_allclose(tr, [0.0, 10.0, 20.0])
    # unsorted input is sorted
    t, e, tr = m.align([1.5, 0.5], [3, 2], t_true, y_true)
    np.testing.assert_allclose(t, [0.5, 1.5])
    np.testing.assert_allclose(e, [2, 3])


def test_estimate_lag_known_shift():
    t = np.arange(0.0, 60.0, 0.05)
    truth = np.sin(0.7 * t) + 0.3 * np.sin(2.3 * t)
    est = np.sin(0.7 * (t - 0.4)) + 0.3 * np.sin(2.3 * (t - 0.4))   # delayed 0.4 s
    assert m.estimate_lag(t, est, t, truth) == pytest.approx(0.4, abs=0.01)
    # estimate leading by 0.25 s, on a coarser, offset time base
    t2 = np.arange(0.013, 60.0, 0.1)
    est2 = np.sin(0.7 * (t2 + 0.25)) + 0.3 * np.sin(2.3 * (t2 + 0.25))
    assert m.estimate_lag(t2, est2, t, truth, dt=0.05) == pytest.approx(-0.25, abs=0.01)
    assert m.estimate_lag(t, truth, t, truth) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(m.estimate_lag([0.0, 1.0], [0.0, 1.0], t, truth))
    assert math.isnan(m.estimate_lag(t, truth, t, np.ones_like(t)))   # constant truth


def test_consistency_of_an_honest_and_of_a_too_small_variance():
    from vehicle_estimation.evaluation.metrics import consistency

    rng = np.random.default_rng(4)
    error = rng.normal(0.0, 2.0, 200_000)
    honest = consistency(error, 4.0)
    assert honest["within_1sigma"] == pytest.approx(0.683, abs=0.005)
    assert honest["within_2sigma"] == pytest.approx(0.954, abs=0.005)
    assert honest["within_3sigma"] == pytest.approx(0.997, abs=0.002)
    assert honest["nees"] == pytest.approx(1.0, abs=0.02)
    # a variance half as large as it should be: NEES 2, and 2 sigma holds only 84 %
    small = consistency(error, 2.0)
    assert small["nees"] == pytest.approx(2.0, abs=0.04)
    assert small["within_2sigma"] == pytest.approx(0.843, abs=0.005)
    # the converged flag selects; non-finite and non-positive variances are left out
    flag = np.arange(error.size) % 2 == 0
    both = consistency(np.r_[error, 1.0, np.nan], np.r_[np.full(error.size, 4.0), 0.0, 4.0], np.r_[flag, 1, 1])
    assert both["n"] == error.size
    assert both["converged_share"] == pytest.approx(0.5)
    assert both["converged_nees"] == pytest.approx(1.0, abs=0.03)
    assert both["converged_beyond_3sigma"] == pytest.approx(0.0027, abs=0.001)
