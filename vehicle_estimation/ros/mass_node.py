"""Mass node: least squares with forgetting on the longitudinal dynamics.

Methods (parameter ``method``):

* ``rls``: paper 003 Secs. 2-4 (Eqs. 4-11), parameters ``mass.*``. Driving samples only
  (a > 0, no brake). The propulsion force comes, in this order, from ``drive`` (tractive
  force at the wheels, if the vehicle reports it), from engine torque x gearing (gear
  reported, or predicted from the engine to vehicle speed ratio, Eqs. 10-11), or from engine
  load and speed through the torque regression of Eq. 49 (coefficients in
  ``mass.torque_regression``).
* ``ffrls`` (default): paper 004 Sec. 6 (Eqs. 28-31), parameters ``ffrls.*``: the braking torque is in
  the regression, so braking and down-hill samples count too, and the threshold judgment of
  Eq. 31 passes only well-excited samples. Drive force from ``drive`` or engine torque.
* ``ta_aekf``: paper 000 (Algorithm 1, Eqs. 16-36), parameters ``ta_aekf.*``: an adaptive EKF
  on [v_x, 1/m] whose second observation is the mass from the shipped transformer
  (``vehicle_estimation/models/mass_transformer``, trained on the heavy truck of paper 000;
  ``ta_aekf.model_path`` picks another), weighted by the confidence level tau of Eq. 19.
  It steps at every powertrain sample (100 Hz, the paper's 0.01 s) and runs the network once
  every ``ta_aekf.inference_period_steps`` samples (10: 10 Hz, ~1 % of a core; see
  :class:`~vehicle_estimation.estimators.mass.ta_aekf.TaAekfConfig`). A model file that fails its
  checks (SHA-256, names, shapes, finiteness) stops the node naming ``ta_aekf.model_path``.
  The slope's published variance, and whether GNSS aids the fusion, set the filter's grade
  error state (``ta_aekf.grade_error_state``).

Heading for the wind compensation of ``rls`` (``mass.wind_compensation``): the yaw of the
fusion odometry's orientation.

With no propulsion source the node keeps publishing its prior with a large variance and says
so in ``/diagnostics``.

Subscribes (sensor-data QoS): ``vehicle/powertrain`` (the trigger), ``vehicle/joint_states``
(brake torque), ``imu/data`` (longitudinal specific force), ``vehicle/speed`` (fallback speed).
From other nodes: ``estimation/imu_bias`` (fusion bias), ``estimation/odometry`` (speed),
``estimation/vehicle_state`` (speed and acceleration when ``speed_source`` /
``accel_source`` say so: paper 004 Fig. 1, mass <- state), ``estimation/road_slope_stamped``. The RLS runs at ``update_rate_hz`` (4 Hz, the CAN rate of
paper 003) on the means of every input over the period (see :class:`UpdateWindow`); the
longitudinal acceleration is the mean bias-compensated specific force minus g·sin(slope).

Publishes ``estimation/mass`` (std_msgs/Float64, kg) and ``estimation/mass_stamped``
(geometry_msgs/Vector3Stamped: x = mass, y = variance [kg^2], z = converged 1/0).

Persistence: with ``persist.path`` set (the launcher sets it: ``run`` under
``$ROS_HOME/vehicle_estimation``, ``replay`` in a fresh temporary directory) the estimate and
its covariance are saved atomically every ``persist.period_s`` of message time
(:mod:`vehicle_estimation.ros.persistence`), and a restarted node resumes from them instead
of its prior. A file for another method or vehicle, or a damaged one, is refused, counted and
reported in ``/diagnostics``, and the node starts from the prior.
"""

from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from std_msgs.msg import Float64

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.interfaces import MassEstimator
from vehicle_estimation.estimators.mass.update_window import ACCEL_SOURCES, UpdateWindow
from vehicle_estimation.estimators.registry import MASS_METHODS
from vehicle_estimation.ros.conversions import (
    MalformedMessage, chassis_reading, forward_speed_entry, odometry_entry, powertrain_reading)
from vehicle_estimation.ros.persistence import PersistedState
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
    speed_scale_at,
)

#: A powertrain reading above this multiple of what the vehicle's engine can deliver (maximum
#: torque, through the lowest gear) is absurd, not a strong engine.
POWERTRAIN_MARGIN = 3.0


