"""Body roll in the measured lateral acceleration, on a car our simulator did not make.

A body-fixed IMU reads g sin(roll) on y when the body rolls on its suspension (~0.9 deg per
m/s^2 on the CommonRoad BMW 320i). The tyre model takes it for lateral force unless the state
node removes it with the fusion attitude (``roll_compensation``). Replayed through the nodes
with the shipped params, once with and once without.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.estimators.common.rotations import quat_from_euler
from vehicle_estimation.ros.conversions import lateral_gravity_entry

PARAMS = Path(__file__).resolve().parents[1] / "params"


def test_lateral_gravity_is_sin_roll_cos_pitch():
    class Msg:   # the fields lateral_gravity_entry reads
        class header:
            class stamp:
                sec, nanosec = 12, 500_000_000

        class orientation:   # sensor_msgs/Imu: the fusion's estimation/imu
            pass

    roll, pitch, yaw = math.radians(4.0), math.radians(-3.0), math.radians(70.0)
    q = quat_from_euler(roll, pitch, yaw)
    o = Msg.orientation
    o.x, o.y, o.z, o.w = (2.0 * float(v) for v in q)      # not normalised: still right
    Msg.orientation_covariance = [0.0] * 9                # no covariance given
    t, (stamp, g_y, variance) = lateral_gravity_entry(Msg)
    assert t == stamp == pytest.approx(12.5)
    assert g_y == pytest.approx(math.sin(roll) * math.cos(pitch), abs=1e-12)
    assert math.isnan(variance)
    # the covariance about the fixed x, y axes: a roll of 1 deg at a 70 deg heading
    cov = np.zeros((3, 3))
    cov[:2, :2] = math.radians(1.0) ** 2 * np.outer((math.cos(yaw), math.sin(yaw)), (math.cos(yaw), math.sin(yaw)))
    Msg.orientation_covariance = cov.ravel().tolist()
    _, (_, _, variance) = lateral_gravity_entry(Msg)
    dg = math.cos(roll) * math.cos(pitch) * math.radians(1.0)
    assert variance == pytest.approx(dg ** 2, rel=0.02)
    o.x = o.y = o.z = o.w = 0.0
    assert lateral_gravity_entry(Msg) is None


def test_lateral_gravity_variance_is_that_of_the_roll_about_the_heading():
    """The ENU-axes attitude covariance, turned to the body's heading, by Monte Carlo."""
    from vehicle_estimation.estimators.common.rotations import (
        gravity_on_body_y, gravity_on_body_y_variance, quat_multiply, quat_from_rotvec)

    roll, pitch, yaw = math.radians(3.0), math.radians(2.0), math.radians(50.0)
    q = np.asarray(quat_from_euler(roll, pitch, yaw), dtype=float)
    # errors about world x, y, z: 1 deg about east, 0.2 deg about north, correlated; yaw free
    cov = np.array([[math.radians(1.0) ** 2, 0.5 * math.radians(1.0) * math.radians(0.2), 0.0],
                    [0.5 * math.radians(1.0) * math.radians(0.2), math.radians(0.2) ** 2, 0.0],
                    [0.0, 0.0, math.radians(5.0) ** 2]])
    rng = np.random.default_rng(3)
    samples = [gravity_on_body_y(*quat_multiply(quat_from_rotvec(d), q))
               for d in rng.multivariate_normal(np.zeros(3), cov, size=20000)]
    predicted = gravity_on_body_y_variance(*q, cov[0, 0], cov[0, 1], cov[1, 1])
    assert predicted == pytest.approx(float(np.var(samples)), rel=0.05)
    # at a 50 deg heading the roll is mostly about north-east, not about east alone
    assert predicted < 0.8 * cov[0, 0]


def _sideslip_rmse_deg(bag: Path, start_s: float) -> tuple[float, dict[str, str]]:
    from rosbags.highlevel import AnyReader

    est, truth, diagnostics = [], [], {}
    with AnyReader([bag]) as reader:
        for conn, log_ns, data in reader.messages():
            if conn.topic == "/estimation/sideslip_stamped":
                m = reader.deserialize(data, conn.msgtype)
                est.append((m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, m.vector.x))
            elif conn.topic == "/ground_truth/sideslip":
                truth.append((log_ns * 1e-9, reader.deserialize(data, conn.msgtype).data))
            elif conn.topic == "/diagnostics":
                for status in reader.deserialize(data, conn.msgtype).status:
                    if status.name.endswith("/vehicle_state"):
                        diagnostics = {kv.key: kv.value for kv in status.values}
    est_a, truth_a = np.array(est), np.array(truth)
    k = est_a[:, 0] >= start_s
    error = est_a[k, 1] - np.interp(est_a[k, 0], truth_a[:, 0], truth_a[:, 1])
    return math.degrees(math.sqrt(float(np.mean(error ** 2)))), diagnostics


@pytest.fixture(scope="module")
def lane_change(tmp_path_factory) -> Path:
    pytest.importorskip("vehiclemodels")
    from vehicle_estimation.validation import commonroad as cr

    tmp = tmp_path_factory.mktemp("roll")
    # the first lane change of the double lane change (5-11.5 s), after 5 s of cruise
    return cr.generate(tmp, manoeuvres=["dlc"], duration=13.0)[0]


