"""Message-to-array conversions of the topic contract (no node state, easy to test)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.rotations import gravity_on_body_y, gravity_on_body_y_variance, yaw_of_quat
from vehicle_estimation.ros.cdr import per_view
from vehicle_estimation.ros.stamps import stamp_to_sec

NAN = float("nan")

# Physical plausibility limits of raw inputs: beyond them a value is a fault, not a reading.
MAX_SPECIFIC_FORCE = 160.0   # m/s^2, ~16 g: a car IMU saturates well below
MAX_ANGULAR_RATE = 35.0      # rad/s, ~2000 deg/s
MAX_SPEED = 100.0            # m/s, 360 km/h (README: 400 km/h is absurd)


class MalformedMessage(ValueError):
    """A message that cannot be read at all (e.g. JointState arrays of the wrong length)."""


class JointReading(NamedTuple):
    position: float = NAN
    velocity: float = NAN
    effort: float = NAN


_NO_JOINT = JointReading()


def joint_readings(msg: Any) -> dict[str, JointReading]:
    """Read a sensor_msgs/JointState into ``{name: JointReading}``.

    Each of position/velocity/effort may be empty (signal not provided) or as long as
    ``name``; anything else is malformed. Non-finite entries stay NaN: the caller decides
    what a missing signal means.
    """
    names = list(msg.name)
    n = len(names)
    arrays = []
    for field in ("position", "velocity", "effort"):
        values = list(getattr(msg, field))
        if len(values) not in (0, n):
            raise MalformedMessage(f"JointState.{field} has {len(values)} entries for {n} names")
        arrays.append(_finite_or_nan_list(values) if values else [NAN] * n)
    return dict(zip(names, map(JointReading, *arrays)))


def _finite_or_nan_list(values: list) -> list[float]:
    """:func:`_finite_or_nan` of each value; numbers (what a message holds) in one pass."""
    try:
        return [float(v) if math.isfinite(v) else NAN for v in values]
    except TypeError:
        return [_finite_or_nan(v) for v in values]


def _finite_or_nan(x: Any) -> float:
    try:
        value = float(x)
    except (TypeError, ValueError):
        return NAN
    return value if math.isfinite(value) else NAN


@dataclass(frozen=True)
class ChassisReading:
    """The chassis signals of ``vehicle/joint_states``."""

    wheel_speeds: np.ndarray          # (4,) rad/s [fl, fr, rl, rr], NaN where missing
    brake_torques: np.ndarray         # (4,) N m, NaN where missing
    steering_wheel_angle: float       # rad, NaN if missing

    @property
    def total_brake_torque(self) -> float:
        finite = [b for b in self.brake_torques.tolist() if math.isfinite(b)]
        return sum(finite, 0.0) if finite else NAN

    @property
    def fastest_wheel_speed(self) -> float:
        """The largest |wheel speed| reported [rad/s]; 0 without any."""
        return max((abs(w) for w in self.wheel_speeds.tolist() if math.isfinite(w)), default=0.0)


@per_view
def chassis_reading(msg: Any) -> ChassisReading:
    """The chassis signals of a ``vehicle/joint_states`` message (arrays read-only: one reading
    of a view is shared by the nodes of a process)."""
    joints = joint_readings(msg)
    wheels = [joints.get(name, _NO_JOINT) for name in topics.WHEEL_JOINTS]
    wheel_speeds = np.array([w.velocity for w in wheels])
    brake_torques = np.array([w.effort for w in wheels])
    wheel_speeds.flags.writeable = brake_torques.flags.writeable = False
    return ChassisReading(wheel_speeds, brake_torques, joints.get(topics.STEERING_JOINT, _NO_JOINT).position)


@dataclass(frozen=True)
class PowertrainReading:
    engine_speed: float     # rad/s
    engine_torque: float    # N m
    engine_load: float      # 0..1 (OBD-II PID 04)
    gear: float             # gear number, NaN if not reported
    drive_force: float      # N at the wheels


def powertrain_reading(msg: Any) -> PowertrainReading:
    joints = joint_readings(msg)
    engine = joints.get(topics.ENGINE_JOINT, _NO_JOINT)
    load = joints.get(topics.ENGINE_LOAD_JOINT, _NO_JOINT).position
    if math.isfinite(load) and not -0.01 <= load <= 1.01:
        load = NAN
    gear = joints.get(topics.GEAR_JOINT, _NO_JOINT).position
    if math.isfinite(gear) and (gear < 0.5 or gear > 40):
        gear = NAN
    return PowertrainReading(
        engine_speed=engine.velocity,
        engine_torque=engine.effort,
        engine_load=load,
        gear=gear,
        drive_force=joints.get(topics.DRIVE_JOINT, _NO_JOINT).effort,
    )


def imu_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """Specific force and angular rate of a sensor_msgs/Imu (body frame, REP-145)."""
    a, w = msg.linear_acceleration, msg.angular_velocity
    return np.array([a.x, a.y, a.z], dtype=float), np.array([w.x, w.y, w.z], dtype=float)


@per_view
def checked_imu_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray, str | None]:
    """:func:`imu_arrays` (read-only: one reading of a view is shared by the nodes of a
    process) and :func:`imu_rejection`'s verdict on them."""
    f, w = imu_arrays(msg)
    f.flags.writeable = w.flags.writeable = False
    return f, w, imu_rejection(f, w)


