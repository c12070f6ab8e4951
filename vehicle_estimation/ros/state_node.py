"""Vehicle-state node: vx, vy, yaw rate and sideslip on the paper-004 4-wheel model.

Filter (parameter ``filter``); ``vbackf`` and ``ckf`` on the paper-004 4-wheel model with
Dugoff tyres (Eqs. 1-9) and sideslip from Eq. 14, ``aoukf`` on the paper-002 3-DOF model:

* ``vbackf``: the variational Bayesian adaptive cubature Kalman filter of paper 004 Sec. 4
  (Eqs. 10-13): the measurement-noise covariance is learnt online (inverse-Wishart), so
  time-varying sensor noise (Eq. 34) does not mis-weight the IMU. Its parameters:
  ``vbackf.*``.
* ``ckf``: the plain cubature Kalman filter, the contrast of paper 004 Sec. 7.
* ``aoukf``: the adaptive anti-outlier UKF of paper 002 (Sec. 3.3, Eqs. 6-7) on the 3-DOF
  Magic-Formula model of its Sec. 2, with the GA-BPNN output correction of Eq. 5
  (``aoukf_correction``: ``auto`` loads the shipped weights for ``vehicle.name`` when the
  package has them, a path loads that file, empty turns it off). Its tuning: ``aoukf.*``
  (``aoukf.filter`` ``ukf`` / ``ekf`` gives the paper's contrasts). Gross errors (spikes,
  bursts, a frozen sensor) are down-weighted or replaced; ``/diagnostics`` counts them. It
  takes vx as a measurement: while there is no speed of any kind (no wheel speed and no
  ``vehicle/speed`` sample for a second, from the start or later in the drive) the node runs
  ``no_speed_filter`` instead, from the AO-UKF's state, until a speed has been back for a
  second, and ``/diagnostics`` (``filter``) says so.

The filter is built from :data:`~vehicle_estimation.estimators.registry.STATE_FILTERS`; what it
adds to ``/diagnostics`` comes from its ``status()``.

Shared tuning of ``ckf``/``vbackf`` (Sec. 7.1 defaults): ``p0_diag``, ``q_diag`` (per ``tau`` =
0.01 s) and ``r_diag`` (the initial R for ``vbackf``).

Subscribes (sensor-data QoS): ``imu/data`` (measurement [ax, ay, r], the trigger),
``vehicle/joint_states`` (steering-wheel angle, four wheel speeds). From other nodes:
``estimation/imu_bias`` (fusion IMU bias), ``estimation/imu`` (the fusion attitude that goes
with the compensated specific force, for ``roll_compensation``),
``estimation/road_slope_stamped`` and ``estimation/mass_stamped`` (paper 004 Fig. 1: state <-
slope, mass). Before the slope or mass arrive the filter uses slope 0 and the vehicle's nominal
mass, and says so in ``/diagnostics``.

Wheel speeds missing: the inputs carry NaN wheel speeds and the core propagates vx with the
measured longitudinal acceleration instead of the wheel-slip tyre forces (see
``estimators.state.vehicle_model``); ``vehicle/speed`` (CAN/OBD-II speed), when it is there, then updates vx
directly (``speed_fallback``), so vx does not drift with the accelerometer bias. Steering missing: the sample is used with the last steering angle
for at most ``stale_input_s``, then the filter runs on the IMU alone (δ = 0) and
diagnostics report it.

Body roll: the models take the measured lateral acceleration for tyre force over mass, but a
body-fixed IMU also reads ``g sin(roll) cos(pitch)`` on y whenever the body rolls on its
suspension or the road is banked (~0.7 m/s^2 at 4 deg of roll). With ``roll_compensation``
(on by default) it is removed with the fusion's attitude, which integrates the body's roll
rate (from ``estimation/imu``, not the odometry: the odometry's roll variance also carries the
mounting roll and the unaided lateral bias, which cancel in the bias-compensated force); before
the fusion has aligned the samples pass uncorrected, and ``/diagnostics`` (``roll
compensation``) says which.

Publishes ``estimation/vehicle_state`` (geometry_msgs/TwistWithCovarianceStamped in
``base_link``: linear.x = vx, linear.y = vy, angular.z = yaw rate; covariance rows/cols
0, 1, 5), ``estimation/sideslip`` (std_msgs/Float64, rad) and ``estimation/sideslip_stamped``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.noise import white_equivalent_variance
from vehicle_estimation.estimators.interfaces import StateEstimator
from vehicle_estimation.estimators.registry import (
    DEFAULT_NO_SPEED_FILTER,
    NO_SPEED_HOLD_S,
    STATE_FILTERS,
    StateFilter,
    StateSettings,
    lookup,
    with_state_settings,
)
from vehicle_estimation.estimators.state.gabpnn import (
    BPCorrection,
    default_weights_path,
    load_correction,
)
from vehicle_estimation.estimators.state.ckf import VehicleStateConfig
from vehicle_estimation.estimators.state.core import (
    DEFAULT_CORNERING_ACCEL_STD, DEFAULT_CORNERING_MIN_YAW_RATE, CorneringSpeed, ModelErrorSettings,
    RollAccelerationTerm, SpeedPresence)
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.ros.conversions import (
    MAX_SPEED, MalformedMessage, add_stated_imu_covariances, base_link_imu_variances, chassis_reading,
    lateral_gravity_entry)
from vehicle_estimation.ros.cdr import StampedLayout, float64_bytes
from vehicle_estimation.ros.runtime.node import EstimatorNode
from vehicle_estimation.ros.runtime.parameters import ParameterError, declared_by_a_method
from vehicle_estimation.ros.runtime.spin import run_node
from vehicle_estimation.ros.stamps import STAMP_TOLERANCE_S, sec_to_ns
from vehicle_estimation.ros.runtime.upstream import (
    FusionImuBias,
    UpstreamHistory,
    companion_bytes,
    companion_value,
    is_fresh,
    speed_scale_at,
    speed_scale_error_variance,
)

#: Where vx comes from, for /diagnostics ("vx source").
VX_FROM_WHEELS = "wheel speeds"
VX_FROM_SPEED = "vehicle/speed (fallback: no wheel speeds)"
VX_DEAD_RECKONED = "dead reckoning from ax (no wheel speeds, no vehicle/speed): drifts"
VX_FROM_CORNERING = ("dead reckoning from ax, measured in corners as mean(ay) / mean(r) (no wheel "
                     "speeds, no vehicle/speed): drifts on straights")

#: The upstream inputs by the names /diagnostics gives them when missing ("missing: ...").
SLOPE_INPUT = "road slope"
MASS_INPUT = "mass"

#: How long the filter waits for wheel speeds to start from before it starts from initial_vx [s].
WHEEL_WAIT_S = 1.0
#: A road grade varies over a hill's length: at highway speed ~5 s. The correlation time of the
#: acceleration error an unknown grade causes (see ``missing_slope_std_deg``) [s].
GRADE_CORRELATION_S = 5.0
#: A wheel faster than this x MAX_SPEED (allowing for spin) is an absurd reading.
WHEEL_SPIN_MARGIN = 1.5


class StateNode(EstimatorNode):
    def parameter_of_another_method(self, name: str) -> bool:
        return name == "aoukf_correction" or declared_by_a_method(STATE_FILTERS, name)

    def __init__(self, **node_kwargs) -> None:
        super().__init__("vehicle_state", **node_kwargs)
        self.vehicle = self.declare_vehicle()
        self.filter_name = self.declare_str("filter", "vbackf", "Vehicle-state filter", tuple(STATE_FILTERS))
        self.method = lookup(STATE_FILTERS, self.filter_name, "vehicle-state filter")
        self.rate = self.declare_float("publish_rate_hz", 100.0, "Output rate [Hz]", 0.1, 1000.0)
        self.filter_rate = self.declare_float(
            "filter_rate_hz", 100.0,
            "Filter step rate: IMU samples in between are averaged (paper 004: tau = 0.01 s); "
            "at or above the IMU rate every sample is a step, and r_diag is the noise of the "
            "averaged measurement", 1.0, 10000.0)
        self.stale_input_s = self.declare_float(
            "stale_input_s", 0.5, "Chassis signals older than this count as missing [s]", 0.01, 10.0)
        self.initial_vx = self.declare_float(
            "initial_vx", 0.0, "Initial longitudinal speed of the filter [m/s] (paper 004: 80/3.6)",
            -100.0, 100.0)
        self.init_from_wheels = self.declare_bool(
            "init_vx_from_wheel_speeds", True,
            "Start vx from the rear wheel speeds when available (else from initial_vx)")
        paper = StateSettings.defaults()
        self.p0_diag = self.declare_float_array(
            "p0_diag", paper.p0_diag, "Initial covariance diagonal of [vx, vy, r, ax, ay] (Sec. 7.1)")
        self.q_diag = self.declare_float_array(
            "q_diag", paper.q_diag, "Process noise diagonal per 0.01 s step (Sec. 7.1's 0.1 I as a density)")
        self.r_diag = self.declare_float_array(
            "r_diag", paper.r_diag, "Measurement noise diagonal of [ax, ay, r] (Sec. 7.1)")
        self.speed_fallback = self.declare_bool(
            "speed_fallback", True,
            "Without wheel speeds, update vx with vehicle/speed (else vx is dead-reckoned from ax)")
        self.roll_compensation = self.declare_bool(
            "roll_compensation", True,
            "Remove from the measured lateral acceleration the gravity that the body's roll (on "
            "its suspension, and the road's bank) puts into it, with the fusion attitude "
            "(estimation/imu); without it the tyre model reads g sin(roll) as lateral force")
        self.roll_error_correlation_s = self.declare_float(
            "roll_error_correlation_s", 1.0,
            "Correlation time of the fusion's roll error [s]. The roll-compensated ay carries "
            "g^2 var(roll) of error (the fusion's attitude covariance) that changes over seconds, "
            "which a filter stepping every dt weighs as white noise of 2 tau / dt times that "
            "variance, added to its ay noise; 0 = the fusion's roll taken as exact", 0.0, 60.0)
        self.speed_fallback_std = self.declare_float(
            "speed_fallback_std", 0.3,
            "Std of vehicle/speed when its message carries no variance [m/s]", 0.001, 10.0)
        self.speed_error_correlation_s = self.declare_float(
            "speed_error_correlation_s", 0.0,
            "Correlation time of vehicle/speed's error [s] (a speed quantised to 1 km/h is off by the "
            "same amount while it stays in one step): its variance is weighed 2 tau / (sample "
            "spacing) times; 0 = white", 0.0, 60.0)
        self._last_speed_used_t = -math.inf
        self.settings = StateSettings(
            tuple(self.p0_diag), tuple(self.q_diag), tuple(self.r_diag), self.initial_vx, self.init_from_wheels,
            **{name: self.declare_setting(VehicleStateConfig, name) for name in (
                "wheel_slip_forces", "wheel_radius_std", "front_axle_force_std", "rear_axle_force_std")},
            **{name: self.declare_setting(ModelErrorSettings, name) for name in (
                "tyre_stiffness_std", "road_bank_std_deg")})
        # Fallbacks whose error the published variance carries, so the sideslip may still be
        # flagged converged: the level road (its grade error is vx process noise) and, where the
        # variance carries a stiffness error, the params' mass (a mass off by some share puts
        # the rear slip angle off by that share, as a stiffness does).
        self._fallbacks_in_variance = frozenset(
            {SLOPE_INPUT} | ({MASS_INPUT} if self.settings.tyre_stiffness_std > 0.0 else set()))
        self.filter_config = self._declare_filter_config()
        self.correction: BPCorrection | None = None
        if self.method.output_correction:
            self.correction = self._load_correction(self.declare_str(
                "aoukf_correction", "auto",
                "GA-BPNN output correction (paper 002 Eq. 5) for filter aoukf: 'auto' = the "
                "package's weights for vehicle.name if it ships them (else none), a path = that "
                ".npz file, '' = none"))
        # Chosen by the speed's presence (_choose_filter), from the first second on.
        self.no_speed_filter = ""
        if self.method.needs_speed:
            self.no_speed_filter = self.declare_str(
                "no_speed_filter", DEFAULT_NO_SPEED_FILTER,
                f"Filter run instead of '{self.filter_name}' while there is no speed of any kind (no wheel "
                "speed, no vehicle/speed for a second: from the start, or lost later), until one has "
                "been back for a second: that filter takes vx as a measurement, and its tyre model alone "
                "pulls an unmeasured vx tens of m/s off; '' = run it all the same",
                tuple(name for name, m in STATE_FILTERS.items() if not m.needs_speed) + ("",))
        self.fallback_method = STATE_FILTERS[self.no_speed_filter] if self.no_speed_filter else None
        self.fallback_config = (self._declare_filter_config(self.fallback_method)
                                if self.fallback_method is not None else None)
        self.speed_presence = SpeedPresence(NO_SPEED_HOLD_S, self.stale_input_s)
        self._start_cores()
        self.bias = FusionImuBias(self.vehicle.imu_mounting_rpy)
        self.slope = UpstreamHistory(lag_s=self.feedback_lag)   # feedback edges (see nodes.PIPELINE)
        self.mass = UpstreamHistory(lag_s=self.feedback_lag)
        self.attitude = UpstreamHistory()
        self.speed_scale = UpstreamHistory()
        self.roll_source = "off" if not self.roll_compensation else "none yet (no fusion attitude)"
        self.chassis = None
        self.chassis_t = -math.inf
        self.speed_t = -math.inf      # stamp of the last vehicle/speed sample
        self._last_pub = -math.inf
        self._steer = 0.0
        self._first_imu_t: float | None = None
        self._vx_measured = False     # by wheel speeds or vehicle/speed at the last filter step
        self._z_sum = np.zeros(3)
        self._imu_cov_sum = np.zeros((2, 9))   # the IMU's stated covariances (imu_link), summed
        # the IMU above the roll axis feels the body's roll acceleration (vehicle.roll_lever)
        self._roll_acceleration = RollAccelerationTerm(self.vehicle.roll_lever)
        self._roll_ay_variance = 0.0   # g^2 var(roll) of the last fusion attitude used [(m/s^2)^2]
        self._z_count = 0
        self._last_step_t = -math.inf
        missing_slope_std = math.radians(self.declare_float(
            "missing_slope_std_deg", 2.0,
            "Without a slope estimate the filter assumes a level road and adds the acceleration "
            "error of a grade of this std to the vx process noise [deg]", 0.0, 30.0))
        # Without the slope the grade's g sin(theta) is an unknown, correlated acceleration
        # error on vx: its white-noise equivalent density 2 sigma^2 tau [(m/s^2)^2 s].
        self.missing_slope_noise_density = (
            2.0 * (self.vehicle.gravity * math.sin(missing_slope_std)) ** 2 * GRADE_CORRELATION_S)
        dead_reckoning_std = self.declare_float(
            "dead_reckoning_accel_std", 0.35,
            "While no wheel speed or vehicle/speed measures vx, the filter integrates the "
            "accelerometer, whose bias and grade error no measurement checks: this acceleration "
            "error std goes into the vx process noise [m/s^2]", 0.0, 5.0)
        # Same white-noise equivalent: the published vx variance then grows as the drift does,
        # and the slope and mass nodes stop taking that vx as a speed (conversions.measured_speed,
        # once the tyre radius's share, which publish_state adds to every vx, is taken out).
        self.dead_reckoning_noise_density = 2.0 * dead_reckoning_std ** 2 * GRADE_CORRELATION_S
        cornering_std = self.declare_float(
            "cornering_speed_accel_std", DEFAULT_CORNERING_ACCEL_STD,
            "While no wheel speed or vehicle/speed measures vx, it is measured in every corner as "
            "mean(ay) / mean(r) over 0.5 s (a_y = vy' + vx r): the window's vy' and the ay of "
            "body roll and road bank, this std [m/s^2] (plus the mean's own, from the samples' "
            "spread), over |mean(r)| give its error; 0 = off (vx only dead-reckoned)", 0.0, 10.0)
        self.cornering_speed = None if cornering_std <= 0.0 else CorneringSpeed(
            accel_std=cornering_std, min_yaw_rate=self.declare_float(
                "cornering_speed_min_yaw_rate", DEFAULT_CORNERING_MIN_YAW_RATE,
                "Below this |mean(r)| a window tells nothing of vx [rad/s]", 0.01, 2.0))
        self.min_dynamic_speed = self.declare_float(
            "sideslip_min_speed", 3.0,
            "Below this |vx| the sideslip is the kinematic one from the steering angle [m/s]", 0.0, 20.0)

        self.pub_state = self.publisher(TwistWithCovarianceStamped, topics.VEHICLE_STATE)
        self._state_layout = StampedLayout(topics.BASE_FRAME, 42)
        self.pub_beta = self.publisher(Float64, topics.SIDESLIP)
        self.pub_beta_stamped = self.publisher(Vector3Stamped, topics.SIDESLIP_STAMPED)
        self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        self.subscribe_primary(JointState, topics.JOINT_STATES, self.on_joint_states)
        self.speed: tuple[float, float, float] | None = None     # (stamp, vx, variance) not yet used
        self.vx_source = VX_FROM_WHEELS if self.speed_fallback else "wheel speeds, else dead reckoning from ax"
        if self.speed_fallback:
            self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
        self.subscribe_imu_bias(self.bias)
        if self.roll_compensation:
            self.subscribe_upstream(Imu, topics.IMU_COMPENSATED, self.attitude, lateral_gravity_entry)
        self.subscribe_upstream(Vector3Stamped, topics.ROAD_SLOPE_STAMPED, self.slope, companion_value)
        self.subscribe_upstream(Vector3Stamped, topics.MASS_STAMPED, self.mass, companion_value)
        # the fusion's rolling radius over the nominal: the wheel and CAN speeds' scale error
        self.subscribe_upstream(Vector3Stamped, topics.SPEED_SCALE, self.speed_scale, companion_value)

    def _load_correction(self, setting: str) -> BPCorrection | None:
        if not setting:
            return None
        path = default_weights_path(self.vehicle.name) if setting == "auto" else setting
        if setting == "auto" and not path.exists():
            self.note_event(f"no shipped GA-BPNN weights for vehicle '{self.vehicle.name}': "
                            "AO-UKF without output correction (train some with train-gabpnn)")
            return None
        try:
            return load_correction(path)
        except ValueError as exc:
            raise ParameterError(f"parameter 'aoukf_correction': {exc}") from exc

    def _declare_filter_config(self, method: StateFilter | None = None) -> Any:
        """The filter's (or ``method``'s) own config, declared as ``<config_prefix>.*`` (None
        for a filter without one); the fields the node declares itself (initial_vx, ...) come
        from :attr:`settings`."""
        method = method or self.method
        defaults = method.config_type()
        if defaults is None:
            return None
        defaults, shared = with_state_settings(defaults, self.settings)
        return self.declare_config(method.config_prefix, defaults, exclude=shared)

    def _start_cores(self) -> None:
        """The configured filter, running, and ``no_speed_filter`` idle beside it: built here
        too, so that a bad config stops the node at start-up, and kept across swaps, so that a
        VB-ACKF keeps the noise it learnt, which is the sensors' and not the drive's."""
        self.running_filter = self.filter_name
        self.core = self._make_core()
        self._idle_core = self._make_fallback_core() if self.fallback_method is not None else None

    def _make_core(self) -> StateEstimator:
        """The configured filter."""
        correction = self.correction.fresh() if self.correction is not None else None
        return self._build(self.method, self.filter_config, correction, f"filter '{self.filter_name}'")

    def _make_fallback_core(self) -> StateEstimator:
        """``no_speed_filter``."""
        assert self.fallback_method is not None
        return self._build(self.fallback_method, self.fallback_config, None,
                           f"no_speed_filter '{self.no_speed_filter}'")

    def _build(self, method: StateFilter, config: Any, correction: BPCorrection | None,
               what: str) -> StateEstimator:
        try:
            return method.build(self.vehicle, config, self.settings, correction)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{what}: {exc}") from exc

    def _choose_filter(self, t: float) -> None:
        """A filter that needs a speed runs only while there is one: after NO_SPEED_HOLD_S with
        no wheel speed and no vehicle/speed (from the start, or lost later) the node runs
        ``no_speed_filter``, and after as long with a speed again the configured filter (a
        recorder's CAN topic may start late, or drop out). Each takes over the other's state;
        the one stepping out waits with what it learnt (a VB-ACKF's noise) for the next swap."""
        if self.fallback_method is None:
            return
        self.speed_presence.clock(t)
        if self.running_filter == self.filter_name and self.speed_presence.lost(t):
            self.running_filter = self.no_speed_filter
            self.note_event(f"no wheel speed and no vehicle/speed for {NO_SPEED_HOLD_S:g} s: filter "
                            f"'{self.no_speed_filter}' runs instead of '{self.filter_name}', which needs a "
                            "speed (no_speed_filter)")
        elif self.running_filter != self.filter_name and self.speed_presence.back(t):
            self.running_filter = self.filter_name
            self.note_event(f"a speed for {NO_SPEED_HOLD_S:g} s: filter '{self.filter_name}' runs again")
        else:
            return
        core = self._idle_core
        assert core is not None             # built with the fallback's method
        if self.core.initialised:
            core.start_from(self.core.x, self.core.P)
        else:
            core.reset()
        self._idle_core, self.core = self.core, core

    def on_joint_states(self, t: float, msg: JointState) -> None:
        try:
            reading = chassis_reading(msg)
        except MalformedMessage:
            self.reject("joint_states:malformed")
            return
        if reading.fastest_wheel_speed * self.vehicle.wheel_radius > WHEEL_SPIN_MARGIN * MAX_SPEED:
            self.reject("joint_states:implausible")
            return
        self.chassis = reading
        self.chassis_t = t
        if _rear_wheels_measured(reading.wheel_speeds):
            self.speed_presence.sample(t)

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        reading = self.read_speed(msg)
        if reading is None:
            return
        v, var = reading
        if math.isnan(var):
            var = self.speed_fallback_std ** 2
        self.speed = (t, v / speed_scale_at(self.speed_scale, t), var)
        self.speed_t = t
        self.speed_presence.sample(t)

    def _update_speed_fallback(self, t: float, rear_wheels_measured: bool) -> None:
        """vx from vehicle/speed when the wheel speeds are missing (each sample used once)."""
        if rear_wheels_measured:
            self.vx_source = VX_FROM_WHEELS
            self.set_missing("wheel speeds and vehicle/speed", False)
            return
        # The source is judged by the last sample's age, not by whether a sample is still
        # unused: at a CAN rate below the filter's there are steps with none, by design.
        fresh = t - self.speed_t <= self.stale_input_s
        self.vx_source = VX_FROM_SPEED if fresh else VX_DEAD_RECKONED
        self.set_missing("wheel speeds and vehicle/speed", math.isfinite(self.speed_t) and not fresh)
        if fresh and self.speed is not None:
            variance = white_equivalent_variance(self.speed[2], self.speed_error_correlation_s,
                                                 self.speed[0] - self._last_speed_used_t)
            if self.core.update_speed(self.speed[1], variance):
                self._last_speed_used_t = self.speed[0]
                self.speed = None

    def _update_cornering_speed(self, t: float, z: np.ndarray, vx_measured: bool) -> None:
        """vx from cornering (mean(ay) / mean(r)) while nothing else measures it."""
        if self.cornering_speed is None:
            return
        if self.vx_source == VX_DEAD_RECKONED:
            self.vx_source = VX_FROM_CORNERING
        found = self.cornering_speed.step(t, float(z[1]), float(z[2]), vx_measured)
        if found is not None:
            self.core.update_speed(*found)

    def _roll_gravity(self, t: float) -> float:
        """The gravity on the body y axis at ``t`` [m/s^2] (0 without a fresh fusion attitude)."""
        self._roll_ay_variance = 0.0
        if not self.roll_compensation:
            return 0.0
        item = self.attitude.at(t)
        if item is None or not is_fresh(t, item[0]):
            self.roll_source = "none (no fresh fusion attitude): lateral acceleration uncorrected"
            return 0.0
        self.roll_source = "fusion attitude"
        variance = item[2]
        self._roll_ay_variance = self.vehicle.gravity ** 2 * variance if math.isfinite(variance) else 0.0
        return self.vehicle.gravity * item[1]

    def _upstream(self, history: UpstreamHistory, t: float, default: float, what: str) -> float:
        item = history.at(t)
        missing = item is None or not is_fresh(t, item.stamp)
        self.set_missing(what, missing)
        return default if missing else item.value

    def on_imu(self, t: float, msg: Imu) -> None:
        imu = self.read_imu(msg)
        if imu is None:
            return
        f, w = imu
        f, w = self.bias.correct(t, f, w)
        fresh = self.chassis is not None and t - self.chassis_t <= self.stale_input_s
        self.set_missing("vehicle/joint_states", not fresh)
        if fresh:
            steer = self.chassis.steering_wheel_angle / self.vehicle.steering_ratio
            wheels = self.chassis.wheel_speeds
        else:
            steer, wheels = 0.0, np.full(4, np.nan)
        if not math.isfinite(steer):
            steer = 0.0
        self._steer = steer
        self._choose_filter(t)
        if (not self.core.initialised and (self.init_from_wheels or self.fallback_method is not None)
                and not np.isfinite(wheels).all()):
            # Starting from initial_vx while the car may be moving costs seconds of transient
            # (and a wrong slope and mass downstream): wait up to WHEEL_WAIT_S for the wheels
            # (and for a speed, where the filter needs one).
            if self._first_imu_t is None:
                self._first_imu_t = t
            if t - self._first_imu_t < WHEEL_WAIT_S:
                return
        # The filter steps at filter_rate_hz on the mean of the IMU samples since its last step:
        # a 200 Hz or 1 kHz IMU costs what a 100 Hz one does, and the mean is the better
        # measurement of the interval than any one sample.
        if self.core.learns_measurement_noise:
            add_stated_imu_covariances(self._imu_cov_sum, msg)
        self._z_sum += (f[0], f[1] - self._roll_gravity(t), w[2])
        self._roll_acceleration.add(w[0])
        self._z_count += 1
        if self.core.initialised and t - self._last_step_t < 1.0 / self.filter_rate - STAMP_TOLERANCE_S:
            return
        slope = self._upstream(self.slope, t, math.nan, SLOPE_INPUT)
        # Without the slope the filter assumes a level road and adds the grade's acceleration
        # error as process noise, so the variance says the estimate knows less.
        self.core.extra_vx_noise_density = (
            (self.missing_slope_noise_density if math.isnan(slope) else 0.0)
            + (0.0 if self._vx_measured or not self.core.initialised else self.dead_reckoning_noise_density))
        inputs = VehicleInputs(
            steer_angle=steer,
            wheel_speeds=wheels / speed_scale_at(self.speed_scale, t),
            slope=0.0 if math.isnan(slope) else slope,
            mass=self._upstream(self.mass, t, self.vehicle.mass, MASS_INPUT),
        )
        count = self._z_count
        z = self._z_sum / count
        z[1] += self._roll_acceleration.step(t)
        self._z_sum[:] = 0.0
        self._z_count = 0
        self._last_step_t = t
        reinitialisations = self.core.reinitialisations
        # The roll's error is the same over many filter steps: as white noise it weighs 2 tau/dt.
        roll_noise = self._roll_ay_variance * 2.0 * self.roll_error_correlation_s * self.filter_rate
        # A filter that learns R from its residuals learns too little where its model is
        # nearly exact (a straight road: it cannot tell the yaw rate's noise from its own
        # process noise); the IMU's stated noise of the step's mean is a floor under it: what
        # the learnt R falls short of it is added, so R is never below the sensor's own noise
        # and a learnt R above it is not counted twice.
        # turned into base_link once a step, not per sample: a turn is linear in the covariance
        floor = base_link_imu_variances(self._imu_cov_sum, self.bias.mounting_at(t)) / (count * count)
        self._imu_cov_sum[:] = 0.0
        if floor.any():
            floor = np.maximum(floor - self.core.measurement_noise_diagonal, 0.0)
        self.core.set_known_noise(ax=floor[0], ay=floor[1] + roll_noise, r=floor[2])
        if not self.core.step(t, inputs, z):
            self.reject("state:rejected_by_filter")
        if self.core.reinitialisations != reinitialisations:
            self.note_event(f"vehicle-state filter {self.core.last_event}")
        rear_wheels_measured = _rear_wheels_measured(wheels)
        if self.speed_fallback:
            self._update_speed_fallback(t, rear_wheels_measured)
        # Without a speed measurement vx integrates the accelerometer and drifts (between
        # corners, where they measure it), and the sideslip with it: still published, never
        # as converged.
        self._vx_measured = rear_wheels_measured or self.vx_source == VX_FROM_SPEED
        self._update_cornering_speed(t, z, self._vx_measured)
        if t - self._last_pub >= 1.0 / self.rate - STAMP_TOLERANCE_S:
            self._last_pub = t
            self.publish_state(t)

    def publish_state(self, t: float) -> None:
        x, P = np.asarray(self.core.x, dtype=float), np.asarray(self.core.P, dtype=float)
        if not (np.isfinite(x).all() and np.isfinite(P).all()):
            self.reject("state:non_finite")
            self.note_event("vehicle-state filter became non-finite: re-initialising")
            self.core.reset()
            return
        # The twist covariance, row-major 6 x 6 over (vx, vy, vz, roll, pitch, yaw rate): the
        # filter's (vx, vy, r) block; vz, roll rate and pitch rate are not estimated (1e6).
        (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = P[:3, :3].tolist()
        # A wheel radius's error lasts: the filter, weighing each wheel sample as new, cannot see
        # it. Added to a dead-reckoned vx too (which started from a wheel speed), so that the
        # slope and mass nodes, taking it out again, tell dead reckoning by the filter's own.
        p00 += speed_scale_error_variance(self.speed_scale, t) * float(x[0]) ** 2
        cov = (p00, p01, 0.0, 0.0, 0.0, p02,
               p10, p11, 0.0, 0.0, 0.0, p12,
               0.0, 0.0, 1e6, 0.0, 0.0, 0.0,
               0.0, 0.0, 0.0, 1e6, 0.0, 0.0,
               0.0, 0.0, 0.0, 0.0, 1e6, 0.0,
               p20, p21, 0.0, 0.0, 0.0, p22)
        twist = (float(x[0]), float(x[1]), 0.0, 0.0, 0.0, float(x[2]))
        self.publish(self.pub_state, self._state_layout.pack(sec_to_ns(t), twist + cov))
        if abs(x[0]) >= self.min_dynamic_speed:
            beta, beta_var = float(self.core.sideslip), float(self.core.sideslip_variance)
            converged = self._vx_measured and not (self.missing - self._fallbacks_in_variance)
        else:
            # Below the speed where the tyre model means anything (the core regularises slip
            # below ~3 m/s) the sideslip is kinematic: no tyre slip, beta = atan(lr tan(delta) / L).
            beta = math.atan(self.vehicle.lr * math.tan(self._steer) / self.vehicle.wheelbase)
            beta_var, converged = math.radians(5.0) ** 2, False
        beta_var = min(beta_var, (math.pi / 2) ** 2) if math.isfinite(beta_var) else (math.pi / 2) ** 2
        self.publish(self.pub_beta_stamped, companion_bytes(t, beta, beta_var, converged))
        self.publish(self.pub_beta, float64_bytes(beta))

    def reset_estimators(self) -> None:
        self._start_cores()
        self.bias.clear()
        self.slope.clear()
        self.mass.clear()
        self.attitude.clear()
        self.chassis = None
        self.speed = None
        self.speed_t = -math.inf
        self.speed_presence.reset()
        self._first_imu_t = None
        self._vx_measured = False
        self._last_pub = -math.inf
        self._z_sum[:] = 0.0
        self._imu_cov_sum[:] = 0.0
        self._z_count = 0
        self._last_speed_used_t = -math.inf
        self._roll_acceleration.reset()
        self._last_step_t = -math.inf

    def status_values(self) -> dict[str, str]:
        x = self.core.x
        extra = dict(self.core.status())
        extra["filter re-initialisations"] = str(self.core.reinitialisations)
        extra["vx source"] = self.vx_source
        extra["roll compensation"] = self.roll_source
        extra["roll compensation sigma [m/s^2]"] = f"{math.sqrt(self._roll_ay_variance):.3f}"
        running = self.filter_name if self.running_filter == self.filter_name else (
            f"{self.running_filter} (instead of {self.filter_name}, which needs a speed: "
            f"{'lost' if self.speed_presence.ever else 'none yet'})")
        return {**extra, "filter": running, "vx [m/s]": f"{x[0]:.3f}", "vy [m/s]": f"{x[1]:.4f}",
                "yaw rate [rad/s]": f"{x[2]:.4f}", "imu bias from fusion": str(self.bias.valid)}


def _rear_wheels_measured(wheel_speeds: np.ndarray) -> bool:
    """Whether both rear wheel speeds are there: the filters read vx from them."""
    return bool(np.isfinite(wheel_speeds[2:]).all())


def main(args: list[str] | None = None) -> int:
    return run_node(StateNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
