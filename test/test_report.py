"""Report on a tiny MCAP bag written with rosbags."""

import json
import math

import numpy as np
import pytest

pytest.importorskip("rosbags")
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from vehicle_estimation.evaluation import report  # noqa: E402
from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane  # noqa: E402
from vehicle_estimation.evaluation.consistency import format_consistency, truth_in_odom  # noqa: E402

TS = get_typestore(Stores.ROS2_JAZZY)
Float64 = TS.types["std_msgs/msg/Float64"]
Header = TS.types["std_msgs/msg/Header"]
Time = TS.types["builtin_interfaces/msg/Time"]
Vector3 = TS.types["geometry_msgs/msg/Vector3"]
Twist = TS.types["geometry_msgs/msg/Twist"]
TwistWithCovariance = TS.types["geometry_msgs/msg/TwistWithCovariance"]
TwistWithCovarianceStamped = TS.types["geometry_msgs/msg/TwistWithCovarianceStamped"]
Odometry = TS.types["nav_msgs/msg/Odometry"]
Pose = TS.types["geometry_msgs/msg/Pose"]
PoseWithCovariance = TS.types["geometry_msgs/msg/PoseWithCovariance"]
Point = TS.types["geometry_msgs/msg/Point"]
Quaternion = TS.types["geometry_msgs/msg/Quaternion"]

T0 = 1_000_000_000_000  # 1000 s, in ns
N = 100                 # 10 Hz, 10 s


def _header(ns):
    return Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id="base_link")


def _twist(ns, vx, vy, wz):
    return TwistWithCovarianceStamped(
        header=_header(ns),
        twist=TwistWithCovariance(twist=Twist(linear=Vector3(x=vx, y=vy, z=0.0),
                                              angular=Vector3(x=0.0, y=0.0, z=wz)),
                                  covariance=np.zeros(36)))