def test_roll_compensation_halves_the_sideslip_error(lane_change, tmp_path):
    off = tmp_path / "no_roll.yaml"
    off.write_text("vehicle_state:\n  ros__parameters:\n    roll_compensation: false\n")
    results = {}
    no_lever = tmp_path / "no_lever.yaml"
    no_lever.write_text("/**:\n  ros__parameters:\n    vehicle:\n      roll_lever: 0.0\n")
    for name, extra in (("on", []), ("off", ["--params", str(off)]), ("no_lever", ["--params", str(no_lever)])):
        out = tmp_path / f"estimates_{name}"
        proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(lane_change),
                               "--record", str(out), "--quiet", "--vehicle", str(PARAMS / "commonroad_bmw320i.yaml"),
                               "--params", "estimation", "--in-process", *extra],
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0 and "lossless: True" in proc.stdout, proc.stdout + proc.stderr[-3000:]
        results[name] = _sideslip_rmse_deg(out, start_s=6.0)
    (on, diag_on), (off_rmse, diag_off) = results["on"], results["off"]
    assert diag_on["roll compensation"] == "fusion attitude" and diag_off["roll compensation"] == "off"
    # the fusion's roll uncertainty is in the ay noise, and /diagnostics says how large it is
    assert float(diag_on["roll compensation sigma [m/s^2]"]) > 0.0
    assert float(diag_off["roll compensation sigma [m/s^2]"]) == 0.0
    assert on < 0.6 * off_rmse, (on, off_rmse)
    # the roll acceleration (vehicle.roll_lever, the IMU 0.61 m above the roll axis) helps too,
    # if less in one lane change than in the slalom (test_validation_commonroad: half the error)
    assert on < 0.97 * results["no_lever"][0], (on, results["no_lever"][0])


def test_roll_acceleration_term_is_the_lever_times_the_roll_acceleration():
    """A body rolling as 3 deg sin(2 pi 0.5 t), sampled at 200 Hz, stepped at 100 Hz: the
    term is h p' within the lag of half a step; 0 without a lever; NaN rates are skipped."""
    from vehicle_estimation.estimators.state.core import RollAccelerationTerm

    w, amp, h = 2.0 * math.pi * 0.5, math.radians(3.0), 0.6
    term, none = RollAccelerationTerm(h), RollAccelerationTerm(0.0)
    got, want = [], []
    for k in range(1, 801):
        t = k / 200.0
        p = amp * w * math.cos(w * t)
        term.add(p)
        term.add(math.nan)
        none.add(p)
        if k % 2 == 0:
            got.append(term.step(t))
            assert none.step(t) == 0.0
            want.append(-h * amp * w * w * math.sin(w * (t - 0.0075)))   # mean of the window's centre
    assert got[0] == 0.0                       # no previous step yet
    np.testing.assert_allclose(got[1:], want[1:], atol=2e-3 * h * amp * w * w + 1e-4)
    term.reset()
    assert term.step(5.0) == 0.0


def test_the_mounting_roll_is_in_the_odometry_roll_and_not_in_the_lateral_force(tmp_path):
    """No constraint sees a roll of the IMU about the car's forward axis, so the vehicle file's
    mounting roll is never refined: our simulator's IMU sits rolled 0.4 deg where the file says
    level, and the odometry's roll is off by that all drive. Its variance carries it
    (``fusion.mounting_roll_sigma``); the vehicle-state node, which removes gravity from the
    IMU's own lateral axis, takes the attitude of ``estimation/imu`` (P's) and is the same to
    the digit whatever that setting says. Through the nodes, the demo's first 150 s with the
    shipped params and with the setting at 0 (a mounting taken as calibrated: GNSS has shrunk
    the roll's sigma to a few hundredths of a degree by 60 s, and 30 % of the samples from
    there lie within 2 sigma)."""
    import dataclasses

    from rosharness import replay_side_by_side

    from vehicle_estimation.contract import topics as T
    from vehicle_estimation.evaluation.report import read_bag
    from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

    scenario = dataclasses.replace(scenario_by_name("default"), duration_s=150.0)
    assert scenario.sensors.imu_misalignment_deg[0] == pytest.approx(0.4)
    bag = write_bag(simulate(scenario), tmp_path / "drive")
    calibrated = tmp_path / "calibrated.yaml"
    calibrated.write_text("fusion:\n  ros__parameters:\n    fusion.mounting_roll_sigma: 0.0\n")
    records = replay_side_by_side({"shipped": [str(bag), "--params", "estimation"],
                                   "calibrated": [str(bag), "--params", "estimation", "--params", str(calibrated)]},
                                  tmp_path)
    within, sideslip = {}, {}
    for name, record in records.items():
        data = read_bag(record, [T.ODOMETRY, T.GT_ODOMETRY, T.SIDESLIP_STAMPED])
        est, truth = data[T.ODOMETRY], data[T.GT_ODOMETRY]
        moving = est["t"] >= est["t"][0] + 12.0
        error = est["roll"][moving] - np.interp(est["t"][moving], truth["t"], truth["roll"])
        within[name] = float(np.mean(np.abs(error) <= 2.0 * np.sqrt(est["var_roll"][moving])))
        sideslip[name] = np.asarray(data[T.SIDESLIP_STAMPED]["value"])
    assert within["shipped"] >= 0.95, within
    assert within["calibrated"] < 0.8, within
    assert sideslip["shipped"].size > 1000
    np.testing.assert_array_equal(sideslip["shipped"], sideslip["calibrated"])
