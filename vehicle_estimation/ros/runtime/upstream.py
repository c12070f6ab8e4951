"""Values from other nodes, looked up "as of" a stamp: histories, the companion encoding, the IMU bias.

A node never uses "whatever arrived last" from another node: that depends on scheduling. It
keeps each upstream topic in an :class:`UpstreamHistory` and asks for the value at the stamp of
the sensor message it is processing (minus a lag in replay, see ``sync``).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from geometry_msgs.msg import Vector3Stamped
from rclpy.serialization import deserialize_message

from vehicle_estimation.estimators.common.rotations import quat_to_rotmat, rotmat_from_euler
from vehicle_estimation.ros.cdr import StampedLayout
from vehicle_estimation.ros.conversions import measured_speed
from vehicle_estimation.ros.stamps import sec_to_ns, stamp_to_sec

#: An upstream value older than this, at the stamp it is wanted for, is missing [s].
STALE_AFTER_S = 1.0


def is_fresh(t: float, stamp: float) -> bool:
    """Whether a value stamped ``stamp`` still stands for stamp ``t``."""
    return t - stamp <= STALE_AFTER_S


@dataclass
class StampedValue:
    """A value from another node: estimate, variance, converged flag, at a stamp."""

    stamp: float
    value: float
    variance: float
    converged: bool


class UpstreamHistory:
    """Stamp-indexed recent values of one upstream topic, looked up "as of" a stamp.

    ``at(t)`` returns the newest entry with stamp <= t - lag. Entries are kept for
    ``horizon_s`` seconds of stamp time. Out-of-order arrivals are inserted in order.
    """

    def __init__(self, lag_s: float = 0.0, horizon_s: float = 5.0) -> None:
        self.lag_s = lag_s
        self.horizon_s = horizon_s
        self._stamps: list[float] = []
        self._values: list[Any] = []
        self.received = 0

    def add(self, stamp: float, value: Any) -> None:
        self.received += 1
        i = bisect.bisect_right(self._stamps, stamp)
        self._stamps.insert(i, stamp)
        self._values.insert(i, value)
        cutoff = self._stamps[-1] - self.horizon_s
        if self._stamps[0] < cutoff:
            k = bisect.bisect_left(self._stamps, cutoff)
            del self._stamps[:k]
            del self._values[:k]

    def at(self, t: float) -> Any | None:
        i = bisect.bisect_right(self._stamps, t - self.lag_s)
        return self._values[i - 1] if i > 0 else None

    def clear(self) -> None:
        self._stamps.clear()
        self._values.clear()

    @property
    def latest_stamp(self) -> float | None:
        return self._stamps[-1] if self._stamps else None


_COMPANION_LAYOUTS: dict[str, StampedLayout] = {}


def companion_bytes(stamp: float, value: float, variance: float, converged: bool,
                    frame_id: str = "base_link") -> bytes:
    """The stamped companion of a scalar estimate, serialized (what the nodes publish):
    a geometry_msgs/Vector3Stamped with x = value, y = variance, z = converged (1/0)."""
    layout = _COMPANION_LAYOUTS.get(frame_id)
    if layout is None:
        layout = _COMPANION_LAYOUTS[frame_id] = StampedLayout(frame_id, 3)
    return layout.pack(sec_to_ns(stamp), (float(value), float(variance), 1.0 if converged else 0.0))


def companion(stamp: float, value: float, variance: float, converged: bool,
              frame_id: str = "base_link") -> Vector3Stamped:
    """:func:`companion_bytes` as a message."""
    return deserialize_message(companion_bytes(stamp, value, variance, converged, frame_id), Vector3Stamped)


def companion_value(msg: Vector3Stamped) -> tuple[float, StampedValue] | None:
    """A companion message as a history entry; None when its value or variance is not finite."""
    t = stamp_to_sec(msg.header.stamp)
    v = msg.vector
    if not (math.isfinite(v.x) and math.isfinite(v.y)):
        return None
    return t, StampedValue(t, v.x, v.y, v.z > 0.5)


def speed_scale_at(history: UpstreamHistory, t: float) -> float:
    """The fusion's ``estimation/speed_scale`` at ``t`` as the speeds' consumers apply it: what the
    wheels and the CAN speed read over the true speed, 1 + k, with k shrunk by its own variance,
    k (1 - 4 var / k^2), and 0 within 2 sigma (a positive-part James-Stein estimate). Within 2
    sigma the scale is not told apart from a quantised speed's lasting offset, or from the CAN
    speed's own scale where the wheels have another; nor does it jump in when it is. 1 without a
    fresh estimate: the speeds as they are."""
    return _applied_speed_scale(history, t)[0]


def speed_scale_error_variance(history: UpstreamHistory, t: float) -> float:
    """The mean square of the scale error left in the speeds once :func:`speed_scale_at` is
    divided out: the published scale's variance plus the square of the part the shrinkage did
    not apply. It lasts (a tyre's radius), so a filter that weighs each wheel-speed sample as
    independent cannot average it down: its consumer adds it, times the speed squared, to the
    speed's published variance (a consider term). Without GNSS it is the fusion's prior, held.
    0 without a fresh estimate (no fusion: nothing is known of it)."""
    return _applied_speed_scale(history, t)[1]


def measured_speed_at(history: UpstreamHistory, t: float, speed_scale: UpstreamHistory) -> tuple | None:
    """The entry of ``history`` at ``t``, ``(stamp, vx, ..., vx variance)``
    (:func:`~vehicle_estimation.ros.conversions.forward_speed_entry`,
    :func:`~vehicle_estimation.ros.conversions.planar_velocity_entry`), if it is fresh and a
    measured speed, not a dead-reckoned one (:func:`~vehicle_estimation.ros.conversions.measured_speed`,
    with what the speed's scale adds taken out, ``speed_scale`` the fusion's); else None."""
    item = history.at(t)
    if item is None or not is_fresh(t, item[0]):
        return None
    return item if measured_speed(item[1], item[-1], speed_scale_error_variance(speed_scale, t)) else None


def _applied_speed_scale(history: UpstreamHistory, t: float) -> tuple[float, float]:
    item = history.at(t)
    if item is None or not is_fresh(t, item.stamp) or not item.variance >= 0.0:
        return 1.0, 0.0
    k = item.value - 1.0
    shrink = 1.0 - 4.0 * item.variance / (k * k) if k != 0.0 else 0.0
    applied = k * shrink if shrink > 0.0 else 0.0
    return 1.0 + applied, item.variance + (k - applied) ** 2


class FusionImuBias:
    """Bias correction of raw IMU samples with the fusion node's estimate.

    The fusion node publishes its accelerometer and gyro bias estimates on
    ``estimation/imu_bias`` (sensor_msgs/Imu: ``linear_acceleration`` = accelerometer bias,
    ``angular_velocity`` = gyro bias, both in the IMU's own frame, with their covariances;
    ``orientation`` = the IMU mounting, imu_link -> base_link) at a low rate: a bias changes
    over minutes, so 10 Hz is plenty and costs downstream nodes almost nothing.
    :meth:`correct` removes the bias and rotates the sample into base_link. Without fusion
    (not started, not yet initialised) samples keep their bias and are turned by the nominal
    mounting ``mounting_rpy`` (``vehicle.imu_mounting_rpy``), and :attr:`valid` is False.
    """

    def __init__(self, mounting_rpy=(0.0, 0.0, 0.0)) -> None:
        self.history = UpstreamHistory(horizon_s=5.0)
        self.valid = False
        self.nominal_mounting = rotmat_from_euler(*(float(a) for a in mounting_rpy))

    @staticmethod
    def convert(msg: Any) -> tuple[float, Any] | None:
        t = stamp_to_sec(msg.header.stamp)
        ba = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        bg = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        if not (np.isfinite(ba).all() and np.isfinite(bg).all()):
            return None
        o = msg.orientation
        q = np.array([o.x, o.y, o.z, o.w], dtype=float)
        norm = float(np.linalg.norm(q)) if np.isfinite(q).all() else 0.0
        # A publisher without a mounting leaves the quaternion at zero: identity.
        mount = quat_to_rotmat(q / norm) if norm > 0.5 else np.eye(3)
        # the along-track bias variance: the covariance is the IMU's, turned into base_link
        cov = np.reshape(np.asarray(msg.linear_acceleration_covariance, float), (3, 3))
        var = float((mount @ cov @ mount.T)[0, 0]) if np.isfinite(cov).all() else 0.0
        return t, (ba, bg, mount, var if var > 0.0 else 0.0)

    def correct(self, t: float, f: Any, w: Any) -> tuple[Any, Any]:
        entry = self.history.at(t)
        self.valid = entry is not None
        if entry is None:
            return self.nominal_mounting @ f, self.nominal_mounting @ w
        ba, bg, mount, _ = entry
        return mount @ (f - ba), mount @ (w - bg)

    def mounting_at(self, t: float) -> np.ndarray:
        """imu_link -> base_link for stamp ``t``: the fusion's refined mounting, else the nominal."""
        entry = self.history.at(t)
        return self.nominal_mounting if entry is None else entry[2]

    def accel_x_variance_at(self, t: float) -> float | None:
        """The along-track bias variance [m^2/s^4] published for stamp ``t``, None without the
        fusion."""
        entry = self.history.at(t)
        return None if entry is None else entry[3]

    def clear(self) -> None:
        self.history.clear()
        self.valid = False
