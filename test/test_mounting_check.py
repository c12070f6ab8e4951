"""The IMU-yaw check on plain arrays (estimators/fusion/mounting_check.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vehicle_estimation.estimators.common.rotations import rotmat_from_euler
from vehicle_estimation.estimators.fusion.mounting_check import MountingYawCheck

G = 9.81


def _drive(imu_yaw_deg: float, *, duration: float = 120.0, accel_amplitude: float = 5.0):
    """100 Hz IMU samples of an IMU turned by ``imu_yaw_deg`` about base_link z, and a CAN speed
    at 50 Hz in 1 km/h steps, for a car that speeds up, slows down and weaves."""
    t = np.arange(0.0, duration, 0.01)
    v = 12.0 + accel_amplitude * np.sin(0.3 * t)
    r = 0.15 * np.sin(0.21 * t)
    accel_base = np.column_stack([np.gradient(v, t), v * r, np.full_like(t, G)])
    C = rotmat_from_euler(0.0, 0.0, math.radians(imu_yaw_deg))     # imu_link -> base_link
    noise = np.random.default_rng(1).normal(0.0, 0.05, (t.size, 3))
    f_imu = accel_base @ C + noise
    w_imu = np.column_stack([np.zeros_like(t), np.zeros_like(t), r]) @ C
    can = np.round(v[::2] * 3.6) / 3.6
    return t, f_imu, w_imu, t[::2], can


def _stream(check: MountingYawCheck, drive) -> MountingYawCheck:
    t, f, w, t_can, can = drive
    j = 0
    for i in range(t.size):
        check.add_imu(t[i], f[i], w[i])
        while j < t_can.size and t_can[j] <= t[i]:
            check.add_speed(t_can[j], can[j])
            j += 1
    return check


@pytest.mark.parametrize("imu_yaw_deg", [0.0, 90.0, 180.0, -35.0])
def test_the_stream_finds_the_imus_yaw(imu_yaw_deg):
    check = _stream(MountingYawCheck((0.0, 0.0, 0.0)), _drive(imu_yaw_deg))
    assert check.offset == pytest.approx(-math.radians(imu_yaw_deg), abs=math.radians(2.0)) or (
        abs(imu_yaw_deg) == 180.0 and abs(check.offset) == pytest.approx(math.pi, abs=math.radians(2.0)))
    assert check.mismatched == (imu_yaw_deg != 0.0)
    yaw = check.implied_yaw_deg()
    assert abs((yaw - imu_yaw_deg + 180.0) % 360.0 - 180.0) < 2.0
    assert ("agrees" in check.status()) == (imu_yaw_deg == 0.0)


def test_the_nominal_mounting_is_what_it_checks():
    """An IMU facing left is right when the vehicle file says so (its yaw 90 deg)."""
    check = _stream(MountingYawCheck((0.0, 0.0, math.pi / 2)), _drive(90.0))
    assert check.offset == pytest.approx(0.0, abs=math.radians(2.0)) and not check.mismatched


def test_no_verdict_without_enough_acceleration_or_samples_and_reset_forgets():
    check = _stream(MountingYawCheck(), _drive(90.0, accel_amplitude=0.2, duration=60.0))
    # the weaving alone (v r ~ 1.8 m/s^2) tells; slow speed changes do not hide it
    assert check.mismatched
    calm = MountingYawCheck()
    t, f, w, t_can, can = _drive(90.0, accel_amplitude=0.0)
    w[:] = 0.0                                              # straight, constant speed: no excitation
    f[:, :2] = np.random.default_rng(2).normal(0.0, 0.05, (t.size, 2))
    _stream(calm, (t, f, w, t_can, can))
    assert calm.offset is None and "no verdict" in calm.status()
    check.reset()
    assert check.samples == 0 and check.offset is None


def test_imu_samples_without_a_speed_do_not_pile_up():
    check = MountingYawCheck()
    for k in range(100_000):                                # 10 000 s of IMU, no speed at all
        check.add_imu(0.1 * k, np.array([0.0, 0.0, G]), np.zeros(3))
    assert len(check._pending) <= (check.baseline_s + 10.0) / check.sample_period_s + 1
    assert check.offset is None
