"""A car with only an IMU and CAN: no GNSS, no wheel speeds, stamps from 0 s, shipped params.

Every node must find its fallback by itself (no hand-picked params), publish every estimate,
and say in /diagnostics which source it uses: the fusion a free heading and dead reckoning,
the slope the IMU + speed observer, the state vx from vehicle/speed, the mass on CAN speed and
the bias-compensated IMU.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from replay_values import diagnostic_statuses
from vehicle_estimation.contract import topics
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag
from vehicle_estimation.io.bagtools import rewrite_bag

ESTIMATES = (topics.ODOMETRY, topics.IMU_COMPENSATED, topics.IMU_BIAS, topics.FUSION_GRADE,
             topics.ROAD_SLOPE, topics.ROAD_SLOPE_STAMPED, topics.VEHICLE_STATE, topics.SIDESLIP,
             topics.SIDESLIP_STAMPED, topics.MASS, topics.MASS_STAMPED)


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("fallbacks")
    full = write_bag(simulate(scenario_by_name("short")), tmp / "full")
    return rewrite_bag(full, tmp / "imu_and_can", start_at_s=0.0, drop_topics=[topics.GNSS],
                       drop_joints=list(topics.WHEEL_JOINTS))


@pytest.fixture(scope="module")
def wheels_only(tmp_path_factory) -> Path:
    """IMU and wheel speeds, no GNSS and no vehicle/speed: the fusion takes the wheels."""
    tmp = tmp_path_factory.mktemp("wheels_only")
    full = write_bag(simulate(scenario_by_name("short")), tmp / "full")
    return rewrite_bag(full, tmp / "imu_and_wheels", start_at_s=0.0, drop_topics=[topics.GNSS, topics.SPEED])


def _replay(bag: Path, out: Path, *extra: str) -> Path:
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record", str(out),
                           "--quiet", *extra], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "lossless: True" in proc.stdout
    return out


@pytest.fixture(scope="module")
def replayed(bare, tmp_path_factory) -> Path:
    return _replay(bare, tmp_path_factory.mktemp("fallbacks_dds") / "estimates")


def _read(bag: Path) -> tuple[dict[str, int], dict[str, dict[str, str]], dict[str, np.ndarray]]:
    counts: dict[str, int] = {}
    diagnostics: dict[str, dict[str, str]] = {}
    series: dict[str, list[tuple[float, ...]]] = {"mass": [], "truth_mass": [], "vx": [], "truth_vx": []}
    wanted = {"/estimation/mass_stamped": "mass", "/ground_truth/mass": "truth_mass",
              "/estimation/vehicle_state": "vx", "/ground_truth/vehicle_state": "truth_vx"}
    with AnyReader([bag]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        conns = [c for c in reader.connections if c.topic == "/diagnostics" or c.topic in wanted]
        for conn, log_ns, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            if conn.topic == "/diagnostics":
                for status in msg.status:
                    values = {kv.key: kv.value for kv in status.values}
                    diagnostics[status.name.split("/")[-1]] = {"message": status.message,
                                                               "level": str(int(status.level)), **values}
                continue
            key = wanted[conn.topic]
            if key == "mass":
                value = msg.vector.x
            elif key == "truth_mass":
                value = msg.data
            else:
                value = msg.twist.twist.linear.x
                if key == "vx":         # with its published variance
                    series[key].append((log_ns * 1e-9, value, msg.twist.covariance[0]))
                    continue
            series[key].append((log_ns * 1e-9, value))
    return counts, diagnostics, {k: np.array(v) for k, v in series.items()}


@pytest.mark.dds
def test_every_estimate_is_published_without_gnss_and_wheel_speeds(replayed):
    counts, _, _ = _read(replayed)
    for topic in ESTIMATES:
        assert counts.get("/" + topic, 0) > 50, f"{topic}: {counts.get('/' + topic, 0)} messages"


@pytest.mark.dds
def test_diagnostics_name_each_fallback(replayed):
    _, diagnostics, _ = _read(replayed)
    assert diagnostics["fusion"]["heading source"].startswith("free")
    assert diagnostics["fusion"]["position source"].startswith("dead reckoning")
    assert "free heading" in diagnostics["fusion"]["message"]
    # Without GNSS the fusion's grade is the kinematic one with the accelerometer bias held at
    # its prior, converged within the prior's variance: the slope node keeps it.
    assert diagnostics["fusion"]["accel bias estimation"].startswith("held at its prior")
    # ... and the mounting is refined by the constraints while the car drives, not at standstill,
    # and its pitch not in the drive's corners.
    mounting = [status["IMU mounting estimation"] for status in diagnostic_statuses(replayed, "fusion")
                if "IMU mounting estimation" in status]
    assert set(mounting) == {"refined by the vehicle constraints (no GNSS)", "held below 1 m/s without GNSS",
                             "yaw refined, pitch held in a corner (no GNSS)"}
    assert mounting[-1] == "held below 1 m/s without GNSS"          # the drive ends at rest
    # ... and its vertical constraint loosened after the corners
    vertical = {status["vertical constraint"] for status in diagnostic_statuses(replayed, "fusion")
                if "vertical constraint" in status}
    assert vertical == {"0.1 m/s", "1 m/s (loosened after a corner: no GNSS)"}
    assert diagnostics["road_slope"]["slope source"].startswith("fusion_pitch")
    assert diagnostics["vehicle_state"]["vx source"].startswith("vehicle/speed")


@pytest.mark.dds
def test_the_fallbacks_estimate_what_they_should(replayed):
    _, _, s = _read(replayed)
    vx, truth_vx = s["vx"], s["truth_vx"]
    moving = vx[:, 0] > 12.0
    error = vx[moving, 1] - np.interp(vx[moving, 0], truth_vx[:, 0], truth_vx[:, 1])
    assert math.sqrt(float(np.mean(error ** 2))) < 0.2      # vx held by vehicle/speed, no drift
    # ... and its variance honest: the 1 km/h quantisation is one offset while the speed stays
    # in a step, not white noise (speed_error_correlation_s; as white: 76 % on FASTSim's car)
    assert float(np.mean(np.abs(error) <= 2.0 * np.sqrt(vx[moving, 2]))) >= 0.95
    mass, truth = s["mass"], float(s["truth_mass"][0, 1])
    last_half = mass[:, 0] >= mass[0, 0] + 0.5 * (mass[-1, 0] - mass[0, 0])
    assert mass[0, 1] == pytest.approx(1000.0)               # the prior ...
    assert np.max(np.abs(mass[last_half, 1] / truth - 1.0)) < 0.10   # ... left for the truth


@pytest.mark.dds
def test_in_process_replay_records_the_same_bytes(bare, replayed, tmp_path):
    """The other sensor set of the in-process check (``test_end_to_end`` has the full one):
    every fallback runs, and ``--in-process`` still records what the DDS replay records."""
    import replay_values

    out = _replay(bare, tmp_path / "estimates", "--in-process")
    dds = replay_values.recorded_estimates(replayed)
    assert len(dds) >= 10
    assert replay_values.first_difference(dds, replay_values.recorded_estimates(out)) is None


def test_without_vehicle_speed_the_fusion_navigates_on_the_wheel_speeds(wheels_only, tmp_path):
    """A car whose bus gives wheel speeds but no vehicle speed, and no GNSS: the fusion aligns
    and navigates with the undriven wheels' speed, says so, and every estimate is published."""
    plan = subprocess.run([sys.executable, "-m", "vehicle_estimation", "inspect", str(wheels_only)],
                          capture_output=True, text=True, timeout=300)
    assert plan.returncode == 0, plan.stdout + plan.stderr
    assert "the undriven wheels' speed aids the filter" in plan.stdout    # inspect says it first
    out = _replay(wheels_only, tmp_path / "estimates", "--in-process")
    counts, diagnostics, _ = _read(out)
    for topic in ESTIMATES:
        assert counts.get("/" + topic, 0) > 50, f"{topic}: {counts.get('/' + topic, 0)} messages"
    assert diagnostics["fusion"]["speed source"].startswith("wheel speeds")
    assert diagnostics["vehicle_state"]["vx source"].startswith("wheel speeds")
    odometry, truth = [], []
    with AnyReader([out]) as reader:
        conns = [c for c in reader.connections if c.topic in ("/estimation/odometry", "/ground_truth/vehicle_state")]
        for conn, _, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
            (odometry if conn.topic == "/estimation/odometry" else truth).append((t, msg.twist.twist.linear.x))
    odometry, truth = np.array(odometry), np.array(truth)
    moving = odometry[:, 1] > 5.0
    error = odometry[moving, 1] - np.interp(odometry[moving, 0], truth[:, 0], truth[:, 1])
    assert moving.sum() > 100 and math.sqrt(float(np.mean(error ** 2))) < 0.2