def imu_plausible(f: np.ndarray, w: np.ndarray) -> bool:
    """Finite IMU arrays (see :func:`imu_arrays`) within the physical limits above."""
    return bool(np.max(np.abs(f)) <= MAX_SPECIFIC_FORCE and np.max(np.abs(w)) <= MAX_ANGULAR_RATE)


def imu_rejection(f: np.ndarray, w: np.ndarray) -> str | None:
    """Why every node refuses an IMU sample (its rejection reason), None for a usable one.

    On the six floats in plain Python: every node checks every sample, and a NaN or an inf
    fails the range comparison too, so a usable sample costs one pass."""
    fl, wl = f.tolist(), w.tolist()
    if all(abs(v) <= MAX_SPECIFIC_FORCE for v in fl) and all(abs(v) <= MAX_ANGULAR_RATE for v in wl):
        return None
    if not all(math.isfinite(v) for v in fl + wl):
        return "imu:non_finite"
    return "imu:implausible"


def stated_covariance(covariance: Any) -> np.ndarray | None:
    """A 3 x 3 covariance an IMU message states (row by row), or None where it states none
    (REP-145: -1 first) or one that is not finite. All zeros, "unknown" to sensor_msgs/Imu,
    comes back as zeros."""
    if covariance[0] < 0.0 or not math.isfinite(sum(covariance)):   # a NaN or an inf makes the sum so
        return None
    return np.asarray(covariance, dtype=float).reshape(3, 3)


def add_stated_imu_covariances(total: np.ndarray, msg: Any) -> None:
    """Add the accelerometer's and the gyro's covariances an IMU message states (imu_link, row
    by row) to ``total[0]`` and ``total[1]``; one that is unknown (REP-145: -1 first) or not
    finite adds nothing."""
    for k, cov in enumerate((msg.linear_acceleration_covariance, msg.angular_velocity_covariance)):
        stated = stated_covariance(cov)
        if stated is not None:
            total[k] += stated.ravel()


def base_link_imu_variances(covariances: np.ndarray, mounting: np.ndarray) -> np.ndarray:
    """[ax, ay, yaw rate] variances in base_link of the accelerometer's and gyro's covariances
    ``covariances[0]``, ``covariances[1]`` in imu_link (row by row), turned by ``mounting``
    (imu_link -> base_link)."""
    diagonals = ((mounting @ covariances.reshape(2, 3, 3)) * mounting).sum(axis=2)   # of M C M^T
    return np.maximum(np.array([diagonals[0, 0], diagonals[0, 1], diagonals[1, 2]]), 0.0)


def speed_reading(msg: Any) -> tuple[float, float] | None:
    """(speed [m/s], variance [m^2/s^2] or NaN when the message gives none) of a
    ``vehicle/speed`` message, None for a non-finite or absurd speed."""
    v = msg.twist.twist.linear.x
    if not math.isfinite(v) or abs(v) > MAX_SPEED:
        return None
    var = msg.twist.covariance[0]
    return v, (var if math.isfinite(var) and var > 0.0 else math.nan)


