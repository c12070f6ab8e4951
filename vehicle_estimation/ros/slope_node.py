"""Road-slope node.

Methods (parameter ``method``):

* ``auto`` (default): ``fusion_pitch`` while the fusion grade is fresh and converged, else
  ``cubic_prediction``; both run all the time, so the observer is converged when the fusion
  grade drops out (no GNSS, fusion not aligned, upstream missing), and a switch fades the
  difference out instead of jumping (:mod:`vehicle_estimation.estimators.slope.auto`).
  ``/diagnostics`` names the source in use.
* ``fusion_pitch``: the grade of paper 003 Sec. 7.2, i.e. the pitch of the fusion
  node's error-state EKF (``estimation/fusion/road_grade``), smoothed as paper 003 Sec. 7.1 does.
* ``cubic_prediction``: paper 004 Sec. 5, the slope prediction model (Eqs. 15-20: the slope
  rate from a fit of recent slopes over travelled distance) with the cubic observer
  (Eqs. 21-27), on the bias-compensated longitudinal specific force and the vehicle speed.
* ``classical``: the contrast of paper 004 Eqs. 32-33 (θ̇ = 0 slope model).

Each method's tuning is declared as ``<method>.*`` parameters (its config dataclass); ``auto``
declares those of the two methods it combines too. The node builds the method from
:data:`vehicle_estimation.estimators.registry.SLOPE_METHODS` and finds its inputs at each IMU
stamp; the estimation, suspension pitch included, is
:class:`~vehicle_estimation.estimators.slope.road_slope.RoadSlopeEstimator`.

Subscribes: ``imu/data`` (sensor-data QoS, the trigger), ``vehicle/speed`` (sensor-data QoS,
speed fallback), ``estimation/imu_bias`` (fusion bias), ``estimation/fusion/road_grade``,
``estimation/vehicle_state`` (vx and vy from the state node, paper 004 Fig. 1: slope <- state).
Publishes ``estimation/road_slope`` (std_msgs/Float64, rad, +uphill) and
``estimation/road_slope_stamped`` (geometry_msgs/Vector3Stamped: x = slope, y = variance,
z = converged 1/0).
"""

from __future__ import annotations

import math

from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu
from std_msgs.msg import Float64

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.registry import SLOPE_METHODS
from vehicle_estimation.estimators.slope.road_slope import GradeSample
from vehicle_estimation.ros.conversions import forward_speed_entry, planar_velocity_entry
from vehicle_estimation.ros.cdr import float64_bytes
from vehicle_estimation.ros.runtime.node import EstimatorNode
from vehicle_estimation.ros.runtime.parameters import ParameterError, declared_by_a_method
from vehicle_estimation.ros.runtime.spin import run_node
from vehicle_estimation.ros.stamps import STAMP_TOLERANCE_S
from vehicle_estimation.ros.runtime.upstream import (
    FusionImuBias,
    UpstreamHistory,
    companion_bytes,
    companion_value,
    is_fresh,
    measured_speed_at,
)

#: Variance published while no estimate exists yet: a 10 deg 1-sigma prior.
PRIOR_VARIANCE = math.radians(10.0) ** 2


