"""Property-based tests (hypothesis) of the message conversions and of every estimator core.

1. Message -> array conversions (ros/conversions.py) and the raw CDR views (ros/cdr.py):
   on random messages the conversions return the message fields in the documented units and
   order, raise nothing but ``MalformedMessage`` (and that exactly when a JointState array
   has the wrong length), and a view read from the serialized bytes equals rclpy's own
   deserialisation field by field (NaN, inf and odd strings included).
2. Each core's step on random sequences of physically bounded inputs (with some absurd but
   finite values mixed in) and increasing stamps: nothing raises, the published outputs
   (state, mass, variance, slope) are finite, and every covariance matrix stays symmetric
   (to 1e-9 relative) and positive semi-definite (min eigenvalue >= -1e-9 max |eigenvalue|).

Examples are few and derandomized (reproducible in CI); the whole file runs in well under a
minute. For a deeper local search raise the counts, e.g.
``PROPERTY_EXAMPLES=400 PROPERTY_SEQUENCES=300 pytest test/test_properties.py`` (minutes),
and ``PROPERTY_RANDOM=1`` draws new examples on every run instead of the fixed ones. No ROS node and no rclpy.init: message classes and (de)serialisation only.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import os
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import TwistWithCovarianceStamped
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.state.aoukf import AOUKFConfig, VehicleStateAOUKF
from vehicle_estimation.estimators.state.ckf import VehicleStateCKF
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.esekf import FusionEKF
from vehicle_estimation.estimators.mass.mass_ffrls import FFRLSMassConfig, FFRLSMassEstimator
from vehicle_estimation.estimators.mass.mass_rls import LongitudinalMassEstimator, MassRLSConfig
from vehicle_estimation.estimators.slope.cubic_prediction import (
    CubicPredictionSlopeConfig,
    CubicPredictionSlopeObserver,
)
from vehicle_estimation.estimators.slope.observers import ClassicalSlopeConfig, ClassicalSlopeObserver
from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeConfig, PitchGradeSlope
from vehicle_estimation.estimators.mass.ta_aekf import TaAekfConfig, TaAekfMassEstimator
from vehicle_estimation.estimators.state.vbackf import VehicleStateVBACKF
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.estimators.mass.wind import WindEstimator
from vehicle_estimation.ros.cdr import DECODERS, raw_reader
from vehicle_estimation.ros.conversions import (
    MAX_ANGULAR_RATE,
    MAX_SPECIFIC_FORCE,
    MalformedMessage,
    chassis_reading,
    forward_speed_entry,
    imu_arrays,
    imu_plausible,
    joint_readings,
    odometry_entry,
    planar_velocity_entry,
    powertrain_reading,
)
from vehicle_estimation.contract.vehicle import load_vehicle_params

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SEDAN = load_vehicle_params(PARAMS_DIR / "sedan_d_class.yaml")
AUDI = load_vehicle_params(PARAMS_DIR / "audi_a4.yaml")
TRUCK = load_vehicle_params(PARAMS_DIR / "heavy_truck.yaml")
G = 9.80665

# Few examples, reproducible: the file must stay fast on a shared 2-core CI machine.
_DERANDOMIZE = not os.environ.get("PROPERTY_RANDOM")     # set it to search new examples each run
_COMMON = {"deadline": None, "derandomize": _DERANDOMIZE, "database": None,
           "suppress_health_check": [HealthCheck.too_slow, HealthCheck.data_too_large]}
FAST = settings(max_examples=int(os.environ.get("PROPERTY_EXAMPLES", "60")), **_COMMON)
SEQ = settings(max_examples=int(os.environ.get("PROPERTY_SEQUENCES", "40")), **_COMMON)


# ============================================================================ helpers
def assert_finite(*values, what="output"):
    for v in values:
        a = np.asarray(v, dtype=float)
        assert np.all(np.isfinite(a)), f"non-finite {what}: {v!r}"


def assert_covariance(P, what="covariance"):
    """Finite, symmetric to 1e-9 relative, PSD: min eigenvalue >= -1e-9 max |eigenvalue|."""
    P = np.atleast_2d(np.asarray(P, dtype=float))
    assert P.shape[0] == P.shape[1], f"{what} not square: {P.shape}"
    assert np.all(np.isfinite(P)), f"non-finite {what}:\n{P}"
    scale = float(np.max(np.abs(P))) if P.size else 0.0
    asym = float(np.max(np.abs(P - P.T))) if P.size else 0.0
    assert asym <= 1e-9 * scale, f"{what} not symmetric: max |P - P^T| = {asym:g}, max |P| = {scale:g}"
    w = np.linalg.eigvalsh(0.5 * (P + P.T))
    assert w.min() >= -1e-9 * max(float(np.max(np.abs(w))), 0.0), f"{what} not PSD: eigenvalues {w}"


def physical(lo: float, hi: float, absurd: float | None = None) -> st.SearchStrategy[float]:
    """A float in [lo, hi]; with ``absurd``, about one draw in eight is +-absurd or 0: a
    glitching sensor, a wrongly scaled bus signal (finite nonsense)."""
    base = st.floats(lo, hi, allow_nan=False, allow_infinity=False)
    if absurd is None:
        return base
    crazy = st.sampled_from([absurd, -absurd, 0.0])
    return st.one_of(*([base] * 7), crazy)


def stamps(dts) -> list[float]:
    t, out = 1.7e9, []            # stamps near the epoch, as in a real drive
    for dt in dts:
        t += dt
        out.append(t)
    return out


def dt_strategy(max_dt: float = 0.1, gap: float = 3.0) -> st.SearchStrategy[float]:
    """Sample intervals: mostly nominal rates, sometimes a gap (re-initialisation paths)."""
    return st.one_of(*([st.floats(1e-4, max_dt)] * 9), st.floats(max_dt, gap))


# ============================================================================ 1. conversions
KNOWN_JOINTS = (*topics.WHEEL_JOINTS, topics.STEERING_JOINT, topics.ENGINE_JOINT,
                topics.ENGINE_LOAD_JOINT, topics.GEAR_JOINT, topics.DRIVE_JOINT)
any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
finite_float = st.floats(allow_nan=False, allow_infinity=False, width=64)
ros_text = st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=12)


def same_float(a, b) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@st.composite
def joint_states(draw, wellformed: bool = True):
    """A JointState with a random subset of the contract's joints (plus strangers) in random
    order; each of position/velocity/effort empty or one value per name (``wellformed``), or
    any length (otherwise)."""
    names = draw(st.lists(st.one_of(st.sampled_from(KNOWN_JOINTS), ros_text), unique=True, max_size=12))
    msg = JointState()
    msg.name = names
    values = st.one_of(*([finite_float] * 5), any_float)
    for field in ("position", "velocity", "effort"):
        if wellformed:
            n = draw(st.sampled_from([0, len(names)]))
        else:
            n = draw(st.integers(0, len(names) + 3))
        setattr(msg, field, draw(st.lists(values, min_size=n, max_size=n)))
    return msg


def _expected(msg: JointState, name: str, field: str) -> float:
    names = list(msg.name)
    values = list(getattr(msg, field))
    if name not in names or not values:
        return math.nan
    v = values[names.index(name)]
    return v if math.isfinite(v) else math.nan


@FAST
@given(joint_states())
def test_joint_state_conversions_equal_the_message_fields(msg):
    readings = joint_readings(msg)
    assert set(readings) == set(msg.name)
    for name, r in readings.items():
        for field in ("position", "velocity", "effort"):
            assert same_float(getattr(r, field), _expected(msg, name, field)), (name, field)

    chassis = chassis_reading(msg)
    assert chassis.wheel_speeds.shape == (4,) and chassis.brake_torques.shape == (4,)
    for i, wheel in enumerate(topics.WHEEL_JOINTS):          # order [fl, fr, rl, rr] whatever the message's
        assert same_float(chassis.wheel_speeds[i], _expected(msg, wheel, "velocity"))
        assert same_float(chassis.brake_torques[i], _expected(msg, wheel, "effort"))
    assert same_float(chassis.steering_wheel_angle, _expected(msg, topics.STEERING_JOINT, "position"))
    finite = [b for b in chassis.brake_torques if math.isfinite(b)]
    assert same_float(chassis.total_brake_torque, float(np.sum(finite)) if finite else math.nan)

    power = powertrain_reading(msg)
    assert same_float(power.engine_speed, _expected(msg, topics.ENGINE_JOINT, "velocity"))
    assert same_float(power.engine_torque, _expected(msg, topics.ENGINE_JOINT, "effort"))
    assert same_float(power.drive_force, _expected(msg, topics.DRIVE_JOINT, "effort"))
    load = _expected(msg, topics.ENGINE_LOAD_JOINT, "position")
    assert same_float(power.engine_load, load if -0.01 <= load <= 1.01 else math.nan)
    gear = _expected(msg, topics.GEAR_JOINT, "position")
    assert same_float(power.gear, gear if 0.5 <= gear <= 40 else math.nan)


@FAST
@given(joint_states(wellformed=False))
def test_malformed_joint_state_raises_only_malformed_message(msg):
    n = len(msg.name)
    malformed = any(len(getattr(msg, f)) not in (0, n) for f in ("position", "velocity", "effort"))
    for convert in (joint_readings, chassis_reading, powertrain_reading):
        if malformed:
            with pytest.raises(MalformedMessage):
                convert(msg)
        else:
            convert(msg)        # anything but MalformedMessage propagates and fails the test


@FAST
@given(st.lists(finite_float, min_size=6, max_size=6))
def test_imu_arrays_equal_the_message_fields(values):
    msg = Imu()
    a, w = msg.linear_acceleration, msg.angular_velocity
    a.x, a.y, a.z, w.x, w.y, w.z = values
    f, rate = imu_arrays(msg)
    assert f.dtype == float and rate.dtype == float and f.shape == rate.shape == (3,)
    np.testing.assert_array_equal(f, values[:3])               # body x, y, z (REP-103/145)
    np.testing.assert_array_equal(rate, values[3:])
    view = DECODERS[Imu](serialize_message(msg))
    for x, y in zip(imu_arrays(view), (f, rate)):
        np.testing.assert_array_equal(x, y)
    plausible = all(abs(v) <= MAX_SPECIFIC_FORCE for v in values[:3]) and \
        all(abs(v) <= MAX_ANGULAR_RATE for v in values[3:])
    assert imu_plausible(f, rate) is plausible


@FAST
@given(st.integers(0, 2 ** 31 - 1), st.integers(0, 999_999_999), any_float,
       st.floats(-math.pi, math.pi), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5),
       st.one_of(st.floats(1e-150, 1e150), st.floats(-1e150, -1e-150)))
def test_odometry_entry_equals_stamp_speed_and_yaw(sec, nanosec, vx, yaw, pitch, roll, scale):
    """Yaw of any (scaled, sign-flipped) quaternion of a ZYX rotation is that yaw."""
    msg = Odometry()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.twist.twist.linear.x = vx
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    q = msg.pose.pose.orientation
    q.w, q.x = scale * (cr * cp * cy + sr * sp * sy), scale * (sr * cp * cy - cr * sp * sy)
    q.y, q.z = scale * (cr * sp * cy + sr * cp * sy), scale * (cr * cp * sy - sr * sp * cy)
    t = (sec * 1_000_000_000 + nanosec) * 1e-9
    for m in (msg, DECODERS[Odometry](serialize_message(msg))):
        entry = odometry_entry(m)
        if not math.isfinite(vx):
            assert entry is None
            continue
        assert entry is not None and entry[0] == t and entry[1][:2] == (t, vx)
        err = (entry[1][2] - yaw + math.pi) % (2 * math.pi) - math.pi
        assert abs(err) < 1e-6, (entry, yaw)


@FAST
@given(st.lists(any_float, min_size=5, max_size=5))
def test_odometry_entry_never_raises_on_any_quaternion(values):
    msg = Odometry()
    q = msg.pose.pose.orientation
    msg.twist.twist.linear.x, q.x, q.y, q.z, q.w = values
    entry = odometry_entry(msg)
    if math.isfinite(values[0]):
        assert entry is not None
        yaw = entry[1][2]
        assert math.isnan(yaw) or -math.pi <= yaw <= math.pi
    else:
        assert entry is None


@FAST
@given(st.sampled_from([Odometry, TwistWithCovarianceStamped]), st.integers(0, 2 ** 31 - 1),
       st.integers(0, 999_999_999), any_float, any_float)
def test_velocity_entries_equal_stamp_and_twist(msg_type, sec, nanosec, vx, vy):
    msg = msg_type()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.twist.twist.linear.x, msg.twist.twist.linear.y = vx, vy
    view = DECODERS[msg_type](serialize_message(msg))
    t = (sec * 1_000_000_000 + nanosec) * 1e-9
    assert abs(t - (sec + nanosec * 1e-9)) <= 1e-6
    for m in (msg, view):
        entry = forward_speed_entry(m)
        assert entry == ((t, (t, vx, 0.0)) if math.isfinite(vx) else None)
        entry2 = planar_velocity_entry(m)
        assert entry2 == ((t, (t, vx, vy, 0.0)) if math.isfinite(vx) and math.isfinite(vy) else None)


# -------------------------------------------------------------------- CDR views
def _fill(msg, data):
    """Random values in every field: NaN/inf/huge doubles, full-range integers, any text
    (no NUL), sequences of any length."""
    for name, kind in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        if kind == "double":
            setattr(msg, name, data.draw(any_float))
        elif kind == "int32":
            setattr(msg, name, data.draw(st.integers(-2 ** 31, 2 ** 31 - 1)))
        elif kind == "uint32":
            setattr(msg, name, data.draw(st.integers(0, 2 ** 32 - 1)))
        elif kind == "string":
            setattr(msg, name, data.draw(ros_text))
        elif kind.startswith("double["):
            n = len(value)
            setattr(msg, name, data.draw(st.lists(any_float, min_size=n, max_size=n)))
        elif kind == "sequence<double>":
            setattr(msg, name, data.draw(st.lists(any_float, max_size=8)))
        elif kind == "sequence<string>":
            setattr(msg, name, data.draw(st.lists(ros_text, max_size=8)))
        elif hasattr(value, "get_fields_and_field_types"):
            _fill(value, data)
        else:
            raise AssertionError(f"field type {kind} not covered by the test")
    return msg


def _assert_same(view, msg, path="msg"):
    for name in msg.get_fields_and_field_types():
        a, b = getattr(view, name), getattr(msg, name)
        where = f"{path}.{name}"
        if hasattr(b, "get_fields_and_field_types"):
            _assert_same(a, b, where)
        elif isinstance(b, float):
            assert same_float(a, b), where
        elif isinstance(b, (int, str)):
            assert a == b and type(a) is type(b), where
        else:
            a, b = list(a), list(b)
            assert len(a) == len(b), where
            for x, y in zip(a, b):
                assert (same_float(x, y) if isinstance(y, float) else x == y), where


@FAST
@given(st.sampled_from(list(DECODERS)), st.data())
def test_cdr_views_equal_rclpy_deserialisation(msg_type, data):
    msg = _fill(msg_type(), data)
    raw = serialize_message(msg)
    reference = deserialize_message(raw, msg_type)
    view = DECODERS[msg_type](raw)
    _assert_same(view, reference)
    read = raw_reader(msg_type)(raw)
    assert type(read) is not msg_type         # the fast path was taken, not the fallback
    _assert_same(read, reference)
    # ... and the conversions read the same from either
    if msg_type is Imu:
        for x, y in zip(imu_arrays(view), imu_arrays(reference)):
            np.testing.assert_array_equal(x, y)
    if msg_type is JointState:
        try:
            expected = chassis_reading(reference), powertrain_reading(reference)
        except MalformedMessage:
            with pytest.raises(MalformedMessage):
                chassis_reading(view)
        else:
            got = chassis_reading(view), powertrain_reading(view)
            np.testing.assert_array_equal(got[0].wheel_speeds, expected[0].wheel_speeds)
            np.testing.assert_array_equal(got[0].brake_torques, expected[0].brake_torques)
            assert same_float(got[0].steering_wheel_angle, expected[0].steering_wheel_angle)
            for field in dataclasses.fields(expected[1]):
                assert same_float(getattr(got[1], field.name), getattr(expected[1], field.name))
    if msg_type in (Odometry, TwistWithCovarianceStamped):
        got, want = forward_speed_entry(view), forward_speed_entry(reference)
        assert (got is None) == (want is None)
        if got is not None:
            assert got[0] == want[0] and all(same_float(a, b) for a, b in zip(got[1], want[1]))


# ============================================================================ 2. cores
# ------------------------------------------------------------------ error-state EKF (paper 003)
@functools.cache
def _aligned_fusion(estimate_mounting: bool) -> FusionEKF:
    """A filter aligned at standstill on level ground (then waiting for its heading)."""
    ekf = FusionEKF(FusionConfig(estimate_mounting=estimate_mounting,
                                 nh_sigma_z=1.0 if estimate_mounting else 15.0))
    f, w = np.array([0.0, 0.0, G]), np.full(3, 1e-3)
    for i in range(250):
        ekf.update_speed(i * 0.005, 0.0)
        ekf.process_imu(i * 0.005, f, w)
    assert ekf.status == "waiting_for_heading"
    return ekf


fusion_step = st.tuples(
    dt_strategy(0.05, 2.0),
    st.lists(physical(-15.0, 15.0, 1e3), min_size=3, max_size=3),      # specific force - g e_z [m/s^2]
    st.lists(physical(-2.0, 2.0, 50.0), min_size=3, max_size=3),       # angular rate [rad/s]
    st.one_of(st.none(), physical(-5.0, 60.0, 1e4)),                  # CAN speed [m/s]
    st.one_of(st.none(), st.tuples(st.lists(physical(-500.0, 500.0, 1e6), min_size=3, max_size=3),
                                   st.one_of(st.none(), st.lists(st.floats(1e-2, 1e3), min_size=3,
                                                                 max_size=3)))),
)


def _check_fusion(ekf: FusionEKF) -> None:
    assert_finite(ekf.position_enu, ekf.velocity_enu, ekf.velocity_body, ekf.quaternion, ekf.rotation_matrix,
                  ekf.accel_bias, ekf.gyro_bias, ekf.mounting_rpy, ekf.roll, ekf.pitch, ekf.yaw, ekf.road_grade)
    assert abs(np.linalg.norm(ekf.quaternion) - 1.0) < 1e-9
    assert_covariance(ekf.covariance, "P")
    for name in ("position_covariance", "velocity_covariance", "velocity_body_covariance",
                 "attitude_covariance", "accel_bias_covariance", "gyro_bias_covariance",
                 "mounting_covariance"):
        assert_covariance(getattr(ekf, name), name)
    var = ekf.road_grade_variance
    assert math.isfinite(var) and var >= -1e-12


@SEQ
@given(st.sampled_from(["scratch", "aligned", "running"]), st.booleans(),
       st.lists(fusion_step, min_size=1, max_size=40))
def test_fusion_ekf_random_inputs(start, mounting, steps):
    if start == "scratch":
        ekf = FusionEKF(FusionConfig(estimate_mounting=mounting, nh_sigma_z=1.0 if mounting else 15.0,
                                     init_stationary_samples=5, in_motion_window_s=1.0))
        t = 0.0
    else:
        ekf = copy.deepcopy(_aligned_fusion(mounting))
        if start == "running":
            ekf.status = "running"          # skip the heading phase (as test_esekf's stress test)
        t = ekf.time
    for dt, f, w, speed, gnss in steps:
        t += dt
        ekf.process_imu(t, np.asarray(f) + [0.0, 0.0, G], w)
        if speed is not None:
            ekf.update_speed(t, speed)
        if gnss is not None:
            pos, cov = gnss
            ekf.update_gnss(t, pos, None if cov is None else np.diag(cov))
        _check_fusion(ekf)


# ------------------------------------------------------------------ slope observers (paper 004 / 003)
slope_step = st.tuples(
    dt_strategy(0.05, 1.0),
    physical(-15.0, 15.0, 1e3),                               # ax specific force [m/s^2]
    physical(-5.0, 60.0, 1e4),                                # vx [m/s]
    physical(-1.0, 1.0, 50.0),                                # yaw rate [rad/s]
    physical(-3.0, 3.0, 1e3),                                 # vy [m/s]
    st.one_of(st.none(), st.floats(1e-6, 10.0)),              # vx variance
)

SLOPE_OBSERVERS = {
    "classical_kalman": lambda: ClassicalSlopeObserver(),
    "classical_cubic": lambda: ClassicalSlopeObserver(ClassicalSlopeConfig(
        gain_mode="luenberger", luenberger_gain=(4.2, -0.92), cubic_kappa=1.5)),
    "cubic_prediction": lambda: CubicPredictionSlopeObserver(
        CubicPredictionSlopeConfig(prediction_warmup_s=0.2, fit_min_span_m=0.5)),
    "cubic_prediction_kalman": lambda: CubicPredictionSlopeObserver(
        CubicPredictionSlopeConfig(gain_mode="kalman", prediction_warmup_s=0.2)),
}


@SEQ
@given(st.sampled_from(sorted(SLOPE_OBSERVERS)), st.lists(slope_step, min_size=1, max_size=60))
def test_slope_observers_random_inputs(kind, steps):
    obs = SLOPE_OBSERVERS[kind]()
    ts = stamps([s[0] for s in steps])
    for t, (_, ax, vx, r, vy, var) in zip(ts, steps):
        obs.step(t, ax, vx, yaw_rate=r, vy=vy, vx_variance=var)
        assert_finite(obs.slope, obs.variance, obs.speed, what=kind)
        assert obs.variance >= 0.0
        assert_covariance(obs._P, f"{kind} P")
        if isinstance(obs, CubicPredictionSlopeObserver):
            assert_finite(obs.slope_rate)


@SEQ
@given(st.sampled_from([1, 25]), st.lists(st.tuples(dt_strategy(0.05, 1.0), physical(-0.5, 0.5, 100.0),
                                                   st.floats(0.0, 1.0)), min_size=1, max_size=60))
def test_pitch_grade_slope_random_inputs(window, steps):
    est = PitchGradeSlope(PitchGradeConfig(lwma_window=window))
    ts = stamps([s[0] for s in steps])
    for t, (_, grade, var) in zip(ts, steps):
        assert est.step(t, grade, var)
        assert_finite(est.slope, est.variance)
        assert est.variance >= 0.0
        lo, hi = min(est._grades), max(est._grades)          # a weighted mean of the buffer
        assert lo - 1e-12 * abs(lo) <= est.slope <= hi + 1e-12 * abs(hi)


# ------------------------------------------------------------------ vehicle state (paper 004 / 002)
vehicle_step = st.tuples(
    dt_strategy(0.05, 1.0),
    physical(-0.6, 0.6, 10.0),                                      # road-wheel steer [rad]
    st.one_of(st.lists(physical(0.0, 200.0, 1e4), min_size=4, max_size=4),   # wheel speeds [rad/s]
              st.just([math.nan] * 4)),                             # ... or none (fallback)
    physical(-0.3, 0.3, 3.0),                                       # slope [rad]
    st.one_of(st.none(), st.floats(800.0, 40000.0)),                # mass [kg]
    st.lists(physical(-15.0, 15.0, 1e3), min_size=2, max_size=2),  # IMU ax, ay [m/s^2]
    physical(-2.0, 2.0, 50.0),                                      # yaw rate [rad/s]
    st.one_of(st.none(), st.tuples(physical(-5.0, 60.0, 1e4), st.floats(1e-4, 10.0))),  # CAN speed
)

VEHICLE_STATE = {
    "ckf": lambda: VehicleStateCKF(SEDAN),
    "vbackf": lambda: VehicleStateVBACKF(SEDAN),
    "aoukf": lambda: VehicleStateAOUKF(SEDAN, AOUKFConfig(filter="aoukf")),
    "ukf": lambda: VehicleStateAOUKF(SEDAN, AOUKFConfig(filter="ukf")),
    "ekf": lambda: VehicleStateAOUKF(SEDAN, AOUKFConfig(filter="ekf")),
}


_NO_WHEELS, _LOCKED = [math.nan] * 4, [0.0] * 4


@SEQ
@given(st.sampled_from(sorted(VEHICLE_STATE)), st.lists(vehicle_step, min_size=1, max_size=30))
# Found by this test (VehicleStateCKF before the moments check in step): a 5e4 rad/s yaw rate,
# or a -1e4 m/s speed, drove the model to ~1e13 m/s and left a finite but indefinite P
# (variances of -6e29) or made the next update raise LinAlgError.
@example(kind="ckf", steps=[(0.03125, 0.0, _NO_WHEELS, 0.0, None, [0.0, 0.0], 0.0, None),
                            (0.03125, 0.0, _LOCKED, 0.0, None, [0.0, 0.0], 5e4, None),
                            (0.03125, 0.0, _LOCKED, 0.0, None, [0.0, 0.0], 0.0, None)])
@example(kind="ckf", steps=[(0.03125, 0.0, _NO_WHEELS, 0.0, None, [0.0, 0.0], 0.0, (-1e4, 1.0)),
                            (0.25, 10.0, _LOCKED, 0.2890625, None, [0.0, 0.0], 0.0, None)])
@example(kind="ckf", steps=[(0.03125, 0.0, _NO_WHEELS, 0.0, None, [0.0, 0.0], 0.0, (1e4, 1.0)),
                            (0.25, 0.0, [0.0, 1e4, 0.0, 0.0], 3.0, None, [0.0, 0.0], 0.0, None)])
def test_vehicle_state_filters_random_inputs(kind, steps):
    est = VEHICLE_STATE[kind]()
    ts = stamps([s[0] for s in steps])
    for t, (_, steer, wheels, slope, mass, a, r, speed) in zip(ts, steps):
        u = VehicleInputs(steer, np.asarray(wheels, float), slope, mass)
        est.step(t, u, [a[0], a[1], r])
        if speed is not None:
            est.update_speed(*speed)
        assert_finite(est.x, what=f"{kind} state")
        assert_covariance(est.P, f"{kind} P")
        assert_finite(est.sideslip)
        var = est.sideslip_variance
        assert var >= 0.0 and not math.isnan(var)              # inf (documented) near vx = vy = 0
        if kind == "vbackf":
            assert_covariance(est.measurement_noise, "E[R]")


def test_every_registered_state_filter_is_a_state_estimator():
    """What the state node relies on: each filter of the registry builds a core with the
    StateEstimator members, whose status() is text for /diagnostics."""
    from vehicle_estimation.estimators.interfaces import StateEstimator
    from vehicle_estimation.estimators.registry import STATE_FILTERS, StateSettings, with_state_settings

    settings = StateSettings(p0_diag=(10.0,) * 5, q_diag=(1e-3,) * 5, r_diag=(4e-2, 4e-2, 6e-5),
                             initial_vx=0.0, init_vx_from_wheel_speeds=True)
    expected_keys = {"ckf": set(), "vbackf": {"learnt R diagonal", "VB fallbacks"},
                     "aoukf": {"aoukf updates", "aoukf speckled_replaced", "GA-BPNN correction"}}
    assert set(STATE_FILTERS) == set(expected_keys)
    for name, method in STATE_FILTERS.items():
        config = method.config_type()
        if config is not None:
            config, shared = with_state_settings(config, settings)
            assert all(getattr(config, field) == getattr(settings, field) for field in shared)
        core = method.build(SEDAN, config, settings, None)
        assert isinstance(core, StateEstimator), name
        core.step(0.0, VehicleInputs(0.0, np.full(4, 20.0 / SEDAN.wheel_radius)), [0.0, 0.0, 0.0])
        status = core.status()
        assert expected_keys[name] <= set(status), (name, status)
        assert all(isinstance(k, str) and isinstance(v, str) for k, v in status.items())


def test_every_state_filter_starts_from_a_handed_over_state():
    """start_from: the next step begins at another filter's [vx, vy, r] and their covariance
    (a wheel speed, where there is one, still gives vx); moments that are not finite or not
    positive definite are ignored, and a reset forgets what was handed over."""
    from vehicle_estimation.estimators.registry import STATE_FILTERS, StateSettings, with_state_settings

    settings = StateSettings(p0_diag=(10.0,) * 5, q_diag=(1e-3,) * 5, r_diag=(4e-2, 4e-2, 6e-5),
                             initial_vx=0.0, init_vx_from_wheel_speeds=True)
    x = np.array([21.5, -0.4, 0.25])
    P = np.diag([0.3, 0.01, 1e-4])
    P[0, 1] = P[1, 0] = 0.02
    no_wheels = VehicleInputs(0.0, np.full(4, np.nan))
    for name, method in STATE_FILTERS.items():
        config = method.config_type()
        config = with_state_settings(config, settings)[0] if config is not None else None
        core = method.build(SEDAN, config, settings, None)
        unmeasured = [math.nan] * 3           # the first step then only starts the filter
        core.start_from(x, P)
        core.step(0.0, no_wheels, unmeasured)
        assert core.x[:3] == pytest.approx(x) and core.P[:3, :3] == pytest.approx(P), name
        core.start_from(x, P)
        core.step(1.0, VehicleInputs(0.0, np.full(4, 20.0 / SEDAN.wheel_radius)), unmeasured)
        assert core.x[:3] == pytest.approx([20.0, -0.4, 0.25]), name
        for bad_x, bad_P in ((np.array([np.nan, 0.0, 0.0]), P), (x, -P)):
            core.start_from(bad_x, bad_P)
            core.step(2.0, no_wheels, unmeasured)
            assert core.x[1:3] == pytest.approx([0.0, 0.0]), name       # from the prior
        core.start_from(x, P)
        core.reset()
        core.step(3.0, no_wheels, unmeasured)
        assert core.x[1:3] == pytest.approx([0.0, 0.0]), name


def test_speed_presence_holds_either_way():
    """A second without a speed sample is "lost" (from the first clock where none came yet), a
    second of samples without a gap over max_gap_s is "back"; shorter dropouts change nothing."""
    from vehicle_estimation.estimators.state.core import SpeedPresence

    presence = SpeedPresence(hold_s=1.0, max_gap_s=0.5)
    presence.clock(10.0)
    assert not presence.lost(10.9) and presence.lost(11.0) and not presence.ever
    for t in np.arange(11.0, 12.0, 0.1):          # 0.9 s of samples: not yet back
        presence.sample(t)
    assert not presence.back(11.95) and not presence.lost(11.95)
    presence.sample(12.05)
    assert presence.back(12.1) and presence.ever
    presence.sample(12.5)                          # a 0.45 s gap keeps the run
    assert presence.back(12.6) and not presence.lost(13.4) and presence.lost(13.5)
    presence.sample(14.2)                          # after the gap a new run: not back at once
    assert not presence.back(14.2) and not presence.lost(14.2)
    presence.reset()
    presence.clock(20.0)
    assert not presence.ever and presence.lost(21.0)


# ------------------------------------------------------------------ mass estimators (papers 003, 004, 000)
mass_step = st.tuples(
    dt_strategy(0.05, 2.0),
    physical(-5.0, 60.0, 1e4),                                        # vx [m/s]
    physical(-8.0, 8.0, 1e3),                                         # ax [m/s^2]
    physical(-0.3, 0.3, 3.0),                                         # slope [rad]
    st.one_of(st.just(math.nan), physical(-5e3, 3e4, 1e7)),           # drive force [N]
    st.one_of(st.just(math.nan), physical(-100.0, 600.0, 1e5)),       # engine torque [N m]
    st.one_of(st.just(math.nan), physical(0.0, 700.0, 1e5)),          # engine speed [rad/s]
    st.one_of(st.just(math.nan), st.floats(0.0, 1.0)),                # engine load [-]
    st.one_of(st.just(math.nan), st.integers(-1, 8).map(float)),      # gear
    st.one_of(st.just(math.nan), physical(0.0, 3000.0, 1e6)),         # brake torque [N m]
    physical(-math.pi, math.pi, 1e3),                                 # heading [rad]
)


def _check_forgetting_estimator(est) -> None:
    assert_finite(est.mass, est.raw_mass, est.variance, est.gain, est.residual_variance, what="mass output")
    assert est.variance >= 0.0 and est.gain > 0.0 and est.residual_variance >= 0.0
    assert est.config.min_mass <= est.mass <= est.config.max_mass


@SEQ
@given(st.sampled_from(["wheel", "propulsion", "tractive", "wind", "regression"]),
       st.lists(mass_step, min_size=1, max_size=60))
def test_rls_mass_estimator_random_inputs(kind, steps):
    cfg = MassRLSConfig()
    if kind in ("wheel", "propulsion", "tractive"):
        cfg = dataclasses.replace(cfg, drive_force_kind=kind)
    elif kind == "wind":
        cfg = dataclasses.replace(cfg, wind_compensation=True, wind_min_speed=2.0)
    else:
        cfg = dataclasses.replace(cfg, torque_regression=[10.0, 300.0, 0.01])
    est = LongitudinalMassEstimator(AUDI, cfg)
    ts = stamps([s[0] for s in steps])
    for t, (_, vx, ax, slope, force, torque, speed, load, gear, brake, heading) in zip(ts, steps):
        est.step(t, vx, ax, slope, drive_force=force, engine_torque=torque, engine_speed=speed,
                 engine_load=load, gear=gear, brake_torque=brake, heading=heading)
        _check_forgetting_estimator(est)
        if est.wind is not None:
            w = est.wind
            assert_finite(w.x, w.wind_enu, w.wind_std, w.wind_speed, w.wind_from_deg, w.nuisance_mass)
            assert_covariance(w.P, "wind P")


@SEQ
@given(st.booleans(), st.lists(mass_step, min_size=1, max_size=60))
def test_ffrls_mass_estimator_random_inputs(inertia, steps):
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(rotating_inertia_correction=inertia))
    ts = stamps([s[0] for s in steps])
    for t, (_, vx, ax, slope, force, torque, speed, load, gear, brake, _h) in zip(ts, steps):
        est.step(t, vx, ax, slope, drive_force=force, drive_torque=10.0 * torque, engine_torque=torque,
                 engine_speed=speed, engine_load=load, gear=gear, brake_torque=brake)
        _check_forgetting_estimator(est)


def _check_ta_aekf(est: TaAekfMassEstimator) -> None:
    assert_finite(est.ekf.x, est.mass, est.raw_mass, est.variance, what="ta_aekf output")
    assert est.ekf.x[1] > 0.0 and est.variance >= 0.0
    assert est.config.min_mass <= est.mass <= est.config.max_mass
    assert_covariance(est.ekf.P, "ta_aekf P")


@SEQ
@given(st.sampled_from([math.nan, 1e-15, 1.0]), st.booleans(), st.lists(mass_step, min_size=1, max_size=60))
def test_ta_aekf_without_network_random_inputs(fixed_tau, accel_from_speed, steps):
    est = TaAekfMassEstimator(TRUCK, TaAekfConfig(use_network=False, fixed_tau=fixed_tau,
                                                  accel_from_speed=accel_from_speed, accel_fit_samples=5))
    ts = stamps([s[0] for s in steps])
    for t, (_, vx, ax, slope, force, torque, speed, load, gear, brake, _h) in zip(ts, steps):
        est.step(t, vx, ax, slope, drive_force=force * 10.0, engine_torque=torque * 5.0, engine_speed=speed,
                 engine_load=load, gear=gear, brake_torque=brake)
        _check_ta_aekf(est)


@functools.cache
def _shipped_mass_model():
    pytest.importorskip("torch")
    from vehicle_estimation.estimators.mass.transformer.model import MassModel
    from vehicle_estimation.estimators.mass.ta_aekf import DEFAULT_MODEL_STEM
    return MassModel.load(DEFAULT_MODEL_STEM)


@settings(max_examples=2, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2 ** 32 - 1), st.floats(5.0, 25.0), st.floats(3000.0, 25000.0))
def test_ta_aekf_with_shipped_network_random_drive(seed, v0, force0):
    """One short random drive through the shipped transformer (Algorithm 1 with the network)."""
    model = _shipped_mass_model()
    est = TaAekfMassEstimator(TRUCK, TaAekfConfig(inference_period_steps=model.spec.block_steps), model=model)
    rng = np.random.default_rng(seed)
    n = model.spec.block_steps * model.spec.window + est.config.accel_fit_samples + 3 * model.spec.block_steps
    v, t = v0, 100.0
    for _ in range(n):
        t += 0.01
        force = force0 + rng.normal(0.0, 2000.0)
        v = max(2.0, v + rng.normal(0.2, 0.3) * 0.01)
        est.step(t, v + rng.normal(0.0, 0.02), math.nan, rng.normal(0.0, 0.02), drive_force=force)
        _check_ta_aekf(est)
    assert math.isfinite(est.last_network_mass)                  # the network did run
    assert est.network_updates + est.network_gated >= 1


# ------------------------------------------------------------------ wind estimator
@SEQ
@given(st.lists(st.tuples(dt_strategy(0.25, 30.0), physical(0.0, 60.0, 1e4), physical(-math.pi, math.pi, 1e3),
                          physical(-3.0, 5.0, 1e3), physical(-5e3, 3e4, 1e7)), min_size=1, max_size=60))
def test_wind_estimator_random_inputs(steps):
    w = WindEstimator(AUDI.air_density, AUDI.drag_area, 1500.0)
    ts = stamps([s[0] for s in steps])
    for t, (_, v, heading, phi, force) in zip(ts, steps):
        w.update(t, v, heading, phi, force)
        assert_finite(w.x, w.wind_enu, w.wind_std, w.wind_speed, w.wind_from_deg, w.nuisance_mass,
                      w.drag(v, heading), w.along(heading))
        assert w.wind_speed <= w.config.max_abs_wind + 1e-9
        assert_covariance(w.P, "wind P")
