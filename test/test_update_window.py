"""The mass update window: the batch twins that calibration and the paper-003 campaign use give
what the mass node's streaming window gives, window by window."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vehicle_estimation.estimators.mass.update_window import (UpdateWindow, window_edges, window_ids, window_max,
                                                               window_mean, window_slope)


def _stream(powertrain_t, wheel_t, wheel_v, brake, period):
    """Feed the samples in stamp order as the node does (a wheel sample at the stamp of a
    powertrain sample comes first) and collect each window's statistics when it closes."""
    events = sorted([(t, 0, i) for i, t in enumerate(wheel_t)] + [(t, 1, i) for i, t in enumerate(powertrain_t)])
    window, closed = UpdateWindow(), []
    for t, kind, i in events:
        if kind == 0:
            window.add_wheel_speed(t, wheel_v[i])
            continue
        window.add(t, brake[i], math.nan, vx=wheel_v[min(i, len(wheel_v) - 1)])
        if window.closes(t, period):
            closed.append((t, window.wheel_accel, window.mean("vx"), window.brake))
            window.clear()
    return closed


def test_batch_windows_are_the_node_windows():
    rng = np.random.default_rng(7)
    # 100 Hz powertrain with jitter, 50 Hz wheel speeds offset by 3 ms: windows are not a grid
    powertrain_t = np.cumsum(0.01 + 0.001 * rng.standard_normal(3000)) + 100.0
    wheel_t = np.arange(100.003, powertrain_t[-1], 0.02)
    wheel_v = 3.0 + 0.7 * (wheel_t - 100.0) + 0.01 * rng.standard_normal(wheel_t.size)
    brake = np.where(rng.random(powertrain_t.size) < 0.05, 50.0, 0.0)
    period = 0.25
    streamed = _stream(powertrain_t, wheel_t, wheel_v, brake, period)

    edges = window_edges(powertrain_t, period)
    n = len(edges)
    assert n == len(streamed) > 100
    np.testing.assert_array_equal(edges, [row[0] for row in streamed])
    ids_w = window_ids(wheel_t, edges)
    slope = window_slope(ids_w, wheel_t, wheel_v, n)
    np.testing.assert_allclose(slope, [row[1] for row in streamed], rtol=1e-9)
    brake_max = window_max(window_ids(powertrain_t, edges), brake, n)
    np.testing.assert_array_equal(brake_max, [row[3] for row in streamed])


def test_window_mean_ignores_non_finite_samples_and_flags_empty_windows():
    ids = np.array([0, 0, 1, 1, 3])
    x = np.array([1.0, 3.0, np.nan, 2.0, 5.0])
    mean = window_mean(ids, x, 4)
    assert mean[0] == pytest.approx(2.0) and mean[1] == pytest.approx(2.0) and mean[3] == pytest.approx(5.0)
    assert math.isnan(mean[2])


def test_acceleration_source_and_what_it_misses():
    window = UpdateWindow()
    for k in range(5):
        window.add_wheel_speed(0.01 * k, 10.0 + 0.02 * k)
        window.add_accel(2.0 + 0.05)
    a, _, missing = window.acceleration("auto", 0.0, 9.80665, imu_bias_known=True)
    assert a == pytest.approx(2.0) and not any(missing.values())
    empty = UpdateWindow()
    empty.add_accel(1.0)
    a, _, missing = empty.acceleration("auto", math.asin(0.05), 9.80665, imu_bias_known=True)
    assert a == pytest.approx(1.0 - 9.80665 * 0.05)
    a, _, missing = empty.acceleration("wheel_speed", 0.0, 9.80665, imu_bias_known=True)
    assert math.isnan(a) and missing["undriven wheel speeds"]
    a, _, missing = empty.acceleration("imu", 0.0, 9.80665, imu_bias_known=False)
    assert math.isnan(a) and missing["IMU bias (estimation/imu_bias)"]


def test_acceleration_variance_is_the_fits_own():
    """The noise variance of a window's acceleration: from the wheel-speed fit's residuals, and
    the IMU mean's; averaged over many windows it matches the noise actually put in."""
    rng = np.random.default_rng(4)
    speed_noise, accel_noise = 0.01, 0.05
    t = np.arange(25) * 0.01
    spread = float(np.sum((t - t.mean()) ** 2))
    wheel, imu, slopes = [], [], []
    for _ in range(400):
        w = UpdateWindow()
        for tk in t:
            w.add_wheel_speed(float(tk), 20.0 + 0.3 * float(tk) + speed_noise * float(rng.standard_normal()))
            w.add_accel(0.3 + accel_noise * float(rng.standard_normal()))
        wheel.append(w.acceleration("auto", 0.0, 9.80665, imu_bias_known=True)[1])
        imu.append(w.acceleration("imu", 0.0, 9.80665, imu_bias_known=True)[1])
        slopes.append(w.wheel_accel)
    assert np.mean(wheel) == pytest.approx(speed_noise ** 2 / spread, rel=0.1)
    assert np.var(slopes) == pytest.approx(speed_noise ** 2 / spread, rel=0.2)
    assert np.mean(imu) == pytest.approx(accel_noise ** 2 / 25, rel=0.1)
    assert math.isnan(UpdateWindow().acceleration("wheel_speed", 0.0, 9.80665, imu_bias_known=True)[1])
