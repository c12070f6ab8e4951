"""rclpy tests of each node: real publishers and subscriptions, synthetic inputs, checked outputs."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rosharness import Harness, init_rclpy, sec_to_time, vehicle_overrides
from sensor_msgs.msg import Imu, JointState, NavSatFix
from std_msgs.msg import Float64

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
from vehicle_estimation.paths import params_file
from vehicle_estimation.ros import conversions
from vehicle_estimation.ros.fusion_node import FusionNode
from vehicle_estimation.ros.mass_node import MassNode
from vehicle_estimation.ros.runtime.upstream import companion
from vehicle_estimation.ros.slope_node import SlopeNode
from vehicle_estimation.ros.state_node import StateNode
from vehicle_estimation.ros.stamps import stamp_ns

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

G = 9.80665
T0 = 1_700_000_000.0


@pytest.fixture(autouse=True)
def ros():
    init_rclpy()
    yield
    rclpy.try_shutdown()


def imu_msg(t: float, f, w) -> Imu:
    m = Imu()
    sec_to_time(t, m.header.stamp)
    m.header.frame_id = "imu_link"
    m.orientation_covariance[0] = -1.0
    m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = map(float, f)
    m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = map(float, w)
    return m


def speed_msg(t: float, v: float) -> TwistWithCovarianceStamped:
    m = TwistWithCovarianceStamped()
    sec_to_time(t, m.header.stamp)
    m.header.frame_id = "base_link"
    m.twist.twist.linear.x = float(v)
    m.twist.covariance[0] = 0.01
    return m


def fix_msg(t: float, lat: float, lon: float, alt: float, status: int = 0) -> NavSatFix:
    m = NavSatFix()
    sec_to_time(t, m.header.stamp)
    m.header.frame_id = "gnss_link"
    m.status.status = status
    m.latitude, m.longitude, m.altitude = lat, lon, alt
    m.position_covariance = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 4.0]
    m.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    return m


def straight_drive(duration: float = 30.0, still: float = 3.0, accel: float = 1.0, vmax: float = 15.0):
    """Stand still, then accelerate east on a flat road: (t, v, x, a) at 200 Hz."""
    t = np.arange(0.0, duration, 0.005)
    a = np.where((t >= still), accel, 0.0)
    v = np.minimum(np.cumsum(a) * 0.005, vmax)
    a = np.where(np.diff(v, prepend=0.0) > 0, a, 0.0)
    x = np.cumsum(v) * 0.005
    return t, v, x, a


def test_fusion_node_tracks_a_straight_drive():
    node = FusionNode(parameter_overrides=[])
    h = Harness(node)
    try:
        probe = h.probe
        for msg_type, topic in ((Imu, topics.IMU), (NavSatFix, topics.GNSS),
                                (TwistWithCovarianceStamped, topics.SPEED)):
            probe.publisher_for(msg_type, topic)
        odom = probe.watch(Odometry, topics.ODOMETRY)
        comp = probe.watch(Imu, topics.IMU_COMPENSATED)
        h.connect([topics.IMU, topics.GNSS, topics.SPEED])
        ltp = LocalTangentPlane(55.78, 12.52, 50.0)
        rng = np.random.default_rng(1)
        t, v, x, a = straight_drive()
        stream = []
        gyro_bias = np.array([0.002, -0.001, 0.003])
        for i, ti in enumerate(t):
            f = np.array([a[i], 0.0, G]) + rng.normal(0, 0.02, 3)
            stream.append((topics.IMU, imu_msg(T0 + ti, f, gyro_bias + rng.normal(0, 1e-3, 3))))
            if i % 2 == 0:
                stream.append((topics.SPEED, speed_msg(T0 + ti, round(v[i] * 3.6) / 3.6)))
            if i % 20 == 0:
                lat, lon, alt = ltp.to_geodetic(np.array([x[i], 0.0, 0.0]) + rng.normal(0, [1, 1, 2]))
                # one fix without a position solution: must be ignored and counted
                status = -1 if i == 2000 else 0
                stream.append((topics.GNSS, fix_msg(T0 + ti, lat, lon, alt, status)))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(odom) > 0 and len(comp) > 0)
        assert node.health.rejected["gnss:no_fix"] == 1
        last = odom[-1]
        t_last = last.header.stamp.sec + 1e-9 * last.header.stamp.nanosec - T0
        v_true = np.interp(t_last, t, v)
        assert abs(last.twist.twist.linear.x - v_true) < 0.3
        assert abs(last.pose.pose.position.x - np.interp(t_last, t, x)) < 5.0
        assert all(math.isfinite(m.linear_acceleration.x) for m in comp)
        # gyro bias learnt at standstill is removed from the compensated IMU
        assert abs(np.mean([m.angular_velocity.z for m in comp[-200:]])) < 1e-3
    finally:
        h.close()


def test_imu_bias_message_carries_the_mounting():
    """estimation/imu_bias: bias in imu_link, orientation = imu_link -> base_link; the
    consumers' correction removes the bias and rotates into base_link."""
    from vehicle_estimation.estimators.common.rotations import (
        quat_from_euler,
        quat_to_rotmat,
    )
    from vehicle_estimation.ros.runtime.upstream import FusionImuBias

    q = quat_from_euler(0.01, -0.02, 0.005)
    msg = Imu()
    sec_to_time(T0, msg.header.stamp)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (float(v) for v in q)
    msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = 0.1, -0.05, 0.02
    msg.angular_velocity.z = 0.003
    msg.linear_acceleration_covariance[0] = 0.05 ** 2
    bias = FusionImuBias()
    entry = FusionImuBias.convert(msg)
    bias.history.add(*entry)
    f_base = np.array([1.0, 0.2, 9.8])
    C = quat_to_rotmat(q)
    f_raw = C.T @ f_base + np.array([0.1, -0.05, 0.02])
    f, w = bias.correct(T0, f_raw, C.T @ np.array([0.0, 0.0, 0.2]) + np.array([0.0, 0.0, 0.003]))
    assert bias.valid
    # the slope observer's along-track bias variance, the IMU's covariance turned into base_link
    assert bias.accel_x_variance_at(T0) == pytest.approx(C[0, 0] ** 2 * 0.05 ** 2, rel=1e-12)
    np.testing.assert_allclose(f, f_base, atol=1e-12)
    np.testing.assert_allclose(w, [0.0, 0.0, 0.2], atol=1e-12)
    # an IMU facing left: its y bias is the car's along-track one
    msg.orientation.z = msg.orientation.w = math.sqrt(0.5)
    msg.orientation.x = msg.orientation.y = 0.0
    msg.linear_acceleration_covariance[4] = 0.02 ** 2
    _, (_, _, _, along_track) = FusionImuBias.convert(msg)
    assert along_track == pytest.approx(0.02 ** 2, rel=1e-12)
    # a publisher that leaves the orientation at zero means "no mounting": identity
    msg.orientation.w = msg.orientation.x = msg.orientation.y = msg.orientation.z = 0.0
    _, (_, _, mount, _) = FusionImuBias.convert(msg)
    np.testing.assert_array_equal(mount, np.eye(3))