class SlopeNode(EstimatorNode):
    def parameter_of_another_method(self, name: str) -> bool:
        return declared_by_a_method(SLOPE_METHODS, name)

    def __init__(self, **node_kwargs) -> None:
        super().__init__("road_slope", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.method = self.declare_str(
            "method", "auto",
            "Slope method; auto: the fusion grade while it is fresh and converged, else the "
            "cubic_prediction observer on the IMU and a speed", tuple(SLOPE_METHODS))
        self.rate = self.declare_float("publish_rate_hz", 50.0, "Output rate [Hz]", 0.1, 1000.0)
        self.configs: dict[str, object] = {}
        self._make_core()
        self.bias = FusionImuBias(self.vehicle.imu_mounting_rpy)
        self.grade = UpstreamHistory()
        self.state_speed = UpstreamHistory()
        self.odom_speed = UpstreamHistory()
        self.speed_scale = UpstreamHistory()
        self.can_speed: tuple[float, float] | None = None
        self._last_pub = -math.inf

        self.pub = self.publisher(Float64, topics.ROAD_SLOPE)
        self.pub_stamped = self.publisher(Vector3Stamped, topics.ROAD_SLOPE_STAMPED)
        self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        # Subscribe only to what the method uses: every subscription costs CPU at 100-200 Hz.
        if self.core.uses_grade:
            self.subscribe_upstream(Vector3Stamped, topics.FUSION_GRADE, self.grade, companion_value)
        if self.core.uses_observer:
            self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
            self.subscribe_imu_bias(self.bias)
            self.subscribe_upstream(TwistWithCovarianceStamped, topics.VEHICLE_STATE, self.state_speed,
                                    planar_velocity_entry)
            self.subscribe_upstream(Odometry, topics.ODOMETRY, self.odom_speed, forward_speed_entry)
            # what the wheels' radius adds to a measured speed's variance: not dead reckoning
            self.subscribe_upstream(Vector3Stamped, topics.SPEED_SCALE, self.speed_scale, companion_value)

    def _config(self, prefix: str, defaults: object) -> object:
        """The ``<prefix>.*`` parameters as a config, declared on first use."""
        if prefix not in self.configs:
            self.configs[prefix] = self.declare_config(prefix, defaults)
        return self.configs[prefix]

    def _make_core(self) -> None:
        """``self.core``: the method's sources, from the registry (again after a reset)."""
        method = SLOPE_METHODS[self.method]
        config = self._config(method.config_prefix, method.config_type())
        try:
            self.core = method.build(self.vehicle, config, self._config)
        except ParameterError:
            raise
        except ValueError as exc:
            raise ParameterError(f"method '{self.method}': {exc}") from exc

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        reading = self.read_speed(msg)
        if reading is None:
            return
        self.can_speed = (t, reading[0])

    def velocity_at(self, t: float) -> tuple[float, float] | None:
        """(vx, vy) for the observer: state node, else fusion (vy 0), else CAN (vy 0)."""
        item = measured_speed_at(self.state_speed, t, self.speed_scale)
        if item is not None:
            return item[1], item[2]
        item = measured_speed_at(self.odom_speed, t, self.speed_scale)
        if item is not None:
            return item[1], 0.0
        if self.can_speed is not None and is_fresh(t, self.can_speed[0]):
            return self.can_speed[1], 0.0
        return None

    def on_imu(self, t: float, msg: Imu) -> None:
        imu = self.read_imu(msg)
        if imu is None:
            return
        f, w = imu
        grade = None
        if self.core.uses_grade:
            item = self.grade.at(t)
            missing = item is None or not is_fresh(t, item.stamp)
            # Where an observer stands in, a missing grade is a fallback, not a missing input.
            self.set_missing("fusion road grade", missing and self.core.requires_grade)
            grade = None if missing else GradeSample(item.value, item.variance, item.converged)
        velocity = None
        if self.core.uses_observer:
            f, w = self.bias.correct(t, f, w)
            velocity = self.velocity_at(t)
            self.set_missing("vehicle speed", velocity is None)
        for _ in range(self.core.step(t, float(f[0]), float(w[2]), grade=grade, velocity=velocity,
                                      accel_bias_variance=self.bias.accel_x_variance_at(t))):
            self.reject("slope:rejected_by_core")
        if t - self._last_pub >= 1.0 / self.rate - STAMP_TOLERANCE_S:
            self._last_pub = t
            self.publish_estimate(t)

    def publish_estimate(self, t: float) -> None:
        slope, variance, converged = self.core.slope, self.core.variance, self.core.converged
        if not (math.isfinite(slope) and math.isfinite(variance)):
            slope, variance, converged = 0.0, PRIOR_VARIANCE, False
        if self.missing:
            variance = max(variance, PRIOR_VARIANCE)
            converged = False
        self.publish(self.pub_stamped, companion_bytes(t, slope, variance, converged))
        self.publish(self.pub, float64_bytes(float(slope)))

    def reset_estimators(self) -> None:
        self._make_core()
        self.bias.clear()
        for history in (self.grade, self.state_speed, self.odom_speed, self.speed_scale):
            history.clear()
        self.can_speed = None
        self._last_pub = -math.inf

    def status_values(self) -> dict[str, str]:
        values = {"method": self.method, "slope [deg]": f"{math.degrees(self.core.slope):.3f}",
                  "converged": str(self.core.converged)}
        if self.core.uses_observer:
            values["imu bias from fusion"] = str(self.bias.valid)
        values.update(self.core.status())
        return values


def main(args: list[str] | None = None) -> int:
    return run_node(SlopeNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