class MassNode(EstimatorNode):
    def parameter_of_another_method(self, name: str) -> bool:
        return declared_by_a_method(MASS_METHODS, name)

    def __init__(self, **node_kwargs) -> None:
        super().__init__("mass", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.method = self.declare_str("method", "ffrls", "Mass estimation method", tuple(MASS_METHODS))
        self.rate = self.declare_float("publish_rate_hz", 10.0, "Output rate [Hz]", 0.1, 1000.0)
        self.update_rate = self.declare_float(
            "update_rate_hz", 4.0,
            "RLS update rate; inputs are averaged over each period (paper 003: 4 Hz CAN)", 0.1, 1000.0)
        spec = MASS_METHODS[self.method]
        self.config = self.declare_config(spec.config_prefix, spec.config_type())
        try:
            self.core: MassEstimator = spec.build(self.vehicle, self.config)
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc
        self.persisted = PersistedState(self, self.declare_str(
            "persist.path", "",
            "File the estimate and its covariance are saved to (atomically) and resumed from "
            "after a restart; empty: off. The launcher sets it"), f"mass/{self.method}", self.vehicle.name,
            self.declare_float("persist.period_s", 1.0, "Save period on the message clock [s]", 0.01, 3600.0),
            "mass state")
        self.resumed_from: float | None = None
        self._resume_persisted()
        self.bias = FusionImuBias(self.vehicle.imu_mounting_rpy)
        self.window = UpdateWindow()
        self.accel_source = self.declare_str(
            "accel_source", "auto", "Longitudinal acceleration for the RLS (see UpdateWindow.acceleration)",
            ACCEL_SOURCES)
        self.speed_source = self.declare_str(
            "speed_source", "fusion",
            "Speed for the regression: fusion odometry, the vehicle-state node or the undriven "
            "wheels' mean speed x radius, each falling back on the CAN speed",
            ("fusion", "vehicle_state", "wheel_speed"))
        self.require_slope = self.declare_bool(
            "require_slope", True,
            "Update only with a slope estimate from the slope node (else assume a level road)")
        self.max_slope_var = math.radians(self.declare_float(
            "max_slope_std_deg", 0.5,
            "Update only while the slope estimate is converged with at most this std [deg]", 0.01, 90.0)) ** 2
        # How long the fusion's accelerometer-bias error lasts decides how much of it the
        # forgetting RLS averages out: while GNSS aids the fusion it corrects the bias within
        # seconds; without GNSS the fusion holds its bias and the error stays for the drive.
        self.gnss_aiding_timeout = self.declare_shared_setting(FusionConfig, "gnss_aiding_timeout_s")
        self.aided_bias_correlation = self.declare_float(
            "gnss_aided_bias_correlation_s", 4.0,
            "Correlation time of the fusion's accelerometer-bias error while GNSS aids it, for "
            "the mass variance [s]; without GNSS the error is taken to last", 0.0, 1.0e6)
        self._gnss_t = -math.inf
        p = self.vehicle
        self.max_engine_torque = POWERTRAIN_MARGIN * p.engine_max_torque
        self.max_drive_force = (POWERTRAIN_MARGIN * p.engine_max_torque * max(p.gear_ratios, default=1.0)
                                * p.final_drive / p.wheel_radius)
        self.undriven_wheels = np.array(self.vehicle.undriven_wheels)
        self.slope = UpstreamHistory()
        self.odom_speed = UpstreamHistory()
        self.state_speed = UpstreamHistory()
        self.speed_scale = UpstreamHistory()
        self.can_speed: tuple[float, float] | None = None
        self.wheel_speed: tuple[float, float] | None = None
        self.brake_torque = 0.0
        self.brake_t = -math.inf
        self._last_pub = -math.inf

        self.pub = self.publisher(Float64, topics.MASS)
        self.pub_stamped = self.publisher(Vector3Stamped, topics.MASS_STAMPED)
        self.subscribe_primary(JointState, topics.POWERTRAIN, self.on_powertrain)
        self.subscribe_primary(JointState, topics.JOINT_STATES, self.on_joint_states)
        # GNSS fixes say how long the slope's and the regressor's accelerometer bias lasts.
        self.subscribe_primary(NavSatFix, topics.GNSS, self.on_gnss)
        # The IMU (200 Hz or more) only feeds the acceleration for "imu", and "auto" without
        # wheel speeds: a node that never reads it does not pay for receiving it.
        uses_imu = self.accel_source in ("imu", "auto")
        if uses_imu:
            self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
        # The bias also says how far a lasting error in the regressor may go (the variance).
        self.subscribe_imu_bias(self.bias)
        if self.speed_source == "fusion" or self.core.needs_heading:
            self.subscribe_upstream(Odometry, topics.ODOMETRY, self.odom_speed, odometry_entry)
        if "vehicle_state" in (self.speed_source, self.accel_source):
            self.subscribe_upstream(TwistWithCovarianceStamped, topics.VEHICLE_STATE, self.state_speed,
                                    forward_speed_entry)
        self.subscribe_upstream(Vector3Stamped, topics.ROAD_SLOPE_STAMPED, self.slope, companion_value)
        # What the wheels read over the true speed (the rolling radius), from the fusion: a scale
        # error of the speed is one of every acceleration derived from it, and of the mass.
        self.subscribe_upstream(Vector3Stamped, topics.SPEED_SCALE, self.speed_scale, companion_value)

    # -------------------------------------------------------------- inputs
    def on_imu(self, t: float, msg: Imu) -> None:
        imu = self.read_imu(msg)
        if imu is None:
            return
        f, w = imu
        f, _ = self.bias.correct(t, f, w)
        self.window.add_accel(float(f[0]))

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        reading = self.read_speed(msg)
        if reading is None:
            return
        self.can_speed = (t, reading[0] / speed_scale_at(self.speed_scale, t))

    def on_joint_states(self, t: float, msg: JointState) -> None:
        try:
            reading = chassis_reading(msg)
            total = reading.total_brake_torque
        except MalformedMessage:
            self.reject("joint_states:malformed")
            return
        if math.isfinite(total):
            self.brake_torque, self.brake_t = max(total, 0.0), t
        undriven = reading.wheel_speeds[self.undriven_wheels].tolist()
        if all(math.isfinite(w) for w in undriven):
            v = sum(undriven) / len(undriven) * self.vehicle.wheel_radius / speed_scale_at(self.speed_scale, t)
            self.window.add_wheel_speed(t, v)
            self.wheel_speed = (t, v)

    def on_gnss(self, t: float, msg: NavSatFix) -> None:
        if msg.status.status >= NavSatStatus.STATUS_FIX and math.isfinite(msg.latitude) \
                and math.isfinite(msg.longitude):
            self._gnss_t = t

    def regressor_bias_correlation(self, t: float) -> float:
        """Correlation time [s] of the regressor's bias error at ``t`` (infinite: it lasts)."""
        return self.aided_bias_correlation if t - self._gnss_t <= self.gnss_aiding_timeout else math.inf

    def on_powertrain(self, t: float, msg: JointState) -> None:
        try:
            pt = powertrain_reading(msg)
        except MalformedMessage:
            self.reject("powertrain:malformed")
            return
        if abs(pt.drive_force) > self.max_drive_force or abs(pt.engine_torque) > self.max_engine_torque:
            self.reject("powertrain:implausible")     # NaN (not reported) passes: comparisons are False
            return
        speed = self._speed_at(t)
        slope_item = self.slope.at(t)
        slope_ok = slope_item is not None and is_fresh(t, slope_item.stamp)
        self.set_missing("road slope", not slope_ok)
        # The regressor carries g sin(slope): a slope still converging (0.5 deg is 0.09 m/s^2,
        # 10-20 % of a typical acceleration) would teach the filter a wrong mass for minutes.
        if not (slope_ok and slope_item.converged and slope_item.variance <= self.max_slope_var):
            self.window.slope_trusted = False
        self.set_missing("vehicle speed", speed is None)
        if not self.core.steps_on_windows:
            # every sample is a step: without a brake torque only the driving ones are used
            brake = self._brake_at(t, unknown=math.nan)
            self.set_missing("brake torque (joint states): driving samples only", math.isnan(brake))
            if speed is not None and (slope_ok or not self.require_slope):
                self.core.step(t, speed, math.nan, slope_item.value if slope_ok else 0.0,
                               drive_force=pt.drive_force, engine_torque=pt.engine_torque,
                               engine_speed=pt.engine_speed, gear=pt.gear, brake_torque=brake,
                               grade_error_variance=self._grade_error_variance(slope_item if slope_ok else None),
                               grade_error_correlation_s=self.regressor_bias_correlation(t))
            self._publish_and_persist(t)
            return
        window = self.window
        if self.accel_source == "vehicle_state":
            item = measured_speed_at(self.state_speed, t, self.speed_scale)
            if item is not None:
                window.add_state_speed(item[0], item[1])
        if speed is not None:
            brake = self._brake_at(t)
            window.add(t, brake, pt.gear, vx=speed, slope=slope_item.value if slope_ok else 0.0,
                       bias_variance=self._regressor_bias_variance(t, slope_item if slope_ok else None),
                       drive_force=pt.drive_force, engine_torque=pt.engine_torque,
                       engine_speed=pt.engine_speed, engine_load=pt.engine_load)
        if window.closes(t, 1.0 / self.update_rate):
            slope = window.mean("slope")
            ax, ax_variance, missing = window.acceleration(self.accel_source, slope, self.vehicle.gravity,
                                                           self.bias.valid)
            for what, is_missing in missing.items():
                self.set_missing(what, is_missing)
            # No update on a guessed slope: a 1 % grade error is a 10 % error in phi at 1 m/s^2.
            ready = math.isfinite(ax) and (window.slope_trusted or not self.require_slope)
            if ready:
                extra = {}
                if self.core.needs_heading:
                    item = self.odom_speed.at(t)
                    fresh = item is not None and is_fresh(t, item[0])
                    self.set_missing("heading (estimation/odometry) for the wind", not fresh)
                    extra["heading"] = item[2] if fresh else math.nan
                self.core.step(t, window.mean("vx"), ax, slope,
                               drive_force=window.mean("drive_force"),
                               engine_torque=window.mean("engine_torque"),
                               engine_speed=window.mean("engine_speed"),
                               engine_load=window.mean("engine_load"), gear=window.gear,
                               brake_torque=window.brake if self.core.window_brake == "max" else window.brake_mean,
                               regressor_bias_variance=window.mean("bias_variance"),
                               regressor_bias_correlation_s=self.regressor_bias_correlation(t),
                               accel_noise_variance=ax_variance, **extra)
            window.clear()
        self._publish_and_persist(t)

    def _publish_and_persist(self, t: float) -> None:
        if t - self._last_pub >= 1.0 / self.rate - STAMP_TOLERANCE_S:
            self._last_pub = t
            self.publish_estimate(t)
        if self.persisted.due(t):
            self.persisted.save(t, self.core.state_dict())

    def _regressor_bias_variance(self, t: float, slope_item) -> float:
        """Variance of a lasting error in a + g sin(slope) [m^2/s^4]: the fusion's bias
        variance (in the slope and the IMU acceleration alike), else, without the fusion,
        the slope's whole variance as if it were all lasting."""
        variance = self.bias.accel_x_variance_at(t)
        return variance if variance is not None else self._grade_error_variance(slope_item)

    def _grade_error_variance(self, slope_item) -> float:
        """Variance of the error in g sin(slope) [m^2/s^4] from the slope's own variance, for a
        method that carries the slope's error as a state (the TA-AEKF's grade error, whose
        correlation time :meth:`regressor_bias_correlation` gives); NaN without a slope."""
        if slope_item is None:
            return math.nan
        return (self.vehicle.gravity * math.cos(slope_item.value)) ** 2 * slope_item.variance

    def _brake_at(self, t: float, unknown: float = 0.0) -> float:
        """Total brake torque [N m] of the latest joint_states, ``unknown`` when it is stale (the
        windowed methods gate on a > 0 and take 0; the TA-AEKF, which steps on every sample,
        needs to know that it does not know)."""
        return self.brake_torque if is_fresh(t, self.brake_t) else unknown

    def _speed_at(self, t: float) -> float | None:
        if self.speed_source == "wheel_speed":
            item = self.wheel_speed
        elif self.speed_source == "fusion":
            item = self.odom_speed.at(t)
        else:
            item = measured_speed_at(self.state_speed, t, self.speed_scale)
        if item is not None and is_fresh(t, item[0]):
            return item[1]
        if self.can_speed is not None and is_fresh(t, self.can_speed[0]):
            return self.can_speed[1]
        return None

    # -------------------------------------------------------------- persistence
    def _resume_persisted(self) -> None:
        """Start from the last persisted estimate and covariance, if there is one."""
        loaded = self.persisted.resume()
        if loaded is None:
            return
        stamp, state = loaded
        try:
            self.core.load_state_dict(state)
        except ValueError as exc:
            self.persisted.refuse(exc)
            self.core.reset()
            return
        self.resumed_from = stamp
        self.note_event(f"resumed from the persisted mass {self.core.mass:.1f} kg "
                        f"(variance {self.core.variance:.1f} kg^2, saved at stamp {stamp:.3f})")

    # -------------------------------------------------------------- outputs
    def publish_estimate(self, t: float) -> None:
        mass, variance, converged = float(self.core.mass), float(self.core.variance), bool(self.core.converged)
        if not (math.isfinite(mass) and math.isfinite(variance)):
            self.reject("mass:non_finite")
            self.note_event("mass estimate became non-finite: resetting to the prior")
            self.core.reset()
            mass, variance, converged = float(self.core.mass), float(self.core.variance), False
        self.publish(self.pub_stamped, companion_bytes(t, mass, variance, converged))
        self.publish(self.pub, float64_bytes(mass))

    def reset_estimators(self) -> None:
        self.core.reset()
        self.bias.clear()
        self.window.clear()
        self.slope.clear()
        self.odom_speed.clear()
        self.state_speed.clear()
        self.can_speed = None
        self.wheel_speed = None
        self._gnss_t = -math.inf
        self._last_pub = -math.inf

    def status_values(self) -> dict[str, str]:
        values = {"method": self.method, "mass [kg]": f"{self.core.mass:.1f}",
                  "converged": str(self.core.converged),
                  "samples used": str(self.core.samples_used)}
        if self.resumed_from is not None:
            values["resumed from persisted state saved at"] = f"{self.resumed_from:.3f}"
        for k, v in self.core.rejected.items():
            values[f"samples skipped: {k}"] = str(v)
        return {**values, **self.core.status()}


def main(args: list[str] | None = None) -> int:
    return run_node(MassNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
