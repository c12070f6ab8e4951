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
from pathlib import Path

import numpy as np
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
from std_msgs.msg import Float64

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.mass.mass_ffrls import (
    FFRLSMassConfig,
    FFRLSMassEstimator,
)
from vehicle_estimation.estimators.mass.mass_rls import (
    LongitudinalMassEstimator,
    MassRLSConfig,
)
from vehicle_estimation.estimators.mass.ta_aekf import TaAekfConfig, TaAekfMassEstimator
from vehicle_estimation.ros.conversions import (
    MAX_SPEED,
    MalformedMessage,
    chassis_reading,
    forward_speed_entry,
    imu_arrays,
    imu_plausible,
    odometry_entry,
    powertrain_reading,
)
from vehicle_estimation.ros.persistence import StateFileError, load_state, save_state
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

METHODS = ("rls", "ffrls", "ta_aekf")
#: A powertrain reading above this multiple of what the vehicle's engine can deliver (maximum
#: torque, through the lowest gear) is absurd, not a strong engine.
POWERTRAIN_MARGIN = 3.0


class UpdateWindow:
    """Means of the inputs over one RLS update period (paper 003 ran its RLS on 4 Hz CAN data).

    Averaging the force signals and the IMU acceleration over the *same* window filters both
    sides of Eq. 4 alike, so a transient cannot appear on one side before the other, and it
    keeps the forgetting factor's memory in seconds what the paper's was (lambda = 0.9995 at
    4 Hz: about 500 s). Brake torque: the maximum for ``rls`` (one braking sample spoils the
    window) and the mean for ``ffrls`` (it enters the regression). The gear takes the last
    value, and a gear change inside the window is passed on as NaN so the core treats the
    window as a shift. Speed samples of the vehicle-state node are kept with their stamps so
    that their least-squares slope can serve as the acceleration.
    """

    FIELDS = ("vx", "slope", "bias_variance", "drive_force", "engine_torque", "engine_speed", "engine_load")

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        self.start = math.nan
        self.sums = dict.fromkeys(self.FIELDS, 0.0)
        self.counts = dict.fromkeys(self.FIELDS, 0)
        self.accel_sum = 0.0
        self.accel_n = 0
        self.wheel_t: list[float] = []
        self.wheel_v: list[float] = []
        self.state_t: list[float] = []
        self.state_v: list[float] = []
        self.brake = 0.0
        self.brake_sum = 0.0
        self.brake_n = 0
        self.gears: set[float] = set()
        self.slope_trusted = True

    def add_accel(self, ax_specific: float) -> None:
        self.accel_sum += ax_specific
        self.accel_n += 1

    def add(self, t: float, brake: float, gear: float, **values: float) -> None:
        if math.isnan(self.start):
            self.start = t
        for key, value in values.items():
            if math.isfinite(value):
                self.sums[key] += value
                self.counts[key] += 1
        self.brake = max(self.brake, brake)
        self.brake_sum += brake
        self.brake_n += 1
        if math.isfinite(gear):
            self.gears.add(gear)

    def add_wheel_speed(self, t: float, v: float) -> None:
        self.wheel_t.append(t)
        self.wheel_v.append(v)

    def add_state_speed(self, t: float, v: float) -> None:
        if not self.state_t or t > self.state_t[-1]:
            self.state_t.append(t)
            self.state_v.append(v)

    @staticmethod
    def _slope(t_list: list[float], v_list: list[float]) -> float:
        if len(t_list) < 3:
            return math.nan
        t = np.asarray(t_list) - t_list[0]
        if t[-1] <= 0.0:
            return math.nan
        return float(np.polyfit(t, np.asarray(v_list), 1)[0])

    @property
    def wheel_accel(self) -> float:
        """Least-squares slope of the undriven wheels' speed over the window [m/s^2]."""
        return self._slope(self.wheel_t, self.wheel_v)

    @property
    def state_accel(self) -> float:
        """Least-squares slope of the vehicle-state node's vx over the window [m/s^2]."""
        return self._slope(self.state_t, self.state_v)

    @property
    def brake_mean(self) -> float:
        return self.brake_sum / self.brake_n if self.brake_n else 0.0

    def mean(self, key: str) -> float:
        return self.sums[key] / self.counts[key] if self.counts[key] else math.nan

    @property
    def accel(self) -> float:
        return self.accel_sum / self.accel_n if self.accel_n else math.nan

    @property
    def gear(self) -> float:
        return next(iter(self.gears)) if len(self.gears) == 1 else math.nan


