"""The speed cornering shows (estimators/state/core.py), on plain numbers."""

import math

import numpy as np
import pytest

from vehicle_estimation.estimators.state.core import CorneringSpeed


def _feed(speed: CorneringSpeed, t, ay, r):
    return [found for found in (speed.add(ti, a, w) for ti, a, w in zip(t, ay, r)) if found is not None]


def test_a_steady_turn_gives_its_speed_with_the_variance_its_yaw_rate_allows():
    t = np.arange(0.0, 5.0, 0.01)
    found = _feed(CorneringSpeed(accel_std=0.7, correlation_s=0.0), t, np.full(t.size, 20.0 * 0.4),
                  np.full(t.size, 0.4))
    assert len(found) == 9                  # a 0.5 s window each, the last still filling
    for vx, variance in found:
        assert vx == pytest.approx(20.0)
        assert variance == pytest.approx((0.7 / 0.4) ** 2)
    # reversing (vx < 0) or turning the other way: the same relation
    vx, _ = _feed(CorneringSpeed(), t[:60], np.full(60, -3.0), np.full(60, 0.3))[0]
    assert vx == pytest.approx(-10.0)


def test_the_lateral_velocity_rate_is_the_error_the_variance_allows():
    """a_y = vy' + vx r: a window whose vy' is accel_std off reads vx 1 sigma off."""
    t = np.arange(0.0, 0.6, 0.01)
    r, vy_rate = 0.5, 1.0
    (vx, variance), = _feed(CorneringSpeed(accel_std=vy_rate, correlation_s=0.0), t,
                            np.full(t.size, 15.0 * r + vy_rate), np.full(t.size, r))
    assert abs(vx - 15.0) == pytest.approx(math.sqrt(variance))


def test_nothing_is_measured_on_a_straight_or_from_bad_samples():
    t = np.arange(0.0, 3.0, 0.01)
    assert _feed(CorneringSpeed(min_yaw_rate=0.2), t, np.full(t.size, 1.0), np.full(t.size, 0.1)) == []
    speed = CorneringSpeed()
    assert speed.add(0.0, math.nan, 0.5) is None and speed.add(0.0, 5.0, math.inf) is None
    # correlated windows (a turn's vy' lasts longer than a window) weigh more
    white = _feed(CorneringSpeed(correlation_s=0.0), t[:60], np.full(60, 5.0), np.full(60, 0.5))[0][1]
    shared = _feed(CorneringSpeed(correlation_s=1.0), t[:60], np.full(60, 5.0), np.full(60, 0.5))[0][1]
    assert shared == pytest.approx(4.0 * white, rel=0.05)


def test_a_vibrating_window_carries_its_mean_s_own_error():
    t = np.arange(0.0, 0.6, 0.01)
    shake = 4.0 * np.where(np.arange(t.size) % 2 == 0, 1.0, -1.0)
    (_, quiet), = _feed(CorneringSpeed(accel_std=0.7, correlation_s=0.0), t, np.full(t.size, 5.0),
                        np.full(t.size, 0.5))
    (vx, shaken), = _feed(CorneringSpeed(accel_std=0.7, correlation_s=0.0), t, 5.0 + shake[:t.size],
                          np.full(t.size, 0.5))
    assert vx == pytest.approx(10.0, abs=0.2)
    n = 51                                          # samples in the first 0.5 s window
    assert shaken == pytest.approx(quiet + 16.0 / (n - 1) / 0.25, rel=0.05)


def test_a_stamp_going_back_starts_a_new_window():
    speed = CorneringSpeed()
    for k in range(40):
        assert speed.add(10.0 + 0.01 * k, 5.0, 0.5) is None
    assert speed.add(1.0, 8.0, 0.5) is None        # a bag loop: the half window is dropped
    found = _feed(speed, 1.0 + 0.01 * np.arange(1, 60), np.full(59, 8.0), np.full(59, 0.5))
    assert found and found[0][0] == pytest.approx(16.0)


def test_while_vx_is_measured_no_window_fills():
    speed = CorneringSpeed()
    for k in range(40):
        assert speed.step(0.01 * k, 5.0, 0.5, vx_measured=False) is None
    assert speed.step(0.40, 5.0, 0.5, vx_measured=True) is None      # the open window is dropped
    found = [f for k in range(41, 100) if (f := speed.step(0.01 * k, 8.0, 0.5, vx_measured=False))]
    assert found and found[0][0] == pytest.approx(16.0)


def test_a_dropout_starts_a_new_window():
    speed = CorneringSpeed()
    for k in range(40):
        assert speed.add(0.01 * k, 5.0, 0.5) is None
    # 2 s without samples, then another turn: the window holds only the new one
    found = _feed(speed, 2.4 + 0.01 * np.arange(60), np.full(60, 8.0), np.full(60, 0.5))
    assert found and found[0][0] == pytest.approx(16.0)


@pytest.mark.parametrize("name, value", [("accel_std", 0.0), ("min_yaw_rate", -1.0), ("window_s", math.nan),
                                         ("correlation_s", -0.5)])
def test_bad_settings_are_refused_by_name(name, value):
    with pytest.raises(ValueError, match=name):
        CorneringSpeed(**{name: value})