def test_the_speeds_scale_is_applied_beyond_what_a_quantised_speed_explains():
    """``estimation/speed_scale`` as the state and mass nodes apply it: 1 without a fresh one,
    1 within 2 sigma of 1 (a quantised speed's lasting offset looks like a scale), beyond that
    shrunk by its variance (positive-part James-Stein), so that it never jumps in."""
    from vehicle_estimation.ros.runtime.upstream import StampedValue, UpstreamHistory, speed_scale_at

    history = UpstreamHistory()
    assert speed_scale_at(history, 10.0) == 1.0
    sigma = 0.0041
    applied = []
    for i, k in enumerate((0.003, 0.008, 0.0083, 0.012, 0.03)):
        history.add(float(i), StampedValue(float(i), 1.0 + k, sigma ** 2, True))
        applied.append(speed_scale_at(history, float(i)) - 1.0)
    assert applied[:2] == [0.0, 0.0]
    assert 0.0 < applied[2] < 0.001                    # just beyond 2 sigma: a little
    assert applied[3] == pytest.approx(0.012 * (1.0 - 4.0 * sigma ** 2 / 0.012 ** 2))
    assert 0.027 < applied[4] < 0.03                   # 3 %: 2.8 % of it
    assert speed_scale_at(history, 4.0 + 60.0) == 1.0  # stale


def test_the_speeds_scale_left_unapplied_is_its_error_variance():
    """What a consumer adds to its speed's variance: the scale's variance plus the square of
    the part it did not apply, so that within 2 sigma of 1 (nothing applied) a real 1 % is
    still covered, and a scale applied in full leaves only its variance. Nothing without a
    fresh estimate."""
    from vehicle_estimation.ros.runtime.upstream import (
        StampedValue, UpstreamHistory, speed_scale_at, speed_scale_error_variance)

    history = UpstreamHistory()
    assert speed_scale_error_variance(history, 10.0) == 0.0
    sigma = 0.0041
    for i, k in enumerate((0.0, 0.008, 0.03)):
        history.add(float(i), StampedValue(float(i), 1.0 + k, sigma ** 2, True))
        left = k - (speed_scale_at(history, float(i)) - 1.0)
        assert speed_scale_error_variance(history, float(i)) == pytest.approx(sigma ** 2 + left ** 2)
    assert speed_scale_error_variance(history, 1.0) == pytest.approx(sigma ** 2 + 0.008 ** 2)
    assert speed_scale_error_variance(history, 2.0) < 2.0 * sigma ** 2
    # held at its prior without GNSS: a 3 % tyre error lies within 2 sigma of the speed
    history.add(3.0, StampedValue(3.0, 1.0, 0.02 ** 2, False))
    assert 0.03 < 2.0 * math.sqrt(speed_scale_error_variance(history, 3.0))
    assert speed_scale_error_variance(history, 3.0 + 60.0) == 0.0


def test_a_speed_carrying_its_held_scale_is_still_a_measured_speed():
    """Without GNSS a wheel-aided vx carries the held scale's 2 % (0.7 m/s at 122 km/h): the
    slope and mass nodes must still take it as a speed (at a flat 0.5 m/s they rejected 8243
    of the demo's state messages and 7918 odometry ones), and still refuse a dead-reckoned vx,
    whose uncertainty grows without bound (a flat 2.5 % allowance let one through: the Stanford
    drive's sideslip RMSE 0.340 -> 0.425 deg)."""
    from vehicle_estimation.ros.conversions import MAX_MEASURED_SPEED_STD, measured_speed

    held = 0.0204 ** 2                     # the fusion's prior with its floor, without GNSS
    assert measured_speed(34.0, 0.05 ** 2 + held * 34.0 ** 2, held)
    assert not measured_speed(34.0, 0.05 ** 2 + held * 34.0 ** 2)     # not without the scale
    assert measured_speed(5.0, 0.3 ** 2, held)
    # a dead-reckoned vx carries the scale's term too (the state node adds it to every vx), so
    # its own growing uncertainty is what is judged, at town speed and on the motorway
    assert not measured_speed(5.0, 0.6 ** 2 + held * 5.0 ** 2, held)
    assert not measured_speed(30.0, 0.6 ** 2 + held * 30.0 ** 2, held)
    assert measured_speed(30.0, math.nan) and measured_speed(30.0, 0.0)   # unknown: taken as measured
    assert not measured_speed(1.0, (MAX_MEASURED_SPEED_STD * 1.01) ** 2)


