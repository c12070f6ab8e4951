"""Tests of the vehicle + sensor simulator (vehicle_estimation.sim)."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.contract import topics as T
from vehicle_estimation.sim import (SCENARIOS, RoadSpec, Scenario, SensorConfig, SpeedProfile,
                                    default_scenario, load_cycle, load_vehicle, params_path,
                                    scenario_by_name, simulate, write_bag)

SEDAN = dataclasses.replace(load_vehicle("sedan_d_class"), pitch_gain=0.0)  # a rigid body: IMU pitch = road
CLEAN = SensorConfig(accel_bias=(0.0, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.0), accel_bias_rw=0.0,
                     gyro_bias_rw=0.0, imu_misalignment_deg=(0.0, 0.0, 0.0))
FLAT_STRAIGHT = RoadSpec(kind="straight", grade_max=0.0)


def _scn(**kw):
    base = Scenario(name="test", vehicle=SEDAN, duration_s=20.0, road=FLAT_STRAIGHT, sensors=CLEAN, seed=3)
    return dataclasses.replace(base, **kw)


@pytest.fixture(scope="module")
def short_result():
    return simulate(scenario_by_name("short"))


def test_params_and_scenarios():
    assert params_path("sedan_d_class").is_file()
    assert params_path("heavy_truck.yaml").is_file()
    for name in ("default", "short", "paper004_loop", "truck_hwfet"):
        assert name in SCENARIOS
        scn = scenario_by_name(name)
        assert dataclasses.replace(scn, seed=9).seed == 9
    d = default_scenario()
    assert d.vehicle.name == "sedan_d_class" and d.duration_s >= 600 and d.standstill_s >= 10
    assert d.wind_enu == (0.0, 0.0, 0.0) and d.vehicle.mass == SEDAN.mass
    with pytest.raises(ValueError):
        scenario_by_name("nope")


def test_cycles_are_the_official_traces():
    # durations and distances of the EPA / UNECE schedules
    for name, n, km in (("hwfet", 766, 16.51), ("udds", 1370, 11.99), ("us06", 601, 12.89), ("wltc3", 1801, 23.27)):
        v = load_cycle(name)
        assert v.size == n
        assert abs(v.sum() / 1000 - km) < 0.02, name
    assert abs(load_cycle("wltc3").max() * 3.6 - 131.3) < 0.05


def test_determinism(short_result):
    again = simulate(scenario_by_name("short"))
    for key, val in short_result.truth.items():
        np.testing.assert_array_equal(val, again.truth[key], err_msg=key)
    for topic, arrays in short_result.sensors.items():
        for key, val in arrays.items():
            np.testing.assert_array_equal(val, again.sensors[topic][key], err_msg=f"{topic}.{key}")
    other = simulate(dataclasses.replace(scenario_by_name("short"), seed=99))
    assert not np.array_equal(other.sensors["imu"]["accel"], short_result.sensors["imu"]["accel"])


def test_steady_speed_flat_drive_force_balances_resistance():
    v = 20.0
    res = simulate(_scn(speed_profile=SpeedProfile(kind="constant", speed_mps=v), initial_speed=v))
    tr = res.truth
    sel = tr["t"] > 10.0
    assert np.all(np.abs(tr["vx"][sel] - v) < 0.05)
    expected = 0.5 * SEDAN.air_density * SEDAN.drag_area * v ** 2 + SEDAN.rolling_resistance * SEDAN.mass * SEDAN.gravity
    assert abs(np.mean(tr["drive_force"][sel]) - expected) / expected < 0.03
    assert np.max(np.abs(tr["sideslip"][sel])) < 1e-3        # straight driving
    assert np.max(np.abs(tr["yaw_rate"][sel])) < 1e-3
    assert np.all(tr["brake_torque"][sel] == 0.0)


def test_coast_down_decelerates():
    v0 = 25.0
    res = simulate(_scn(speed_profile=SpeedProfile(kind="coast", speed_mps=v0, coast_after_s=1.0),
                        initial_speed=v0, duration_s=30.0))
    tr = res.truth
    vx = tr["vx"][tr["t"] > 1.5]
    assert np.all(np.diff(vx) <= 1e-9) and vx[-1] < v0 - 5.0
    k = np.searchsorted(tr["t"], 2.0)
    v = tr["vx"][k]
    meff = SEDAN.mass + SEDAN.wheel_inertia / SEDAN.wheel_radius ** 2
    expected = -(0.5 * SEDAN.air_density * SEDAN.drag_area * v ** 2 + SEDAN.rolling_resistance * SEDAN.mass * SEDAN.gravity) / meff
    assert abs(tr["vx_dot"][k] - expected) / abs(expected) < 0.05
    assert np.all(tr["drive_force"][tr["t"] > 1.5] == 0.0)


def test_at_rest_imu_reads_gravity_and_car_holds():
    res = simulate(_scn(duration_s=8.0, speed_profile=SpeedProfile(kind="constant", speed_mps=0.0)))
    imu = res.sensors["imu"]
    g = SEDAN.gravity
    assert abs(np.mean(imu["accel"][:, 2]) - g) < 0.01
    assert abs(np.mean(imu["accel"][:, 0])) < 0.01 and abs(np.mean(imu["accel"][:, 1])) < 0.01
    assert np.all(res.truth["vx"] == 0.0)
    assert np.all(res.truth["engine_speed"] == SEDAN.engine_idle_speed)


def test_grade_at_rest_imu_x_reads_g_sin_alpha():
    grade = 0.05
    res = simulate(_scn(duration_s=6.0, speed_profile=SpeedProfile(kind="constant", speed_mps=0.0),
                        road=RoadSpec(kind="straight", grade_max=0.0, constant_grade=grade)))
    alpha = math.atan(grade)
    imu = res.sensors["imu"]
    g = SEDAN.gravity
    assert abs(np.mean(imu["accel"][:, 0]) - g * math.sin(alpha)) < 0.01   # uphill nose-up: +x
    assert abs(np.mean(imu["accel"][:, 2]) - g * math.cos(alpha)) < 0.01
    assert np.allclose(res.truth["slope"], alpha)
    assert np.allclose(res.truth["pitch"], -alpha)                            # REP-103: nose up = negative
    assert np.all(res.truth["vx"] == 0.0)                                     # no rolling back


def test_circle_yaw_rate_is_v_over_r():
    v, radius = 10.0, 100.0
    res = simulate(_scn(duration_s=25.0, speed_profile=SpeedProfile(kind="constant", speed_mps=v), initial_speed=v,
                        road=RoadSpec(kind="circle", radius=radius)))
    tr = res.truth
    sel = tr["t"] > 15.0
    assert abs(np.mean(tr["yaw_rate"][sel]) - v / radius) / (v / radius) < 0.03
    assert abs(np.mean(tr["ay"][sel]) - v ** 2 / radius) / (v ** 2 / radius) < 0.05
    assert np.max(np.abs(tr["lateral_error"][sel])) < 0.5
    # left turn: outer (right) wheels spin faster
    ws = tr["wheel_speed"][sel]
    assert np.all(ws[:, 1] > ws[:, 0]) and np.all(ws[:, 3] > ws[:, 2])


def test_obd_speed_quantised(short_result):
    sp = short_result.sensors["speed"]
    kmh = sp["v"] * 3.6
    np.testing.assert_allclose(kmh, np.round(kmh), atol=1e-9)
    assert sp["v"].max() > 15.0
    assert abs(sp["var"] - (1 / 3.6) ** 2 / 12) < 1e-9
    # truth ends at standstill, and the drive moved the car on a curvy, hilly road
    tr = short_result.truth
    assert tr["vx"][-1] == 0.0 and np.ptp(tr["z"]) > 1.0 and np.max(np.abs(tr["yaw_rate"])) > 0.05


def test_noise_schedule_outliers_and_gnss_outage():
    cfg = dataclasses.replace(CLEAN, eq34_noise=True, outliers=True, gnss_outages=((5.0, 8.0),))
    res = simulate(_scn(duration_s=200.0, sensors=cfg, speed_profile=SpeedProfile(kind="constant", speed_mps=0.0)))
    imu = res.sensors["imu"]
    t = imu["t"]
    clean = imu["outlier_mask"] == 0
    std = [np.std(imu["accel"][(t >= a) & (t < a + 40) & clean, 0]) for a in (0, 40, 80, 120)]
    ratios = np.array(std) / std[1]
    np.testing.assert_allclose(ratios, [3, 1, 2, 0.5], rtol=0.1)
    assert (imu["outlier_mask"] & 1).any() and (imu["outlier_mask"] & 2).any()
    gn = res.sensors["gnss"]
    inside = (gn["t"] >= 5.0) & (gn["t"] < 8.0)
    assert np.all(gn["status"][inside] == -1) and np.all(np.isnan(gn["lat"][inside]))
    assert np.all(gn["status"][~inside] == 0)


def test_gnss_positions_match_truth():
    res = simulate(_scn(duration_s=20.0, speed_profile=SpeedProfile(kind="constant", speed_mps=15.0), initial_speed=15.0,
                        sensors=dataclasses.replace(CLEAN, gnss_noise=(0.0, 0.0, 0.0))))
    from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
    gn, scn = res.sensors["gnss"], res.scenario
    enu = LocalTangentPlane(scn.origin_lat, scn.origin_lon, scn.origin_alt).to_enu(gn["lat"], gn["lon"], gn["alt"])
    np.testing.assert_allclose(enu, gn["enu_true"], atol=1e-3)
    e = enu[:, 0]
    assert abs(e[-1] - 15.0 * 20.0) < 0.5


def test_bag_round_trip(tmp_path, short_result):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    from vehicle_estimation.sim.bag import T0_NS

    res = simulate(dataclasses.replace(scenario_by_name("short"), duration_s=14.0))
    path = write_bag(res, tmp_path / "bag")
    with pytest.raises(FileExistsError):
        write_bag(res, path)
    expected = {
        T.IMU: "sensor_msgs/msg/Imu", T.GNSS: "sensor_msgs/msg/NavSatFix",
        T.SPEED: "geometry_msgs/msg/TwistWithCovarianceStamped", T.JOINT_STATES: "sensor_msgs/msg/JointState",
        T.POWERTRAIN: "sensor_msgs/msg/JointState", T.GT_MASS: "std_msgs/msg/Float64",
        T.GT_ROAD_SLOPE: "std_msgs/msg/Float64", T.GT_SIDESLIP: "std_msgs/msg/Float64",
        T.GT_VEHICLE_STATE: "geometry_msgs/msg/TwistWithCovarianceStamped", T.GT_ODOMETRY: "nav_msgs/msg/Odometry",
        T.GT_DATUM: "sensor_msgs/msg/NavSatFix", T.GT_IMU_BIAS: "sensor_msgs/msg/Imu",
    }
    ts = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([Path(path)], default_typestore=ts) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == expected
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts[T.IMU] == 14 * 200 + 1 and counts[T.GNSS] == 14 * 10 + 1 and counts[T.GT_MASS] == 1401
        last = -1
        first = {}
        for conn, stamp, raw in reader.messages():
            assert stamp >= last
            last = stamp
            msg = reader.deserialize(raw, conn.msgtype)
            if hasattr(msg, "header"):
                assert msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec == stamp
            if conn.msgtype == "sensor_msgs/msg/JointState":
                assert len(msg.name) == len(msg.position) == len(msg.velocity) == len(msg.effort)
            first.setdefault(conn.topic, (stamp, msg))
    assert min(s for s, _ in first.values()) == T0_NS
    imu = first[T.IMU][1]
    assert imu.header.frame_id == T.IMU_FRAME and imu.orientation_covariance[0] == -1.0
    assert abs(imu.linear_acceleration.z - SEDAN.gravity) < 0.5
    js = first[T.JOINT_STATES][1]
    assert list(js.name) == list(T.WHEEL_JOINTS) + [T.STEERING_JOINT] and math.isnan(js.velocity[4])
    pt = first[T.POWERTRAIN][1]
    assert list(pt.name) == [T.ENGINE_JOINT, T.ENGINE_LOAD_JOINT, T.GEAR_JOINT, T.DRIVE_JOINT]
    assert pt.position[2] == 1.0 and abs(pt.velocity[0] - SEDAN.engine_idle_speed) < 1e-9
    assert 0.0 <= pt.position[1] <= 1.0 and math.isnan(pt.position[0])
    gn = first[T.GNSS][1]
    assert gn.status.status == 0 and gn.status.service == 1 and gn.position_covariance_type == 2
    assert abs(gn.latitude - 55.78) < 1e-3 and gn.header.frame_id == T.GNSS_FRAME
    od = first[T.GT_ODOMETRY][1]
    assert od.header.frame_id == T.ODOM_FRAME and od.child_frame_id == T.BASE_FRAME
    assert first[T.GT_MASS][1].data == SEDAN.mass
    # the truth's frame in WGS84 and the IMU's own biases, for the report's consistency checks
    datum = first[T.GT_DATUM][1]
    assert (datum.latitude, datum.longitude, datum.altitude) == (res.scenario.origin_lat, res.scenario.origin_lon,
                                                                 res.scenario.origin_alt)
    bias = first[T.GT_IMU_BIAS][1]
    np.testing.assert_allclose([bias.linear_acceleration.x, bias.angular_velocity.z],
                               [res.sensors["imu"]["accel_bias"][0, 0], res.sensors["imu"]["gyro_bias"][0, 2]])
    assert counts[T.GT_IMU_BIAS] == 14 * 10 + 1 and counts[T.GT_DATUM] == 1


def test_vectorised_serialisation_matches_rosbags(short_result):
    from vehicle_estimation.sim.bag import build_streams, typestore
    ts = typestore()
    for topic, msgtype, stamps, mat in build_streams(short_result):
        for i in (0, stamps.size // 2, stamps.size - 1):
            msg = ts.deserialize_cdr(mat[i].tobytes(), msgtype)
            assert bytes(ts.serialize_cdr(msg, msgtype)) == mat[i].tobytes(), topic


def test_cli(tmp_path):
    from vehicle_estimation.sim.cli import main
    out = tmp_path / "cli_bag"
    assert main(["--scenario", "short", "--out", str(out), "--duration", "5", "--seed", "3", "--mass", "1700"]) == 0
    assert (out / "metadata.yaml").is_file()
    assert main(["--scenario", "short", "--out", str(out)]) == 2


def test_bag_paths_that_could_not_be_read_back_are_refused(tmp_path, short_result):
    """A rosbag2 directory named '*.bag' would be read as a ROS 1 bag file: refused up front,
    as is an existing path; the CLI says why with exit code 2."""
    with pytest.raises(ValueError, match="must not end in '.bag'"):
        write_bag(short_result, tmp_path / "drive.bag")
    assert not (tmp_path / "drive.bag").exists()
    (tmp_path / "taken").mkdir()
    with pytest.raises(FileExistsError):
        write_bag(short_result, tmp_path / "taken")
    from vehicle_estimation.sim.cli import main
    assert main(["--scenario", "short", "--duration", "2", "--out", str(tmp_path / "x.bag")]) == 2