#: Largest published vx standard deviation [m/s] of a speed that an observer may take as a
#: measurement, once the speed's scale share is taken out (:func:`measured_speed`). A wheel- or
#: CAN-aided vx has a few cm/s; a vx the state node dead-reckons from the accelerometer has its
#: growing uncertainty (and carries the very grade and bias an observer would estimate from it:
#: a closed loop that runs away).
MAX_MEASURED_SPEED_STD = 0.5


def measured_speed(vx: float, variance: float, scale_error_variance: float = 0.0) -> bool:
    """Whether a published vx is a measured speed, not a dead-reckoned one: its variance (NaN or
    <= 0: unknown, taken as measured), less what the speed's scale adds to a measured vx (the
    wheels' rolling radius, ``estimation/speed_scale``: 2 % of the speed without GNSS, so 0.7 m/s
    at 122 km/h), within :data:`MAX_MEASURED_SPEED_STD`. Told apart at the lookup, where the
    scale is known, not when the message arrives."""
    if not (math.isfinite(variance) and variance > 0.0):
        return True
    return variance - scale_error_variance * vx * vx <= MAX_MEASURED_SPEED_STD ** 2


def forward_speed_entry(msg: Any) -> tuple[float, tuple[float, float, float]] | None:
    """``(stamp, (stamp, vx, vx variance))`` of an Odometry or TwistWithCovarianceStamped, for a
    history. Both carry the body-frame forward speed in ``twist.twist.linear.x``; whether it is
    measured is the reader's to ask (:func:`measured_speed`)."""
    stamp = msg.header.stamp
    t = stamp_to_sec(stamp)
    v = msg.twist.twist.linear.x
    return (t, (t, v, float(msg.twist.covariance[0]))) if math.isfinite(v) else None


def odometry_entry(msg: Any) -> tuple[float, tuple[float, float, float]] | None:
    """``(stamp, (stamp, vx, yaw))`` of an Odometry, for a history: the body-frame forward
    speed and the ENU yaw of ``pose.pose.orientation`` (NaN when the quaternion is not finite
    or has zero norm; the speed alone is still usable)."""
    stamp = msg.header.stamp
    t = stamp_to_sec(stamp)
    v = msg.twist.twist.linear.x
    if not math.isfinite(v):
        return None
    q = msg.pose.pose.orientation
    return (t, (t, v, yaw_of_quat(q.x, q.y, q.z, q.w)))


def lateral_gravity_entry(msg: Any) -> tuple[float, tuple[float, float, float]] | None:
    """``(stamp, (stamp, g_y, variance of g_y))`` of the fusion's compensated IMU
    (``estimation/imu``), for a history: the share of gravity on the body y axis,
    ``R[2, 1] = sin(roll) cos(pitch)`` of the base_link -> ENU ``orientation``, and its variance
    from ``orientation_covariance`` (NaN where that is not given: all zeros, a negative diagonal).

    A body-fixed accelerometer reads ``g g_y`` on y on top of the lateral acceleration when the
    body rolls on its suspension or the road is banked. The attitude is the one that goes with
    the compensated specific force, not the odometry's: that one also carries what no sensor
    tells apart from a roll (the unaided lateral bias, the mounting roll), which cancels here."""
    stamp = msg.header.stamp
    t = stamp_to_sec(stamp)
    q = msg.orientation
    share = gravity_on_body_y(q.x, q.y, q.z, q.w)
    if math.isnan(share):
        return None
    c = msg.orientation_covariance
    cov_xx, cov_xy, cov_yy = float(c[0]), float(c[1]), float(c[4])
    given = cov_xx > 0.0 and cov_yy > 0.0
    variance = gravity_on_body_y_variance(q.x, q.y, q.z, q.w, cov_xx, cov_xy, cov_yy) if given else math.nan
    return (t, (t, share, variance))


def planar_velocity_entry(msg: Any) -> tuple[float, tuple[float, float, float, float]] | None:
    """``(stamp, (stamp, vx, vy, vx variance))`` of a TwistWithCovarianceStamped (the
    vehicle-state node's output), for a history (as :func:`forward_speed_entry`)."""
    stamp = msg.header.stamp
    t = stamp_to_sec(stamp)
    vx, vy = msg.twist.twist.linear.x, msg.twist.twist.linear.y
    return (t, (t, vx, vy, float(msg.twist.covariance[0]))) if math.isfinite(vx) and math.isfinite(vy) else None