class MassNode(EstimatorNode):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("mass", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.method = self.declare_str("method", "ffrls", "Mass estimation method", METHODS)
        self.rate = self.declare_float("publish_rate_hz", 10.0, "Output rate [Hz]", 0.1, 1000.0)
        self.update_rate = self.declare_float(
            "update_rate_hz", 4.0,
            "RLS update rate; inputs are averaged over each period (paper 003: 4 Hz CAN)", 0.1, 1000.0)
        self.core: LongitudinalMassEstimator | FFRLSMassEstimator | TaAekfMassEstimator
        if self.method == "rls":
            self.config = self.declare_config("mass", MassRLSConfig())
            self.core = LongitudinalMassEstimator(self.vehicle, self.config)
        elif self.method == "ta_aekf":
            self.config = self.declare_config("ta_aekf", TaAekfConfig())
            if self.config.use_network:
                import torch
                # One window per inference: torch's intra-op threads only contend with the other
                # nodes for the cores (2 threads on a busy 2-core machine: 120 ms per inference,
                # 1 thread: 0.6 ms).
                torch.set_num_threads(1)
            try:
                self.core = TaAekfMassEstimator(self.vehicle, self.config)
            except ValueError as exc:   # the model files failed a check: name the parameter
                raise ParameterError(f"parameter 'ta_aekf.model_path': {exc}") from exc
        else:
            self.config = self.declare_config("ffrls", FFRLSMassConfig())
            self.core = FFRLSMassEstimator(self.vehicle, self.config)
        self.persist_path = self.declare_str(
            "persist.path", "",
            "File the estimate and its covariance are saved to (atomically) and resumed from "
            "after a restart; empty: off. The launcher sets it")
        self.persist_period = self.declare_float(
            "persist.period_s", 1.0, "Save period on the message clock [s]", 0.01, 3600.0)
        self._last_persist = -math.inf
        self.resumed_from: float | None = None
        self._resume_persisted()
        self.bias = FusionImuBias()
        self.window = UpdateWindow()
        self.have_imu = False
        self.accel_source = self.declare_str(
            "accel_source", "auto", "Longitudinal acceleration for the RLS (see _window_accel)",
            ("auto", "wheel_speed", "imu", "vehicle_state"))
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
        self.gnss_aiding_timeout = self.declare_float(
            "gnss_aiding_timeout_s", 5.0,
            "A GNSS fix within this time means the fusion's bias is being corrected (as the "
            "fusion's own gnss_aiding_timeout_s) [s]", 0.1, 3600.0)
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
        self.can_speed: tuple[float, float] | None = None
        self.wheel_speed: tuple[float, float] | None = None
        self.brake_torque = 0.0
        self.brake_t = -math.inf
        self._last_pub = -math.inf

        self.pub = self.publisher(Float64, topics.MASS)
        self.pub_stamped = self.publisher(Vector3Stamped, topics.MASS_STAMPED)
        self.subscribe_primary(JointState, topics.POWERTRAIN, self.on_powertrain)
        self.subscribe_primary(JointState, topics.JOINT_STATES, self.on_joint_states)
        if self.method != "ta_aekf":
            self.subscribe_primary(NavSatFix, topics.GNSS, self.on_gnss)
        # The IMU (200 Hz or more) only feeds the acceleration for "imu", and "auto" without
        # wheel speeds: a node that never reads it does not pay for receiving it.
        uses_imu = self.accel_source in ("imu", "auto")
        if uses_imu:
            self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
        # The bias also says how far a lasting error in the regressor may go (the variance).
        self.subscribe_imu_bias(self.bias)
        self.needs_heading = self.method == "rls" and self.config.wind_compensation
        if self.speed_source == "fusion" or self.needs_heading:
            self.subscribe_upstream(Odometry, topics.ODOMETRY, self.odom_speed, odometry_entry)
        if "vehicle_state" in (self.speed_source, self.accel_source):
            self.subscribe_upstream(TwistWithCovarianceStamped, topics.VEHICLE_STATE, self.state_speed,
                                    forward_speed_entry)
        self.subscribe_upstream(Vector3Stamped, topics.ROAD_SLOPE_STAMPED, self.slope, companion_value)

    # -------------------------------------------------------------- inputs
    def on_imu(self, t: float, msg: Imu) -> None:
        f, w = imu_arrays(msg)
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(w))) or not imu_plausible(f, w):
            self.reject("imu:invalid")
            return
        f, _ = self.bias.correct(t, f, w)
        self.window.add_accel(float(f[0]))
        self.have_imu = True

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        v = msg.twist.twist.linear.x
        if math.isfinite(v) and abs(v) <= MAX_SPEED:
            self.can_speed = (t, v)
        else:
            self.reject("speed:invalid")

    def on_joint_states(self, t: float, msg: JointState) -> None:
        try:
            reading = chassis_reading(msg)
            total = reading.total_brake_torque
        except MalformedMessage:
            self.reject("joint_states:malformed")
            return
        if math.isfinite(total):
            self.brake_torque, self.brake_t = max(total, 0.0), t
        undriven = reading.wheel_speeds[self.undriven_wheels]
        if np.all(np.isfinite(undriven)):
            v = float(np.mean(undriven)) * self.vehicle.wheel_radius
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
        if self.method == "ta_aekf":
            # Algorithm 1 steps at every sample (0.01 s); the core averages its network
            # features over blocks itself, and gaps restart its speed state.
            if speed is not None and (slope_ok or not self.require_slope):
                self.core.step(t, speed, math.nan, slope_item.value if slope_ok else 0.0,
                               drive_force=pt.drive_force, engine_torque=pt.engine_torque,
                               engine_speed=pt.engine_speed, gear=pt.gear, brake_torque=self._brake_at(t))
            self._publish_and_persist(t)
            return
        window = self.window
        if self.accel_source == "vehicle_state":
            item = self.state_speed.at(t)
            if item is not None and is_fresh(t, item[0]):
                window.add_state_speed(*item)
        if speed is not None:
            brake = self._brake_at(t)
            window.add(t, brake, pt.gear, vx=speed, slope=slope_item.value if slope_ok else 0.0,
                       bias_variance=self._regressor_bias_variance(t, slope_item if slope_ok else None),
                       drive_force=pt.drive_force, engine_torque=pt.engine_torque,
                       engine_speed=pt.engine_speed, engine_load=pt.engine_load)
        if not math.isnan(window.start) and t - window.start >= 1.0 / self.update_rate - STAMP_TOLERANCE_S:
            slope = window.mean("slope")
            ax = self._window_accel(window, slope)
            # No update on a guessed slope: a 1 % grade error is a 10 % error in phi at 1 m/s^2.
            ready = math.isfinite(ax) and (window.slope_trusted or not self.require_slope)
            if ready:
                extra = {}
                if self.needs_heading:
                    item = self.odom_speed.at(t)
                    fresh = item is not None and is_fresh(t, item[0])
                    self.set_missing("heading (estimation/odometry) for the wind", not fresh)
                    extra["heading"] = item[2] if fresh else math.nan
                self.core.step(t, window.mean("vx"), ax, slope,
                               drive_force=window.mean("drive_force"),
                               engine_torque=window.mean("engine_torque"),
                               engine_speed=window.mean("engine_speed"),
                               engine_load=window.mean("engine_load"), gear=window.gear,
                               brake_torque=window.brake if self.method == "rls" else window.brake_mean,
                               regressor_bias_variance=window.mean("bias_variance"),
                               regressor_bias_correlation_s=self.regressor_bias_correlation(t), **extra)
            window.clear()
        self._publish_and_persist(t)

    def _publish_and_persist(self, t: float) -> None:
        if t - self._last_pub >= 1.0 / self.rate - STAMP_TOLERANCE_S:
            self._last_pub = t
            self.publish_estimate(t)
        if self.persist_path and t - self._last_persist >= self.persist_period - STAMP_TOLERANCE_S:
            self._last_persist = t
            self._persist(t)

    def _regressor_bias_variance(self, t: float, slope_item) -> float:
        """Variance of a lasting error in a + g sin(slope) [m^2/s^4]: the fusion's bias
        variance (in the slope and the IMU acceleration alike), else, without the fusion,
        the slope's whole variance as if it were all lasting."""
        variance = self.bias.accel_x_variance_at(t)
        if variance is not None:
            return variance
        if slope_item is None:
            return math.nan
        return (self.vehicle.gravity * math.cos(slope_item.value)) ** 2 * slope_item.variance

    def _window_accel(self, window: UpdateWindow, slope: float) -> float:
        """Longitudinal acceleration dv/dt over the window.

        ``wheel_speed``: the slope of the undriven wheels' speed. It carries no gravity and no
        body pitch, so neither the accelerometer bias nor the suspension's squat and dive
        (which tilt the IMU by ~0.1 deg per m/s^2) reach the mass. ``imu``: paper 003's choice,
        the mean bias-compensated specific force minus g sin(slope); needs the fusion's bias.
        ``auto`` takes the wheels when they report and the IMU otherwise. ``vehicle_state``:
        the slope of the vehicle-state node's vx (paper 004 Fig. 1: mass <- state).
        """
        if self.accel_source == "vehicle_state":
            a = window.state_accel
            self.set_missing("vehicle state speed", not math.isfinite(a))
            return a
        if self.accel_source in ("wheel_speed", "auto"):
            a = window.wheel_accel
            self.set_missing("undriven wheel speeds", not math.isfinite(a) and self.accel_source == "wheel_speed")
            if math.isfinite(a) or self.accel_source == "wheel_speed":
                return a
        if not self.bias.valid:
            self.set_missing("IMU bias (estimation/imu_bias)", True)
            return math.nan
        self.set_missing("IMU bias (estimation/imu_bias)", False)
        return window.accel - self.vehicle.gravity * math.sin(slope)

    def _brake_at(self, t: float) -> float:
        """Total brake torque [N m] of the latest joint_states, 0 when it is stale."""
        return self.brake_torque if is_fresh(t, self.brake_t) else 0.0

    def _speed_at(self, t: float) -> float | None:
        if self.speed_source == "wheel_speed":
            item = self.wheel_speed
        else:
            item = (self.odom_speed if self.speed_source == "fusion" else self.state_speed).at(t)
        if item is not None and is_fresh(t, item[0]):
            return item[1]
        if self.can_speed is not None and is_fresh(t, self.can_speed[0]):
            return self.can_speed[1]
        return None

    # -------------------------------------------------------------- persistence
    def _resume_persisted(self) -> None:
        """Start from the last persisted estimate and covariance, if there is one."""
        if not self.persist_path:
            return
        try:
            loaded = load_state(Path(self.persist_path), f"mass/{self.method}")
            if loaded is None:
                self.note_event(f"no persisted mass state at {self.persist_path}: starting from the prior")
                return
            stamp, state, meta = loaded
            if meta.get("vehicle") != self.vehicle.name:
                raise StateFileError(f"state is for vehicle {meta.get('vehicle')!r}, not {self.vehicle.name!r}")
            self.core.load_state_dict(state)
        except (StateFileError, ValueError) as exc:
            self.reject("persist:unusable_state_file")
            self.note_event(f"ignoring persisted mass state ({exc}): starting from the prior")
            self.core.reset()
            return
        self.resumed_from = stamp
        self.note_event(f"resumed from the persisted mass {self.core.mass:.1f} kg "
                        f"(variance {self.core.variance:.1f} kg^2, saved at stamp {stamp:.3f})")

    def _persist(self, t: float) -> None:
        try:
            save_state(Path(self.persist_path), f"mass/{self.method}", t, self.core.state_dict(),
                       vehicle=self.vehicle.name)
        except (OSError, ValueError) as exc:
            self.reject("persist:write_failed")
            self.get_logger().error(f"cannot persist the mass state: {exc}", throttle_duration_sec=30.0)

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
        self.window.clear()
        self.have_imu = False
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
        if isinstance(self.core, TaAekfMassEstimator):
            values["confidence level tau (Eq. 19)"] = f"{self.core.last_tau:.3g}"
            values["network mass [kg]"] = f"{self.core.last_network_mass:.1f}"
        wind = getattr(self.core, "wind", None)
        if wind is not None:
            east, north = wind.wind_enu
            values["wind east, north [m/s]"] = f"{east:.2f}, {north:.2f}"
            values["wind from [deg]"] = f"{wind.wind_from_deg:.0f}"
        return values



def main(args: list[str] | None = None) -> int:
    return run_node(MassNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