def _odom(ns, x, y, vx, vy):
    return Odometry(
        header=_header(ns), child_frame_id="base_link",
        pose=PoseWithCovariance(pose=Pose(position=Point(x=x, y=y, z=0.0),
                                          orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                                covariance=np.zeros(36)),
        twist=TwistWithCovariance(twist=Twist(linear=Vector3(x=vx, y=vy, z=0.0),
                                              angular=Vector3(x=0.0, y=0.0, z=0.0)),
                                  covariance=np.zeros(36)))


ORIGIN = (55.78, 12.52, 50.0)


def _fix(ns, lat, lon, alt):
    fix = TS.types["sensor_msgs/msg/NavSatFix"]
    status = TS.types["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
    return fix(header=_header(ns), status=status, latitude=float(lat), longitude=float(lon), altitude=float(alt),
               position_covariance=np.zeros(9), position_covariance_type=0)


@pytest.fixture()
def bag(tmp_path):
    path = tmp_path / "drive"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for topic, msgtype in [
            ("/estimation/mass", "std_msgs/msg/Float64"), ("/ground_truth/mass", "std_msgs/msg/Float64"),
            ("/estimation/road_slope", "std_msgs/msg/Float64"), ("/ground_truth/road_slope", "std_msgs/msg/Float64"),
            ("/estimation/sideslip", "std_msgs/msg/Float64"), ("/ground_truth/sideslip", "std_msgs/msg/Float64"),
            ("/estimation/vehicle_state", "geometry_msgs/msg/TwistWithCovarianceStamped"),
            ("/ground_truth/vehicle_state", "geometry_msgs/msg/TwistWithCovarianceStamped"),
            ("/estimation/odometry", "nav_msgs/msg/Odometry"), ("/ground_truth/odometry", "nav_msgs/msg/Odometry"),
            ("/estimation/datum", "sensor_msgs/msg/NavSatFix"), ("/ground_truth/datum", "sensor_msgs/msg/NavSatFix"),
        ]:
            conns[topic] = (writer.add_connection(topic, msgtype, typestore=TS), msgtype)

        def write(topic, ns, msg):
            conn, msgtype = conns[topic]
            writer.write(conn, ns, bytes(TS.serialize_cdr(msg, msgtype)))

        write("/ground_truth/mass", T0, Float64(data=1600.0))          # latched once
        # odom's origin (the first fix) lies 2 m north of the truth's: the truth is at y = -2 there
        north = LocalTangentPlane(*ORIGIN).to_geodetic(np.array([0.0, 2.0, 0.0]))
        write("/ground_truth/datum", T0, _fix(T0, *ORIGIN))
        write("/estimation/datum", T0, _fix(T0, *north))
        for k in range(N):
            ns = T0 + k * 100_000_000
            t = k * 0.1
            write("/estimation/mass", ns, Float64(data=1600.0 * (1.10 if k < 50 else 1.01)))
            write("/ground_truth/road_slope", ns, Float64(data=0.05))
            write("/estimation/road_slope", ns, Float64(data=0.05 + (0.01 if k % 2 else -0.01)))
            write("/ground_truth/sideslip", ns, Float64(data=0.02 * math.sin(0.8 * t)))
            write("/estimation/sideslip", ns, Float64(data=0.02 * math.sin(0.8 * (t - 0.3))))
            # header stamps differ from log times (log 50 ms later): the header is used
            write("/ground_truth/vehicle_state", ns + 50_000_000, _twist(ns, 10.0, 0.2, 0.1))
            write("/estimation/vehicle_state", ns + 50_000_000, _twist(ns, 10.5, 0.2, 0.1))
            write("/ground_truth/odometry", ns, _odom(ns, 10.0 * t, 0.0, 10.0, 0.0))
            write("/estimation/odometry", ns, _odom(ns, 10.0 * t, 1.0, 6.0, 8.0))
    return path


def test_report_numbers_and_figures(bag, tmp_path):
    out = tmp_path / "out"
    res = report.make_report(bag, out, warmup_s=0.0, print_table=False)
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk == res
    g = res["groups"]

    mass = g["mass"]
    assert mass["n"] == N
    assert mass["mape_percent"] == pytest.approx(5.5)            # half 10 %, half 1 %
    assert mass["mae"] == pytest.approx(88.0)
    assert mass["rmse"] == pytest.approx(math.sqrt((160.0 ** 2 + 16.0 ** 2) / 2))
    assert mass["last_half_max_abs_percent_error"] == pytest.approx(1.0)
    assert mass["share_within_3_percent"] == pytest.approx(0.5)
    assert mass["share_within_5_percent"] == pytest.approx(0.5)
    # cv window = 5 s / 0.1 s = 50 samples. Error < 2 % from k = 50; c_v of the window
    # ending at k holds j = 98 - k samples at 1.10 and 50 - j at 1.01:
    # c_v = 0.09 sqrt(p (1 - p)) / (1.01 + 0.09 p), p = j / 50: j = 3 -> 0.0210, j = 2 -> 0.0174
    # so the first converged sample is k = 97 and CR = 98 steps (9.7 s).
    assert mass["cv_window_samples"] == 50
    assert mass["convergence_rate_steps"] == 98
    assert mass["convergence_time_s"] == pytest.approx(9.7)

    slope = g["slope"]
    assert slope["mae"] == pytest.approx(0.01)
    assert slope["rmse"] == pytest.approx(0.01)
    assert slope["max_abs_error"] == pytest.approx(0.01)
    assert slope["mae_deg"] == pytest.approx(math.degrees(0.01))
    assert slope["lag_s"] is None                 # constant truth: lag not observable

    vs = g["vehicle_state"]
    assert vs["vx"]["mae"] == pytest.approx(0.5)
    assert vs["vx"]["n"] == N                       # header stamps align exactly
    assert vs["vy"]["rmse"] == pytest.approx(0.0)
    assert vs["yaw_rate"]["rmse"] == pytest.approx(0.0)
    assert vs["sideslip"]["n"] == N
    assert vs["sideslip"]["lag_s"] == pytest.approx(0.3, abs=0.02)

    fu = g["fusion"]
    assert fu["speed"]["rmse"] == pytest.approx(0.0)          # |(6, 8)| = 10
    assert fu["position"]["horizontal_rmse"] == pytest.approx(3.0)   # 1 m north of y = -2
    assert fu["position"]["frame"] == "ENU about estimation/datum"

    assert sorted(res["figures"]) == ["fusion.png", "mass.png", "slope.png", "vehicle_state.png"]
    for name in res["figures"]:
        assert (out / name).stat().st_size > 1000

    # deterministic: a second run gives the same JSON
    res2 = report.make_report(bag, tmp_path / "out2", warmup_s=0.0, print_table=False)
    assert res2 == res
    assert (tmp_path / "out2" / "report.json").read_text() == (out / "report.json").read_text()


def test_report_missing_topics_and_cli(tmp_path, capsys):
    path = tmp_path / "empty"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/ground_truth/mass", "std_msgs/msg/Float64", typestore=TS)
        writer.write(conn, T0, bytes(TS.serialize_cdr(Float64(data=1500.0), "std_msgs/msg/Float64")))
    out = tmp_path / "rep"
    assert report.main([str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "no data" in text
    res = json.loads((out / "report.json").read_text())
    assert all(v == {"status": "no data"} for v in res["groups"].values())
    assert res["figures"] == []
    assert report.main([str(tmp_path / "nope")]) == 2


def test_report_sqlite3_bag_with_namespace(tmp_path):
    path = tmp_path / "ns_bag"
    with Writer(path, version=8) as writer:            # default storage: sqlite3
        est = writer.add_connection("/car1/estimation/mass", "std_msgs/msg/Float64", typestore=TS)
        true = writer.add_connection("/car1/ground_truth/mass", "std_msgs/msg/Float64", typestore=TS)
        writer.write(true, T0, bytes(TS.serialize_cdr(Float64(data=2000.0), "std_msgs/msg/Float64")))
        for k in range(20):
            writer.write(est, T0 + k * 500_000_000,
                         bytes(TS.serialize_cdr(Float64(data=2100.0), "std_msgs/msg/Float64")))
    res = report.make_report(path, tmp_path / "o", warmup_s=0.0, print_table=False)
    assert res["groups"]["mass"]["mape_percent"] == pytest.approx(5.0)
    assert res["groups"]["mass"]["convergence_rate_steps"] is None
    assert res["groups"]["slope"] == {"status": "no data"}
    assert res["figures"] == ["mass.png"]


def test_consistency_group_checks_each_published_variance():
    t = np.arange(0.0, 40.0, 0.1)
    truth = {"t": t, "value": np.full(t.size, 0.05)}
    # slope error +-0.009 with sigma 0.01, flagged converged after 20 s
    slope = {"t": t, "value": 0.05 + np.where(np.arange(t.size) % 2, 0.009, -0.009),
             "variance": np.full(t.size, 1e-4), "converged": (t >= 20.0).astype(float)}
    state = {"t": t, "vx": np.full(t.size, 10.5), "vy": np.zeros(t.size), "yaw_rate": np.zeros(t.size),
             "var_vx": np.full(t.size, 0.0625), "var_vy": np.full(t.size, 1.0), "var_yaw_rate": np.zeros(t.size)}
    gt_state = {"t": t, "vx": np.full(t.size, 10.0), "vy": np.zeros(t.size), "yaw_rate": np.zeros(t.size)}
    # the fusion's odometry: vx 0.1 m/s off at sigma 0.1, pitch exact at sigma 0.01 rad, roll
    # 0.03 rad off at sigma 0.01 rad, yaw rate 0.002 rad/s off at sigma 0.001 rad/s
    path = {"x": 10.0 * t, "y": np.zeros(t.size), "pitch": np.full(t.size, -0.05)}
    odom = {"t": t, "vx": np.full(t.size, 10.1), "speed": np.full(t.size, 10.1), **path,
            "roll": np.full(t.size, 0.03), "var_vx": np.full(t.size, 0.01), "var_pitch": np.full(t.size, 1e-4),
            "var_roll": np.full(t.size, 1e-4), "yaw_rate": np.full(t.size, 0.002),
            "var_yaw_rate": np.full(t.size, 1e-6)}
    gt_odom = {"t": t, "vx": np.full(t.size, 10.0), "speed": np.full(t.size, 10.0), "roll": np.zeros(t.size),
               "yaw_rate": np.zeros(t.size), **path}
    data = {"estimation/road_slope": slope, "ground_truth/road_slope": truth,
            "estimation/vehicle_state": state, "ground_truth/vehicle_state": gt_state,
            "estimation/odometry": odom, "ground_truth/odometry": gt_odom}
    groups, series = report.compute_groups(data, warmup_s=5.0)
    c = groups["consistency"]
    # yaw rate: no variance published, nothing to check
    assert c["status"] == "ok" and set(series["consistency"]) == {"slope", "vx", "vy", "fusion_vx", "fusion_pitch",
                                                                 "fusion_roll", "fusion_yaw_rate"}
    assert c["fusion_yaw_rate"]["nees"] == pytest.approx(4.0)
    assert c["fusion_vx"]["nees"] == pytest.approx(1.0) and c["fusion_pitch"]["nees"] == pytest.approx(0.0)
    assert c["fusion_roll"]["nees"] == pytest.approx(9.0) and c["fusion_roll"]["within_2sigma"] == 0.0
    assert c["slope"]["n"] == t.size - 50                          # after the warm-up
    assert c["slope"]["within_1sigma"] == pytest.approx(1.0)
    assert c["slope"]["nees"] == pytest.approx(0.81)
    assert c["slope"]["converged_share"] == pytest.approx(200 / 350)
    assert c["vx"]["nees"] == pytest.approx(4.0)                   # 0.5 m/s error, sigma 0.25
    assert c["vx"]["within_1sigma"] == pytest.approx(0.0)
    text = "\n".join(format_consistency({k: v for k, v in c.items() if isinstance(v, dict)}))
    assert "slope" in text and "NEES" in text


@pytest.mark.parametrize("yaw_deg", [0.0, 90.0, 30.0])
def test_the_tilt_variances_are_about_the_heading_and_its_left(yaw_deg):
    """The odometry's rotation covariance is about the fixed ENU axes: a car heading north
    pitches about ENU x, not y, and rolls about ENU y."""
    from vehicle_estimation.evaluation.report import _extract

    yaw = math.radians(yaw_deg)
    cov = np.zeros(36)
    cov[21], cov[28], cov[35] = 1e-4, 9e-4, 4e-4            # about ENU x, y, z
    msg = _odom(0, 0.0, 0.0, 10.0, 0.0)
    msg.pose.pose.orientation = Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    msg.pose.covariance = cov
    values = _extract("nav_msgs/msg/Odometry", msg)
    assert values["var_pitch"] == pytest.approx(math.sin(yaw) ** 2 * 1e-4 + math.cos(yaw) ** 2 * 9e-4)
    assert values["var_roll"] == pytest.approx(math.cos(yaw) ** 2 * 1e-4 + math.sin(yaw) ** 2 * 9e-4)


def test_without_a_datum_the_truth_is_put_where_the_estimate_started():
    """No estimation/datum (no GNSS): odom is the pose at alignment with a free heading, so the
    truth is turned and moved onto the first estimate; with both datums it is moved by the
    difference of the origins only, from the datum's stamp on."""
    t = np.arange(0.0, 10.0, 0.1)
    # the car drives east at 10 m/s from (100, 50); odom's free frame has it driving along +y
    truth = {"t": t, "x": 100.0 + 10.0 * t, "y": np.full(t.size, 50.0), "yaw": np.zeros(t.size)}
    est = {"t": t, "x": np.zeros(t.size), "y": 10.0 * t, "yaw": np.full(t.size, math.pi / 2)}
    aligned = truth_in_odom({"estimation/odometry": est, "ground_truth/odometry": truth})
    assert aligned["frame"].startswith("free")
    np.testing.assert_allclose(aligned["x"], 0.0, atol=1e-9)
    np.testing.assert_allclose(aligned["y"], 10.0 * t, atol=1e-9)
    np.testing.assert_allclose(aligned["yaw"], math.pi / 2)

    north = LocalTangentPlane(*ORIGIN).to_geodetic(np.array([3.0, -4.0, 0.0]))
    datums = {"estimation/datum": {"t": np.array([2.0]), "lat": np.array([north[0]]), "lon": np.array([north[1]]),
                                   "alt": np.array([north[2]])},
              "ground_truth/datum": {"t": np.array([0.0]), **{k: np.array([v]) for k, v in
                                                              zip(("lat", "lon", "alt"), ORIGIN)}}}
    aligned = truth_in_odom({"estimation/odometry": est, "ground_truth/odometry": truth, **datums})
    assert aligned["t"][0] == pytest.approx(2.0)                # the frame is ENU from the datum on
    np.testing.assert_allclose(aligned["x"], 97.0 + 10.0 * aligned["t"], atol=1e-6)
    np.testing.assert_allclose(aligned["y"], 54.0, atol=1e-6)
    np.testing.assert_allclose(aligned["yaw"], 0.0)


def test_the_position_heading_and_biases_are_checked_against_their_own_sigma():
    from vehicle_estimation.evaluation.consistency import consistency_group

    t = np.arange(0.0, 20.0, 0.1)
    n = t.size
    truth = {"t": t, "x": 10.0 * t, "y": np.zeros(n), "yaw": np.full(n, 0.1)}
    # x 0.5 m off at sigma 0.5 (NEES 1), y exact: pooled NEES 0.5; heading 0.02 rad off at sigma 0.01
    est = {"t": t, "x": 10.0 * t + 0.5, "y": np.zeros(n), "yaw": np.full(n, 0.12), "var_x": np.full(n, 0.25),
           "var_y": np.full(n, 0.25), "var_yaw": np.full(n, 1e-4)}
    bias_truth = {"t": t, **{f"a{a}": np.full(n, 0.05) for a in "xyz"}, **{f"g{a}": np.full(n, 0.002) for a in "xyz"}}
    bias = {"t": t, **{f"a{a}": np.full(n, 0.05) for a in "xy"}, "az": np.full(n, 0.08),
            **{f"g{a}": np.full(n, 0.002) for a in "xyz"},
            **{f"var_a{a}": np.full(n, 1e-4) for a in "xyz"}, **{f"var_g{a}": np.full(n, 1e-8) for a in "xyz"}}
    datum = {"t": np.array([0.0]), **{k: np.array([v]) for k, v in zip(("lat", "lon", "alt"), ORIGIN)}}
    checked, series = consistency_group({"estimation/odometry": est, "ground_truth/odometry": truth,
                                         "estimation/datum": datum, "ground_truth/datum": datum,
                                         "estimation/imu_bias": bias, "ground_truth/imu_bias": bias_truth}, 5.0)
    assert set(checked) == {"fusion_xy", "fusion_yaw", "accel_bias", "gyro_bias"}
    assert checked["fusion_xy"]["nees"] == pytest.approx(0.5) and checked["fusion_xy"]["n"] == 2 * (n - 50)
    assert checked["fusion_yaw"]["nees"] == pytest.approx(4.0)
    assert checked["accel_bias"]["nees"] == pytest.approx(3.0)        # z: 0.03 off at sigma 0.01
    assert checked["accel_bias"]["within_2sigma"] == pytest.approx(2 / 3)
    assert checked["gyro_bias"]["nees"] == pytest.approx(0.0)
    assert series["accel_bias"]["error"].shape == (n - 50, 3)
