"""Tests of the road-slope observers (vehicle_estimation.core.slope)."""

import math

import numpy as np
import pytest

from vehicle_estimation.core.slope import (
    SLOPE_METHODS,
    ClassicalSlopeConfig,
    ClassicalSlopeObserver,
    PitchGradeConfig,
    PitchGradeSlope,
    grade_from_pitch,
)

G = 9.80665
DT = 0.01


def _run(observer, theta_of_t, seconds, seed=1, ax_std=0.2, v_std=0.05):
    """Synthetic drive: vx(t) with sine acceleration, ax_acc = vx' + g sin(theta) + noise."""
    rng = np.random.default_rng(seed)
    vx = 15.0
    est, truth = [], []
    for k in range(int(round(seconds / DT))):
        t = k * DT
        a = 0.5 * math.sin(0.5 * t)
        vx += a * DT
        th = theta_of_t(t)
        observer.step(t, a + G * math.sin(th) + rng.normal(0, ax_std), vx + rng.normal(0, v_std))
        est.append(observer.slope)
        truth.append(th)
    return np.arange(len(est)) * DT, np.array(est), np.array(truth)


@pytest.mark.parametrize("mode", ["kalman", "luenberger"])
def test_classical_converges_to_constant_3_percent(mode):
    theta = math.atan(0.03)
    obs = ClassicalSlopeObserver(ClassicalSlopeConfig(gain_mode=mode))
    t, est, _ = _run(obs, lambda _t: theta, 30.0)
    tail = est[t > 15.0]
    assert abs(tail.mean() - theta) < 0.002           # sin(theta) ~ theta at 3 %
    assert tail.std() < (0.005 if mode == "kalman" else 0.015)
    if mode == "kalman":
        assert obs.converged
        assert math.sqrt(obs.variance) < 0.005


@pytest.mark.parametrize("mode,max_lag", [("kalman", 1.5), ("luenberger", 0.5)])
def test_classical_lags_a_ramp(mode, max_lag):
    rate = 0.005  # rad/s, 0 -> 0.06 rad between 5 s and 17 s
    obs = ClassicalSlopeObserver(ClassicalSlopeConfig(gain_mode=mode))
    t, est, truth = _run(obs, lambda tt: min(rate * max(tt - 5.0, 0.0), 0.06), 40.0, seed=2)
    m = (t > 10.0) & (t < 16.0)
    lag = np.mean(truth[m] - est[m]) / rate
    print(f"{mode}: ramp lag {lag:.3f} s")
    assert 0.0 < lag < max_lag                     # theta' = 0 model: lags, does not lead
    assert abs(est[t > 30.0].mean() - 0.06) < 0.003


def test_classical_uses_yaw_rate_term_and_rejects():
    obs = ClassicalSlopeObserver()
    assert obs.step(0.0, 0.0, 10.0)
    assert not obs.step(0.0, 0.0, 10.0)
    assert not obs.step(0.01, float("nan"), 10.0)
    assert not obs.step(0.01, 0.0, float("nan"))        # predicted only
    assert obs.rejected == {"nonfinite_input": 1, "stamp_not_increasing": 1, "nonfinite_speed": 1}
    assert obs.step(2.0, 0.0, 10.0)                      # gap -> re-initialised
    assert obs.reinitialisations == 1
    # u1 = ax + r vy: with r vy = 0.3 and ax = -0.3 on flat road at constant speed, slope ~ 0
    obs = ClassicalSlopeObserver()
    for k in range(2000):
        obs.step(k * DT, -0.3, 10.0, yaw_rate=0.1, vy=3.0)
    assert abs(obs.slope) < 0.003


def test_classical_cubic_term_runs():
    obs = ClassicalSlopeObserver(ClassicalSlopeConfig(gain_mode="luenberger", cubic_kappa=0.5))
    t, est, _ = _run(obs, lambda _t: 0.03, 20.0)
    assert np.all(np.isfinite(est)) and abs(est[t > 10].mean() - 0.03) < 0.003


def test_config_validate_names_field():
    with pytest.raises(ValueError, match="gain_mode"):
        ClassicalSlopeConfig(gain_mode="x").validate()
    with pytest.raises(ValueError, match="slope_rate_std"):
        ClassicalSlopeConfig(slope_rate_std=-1.0).validate()
    with pytest.raises(ValueError, match="luenberger_gain"):
        ClassicalSlopeConfig(gain_mode="luenberger", luenberger_gain=(-1.0, 2.0)).validate()
    with pytest.raises(ValueError, match="lwma_window"):
        PitchGradeConfig(lwma_window=0).validate()


def test_pitch_grade_passes_through():
    obs = PitchGradeSlope()
    for k, g in enumerate(np.linspace(-0.05, 0.05, 50)):
        assert obs.step(k * 0.005, g, 1e-4)
        assert obs.slope == pytest.approx(g)
        assert obs.variance == pytest.approx(1e-4)
    assert obs.converged
    assert not obs.step(0.0, 0.0, 1e-4)
    assert not obs.step(1.0, float("nan"), 1e-4)
    assert grade_from_pitch(-0.03) == pytest.approx(0.03)


def test_pitch_grade_lwma_delay():
    obs = PitchGradeSlope(PitchGradeConfig(lwma_window=25))
    rate = 0.01
    for k in range(200):
        obs.step(k * 0.005, rate * k, 1e-4)
        if k < 24:
            assert not obs.converged
    assert obs.converged
    lag_samples = (rate * 199 - obs.slope) / rate
    assert lag_samples == pytest.approx(8.0)              # (N - 1) / 3
    assert obs.step(10.0, 0.02, 1e-4) and obs.reinitialisations == 1
    assert obs.slope == pytest.approx(0.02)


def test_registry():
    assert SLOPE_METHODS["classical"] is ClassicalSlopeObserver
    assert SLOPE_METHODS["fusion_pitch"] is PitchGradeSlope
