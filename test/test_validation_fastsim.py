"""Hilly drives of NREL FASTSim 3 (vehicle_estimation.validation.fastsim_drive)."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

fastsim = pytest.importorskip("fastsim")

from vehicle_estimation.contract import topics as T
from vehicle_estimation.validation import fastsim_drive as fd
from vehicle_estimation.contract.vehicle import load_vehicle_params
from vehicle_estimation.estimators.common.rotations import quat_from_euler, quat_to_rotmat

PARAMS_FILE = Path(__file__).resolve().parents[1] / "params" / f"{fd.VEHICLE_NAME}.yaml"
DURATION = 100.0  # s: two starts, cruise, braking, hills up and down
BAG_DURATION = 10.0
E2E_DURATION = 120.0


@pytest.fixture(scope="module")
def drive():
    return fd.simulate(DURATION)


@pytest.fixture(scope="module")
def result(drive):
    return fd.sensor_result(drive, seed=3)


def _window_mean(t, x, width=1.0):
    """Means of ``x`` over consecutive ``width`` s windows."""
    k = np.floor(t / width).astype(int)
    n = k.max() + 1
    return np.bincount(k, x, minlength=n) / np.maximum(np.bincount(k, minlength=n), 1)


def test_fastsim_version_and_vehicle(drive):
    assert fastsim.__version__ == fd.FASTSIM_VERSION
    assert drive.vehicle["veh.name"] == "2012 Ford Fusion"
    assert "veh.pt_type.Conv.fc.pwr_out_max_watts" in drive.vehicle   # a conventional car
    assert drive.mass == pytest.approx(1644.27, abs=0.01)


def test_the_full_cycle_is_hilly_with_stops():
    cyc = fd.cycle_arrays()
    assert cyc["t"][-1] == pytest.approx(fd.FULL_DURATION)
    assert 0.05 < np.max(cyc["grade"]) <= 0.065 and -0.065 <= np.min(cyc["grade"]) < -0.05
    moving = cyc["speed"] > 0.5
    starts = np.count_nonzero(moving[1:] & ~moving[:-1])
    assert starts >= 3                                       # the first start and two stops mid-drive
    accel = np.gradient(cyc["speed"], cyc["t"])
    assert accel.max() > 1.5 and accel.min() < -1.5


def test_truth_speed_is_fastsims_and_meets_the_cycle(drive, result):
    h = drive.history
    assert np.all(h["cyc_met"][1:] == 1.0)
    np.testing.assert_allclose(h["speed"], drive.cycle["speed"], atol=1e-6)
    np.testing.assert_allclose(h["grade"], drive.cycle["grade"], atol=1e-12)
    truth = result.truth
    np.testing.assert_allclose(truth["vx"], np.interp(truth["t"], drive.t, h["speed"]), atol=1e-12)
    np.testing.assert_allclose(truth["slope"], np.arctan(np.interp(truth["t"], drive.t, h["grade"])), atol=1e-12)
    assert np.all(truth["mass"] == drive.mass)
    assert np.max(np.abs(truth["slope"])) > math.radians(2.0)


def test_the_params_file_describes_fastsims_power_balance(drive):
    """FASTSim's tractive power, rebuilt from the committed vehicle file's values (our Eq. 1
    with FASTSim's per-step discretisation): mass, C_rr, g, drag (via the air density), wheel
    inertia and radius all as FASTSim uses them."""
    p = load_vehicle_params(PARAMS_FILE)
    h = drive.history
    dt = float(drive.t[1] - drive.t[0])
    v, theta = h["speed"], np.arctan(h["grade"])
    v_avg = 0.5 * (v[1:] + v[:-1])
    a = np.diff(v) / dt
    m_eq = p.mass + p.wheel_inertia / p.wheel_radius ** 2
    force = (m_eq * a + p.mass * p.gravity * (np.sin(theta[1:]) + p.rolling_resistance * np.cos(theta[1:]))
             + 0.5 * p.air_density * p.drag_area * v_avg ** 2)
    sel = v_avg > 1.0
    residual = force[sel] * v_avg[sel] - h["pwr_tractive"][1:][sel]
    assert np.max(np.abs(residual)) < 20.0 + 1e-3 * np.max(np.abs(h["pwr_tractive"]))
    # and the wheel force the bag carries is FASTSim's transmission output over the speed
    f = fd.forces(drive)
    np.testing.assert_allclose(f["propulsion"][1:][sel] * v_avg[sel], h["pwr_trans_out"][1:][sel], rtol=1e-9)
    np.testing.assert_allclose(h["pwr_trans_out"], np.maximum(h["pwr_tractive"], 0.0), atol=1e-6)


def test_committed_params_file_is_params_yaml():
    assert PARAMS_FILE.read_text(encoding="utf-8") == fd.params_yaml()
    p = load_vehicle_params(PARAMS_FILE)
    assert p.name == fd.VEHICLE_NAME and p.driven_axle == "front" and p.gravity == fd.G_MODEL


def test_specific_force_is_dvdt_plus_g_sin_grade(drive, result):
    """IMU x, less its bias, against FASTSim's own acceleration power m a v_avg (1 s means)."""
    h = drive.history
    imu = result.sensors["imu"]
    assert imu["t"][0] == 0.0 and np.median(np.diff(imu["t"])) == pytest.approx(1.0 / fd.IMU_RATE_HZ)
    v_avg = 0.5 * (h["speed"][1:] + h["speed"][:-1])
    a_fastsim = np.where(v_avg > 0.0, h["pwr_accel"][1:] / (drive.mass * np.maximum(v_avg, 1e-9)),
                         np.diff(h["speed"]) * fd.SIM_RATE_HZ)
    expected = a_fastsim + fd.G_MODEL * np.sin(np.arctan(h["grade"][1:]))
    got = _window_mean(imu["t"][1:], imu["accel"][1:, 0] - imu["bias_accel"][0])
    want = _window_mean(drive.t[1:], expected)
    assert np.max(np.abs(got - want)[:-1]) < 0.03          # noise 0.05 / sqrt(200) ~ 0.004 per window
    # z: g cos(slope) and the centripetal v d(slope)/dt over crests and dips (up to ~0.15 m/s^2)
    slope = np.arctan(h["grade"])
    fz = _window_mean(imu["t"], imu["accel"][:, 2] - imu["bias_accel"][2])
    gz = _window_mean(drive.t, fd.G_MODEL * np.cos(slope) + h["speed"] * np.gradient(slope, drive.t))
    assert np.max(np.abs(fz - gz)) < 0.03
    # the gyro's pitch rate integrates to the change of -slope
    wy = imu["gyro"][:, 1] - imu["bias_gyro"][1]
    pitch = np.concatenate([[0.0], np.cumsum(0.5 * (wy[1:] + wy[:-1]) * np.diff(imu["t"]))])
    assert np.max(np.abs(pitch + (slope - slope[0]))) < 0.01


def test_a_turned_imu_reads_the_same_motion_in_its_own_axes(drive, result):
    """``imu_rpy_deg``: imu/data in an imu_link turned in base_link (an IMU facing left, nose
    0.5 deg down): the level IMU's motion, v_imu = C^T v_base, with the same noise and biases
    (the same draws) in the IMU's own axes."""
    turned = fd.sensor_result(drive, seed=3, imu_rpy_deg=(0.5, 0.0, 90.0))
    level, imu = result.sensors["imu"], turned.sensors["imu"]
    C = quat_to_rotmat(quat_from_euler(math.radians(0.5), 0.0, math.radians(90.0)))   # imu_link -> base_link
    truth = fd.truth_signals(drive)
    idx = fd._every(drive.t, fd.IMU_RATE_HZ)
    motion = {"accel": truth["accel"][idx], "gyro": np.column_stack([truth[k][idx] for k in ("wx", "wy", "wz")])}
    for key, bias in (("accel", "bias_accel"), ("gyro", "bias_gyro")):
        np.testing.assert_array_equal(imu[bias], level[bias])
        noise = level[key] - level[bias] - motion[key]
        np.testing.assert_allclose(imu[key], motion[key] @ C + level[bias] + noise, rtol=0.0, atol=1e-12)
    # facing left: the car's forward specific force is on the IMU's -y, gravity stays on z
    assert np.corrcoef(imu["accel"][:, 1], -level["accel"][:, 0])[0, 1] > 0.99
    assert np.mean(imu["accel"][:, 2]) == pytest.approx(np.mean(level["accel"][:, 2]), abs=0.01)


def test_wheels_speed_and_powertrain(drive, result):
    S = result.sensors
    r = float(drive.vehicle["veh.chassis.wheel_radius_meters"])
    js, sp, pt = S["joint_states"], S["speed"], S["powertrain"]
    v = np.interp(js["t"], drive.t, drive.history["speed"])
    assert np.max(np.abs(js["velocity"][:, :4] - v[:, None] / r)) < 0.15      # 0.02 rad/s noise
    assert np.all(js["velocity"][v == 0.0, :4] == 0.0)
    assert np.all(js["effort"][:, :4] >= 0.0) and np.any(js["effort"][:, :4] > 10.0)   # it brakes
    np.testing.assert_allclose(sp["v"] * 3.6, np.round(v * 3.6), atol=1e-9)
    for name in ("engine_speed", "engine_torque", "load", "gear"):
        assert np.all(np.isnan(pt[name])), name
    drive_force = np.interp(pt["t"], result.truth["t"], result.truth["drive_force"])
    assert np.max(np.abs(pt["drive_force"] - drive_force)) < 100.0            # 20 N noise
    braking = js["effort"][:, :4].sum(axis=1) > 1.0
    assert np.all(pt["drive_force"][braking] == 0.0)                          # brakes or engine, not both


def test_generate_writes_the_three_variants_and_the_vehicle_file(tmp_path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = fd.generate(tmp_path, duration=BAG_DURATION, seed=1)
    assert [p.name for p in paths] == list(fd.VARIANTS)
    assert (tmp_path / f"{fd.VEHICLE_NAME}.yaml").read_text(encoding="utf-8") == PARAMS_FILE.read_text(encoding="utf-8")
    inputs = {T.IMU, T.GNSS, T.SPEED, T.JOINT_STATES, T.POWERTRAIN}
    truth = {T.GT_MASS, T.GT_ROAD_SLOPE, T.GT_VEHICLE_STATE, T.GT_ODOMETRY, T.GT_SIDESLIP, T.GT_DATUM, T.GT_IMU_BIAS}
    counts = {}
    for path, (gnss, wheels) in zip(paths, fd.VARIANTS.values()):
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
            found = {c.topic.lstrip("/"): c.msgcount for c in reader.connections}
            logs = [log for _, log, _ in reader.messages()]
            conn = next(c for c in reader.connections if c.topic.lstrip("/") == T.IMU)
            first = next(reader.messages(connections=[conn]))
            msg = reader.deserialize(first[2], conn.msgtype)
        want = inputs - ({T.GNSS} if not gnss else set()) - ({T.JOINT_STATES} if not wheels else set())
        assert set(found) == want | truth, path.name
        assert min(logs) == 0 and msg.header.stamp.sec == 0 and msg.header.stamp.nanosec == 0
        assert max(logs) == pytest.approx(BAG_DURATION * 1e9)
        counts[path.name] = found
    full = counts["fastsim_hills"]
    assert full[T.IMU] == BAG_DURATION * fd.IMU_RATE_HZ + 1 and full[T.GNSS] == BAG_DURATION * fd.GNSS_RATE_HZ + 1
    for other in counts.values():   # the same drive in every variant
        assert all(other[topic] == full[topic] for topic in other)


def test_cli(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(fd, "generate", lambda out, **kw: calls.append((out, kw)) or [])
    out = tmp_path / "new"      # the params file goes into the --out folder, not made yet
    assert fd.main(["--out", str(out), "--duration", "30", "--seed", "2",
                    "--write-params", str(out / "v.yaml")]) == 0
    assert fd.main(["--out", str(out), "--imu-rpy-deg", "0.5", "0", "90", "--write-params", str(out / "t.yaml")]) == 0
    assert calls == [(out, {"seed": 2, "duration": 30.0, "imu_rpy_deg": (0.0, 0.0, 0.0)}),
                     (out, {"seed": 0, "duration": None, "imu_rpy_deg": (0.5, 0.0, 90.0)})]
    # a turned IMU's vehicle file says how it is turned; a level one's is the committed file
    turned = load_vehicle_params(out / "t.yaml")
    np.testing.assert_allclose(turned.imu_mounting_rpy, np.radians([0.5, 0.0, 90.0]), rtol=0, atol=1e-15)
    assert dataclasses.replace(turned, imu_mounting_rpy=(0.0, 0.0, 0.0)) == load_vehicle_params(PARAMS_FILE)
    assert (out / "v.yaml").read_text(encoding="utf-8") == PARAMS_FILE.read_text(encoding="utf-8")


def test_a_short_hilly_fastsim_drive_through_the_nodes(tmp_path):
    """120 s of the drive (GNSS, wheel speeds, drive force) replayed with the shipped params and
    the FASTSim vehicle file: mass within +-5 % over the last half, slope RMSE below 0.8 deg."""
    from vehicle_estimation.evaluation import report

    bag = fd.write_drive(fd.sensor_result(fd.simulate(E2E_DURATION), seed=0), tmp_path / "fastsim_hills")
    out = tmp_path / "estimates"
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record", str(out),
                           "--vehicle", str(PARAMS_FILE), "--quiet", "--in-process"], capture_output=True, text=True, timeout=900, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "lossless: True" in proc.stdout
    _, series = report.compute_groups(report.read_bag(out, report.WANTED))
    m = series["mass"]
    half = m["t"] >= m["t"][0] + 0.5 * (m["t"][-1] - m["t"][0])
    error = np.abs(m["est"][half] / m["true"][half] - 1.0)
    assert error.max() < 0.05, f"last-half mass error up to {100 * error.max():.1f} %"
    s = series["slope"]
    sel = s["t"] >= s["t"][0] + 5.0
    rmse = math.degrees(math.sqrt(float(np.mean((s["est"][sel] - s["true"][sel]) ** 2))))
    assert rmse < 0.8, f"slope RMSE {rmse:.2f} deg"
