"""Mass node: recursive least squares with forgetting on the longitudinal dynamics.

Method (parameter ``method``): ``rls``, paper 003 Secs. 2-4 (Eqs. 4-11). The propulsion
force comes, in this order, from ``drive`` (tractive force at the wheels, if the vehicle
reports it), from engine torque x gearing (gear reported, or predicted from the engine to
vehicle speed ratio, Eqs. 10-11), or from engine load and speed through the torque
regression of Eq. 49 (coefficients in ``mass.torque_regression``). With none of them the
node keeps publishing its prior with a large variance and says so in ``/diagnostics``.

Subscribes (sensor-data QoS): ``vehicle/powertrain`` (the trigger), ``vehicle/joint_states``
(brake torque), ``imu/data`` (longitudinal specific force), ``vehicle/speed`` (fallback speed).
From other nodes: ``estimation/imu`` (fusion bias), ``estimation/odometry`` (speed),
``estimation/road_slope_stamped``. The longitudinal acceleration is the bias-compensated
specific force minus g·sin(slope), smoothed with the 25-sample linearly weighted moving
average of paper 003 Sec. 7.1.

Publishes ``estimation/mass`` (std_msgs/Float64, kg) and ``estimation/mass_stamped``
(geometry_msgs/Vector3Stamped: x = mass, y = variance [kg^2], z = converged 1/0).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

from vehicle_estimation import topics
from vehicle_estimation.core.mass_rls import LongitudinalMassEstimator, MassRLSConfig
from vehicle_estimation.nodes.base import (
    EstimatorNode, FusionImuBias, ParameterError, UpstreamHistory, companion, companion_value,
    run_node, stamp_to_sec)
from vehicle_estimation.nodes.conversions import (
    MalformedMessage, chassis_reading, imu_arrays, powertrain_reading)

METHODS = ("rls",)
STALE_AFTER_S = 1.0


class LinearlyWeightedMovingAverage:
    """LWMA over the last ``n`` samples, newest weighted n, oldest 1 (paper 003 Sec. 7.1)."""

    def __init__(self, n: int) -> None:
        self.values: deque[float] = deque(maxlen=n)
        self.weights = np.arange(1, n + 1, dtype=float)

    def add(self, x: float) -> float:
        self.values.append(x)
        w = self.weights[-len(self.values):]
        return float(np.dot(w, self.values) / w.sum())

    def clear(self) -> None:
        self.values.clear()


class MassNode(EstimatorNode):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("mass", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.method = self.declare_str("method", "rls", "Mass estimation method", METHODS)
        self.rate = self.declare_float("publish_rate_hz", 10.0, "Output rate [Hz]", 0.1, 1000.0)
        self.accel_window = self.declare_int(
            "accel_filter_samples", 25, "LWMA length on the IMU acceleration (paper 003: 25)", 1, 1000)
        defaults = MassRLSConfig()
        overrides = {}
        for name, value in vars(defaults).items():
            if isinstance(value, bool):
                overrides[name] = self.declare_bool(f"mass.{name}", value, f"MassRLSConfig.{name}")
            elif isinstance(value, (int, float)):
                overrides[name] = type(value)(self.declare_float(
                    f"mass.{name}", float(value), f"MassRLSConfig.{name} (paper 003 default)"))
            elif isinstance(value, (list, tuple)):
                overrides[name] = type(value)(self.declare_float_array(
                    f"mass.{name}", list(value), f"MassRLSConfig.{name}"))
        try:
            self.config = MassRLSConfig(**{**vars(defaults), **overrides})
            self.config.validate()
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"mass.*: {exc}") from exc
        self.core = LongitudinalMassEstimator(self.vehicle, self.config)
        self.bias = FusionImuBias()
        self.accel_filter = LinearlyWeightedMovingAverage(self.accel_window)
        self.ax_specific: float | None = None
        self.slope = UpstreamHistory()
        self.odom_speed = UpstreamHistory()
        self.can_speed: tuple[float, float] | None = None
        self.brake_torque = 0.0
        self.brake_t = -math.inf
        self._last_pub = -math.inf

        self.pub = self.publisher(Float64, topics.MASS)
        self.pub_stamped = self.publisher(Vector3Stamped, topics.MASS_STAMPED)
        self.subscribe_primary(JointState, topics.POWERTRAIN, self.on_powertrain)
        self.subscribe_primary(JointState, topics.JOINT_STATES, self.on_joint_states)
        self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
        self.subscribe_imu_bias(self.bias)
        self.subscribe_upstream(Odometry, topics.ODOMETRY, self.odom_speed, _odom_speed)
        self.subscribe_upstream(Vector3Stamped, topics.ROAD_SLOPE_STAMPED, self.slope, companion_value)

    # -------------------------------------------------------------- inputs
    def on_imu(self, t: float, msg: Imu) -> None:
        f, w = imu_arrays(msg)
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(w))) or abs(f[0]) > 160.0:
            self.reject("imu:invalid")
            return
        f, _ = self.bias.correct(t, f, w)
        self.ax_specific = self.accel_filter.add(float(f[0]))

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        v = msg.twist.twist.linear.x
        if math.isfinite(v) and abs(v) < 120.0:
            self.can_speed = (t, v)
        else:
            self.reject("speed:invalid")

    def on_joint_states(self, t: float, msg: JointState) -> None:
        try:
            total = chassis_reading(msg).total_brake_torque
        except MalformedMessage:
            self.reject("joint_states:malformed")
            return
        if math.isfinite(total):
            self.brake_torque, self.brake_t = max(total, 0.0), t

    def on_powertrain(self, t: float, msg: JointState) -> None:
        try:
            pt = powertrain_reading(msg)
        except MalformedMessage:
            self.reject("powertrain:malformed")
            return
        speed = self._speed_at(t)
        slope_item = self.slope.at(t)
        slope_ok = slope_item is not None and t - slope_item.stamp <= STALE_AFTER_S
        self.set_missing("road slope", not slope_ok)
        self.set_missing("vehicle speed", speed is None)
        self.set_missing("acceleration (imu/data)", self.ax_specific is None)
        if speed is not None and self.ax_specific is not None:
            slope = slope_item.value if slope_ok else 0.0
            ax = self.ax_specific - self.vehicle.gravity * math.sin(slope)
            brake = self.brake_torque if t - self.brake_t <= STALE_AFTER_S else 0.0
            self.core.step(t, speed, ax, slope, drive_force=pt.drive_force,
                           engine_torque=pt.engine_torque, engine_speed=pt.engine_speed,
                           engine_load=pt.engine_load, gear=pt.gear, brake_torque=brake)
        if t - self._last_pub >= 1.0 / self.rate - 1e-9:
            self._last_pub = t
            self.publish_estimate(t)

    def _speed_at(self, t: float) -> float | None:
        item = self.odom_speed.at(t)
        if item is not None and t - item[0] <= STALE_AFTER_S:
            return item[1]
        if self.can_speed is not None and t - self.can_speed[0] <= STALE_AFTER_S:
            return self.can_speed[1]
        return None

    # -------------------------------------------------------------- outputs
    def publish_estimate(self, t: float) -> None:
        mass, variance, converged = float(self.core.mass), float(self.core.variance), bool(self.core.converged)
        if not (math.isfinite(mass) and math.isfinite(variance)):
            self.reject("mass:non_finite")
            self.note_event("mass estimate became non-finite: resetting to the prior")
            self.core.reset()
            mass, variance, converged = float(self.core.mass), float(self.core.variance), False
        self.publish(self.pub_stamped, companion(t, mass, variance, converged))
        self.publish(self.pub, Float64(data=mass))

    def reset_estimators(self) -> None:
        self.core.reset()
        self.bias.clear()
        self.accel_filter.clear()
        self.ax_specific = None
        self.slope.clear()
        self.odom_speed.clear()
        self.can_speed = None
        self._last_pub = -math.inf

    def status_values(self) -> dict[str, str]:
        values = {"method": self.method, "mass [kg]": f"{self.core.mass:.1f}",
                  "converged": str(self.core.converged),
                  "samples used": str(self.core.samples_used)}
        for k, v in self.core.rejected.items():
            values[f"samples skipped: {k}"] = str(v)
        return values


def _odom_speed(msg: Odometry) -> tuple[float, tuple[float, float]] | None:
    t = stamp_to_sec(msg.header.stamp)
    v = msg.twist.twist.linear.x
    return (t, (t, v)) if math.isfinite(v) else None


def main(args: list[str] | None = None) -> int:
    return run_node(MassNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