@pytest.mark.parametrize("estimated", [False, True])
def test_the_fusion_always_advertises_the_speeds_scale(estimated):
    """The state and mass nodes subscribe to ``estimation/speed_scale`` whatever the fusion's
    settings, and a replay's start-up waits until every subscription has its publisher: with
    ``fusion.estimate_speed_scale`` off the fusion still advertises the topic (it hung a DDS
    replay at start-up once), and publishes on it only where the scale is estimated."""
    node = FusionNode(parameter_overrides=[Parameter("fusion.estimate_speed_scale", value=estimated)])
    try:
        advertised = {name for name, _ in node.get_publisher_names_and_types_by_node(node.get_name(),
                                                                                    node.get_namespace())}
        assert "/" + topics.SPEED_SCALE in advertised, sorted(advertised)
        assert node.ekf.config.estimate_speed_scale is estimated
    finally:
        node.destroy_node()


def test_before_the_fusion_speaks_the_imu_is_turned_by_the_vehicles_mounting():
    """Until the fusion publishes its bias and refined mounting (or without a fusion node), a
    node still turns imu/data into base_link by ``vehicle.imu_mounting_rpy``: an IMU facing
    left reads the car's forward specific force on its -y axis."""
    mounting = Parameter("vehicle.imu_mounting_rpy", value=[0.0, 0.0, math.pi / 2])
    node = SlopeNode(parameter_overrides=vehicle_overrides() + [mounting])
    h = Harness(node)
    try:
        f, w = node.bias.correct(T0, np.array([0.0, -1.0, 9.8]), np.array([0.02, 0.0, 0.1]))
        assert not node.bias.valid
        np.testing.assert_allclose(f, [1.0, 0.0, 9.8], atol=1e-12)
        np.testing.assert_allclose(w, [0.0, 0.02, 0.1], atol=1e-12)
    finally:
        h.close()


def test_the_state_node_reads_a_turned_imus_stated_noise_in_base_link():
    from vehicle_estimation.estimators.common.rotations import quat_from_euler, quat_to_rotmat
    from vehicle_estimation.ros.conversions import add_stated_imu_covariances, base_link_imu_variances

    def _stated_imu_variances(msg, mounting):
        covariances = np.zeros((2, 9))
        add_stated_imu_covariances(covariances, msg)
        return tuple(base_link_imu_variances(covariances, mounting))

    msg = Imu()
    msg.linear_acceleration_covariance = [0.1, 0.0, 0.0, 0.0, 0.4, 0.0, 0.0, 0.0, 0.9]
    msg.angular_velocity_covariance = [1e-4, 0.0, 0.0, 0.0, 2e-4, 0.0, 0.0, 0.0, 3e-4]
    facing_left = quat_to_rotmat(quat_from_euler(0.0, 0.0, math.pi / 2))
    on_its_side = quat_to_rotmat(quat_from_euler(math.pi / 2, 0.0, 0.0))
    assert _stated_imu_variances(msg, np.eye(3)) == pytest.approx((0.1, 0.4, 3e-4))
    assert _stated_imu_variances(msg, facing_left) == pytest.approx((0.4, 0.1, 3e-4))
    assert _stated_imu_variances(msg, on_its_side) == pytest.approx((0.1, 0.9, 2e-4))
    msg.linear_acceleration_covariance[0] = -1.0            # REP-145: unknown
    assert _stated_imu_variances(msg, facing_left) == pytest.approx((0.0, 0.0, 3e-4))


def test_slope_node_passes_the_fusion_grade():
    node = SlopeNode(parameter_overrides=vehicle_overrides() + [Parameter("method", value="fusion_pitch")])
    h = Harness(node)
    try:
        h.probe.publisher_for(Imu, topics.IMU)
        h.probe.publisher_for(Vector3Stamped, topics.FUSION_GRADE)
        out = h.probe.watch(Vector3Stamped, topics.ROAD_SLOPE_STAMPED)
        plain = h.probe.watch(Float64, topics.ROAD_SLOPE)
        h.connect([topics.IMU, topics.FUSION_GRADE])
        grade = math.radians(3.0)
        stream = []
        for i in range(400):
            ti = T0 + i * 0.005
            if i % 4 == 0:
                g = Vector3Stamped()
                sec_to_time(ti, g.header.stamp)
                g.vector.x, g.vector.y, g.vector.z = grade, 1e-6, 1.0
                stream.append((topics.FUSION_GRADE, g))
            stream.append((topics.IMU, imu_msg(ti, [G * math.sin(grade), 0, G * math.cos(grade)], [0, 0, 0])))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(out) > 10)
        assert out[-1].vector.x == pytest.approx(grade, abs=1e-3)
        assert plain[-1].data == pytest.approx(grade, abs=1e-3)
    finally:
        h.close()


