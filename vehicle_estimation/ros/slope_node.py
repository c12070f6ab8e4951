"""Road-slope node.

Methods (parameter ``method``):

* ``auto`` (default): ``fusion_pitch`` while the fusion grade is fresh and converged, else
  ``cubic_prediction``; both run all the time, so the observer is converged when the fusion
  grade drops out (no GNSS, fusion not aligned, upstream missing), and a switch fades the
  difference out instead of jumping (:mod:`vehicle_estimation.estimators.slope.slope_auto`).
  ``/diagnostics`` names the source in use.
* ``fusion_pitch``: the grade of paper 003 Sec. 7.2, i.e. the pitch of the fusion
  node's error-state EKF (``estimation/fusion/road_grade``), smoothed as paper 003 Sec. 7.1 does.
* ``cubic_prediction``: paper 004 Sec. 5, the slope prediction model (Eqs. 15-20: the slope
  rate from a fit of recent slopes over travelled distance) with the cubic observer
  (Eqs. 21-27), on the bias-compensated longitudinal specific force and the vehicle speed.
* ``classical``: the contrast of paper 004 Eqs. 32-33 (θ̇ = 0 slope model).

Each method's tuning is declared as ``<method>.*`` parameters (its config dataclass).

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
from vehicle_estimation.estimators.slope import slope as slope_core
from vehicle_estimation.estimators.slope.slope_auto import (
    SOURCE_FUSION,
    AutoSlope,
    AutoSlopeConfig,
)
from vehicle_estimation.ros.conversions import (
    MAX_SPEED,
    forward_speed_entry,
    imu_arrays,
    imu_plausible,
    planar_velocity_entry,
)
from vehicle_estimation.ros.runtime.node import EstimatorNode
from vehicle_estimation.ros.runtime.parameters import ParameterError
from vehicle_estimation.ros.runtime.spin import run_node
from vehicle_estimation.ros.runtime.stamps import STAMP_TOLERANCE_S
from vehicle_estimation.ros.runtime.upstream import (
    FusionImuBias,
    UpstreamHistory,
    companion,
    companion_value,
    is_fresh,
)

METHODS = ("auto", *slope_core.SLOPE_METHODS)
CONFIGS = {"classical": slope_core.ClassicalSlopeConfig,
           "cubic_prediction": slope_core.CubicPredictionSlopeConfig,
           "fusion_pitch": slope_core.PitchGradeConfig}
#: Variance published while no estimate exists yet: a 10 deg 1-sigma prior.
PRIOR_VARIANCE = math.radians(10.0) ** 2


class SuspensionPitch:
    """Body pitch on the suspension from longitudinal acceleration (squat and dive).

    The fusion pitch is the IMU's, i.e. the body's; the road's grade is that minus the pitch
    the suspension adds, ``pitch_gain * a_x`` through a first-order lag of
    ``pitch_time_constant`` (vehicle parameters). Uncorrected, it makes the grade error follow
    the acceleration, which is exactly what the mass estimator's regressor cannot tolerate.
    """

    def __init__(self, gain: float, time_constant: float) -> None:
        self.gain, self.tau = gain, time_constant
        self.state = 0.0
        self.t: float | None = None

    def update(self, t: float, accel: float) -> float:
        if not math.isfinite(accel):
            return self.state
        target = self.gain * accel
        if self.t is None or self.tau <= 0.0:
            self.state = target
        else:
            dt = min(max(t - self.t, 0.0), 1.0)
            self.state += (target - self.state) * (1.0 - math.exp(-dt / self.tau))
        self.t = t
        return self.state

    def reset(self) -> None:
        self.state, self.t = 0.0, None


class SlopeNode(EstimatorNode):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("road_slope", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.method = self.declare_str(
            "method", "auto",
            "Slope method; auto: the fusion grade while it is fresh and converged, else the "
            "cubic_prediction observer on the IMU and a speed", METHODS)
        self.rate = self.declare_float("publish_rate_hz", 50.0, "Output rate [Hz]", 0.1, 1000.0)
        # The cores this method steps: the fusion grade, the IMU + speed observer, or both.
        self.uses_grade = self.method in ("auto", "fusion_pitch")
        self.uses_observer = self.method != "fusion_pitch"
        self.observer_method = "cubic_prediction" if self.method == "auto" else self.method
        self.configs = {}
        if self.uses_grade:
            self.configs["fusion_pitch"] = self.declare_config("fusion_pitch", CONFIGS["fusion_pitch"]())
        if self.uses_observer:
            self.configs[self.observer_method] = self.declare_config(
                self.observer_method, CONFIGS[self.observer_method]())
        if self.method == "auto":
            self.auto_config = self.declare_config("auto", AutoSlopeConfig())
        self._make_cores()
        self.squat = SuspensionPitch(self.vehicle.pitch_gain, self.vehicle.pitch_time_constant)
        self.bias = FusionImuBias()
        self.grade = UpstreamHistory()
        self.state_speed = UpstreamHistory()
        self.odom_speed = UpstreamHistory()
        self.can_speed: tuple[float, float] | None = None
        self._last_pub = -math.inf

        self.pub = self.publisher(Float64, topics.ROAD_SLOPE)
        self.pub_stamped = self.publisher(Vector3Stamped, topics.ROAD_SLOPE_STAMPED)
        self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        # Subscribe only to what the method uses: every subscription costs CPU at 100-200 Hz.
        if self.uses_grade:
            self.subscribe_upstream(Vector3Stamped, topics.FUSION_GRADE, self.grade, companion_value)
        if self.uses_observer:
            self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
            self.subscribe_imu_bias(self.bias)
            self.subscribe_upstream(TwistWithCovarianceStamped, topics.VEHICLE_STATE, self.state_speed,
                                    planar_velocity_entry)
            self.subscribe_upstream(Odometry, topics.ODOMETRY, self.odom_speed, forward_speed_entry)

    def _make_cores(self) -> None:
        """``self.core`` is what is published: the one core, or the auto selection of two."""
        try:
            self.grade_core = (slope_core.PitchGradeSlope(self.configs["fusion_pitch"])
                               if self.uses_grade else None)
            self.observer = (slope_core.SLOPE_METHODS[self.observer_method](self.configs[self.observer_method])
                             if self.uses_observer else None)
            if self.method == "auto":
                self.core = AutoSlope(self.grade_core, self.observer, self.auto_config)
            else:
                self.core = self.grade_core if self.grade_core is not None else self.observer
        except ValueError as exc:
            raise ParameterError(f"method '{self.method}': {exc}") from exc

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        v = msg.twist.twist.linear.x
        if math.isfinite(v) and abs(v) <= MAX_SPEED:
            self.can_speed = (t, v)
        else:
            self.reject("speed:invalid")

    def velocity_at(self, t: float) -> tuple[float, float] | None:
        """(vx, vy) for the observer: state node, else fusion (vy 0), else CAN (vy 0)."""
        item = self.state_speed.at(t)
        if item is not None and is_fresh(t, item[0]):
            return item[1], item[2]
        item = self.odom_speed.at(t)
        if item is not None and is_fresh(t, item[0]):
            return item[1], 0.0
        if self.can_speed is not None and is_fresh(t, self.can_speed[0]):
            return self.can_speed[1], 0.0
        return None

    def on_imu(self, t: float, msg: Imu) -> None:
        f, w = imu_arrays(msg)
        if not all(math.isfinite(x) for x in (*f, *w)):
            self.reject("imu:non_finite")
            return
        if not imu_plausible(f, w):
            self.reject("imu:implausible")
            return
        grade_usable = False
        fresh_grade = None
        if self.grade_core is not None:
            item = self.grade.at(t)
            missing = item is None or not is_fresh(t, item.stamp)
            # With auto the observer takes over: a fallback, not a missing input.
            self.set_missing("fusion road grade", missing and self.method == "fusion_pitch")
            fresh_grade = None if missing else item
        if self.observer is not None:
            f, w = self.bias.correct(t, f, w)
        # The body's pitch on its suspension (one filter step per IMU sample), driven by the
        # acceleration less gravity along the best slope known now: it tilts both the fusion
        # pitch and the accelerometer, so both sources take it out to get the road's grade.
        reference = (fresh_grade.value if fresh_grade is not None
                     else self.observer.slope if self.observer is not None else 0.0)
        squat = self.squat.update(t, float(f[0]) - self.vehicle.gravity * math.sin(reference))
        if fresh_grade is not None:
            if not self.grade_core.step(t, fresh_grade.value - squat, fresh_grade.variance):
                self.reject("slope:rejected_by_core")
            grade_usable = fresh_grade.converged and self.grade_core.converged
        if self.observer is not None:
            velocity = self.velocity_at(t)
            self.set_missing("vehicle speed", velocity is None)
            # Eq. 21: a_x,acc = vx' - r vy + g theta (the observer adds r vy back).
            ax = float(f[0]) - self.vehicle.gravity * math.sin(squat)
            if velocity is not None and not self.observer.step(t, ax, velocity[0],
                                                               yaw_rate=float(w[2]), vy=velocity[1]):
                self.reject("slope:rejected_by_core")
        if isinstance(self.core, AutoSlope):
            # The accelerometer bias left in the observer's input goes into its slope one to one:
            # the fusion's bias uncertainty, or without the fusion the sensor's turn-on bias.
            bias_variance = self.bias.accel_x_variance_at(t)
            if bias_variance is None:
                bias_variance = self.auto_config.uncompensated_accel_bias_std ** 2
            self.core.update(t, grade_usable, bias_variance / self.vehicle.gravity ** 2)
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
        self.publish(self.pub_stamped, companion(t, slope, variance, converged))
        self.publish(self.pub, Float64(data=float(slope)))

    def reset_estimators(self) -> None:
        self._make_cores()
        self.squat.reset()
        self.bias.clear()
        for history in (self.grade, self.state_speed, self.odom_speed):
            history.clear()
        self.can_speed = None
        self._last_pub = -math.inf

    def status_values(self) -> dict[str, str]:
        values = {"method": self.method, "slope [deg]": f"{math.degrees(self.core.slope):.3f}",
                  "converged": str(self.core.converged)}
        if self.observer is not None:
            values["imu bias from fusion"] = str(self.bias.valid)
        if isinstance(self.core, AutoSlope):
            values["slope source"] = (
                "fusion_pitch (fusion grade)" if self.core.source == SOURCE_FUSION
                else "cubic_prediction (IMU + speed observer: fusion grade missing or not converged)")
            values["slope source switches"] = str(self.core.switches)
        return values




def main(args: list[str] | None = None) -> int:
    return run_node(SlopeNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