@pytest.mark.dds
def test_an_imu_turned_about_z_is_named_in_diagnostics(bare, replayed, tmp_path):
    """An IMU facing left in a car whose vehicle file says it faces forward reads gravity as a
    level one does; the fusion's yaw check, on the car's accelerations from vehicle/speed,
    names it (WARN, with the IMU's yaw) while the well-mounted drive's check agrees."""
    from test_inspect import _copy, _turned_imu
    from vehicle_estimation.estimators.common.rotations import rotmat_from_euler

    _, diagnostics, _ = _read(replayed)
    assert diagnostics["fusion"]["IMU yaw check"].startswith("agrees with vehicle.imu_mounting_rpy")
    assert diagnostics["fusion"]["level"] != "1" or "IMU" not in diagnostics["fusion"]["message"]
    C = rotmat_from_euler(0.0, 0.0, math.pi / 2)
    turned = _copy(bare, tmp_path / "facing_left", lambda i, topic, typ, raw: (
        topic, _turned_imu(raw, C) if topics.relative(topic) == topics.IMU else raw))
    _, diagnostics, _ = _read(_replay(turned, tmp_path / "estimates", "--in-process"))
    fusion = diagnostics["fusion"]
    assert fusion["level"] == "1", fusion                   # WARN
    found = re.search(r"horizontal axes are (\d+) deg about base_link z .* its yaw is about (-?\d+) deg",
                      fusion["message"])
    assert found and abs(int(found.group(1)) - 90) <= 10 and abs(int(found.group(2)) - 90) <= 10, fusion["message"]
    assert fusion["IMU yaw check"] in fusion["message"]