@pytest.mark.parametrize("method", ["cubic_prediction", "classical"])
def test_slope_node_observers_find_a_grade(method):
    """Paper 004 observers on IMU + CAN speed: a 4 % grade, gentle acceleration, 30 s."""
    node = SlopeNode(parameter_overrides=vehicle_overrides() + [Parameter("method", value=method)])
    h = Harness(node)
    try:
        h.probe.publisher_for(Imu, topics.IMU)
        h.probe.publisher_for(TwistWithCovarianceStamped, topics.SPEED)
        out = h.probe.watch(Vector3Stamped, topics.ROAD_SLOPE_STAMPED)
        h.connect([topics.IMU, topics.SPEED])
        grade, a, v = math.atan(0.04), 0.3, 8.0
        squat = node.vehicle.pitch_gain * a     # the body pitch the node takes out
        stream = []
        for i in range(6000):
            ti = T0 + i * 0.005
            v += a * 0.005
            body = grade + squat
            stream.append((topics.IMU, imu_msg(ti, [a + G * math.sin(body), 0, G * math.cos(body)], [0, 0, 0])))
            if i % 2 == 0:
                stream.append((topics.SPEED, speed_msg(ti, v)))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(out) > 100 and out[-1].header.stamp.sec >= int(T0) + 29)
        assert all(math.isfinite(m.vector.x) and m.vector.y > 0 for m in out)
        assert out[-1].vector.x == pytest.approx(grade, abs=math.radians(0.15))
        assert out[-1].vector.z == 1.0      # converged
    finally:
        h.close()


@pytest.mark.parametrize("filter_name", ["vbackf", "ckf", "aoukf"])
def test_state_node_estimates_speed_from_wheels_and_imu(filter_name):
    node = StateNode(parameter_overrides=vehicle_overrides() + [Parameter("filter", value=filter_name)])
    h = Harness(node)
    try:
        h.probe.publisher_for(Imu, topics.IMU)
        h.probe.publisher_for(JointState, topics.JOINT_STATES)
        state = h.probe.watch(TwistWithCovarianceStamped, topics.VEHICLE_STATE)
        beta = h.probe.watch(Float64, topics.SIDESLIP)
        h.connect([topics.IMU, topics.JOINT_STATES])
        v = 20.0
        omega = v / node.vehicle.wheel_radius
        stream = []
        for i in range(600):
            ti = T0 + i * 0.005
            if i % 2 == 0:
                js = JointState()
                sec_to_time(ti, js.header.stamp)
                js.name = list(topics.WHEEL_JOINTS) + [topics.STEERING_JOINT]
                js.position = [math.nan] * 4 + [0.0]
                js.velocity = [omega] * 4 + [math.nan]
                js.effort = [0.0] * 4 + [math.nan]
                stream.append((topics.JOINT_STATES, js))
            stream.append((topics.IMU, imu_msg(ti, [0.0, 0.0, G], [0, 0, 0])))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(state) > 100)
        last = state[-1].twist.twist
        assert last.linear.x == pytest.approx(v, abs=0.5)
        assert abs(last.linear.y) < 0.1 and abs(last.angular.z) < 0.01
        assert all(math.isfinite(b.data) for b in beta)
        cov = np.array(state[-1].twist.covariance).reshape(6, 6)
        assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) >= -1e-12)
        assert node.running_filter == filter_name           # wheel speeds: no fallback
        assert node.status_values()["filter"] == filter_name
    finally:
        h.close()


def steering_msg(t: float, angle: float) -> JointState:
    js = JointState()
    sec_to_time(t, js.header.stamp)
    js.name = [topics.STEERING_JOINT]
    js.position = [angle]
    return js


def watch_state_outputs(h: Harness, topics_in: list) -> tuple[list, list]:
    """Publishers for ``topics_in`` ((type, topic) pairs) and watches of the state and sideslip."""
    for msg_type, topic in topics_in:
        h.probe.publisher_for(msg_type, topic)
    state = h.probe.watch(TwistWithCovarianceStamped, topics.VEHICLE_STATE)
    sideslip = h.probe.watch(Vector3Stamped, topics.SIDESLIP_STAMPED)
    h.connect([topic for _, topic in topics_in])
    return state, sideslip


@pytest.mark.parametrize("fallback", [True, False])
def test_state_node_without_wheel_speeds_uses_vehicle_speed(fallback):
    """No wheel speeds, an accelerometer biased by +0.3 m/s^2 at a steady 20 m/s: the CAN speed
    holds vx; without it vx is dead-reckoned and drifts with the bias (~3 m/s in 10 s), and the
    sideslip that rests on it is never published as converged."""
    node = StateNode(parameter_overrides=vehicle_overrides() + [
        Parameter("speed_fallback", value=fallback), Parameter("initial_vx", value=20.0)])
    h = Harness(node)
    try:
        # Slope and mass upstream too, as a full pipeline has them.
        topics_in = [(Imu, topics.IMU), (JointState, topics.JOINT_STATES),
                     (Vector3Stamped, topics.ROAD_SLOPE_STAMPED), (Vector3Stamped, topics.MASS_STAMPED)]
        if fallback:
            topics_in.append((TwistWithCovarianceStamped, topics.SPEED))
        state, sideslip = watch_state_outputs(h, topics_in)
        stream = []
        for i in range(2000):
            ti = T0 + i * 0.005
            if i % 2 == 0:
                stream.append((topics.JOINT_STATES, steering_msg(ti, 0.0)))
                if fallback:
                    stream.append((topics.SPEED, speed_msg(ti, 20.0)))
            if i % 10 == 0:
                stream.append((topics.ROAD_SLOPE_STAMPED, companion(ti, 0.0, 1e-6, True)))
                stream.append((topics.MASS_STAMPED, companion(ti, 1500.0, 100.0, True)))
            stream.append((topics.IMU, imu_msg(ti, [0.3, 0.0, G], [0, 0, 0])))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(state) > 100 and state[-1].header.stamp.sec >= int(T0) + 9)
        vx = state[-1].twist.twist.linear.x
        assert h.wait_for(lambda: len(sideslip) > 100)
        converged = [m.vector.z > 0.5 for m in sideslip[-50:]]
        if fallback:
            assert vx == pytest.approx(20.0, abs=0.3)
            assert node.core.speed_updates > 500
            assert all(converged), (node.missing, node.vx_source)
            assert math.sqrt(state[-1].twist.covariance[0]) < conversions.MAX_MEASURED_SPEED_STD
        else:
            assert vx > 22.0        # the drift the fallback removes
            assert not any(converged)
            # The published variance covers the drift (within 2 sigma), and says "not measured",
            # so no slope observer or mass filter takes this vx for a speed.
            std = math.sqrt(state[-1].twist.covariance[0])
            assert abs(vx - 20.0) < 2.0 * std and std > conversions.MAX_MEASURED_SPEED_STD
            assert not conversions.measured_speed(vx, state[-1].twist.covariance[0])
    finally:
        h.close()


def _circle_without_speed(p, vx: float, r: float, seconds: float, ax_bias: float = 0.0) -> list:
    """A steady circle at ``vx`` and yaw rate ``r``: 200 Hz IMU and the steering angle at
    100 Hz, no wheel speeds, no vehicle/speed."""
    steering_wheel = p.steering_ratio * p.wheelbase * r / vx
    stream = []
    for i in range(int(round(seconds / 0.005))):
        ti = T0 + i * 0.005
        if i % 2 == 0:
            stream.append((topics.JOINT_STATES, steering_msg(ti, steering_wheel)))
        stream.append((topics.IMU, imu_msg(ti, [ax_bias, vx * r, G], [0, 0, r])))
    return stream


@pytest.mark.parametrize("corners", [True, False])
def test_state_node_without_any_speed_measures_vx_in_corners(corners):
    """No wheel speeds, no vehicle/speed, an accelerometer biased by +0.3 m/s^2, on a steady
    circle at 20 m/s and 0.25 rad/s: mean(ay) / mean(r) measures vx in the turn and holds it,
    and /diagnostics says so; with cornering_speed_accel_std 0 nothing but the tyre model
    updates vx (on this circle, which the model explains, that holds it too; the real drive's
    limit corners do not: test_vbackf). Either way the sideslip is never flagged converged."""
    vx_true, r_true = 20.0, 0.25
    node = StateNode(parameter_overrides=vehicle_overrides() + [
        Parameter("initial_vx", value=vx_true),
        Parameter("cornering_speed_accel_std", value=1.0 if corners else 0.0)])
    h = Harness(node)
    try:
        state, sideslip = watch_state_outputs(h, [(Imu, topics.IMU), (JointState, topics.JOINT_STATES)])
        h.publish_stream(_circle_without_speed(node.vehicle, vx_true, r_true, 20.0, ax_bias=0.3))
        assert h.wait_for(lambda: len(state) > 100 and state[-1].header.stamp.sec >= int(T0) + 19)
        assert h.wait_for(lambda: len(sideslip) > 100)
        vx = state[-1].twist.twist.linear.x
        assert not any(m.vector.z > 0.5 for m in sideslip)
        if corners:
            assert vx == pytest.approx(vx_true, abs=0.5), vx
            assert node.core.speed_updates >= 30
            assert node.vx_source.startswith("dead reckoning from ax, measured in corners"), node.vx_source
        else:
            assert node.core.speed_updates == 0
            assert node.vx_source.startswith("dead reckoning from ax (no wheel"), node.vx_source
    finally:
        h.close()


@pytest.mark.parametrize("fallback", ["vbackf", ""])
def test_aoukf_without_any_speed_runs_the_no_speed_filter(fallback):
    """paper 002's AO-UKF takes vx as a measurement; on a drive with no wheel speeds and no
    vehicle/speed (the circle above) the node runs ``no_speed_filter`` instead and says so
    (with '' the AO-UKF runs all the same)."""
    vx_true, r_true = 20.0, 0.25
    node = StateNode(parameter_overrides=vehicle_overrides() + [
        Parameter("filter", value="aoukf"), Parameter("no_speed_filter", value=fallback),
        Parameter("initial_vx", value=vx_true)])
    h = Harness(node)
    try:
        state, _ = watch_state_outputs(h, [(Imu, topics.IMU), (JointState, topics.JOINT_STATES)])
        h.publish_stream(_circle_without_speed(node.vehicle, vx_true, r_true, 10.0))
        assert h.wait_for(lambda: len(state) > 100 and state[-1].header.stamp.sec >= int(T0) + 9)
        assert node.core.initialised
        status = node.status_values()["filter"]
        if fallback:
            assert node.running_filter == "vbackf" and type(node.core).__name__ == "VehicleStateVBACKF"
            assert status == "vbackf (instead of aoukf, which needs a speed: none yet)"
            assert state[-1].twist.twist.linear.x == pytest.approx(vx_true, abs=0.5)
        else:
            assert node.running_filter == "aoukf" and status == "aoukf"
        node.reset_estimators()                             # a bag loop starts with the configured filter
        assert node.running_filter == "aoukf" and type(node.core).__name__ == "VehicleStateAOUKF"
    finally:
        h.close()


#: The state node's inputs in the AO-UKF tests: vehicle/speed too.
AOUKF_INPUTS = [(Imu, topics.IMU), (JointState, topics.JOINT_STATES), (TwistWithCovarianceStamped, topics.SPEED)]


def _aoukf_node(initial_vx: float) -> tuple[StateNode, Harness]:
    node = StateNode(parameter_overrides=vehicle_overrides() + [
        Parameter("filter", value="aoukf"), Parameter("initial_vx", value=initial_vx)])
    return node, Harness(node)


def test_a_speed_that_starts_late_hands_the_drive_back_to_aoukf():
    """A recorder's CAN topic may start seconds after its IMU: the no-speed filter runs until
    vehicle/speed has come for a second, then the configured AO-UKF takes over its state."""
    vx_true, r_true = 20.0, 0.25
    node, h = _aoukf_node(vx_true)
    try:
        state, _ = watch_state_outputs(h, AOUKF_INPUTS)
        stream = _circle_without_speed(node.vehicle, vx_true, r_true, 6.0)
        h.publish_stream(stream[:len(stream) // 2])          # 3 s without a speed
        assert h.wait_for(lambda: node.running_filter == "vbackf" and node.core.initialised)
        late = [(topics.SPEED, speed_msg(T0 + 3.0 + i * 0.02, vx_true)) for i in range(150)]
        h.publish_stream(sorted(stream[len(stream) // 2:] + late, key=lambda m: stamp_ns(m[1].header.stamp)))
        assert h.wait_for(lambda: len(state) > 100 and state[-1].header.stamp.sec >= int(T0) + 5)
        assert node.running_filter == "aoukf" and type(node.core).__name__ == "VehicleStateAOUKF"
        assert node.status_values()["filter"] == "aoukf"
        assert state[-1].twist.twist.linear.x == pytest.approx(vx_true, abs=0.5)
    finally:
        h.close()


def test_a_speed_lost_mid_drive_runs_the_no_speed_filter_until_it_comes_back():
    """A CAN speed that drops out mid-drive leaves the AO-UKF without the vx it measures (on
    this circle its tyres pull vx up by some 1.5 m/s per second): after a second without one
    the no-speed filter takes over the AO-UKF's state, and a second after the speed is back
    the AO-UKF takes over again. A dropout shorter than that second swaps nothing, and a
    swap does not move vy (each filter starts from the other's [vx, vy, r]). A second dropout
    runs the same no-speed filter again, with the noise it learnt in the first."""
    vx_true, r_true = 20.0, 0.25
    node, h = _aoukf_node(vx_true)
    try:
        state, _ = watch_state_outputs(h, AOUKF_INPUTS)
        circle = _circle_without_speed(node.vehicle, vx_true, r_true, 13.1)
        # vehicle/speed at 50 Hz, with a 0.6 s dropout at 2 s, none from 4 to 8 s and from 12 s
        speed = [(topics.SPEED, speed_msg(T0 + i * 0.02, vx_true)) for i in range(600)
                 if not (2.0 <= i * 0.02 < 2.6 or 4.0 <= i * 0.02 < 8.0)]
        stream = sorted(circle + speed, key=lambda m: stamp_ns(m[1].header.stamp))

        def publish_until(seconds: float) -> None:
            end_ns = int(round((T0 + seconds) * 1e9))
            chunk = [m for m in stream if stamp_ns(m[1].header.stamp) < end_ns]
            del stream[:len(chunk)]
            h.publish_stream(chunk)
            assert h.wait_for(lambda: state and stamp_ns(state[-1].header.stamp) >= end_ns - 20_000_000)

        publish_until(3.9)
        assert node.running_filter == "aoukf" and node.core.initialised    # the short dropout swapped nothing
        publish_until(4.9)
        assert node.running_filter == "aoukf"                              # a second not yet over
        publish_until(5.1)
        assert node.running_filter == "vbackf" and type(node.core).__name__ == "VehicleStateVBACKF"
        assert node.status_values()["filter"] == "vbackf (instead of aoukf, which needs a speed: lost)"
        fallback = node.core
        publish_until(8.0)
        assert state[-1].twist.twist.linear.x == pytest.approx(vx_true, abs=0.2)   # the corner's vx
        publish_until(8.9)
        assert node.running_filter == "vbackf"                             # back for under a second
        publish_until(12.0)
        assert node.running_filter == "aoukf" and type(node.core).__name__ == "VehicleStateAOUKF"
        assert state[-1].twist.twist.linear.x == pytest.approx(vx_true, abs=0.1)
        vy = np.array([m.twist.twist.linear.y for m in state])
        assert np.abs(np.diff(vy)).max() < 0.05
        learnt = fallback.measurement_noise_diagonal.copy()
        prior = node._make_fallback_core().measurement_noise_diagonal
        assert not np.allclose(learnt, prior, rtol=0.2)
        publish_until(13.1)
        assert node.core is fallback                                       # the same filter ...
        assert node.core.measurement_noise_diagonal == pytest.approx(learnt, rel=0.05)   # ... and its noise
    finally:
        h.close()


def _mass_drive_stream(p, mass_true: float, slope_msgs: bool, low_accel: float = 0.2, v0: float = 5.0):
    """40 s of pulses of 1.2 m/s^2 and ``low_accel`` on a level road: IMU, CAN speed, wheels
    (brake torque when the pulse decelerates harder than the resistances), drive force, slope."""
    stream, v = [], v0
    inertia = mass_true + p.wheel_inertia / p.wheel_radius ** 2
    for i in range(8000):
        ti = T0 + i * 0.005
        a = 1.2 if (i // 400) % 2 == 0 else low_accel
        v += a * 0.005
        stream.append((topics.IMU, imu_msg(ti, [a, 0, G], [0, 0, 0])))
        if i % 2:
            continue
        resist = 0.5 * p.air_density * p.drag_area * v * v + mass_true * p.gravity * p.rolling_resistance
        drive = max(inertia * a + resist, 0.0)
        brake = max(-(inertia * a + resist), 0.0) * p.wheel_radius   # total over the wheels [N m]
        stream.append((topics.SPEED, speed_msg(ti, v)))
        js = JointState()
        sec_to_time(ti, js.header.stamp)
        js.name = list(topics.WHEEL_JOINTS)
        js.velocity = [v / p.wheel_radius] * 4
        js.effort = [brake / 4.0] * 4
        stream.append((topics.JOINT_STATES, js))
        pt = JointState()
        sec_to_time(ti, pt.header.stamp)
        pt.name = [topics.ENGINE_JOINT, topics.DRIVE_JOINT]
        pt.velocity = [math.nan, math.nan]
        pt.effort = [math.nan, drive]
        stream.append((topics.POWERTRAIN, pt))
        if slope_msgs and i % 10 == 0:
            slope = Vector3Stamped()
            sec_to_time(ti, slope.header.stamp)
            slope.vector.x, slope.vector.y, slope.vector.z = 0.0, 1e-6, 1.0
            stream.append((topics.ROAD_SLOPE_STAMPED, slope))
    return stream


def _connect_mass_inputs(h: Harness) -> list:
    """Publishers for every mass-node input; returns the list collecting mass_stamped."""
    inputs = [(JointState, topics.POWERTRAIN), (Imu, topics.IMU), (JointState, topics.JOINT_STATES),
              (TwistWithCovarianceStamped, topics.SPEED), (Vector3Stamped, topics.ROAD_SLOPE_STAMPED)]
    for msg_type, topic in inputs:
        h.probe.publisher_for(msg_type, topic)
    out = h.probe.watch(Vector3Stamped, topics.MASS_STAMPED)
    h.connect([topic for _, topic in inputs])
    return out


@pytest.mark.parametrize("with_slope", [True, False])
def test_mass_node_recovers_mass_from_drive_force(with_slope):
    mass_true = 1800.0
    node = MassNode(parameter_overrides=vehicle_overrides() + [Parameter("method", value="rls")])
    h = Harness(node)
    try:
        diagnostics = h.probe.watch(DiagnosticArray, "/diagnostics")
        out = _connect_mass_inputs(h)
        h.publish_stream(_mass_drive_stream(node.vehicle, mass_true, with_slope))
        assert h.wait_for(lambda: len(out) > 50)
        assert all(math.isfinite(m.vector.x) and m.vector.y >= 0 for m in out)
        if with_slope:
            assert out[-1].vector.x == pytest.approx(mass_true, rel=0.03)
        else:
            # no slope node: no update on a guessed grade, the prior stays, diagnostics say why
            assert out[-1].vector.x == pytest.approx(1000.0)
            assert h.wait_for(lambda: any("road slope" in s.message for d in diagnostics for s in d.status),
                              timeout=5.0)
    finally:
        h.close()


def test_mass_node_rls_with_wind_compensation_takes_the_heading_from_the_odometry():
    """A 6 m/s headwind on an eastbound drive (fusion odometry: yaw 0): the RLS with
    ``mass.wind_compensation`` feeds the heading to the wind estimator, which learns the wind
    from the force residual; the node reports it in /diagnostics."""
    mass_true, headwind = 1800.0, 6.0
    node = MassNode(parameter_overrides=vehicle_overrides() + [
        Parameter("method", value="rls"), Parameter("mass.wind_compensation", value=True)])
    h = Harness(node)
    try:
        h.probe.publisher_for(Odometry, topics.ODOMETRY)
        diagnostics = h.probe.watch(DiagnosticArray, "/diagnostics")
        out = _connect_mass_inputs(h)
        h.connect([topics.ODOMETRY])
        p = node.vehicle
        stream, v = [], 12.0
        for topic, msg in _mass_drive_stream(p, mass_true, True, v0=12.0):
            if topic == topics.POWERTRAIN:
                # the drive force that also overcomes the extra drag of the headwind
                t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
                msg.effort[1] += 0.5 * p.air_density * p.drag_area * ((v + headwind) ** 2 - v * v)
                odom = Odometry()
                sec_to_time(t, odom.header.stamp)
                odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
                odom.pose.pose.orientation.w = 1.0          # yaw 0: heading east (REP-103 ENU)
                odom.twist.twist.linear.x = v
                stream.append((topics.ODOMETRY, odom))
            if topic == topics.SPEED:
                v = msg.twist.twist.linear.x        # sent before the powertrain of its stamp
            stream.append((topic, msg))
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(out) > 50)
        wind = node.core.wind
        assert wind is not None and wind.samples_used > 100
        east, north = wind.wind_enu
        assert east == pytest.approx(-headwind, abs=2.0) and abs(north) < 6.0   # blowing west
        assert out[-1].vector.x == pytest.approx(mass_true, rel=0.03)
        assert h.wait_for(lambda: any(kv.key == "wind east, north [m/s]" for d in diagnostics
                                      for st in d.status for kv in st.values), timeout=5.0)
    finally:
        h.close()


def test_mass_node_rls_estimates_the_rolling_resistance_without_a_heading():
    """Tyres with C_r 0.006 above the vehicle file's: ``mass.rolling_resistance_estimation``
    separates that force from the mass (no odometry, so no wind: the heading is not needed);
    the node reports the C_r in /diagnostics. The forces here are exact, so the EKF may trust
    them more than a real torque map's (150 N per window, the wind's, not 600 N)."""
    mass_true, extra_cr = 1800.0, 0.006
    node = MassNode(parameter_overrides=vehicle_overrides() + [
        Parameter("method", value="rls"), Parameter("mass.rolling_resistance_estimation", value=True),
        Parameter("mass.rolling_resistance_force_std", value=150.0)])
    h = Harness(node)
    try:
        diagnostics = h.probe.watch(DiagnosticArray, "/diagnostics")
        out = _connect_mass_inputs(h)
        stream = _mass_drive_stream(node.vehicle, mass_true, True, v0=12.0)
        for topic, msg in stream:
            if topic == topics.POWERTRAIN:
                msg.effort[1] += mass_true * node.vehicle.gravity * extra_cr
        h.publish_stream(stream)
        assert h.wait_for(lambda: len(out) > 50)
        assert node.core.wind is not None and node.core.wind.samples_used > 100
        cr = node.core.rolling_resistance - node.vehicle.rolling_resistance
        assert node.core.wind.rolling_resistance_offset_std < 0.002
        assert cr == pytest.approx(extra_cr, abs=2.0 * node.core.wind.rolling_resistance_offset_std)
        assert out[-1].vector.x == pytest.approx(mass_true, rel=0.03)
        assert h.wait_for(lambda: any(kv.key == "rolling resistance" for d in diagnostics
                                      for st in d.status for kv in st.values), timeout=5.0)
    finally:
        h.close()


def test_mass_node_ffrls_uses_braking_samples():
    """FFRLS (paper 004 Eqs. 28-31): driving and braking pulses, brake torque on the wheels."""
    mass_true = 1650.0
    node = MassNode(parameter_overrides=vehicle_overrides() + [
        Parameter("method", value="ffrls"), Parameter("ffrls.rotating_inertia_correction", value=True)])
    h = Harness(node)
    try:
        out = _connect_mass_inputs(h)
        h.publish_stream(_mass_drive_stream(node.vehicle, mass_true, True, low_accel=-1.0, v0=10.0))
        assert h.wait_for(lambda: len(out) > 50)
        assert all(math.isfinite(m.vector.x) and m.vector.y >= 0 for m in out)
        assert out[-1].vector.x == pytest.approx(mass_true, rel=0.02)
        # inside a pulse |Omega| >= 0.87 m/s^2 passes Eq. 31; only windows that straddle one of
        # the 19 pulse switches can average below the threshold, and some do
        assert 0 < node.core.rejected["threshold"] <= 19
        assert node.core.samples_used > 100     # braking windows count: about half of them
    finally:
        h.close()


@pytest.mark.parametrize("module, override, name", [
    ("mass_node", "ffrls.forgetting_factor:=1.5", "forgetting_factor"),
    ("mass_node", "method:=bogus", "method"),
    ("mass_node", "method:=rls;mass.rolling_resistance_std:=0.0", "rolling_resistance_std"),
    ("state_node", "filter:=vbackf;vbackf.noise_structure:=banded", "noise_structure"),
    ("mass_node", "method:=ta_aekf;ta_aekf.fixed_tau:=2.0", "fixed_tau"),
    ("mass_node", "method:=ta_aekf;ta_aekf.model_path:=/nonexistent/model", "ta_aekf.model_path"),
    ("state_node", "filter:=aoukf;aoukf.outlier_c:=-1.0", "outlier_c"),
    ("state_node", "filter:=aoukf;aoukf_correction:=/nonexistent/weights.npz", "aoukf_correction"),
    ("state_node", "filter:=aoukf;no_speed_filter:=aoukf", "no_speed_filter"),
    ("slope_node", "method:=bogus", "method"),
    ("slope_node", "cubic_prediction.fit_min_points:=2", "cubic_prediction.fit_min_points"),
    ("state_node", "vehicle.mass:=-5.0", "vehicle.mass"),
    ("fusion_node", "vehicle.imu_mounting_rpy:=[0.0, 5.0, 0.0]", "imu_mounting_rpy"),
    ("slope_node", "vehicle.imu_mounting_rpy:=[0.0, 0.0]", "imu_mounting_rpy"),
    ("fusion_node", "fusion.mounting_rpy:=[0.0, 0.0, 1.5]", "'fusion.mounting_rpy' (now 'vehicle.imu_mounting_rpy')"),
    ("fusion_node", "fusion.gravity:=9.81", "'fusion.gravity' (now 'vehicle.gravity')"),
])
def test_bad_parameter_stops_node_naming_it(module, override, name):
    proc = subprocess.run(
        [sys.executable, "-m", f"vehicle_estimation.ros.{module}", "--ros-args",
         "--params-file", str(params_file("sedan_d_class"))]
        + [arg for assignment in override.split(";") for arg in ("-p", assignment)],
        capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert name in proc.stderr
