"""Fusion node: IMU + GNSS + CAN speed in the error-state EKF of paper 003 (Sec. 5, Alg. 1).

Subscribes (sensor-data QoS): ``imu/data``, ``gnss/fix``, ``vehicle/speed`` and, for the
wheel-speed fallback, ``vehicle/joint_states``: while ``vehicle/speed`` is missing or stale
(``fusion.speed_timeout_s``), the mean speed of the undriven wheels times
``vehicle.wheel_radius`` is the speed the filter aligns and navigates with, and
``/diagnostics`` says so (``speed source``).
Publishes: ``estimation/odometry`` (pose in ENU ``odom``, twist in ``base_link``; the tilt's
covariance with what no sensor separates from it: the mounting roll, an unaided bias),
``estimation/imu`` (bias-compensated IMU with the estimated orientation and the filter's own
covariance of it, the attitude its specific force goes with; at ``imu_rate_hz``) and
``estimation/fusion/road_grade`` (pitch-derived grade, stamped companion: x = grade [rad,
+uphill], y = variance, z = converged) and ``estimation/datum`` (latched).

The ENU origin of ``odom`` is the first valid GNSS fix; fixes with ``status.status < 0`` are
ignored and counted. Once the GNSS track has fixed the heading, ``odom`` is ENU about that
origin, and ``estimation/datum`` (sensor_msgs/NavSatFix, transient local, stamped then) gives
it in WGS84: what a consumer needs to put the pose on a map, and the report to compare it
with a truth given in another frame. Without GNSS (a car that has none, or before the first
fixes show the heading) every output is still published once the filter has aligned:
``odom`` is then the pose at alignment with a free heading, the position is dead-reckoned and
its covariance grows, and ``/diagnostics`` says so (``heading source``, ``position source``
and a ``missing`` entry).

Persistence: with ``persist.path`` set (the launcher sets it: ``run`` under ``--state-dir``,
``replay --state-dir``) the learnt speed scale and its variance are saved every
``persist.period_s`` of message time, and the next start, the next drive too, resumes from them
(:meth:`FusionEKF.resume_speed_scale`): a tyre's radius outlives a drive.
"""

from __future__ import annotations

import math

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
from vehicle_estimation.estimators.common.noise import SuccessiveDifferenceNoise, with_floor
from vehicle_estimation.estimators.common.rotations import rotmat_to_quat
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.esekf import FusionEKF
from vehicle_estimation.estimators.fusion.mounting_check import MountingYawCheck
from vehicle_estimation.ros.conversions import MAX_SPEED, MalformedMessage, chassis_reading, stated_covariance
from vehicle_estimation.ros.runtime.node import EstimatorNode
from vehicle_estimation.ros.runtime.spin import run_node
from vehicle_estimation.ros.cdr import StampedLayout
from vehicle_estimation.ros.persistence import PersistedState
from vehicle_estimation.ros.stamps import STAMP_TOLERANCE_S, sec_to_ns, stamp_ns, stamp_to_sec
from vehicle_estimation.ros.runtime.upstream import companion_bytes

FUSION_GRADE = topics.FUSION_GRADE
#: Floor of the wheel-speed fallback's std (wheel-speed resolution at a crawl) [m/s].
WHEEL_SPEED_FLOOR_STD = 0.05
SPEED_FROM_CAN, SPEED_FROM_WHEELS = "vehicle/speed", "wheel speeds (no vehicle/speed)"
FREE_HEADING = ("gnss/fix: no heading from GNSS yet, so free heading: odom = the pose at alignment, "
                "position dead-reckoned")


class FusionNode(EstimatorNode):
    def __init__(self, **node_kwargs) -> None:
        super().__init__("fusion", **node_kwargs)
        # FusionConfig as fusion.* parameters (Tables 2-3 defaults where the paper gives one).
        # How long GNSS aids after a fix: the mass node must agree, so it is one node-level
        # parameter (set under /**), not fusion.gnss_aiding_timeout_s.
        timeout = self.declare_shared_setting(FusionConfig, "gnss_aiding_timeout_s")
        # The IMU's nominal mounting is the vehicle's (every node turns the IMU by it), not fusion.*.
        self.vehicle = self.declare_vehicle()
        # One gravity for every node: the vehicle file's (local g; a simulator's own constant).
        config = self.declare_config("fusion", FusionConfig(gnss_aiding_timeout_s=timeout,
                                                            mounting_rpy=self.vehicle.imu_mounting_rpy,
                                                            gravity=self.vehicle.gravity),
                                     exclude=("gnss_aiding_timeout_s", "mounting_rpy", "gravity"))
        self.config = config
        self.odometry_rate = self.declare_float(
            "odometry_rate_hz", 50.0, "Rate of estimation/odometry and the grade [Hz]", 0.1, 1000.0)
        self.base_frame = self.declare_str("base_frame", topics.BASE_FRAME, "Body frame id")
        self.odom_frame = self.declare_str("odom_frame", topics.ODOM_FRAME, "ENU world frame id")

        self.ekf = FusionEKF(config)
        # The tyres' rolling radius outlives a drive: the speed's scale that GNSS taught one drive
        # starts the next (without GNSS nothing else can teach it).
        self.persisted = PersistedState(self, self.declare_str(
            "persist.path", "", "File the CAN speed's learnt scale (fusion.estimate_speed_scale) is saved "
            "to and resumed from, in the next drive too; empty: off. The launcher sets it"),
            "fusion/speed_scale", self.vehicle.name,
            self.declare_float("persist.period_s", 10.0, "Save period on the message clock [s]", 0.01, 3600.0),
            "speed scale")
        if config.estimate_speed_scale:
            self._resume_speed_scale()
        # The mounting states refine a few degrees; a nominal yaw tens of degrees off is named.
        self.yaw_check = MountingYawCheck(self.vehicle.imu_mounting_rpy)
        self.origin: LocalTangentPlane | None = None
        self._last_odom_t = -math.inf
        self._last_angular_rate = np.zeros(3)
        # The published rates are single compensated samples: their covariance holds the gyro's
        # noise (the larger of what the IMU states and what its samples show) and the bias's.
        self.gyro_noise = SuccessiveDifferenceNoise()

        self.pub_odom = self.publisher(Odometry, topics.ODOMETRY)
        self.pub_imu = self.publisher(Imu, topics.IMU_COMPENSATED)
        self.pub_grade = self.publisher(Vector3Stamped, FUSION_GRADE)
        self.pub_bias = self.publisher(Imu, topics.IMU_BIAS)
        # always advertised (the replay's start-up waits for every subscription's publisher),
        # published only where the scale is estimated
        self.pub_speed_scale = self.publisher(Vector3Stamped, topics.SPEED_SCALE)
        self.pub_datum = self.publisher(NavSatFix, topics.DATUM, latched=True)
        self._origin_fix: NavSatFix | None = None      # a copy: a subscription may reuse its message
        self._datum_published = False
        self._imu_layout = StampedLayout(self.base_frame, 37)
        self._odom_layout = StampedLayout(self.odom_frame, 85, child_frame_id=self.base_frame)
        self.bias_rate = self.declare_float(
            "bias_rate_hz", 10.0, "Rate of estimation/imu_bias [Hz]", 0.1, 1000.0)
        # Each publish costs ~0.1 ms of Python and DDS: at the IMU rate this output alone was a
        # third of the node's CPU. Set it at or above the IMU rate for every sample.
        self.imu_rate = self.declare_float(
            "imu_rate_hz", 50.0, "Rate of estimation/imu (compensated IMU; the vehicle-state node "
            "takes its roll from it) [Hz]", 0.1, 10000.0)
        self._last_bias_t = -math.inf
        self._last_imu_pub_t = -math.inf
        self.subscribe_primary(Imu, topics.IMU, self.on_imu)
        self.subscribe_primary(NavSatFix, topics.GNSS, self.on_gnss)
        self.subscribe_primary(TwistWithCovarianceStamped, topics.SPEED, self.on_speed)
        self.wheel_speed_fallback = self.declare_bool(
            "wheel_speed_fallback", True,
            "While vehicle/speed is missing or older than fusion.speed_timeout_s, use the undriven "
            "wheels' mean speed x vehicle.wheel_radius as the speed (vehicle/joint_states)")
        self._undriven_wheels = list(self.vehicle.undriven_wheels)
        self.wheel_speed_std = self.declare_float(
            "wheel_speed_std", 0.01, "Relative std of the wheel-speed fallback's speed (the rolling "
            "radius's uncertainty: tyre wear, pressure, load) [-]", 0.0, 0.2)
        self._can_speed_t = -math.inf
        self._wheel_speed_t = -math.inf
        self._imu_t = -math.inf
        if self.wheel_speed_fallback:
            self.subscribe_primary(JointState, topics.JOINT_STATES, self.on_joint_states)

    # -------------------------------------------------------------- inputs
    def on_imu(self, t: float, msg: Imu) -> None:
        imu = self.read_imu(msg)
        if imu is None:
            return
        f, w = imu
        self._imu_t = t
        self._last_angular_rate = w
        self.gyro_noise.add(w)
        self.yaw_check.add_imu(t, f, w)
        if not self.ekf.process_imu(t, f, w):
            self.reject("imu:out_of_order")
            return
        if not self.ekf.navigating:
            self.set_missing("initialisation: " + self.ekf.status, True)
            return
        self.missing.difference_update([m for m in self.missing if m.startswith("initialisation")])
        # The fallback without GNSS, named in /diagnostics: outputs go on, the pose is relative.
        self.set_missing(FREE_HEADING, not self.ekf.initialized)
        imu_due = t - self._last_imu_pub_t >= 1.0 / self.imu_rate - STAMP_TOLERANCE_S
        odometry_due = t - self._last_odom_t >= 1.0 / self.odometry_rate - STAMP_TOLERANCE_S
        if imu_due or odometry_due:
            # both carry this sample's compensated rate: one covariance for the two
            rate_covariance = self._angular_rate_covariance(msg)
            if imu_due:
                self._last_imu_pub_t = t
                self.publish_imu(t, msg, f, w, rate_covariance)
            if odometry_due:
                self._last_odom_t = t
                self.publish_odometry(t, rate_covariance)
        # Right after an in-motion alignment the bias estimate is still rough; with GNSS the
        # heading follows within seconds, and downstream nodes do better on raw samples until
        # then (measured: the paper-004 experiment's slope over its first 20 s). Without GNSS
        # there is nothing to wait for, and the bias goes out from the alignment on.
        bias_ready = self.ekf.initialized or self.origin is None
        if bias_ready and t - self._last_bias_t >= 1.0 / self.bias_rate - STAMP_TOLERANCE_S:
            self._last_bias_t = t
            self.publish_bias(msg)

    def on_gnss(self, t: float, msg: NavSatFix) -> None:
        if msg.status.status < NavSatStatus.STATUS_FIX:
            self.reject("gnss:no_fix")
            return
        if not all(math.isfinite(v) for v in (msg.latitude, msg.longitude, msg.altitude)) or abs(msg.latitude) > 90.0 \
                or abs(msg.longitude) > 180.0:
            self.reject("gnss:invalid_position")
            return
        if self.origin is None:
            self.origin = LocalTangentPlane(msg.latitude, msg.longitude, msg.altitude)
            self._origin_fix = NavSatFix(
                status=NavSatStatus(status=int(msg.status.status), service=int(msg.status.service)),
                latitude=msg.latitude, longitude=msg.longitude, altitude=msg.altitude,
                position_covariance=[float(c) for c in msg.position_covariance],
                position_covariance_type=int(msg.position_covariance_type))
            self.note_event(f"ENU origin set at {msg.latitude:.7f}, {msg.longitude:.7f}, "
                            f"{msg.altitude:.2f} m")
        enu = np.asarray(self.origin.to_enu(msg.latitude, msg.longitude, msg.altitude), dtype=float)
        cov = None
        if msg.position_covariance_type != NavSatFix.COVARIANCE_TYPE_UNKNOWN:
            c = np.array(msg.position_covariance, dtype=float).reshape(3, 3)
            if np.isfinite(c).all() and np.all(np.diag(c) > 0.0):
                cov = c
        if not self.ekf.update_gnss(t, enu, cov):
            self.reject("gnss:rejected_by_filter")

    def on_speed(self, t: float, msg: TwistWithCovarianceStamped) -> None:
        reading = self.read_speed(msg)
        if reading is None:
            return
        v, var = reading
        self._can_speed_t = t
        self.yaw_check.add_speed(t, v)
        if not self.ekf.update_speed(t, v, None if math.isnan(var) else var):
            self.reject("speed:rejected_by_filter")

    def on_joint_states(self, t: float, msg: JointState) -> None:
        """The wheel-speed fallback: only while vehicle/speed is missing or stale."""
        if t - self._can_speed_t <= self.config.speed_timeout_s:
            return
        try:
            wheels = chassis_reading(msg).wheel_speeds[self._undriven_wheels]
        except MalformedMessage:
            self.reject("joint_states:malformed")
            return
        if not np.isfinite(wheels).all():
            return                  # no wheel speeds in this message (steering only, say)
        v = float(np.mean(wheels)) * self.vehicle.wheel_radius
        if abs(v) > MAX_SPEED:
            self.reject("joint_states:implausible")
            return
        self._wheel_speed_t = t
        self.yaw_check.add_speed(t, v)
        variance = (self.wheel_speed_std * v) ** 2 + WHEEL_SPEED_FLOOR_STD ** 2
        if not self.ekf.update_speed(t, v, variance):
            self.reject("joint_states:speed_rejected_by_filter")

    # -------------------------------------------------------------- outputs
    def publish_imu(self, t: float, raw: Imu, f: np.ndarray, w: np.ndarray, rate_covariance: np.ndarray) -> None:
        fc, wc = self.ekf.compensated_imu(f, w)
        # raw may be a message or a ros.cdr view: its stamp and covariances are read, not copied
        values = np.concatenate((self.ekf.quaternion, np.ravel(self.ekf.attitude_covariance), wc,
                                 np.ravel(rate_covariance), fc,
                                 np.ravel(self._specific_force_covariance(raw))))
        self.publish(self.pub_imu, self._imu_layout.pack(stamp_ns(raw.header.stamp), values.tolist()))

    def publish_datum(self, t: float) -> None:
        """odom's origin in WGS84, from this pose on ENU about it (before: the free frame)."""
        msg = self._origin_fix
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(sec_to_ns(t), 1_000_000_000)
        msg.header.frame_id = self.odom_frame
        self.publish(self.pub_datum, msg)
        self._datum_published = True
        # logged, not a /diagnostics event: after a reset the last event stays the reset's
        self.get_logger().info(f"odom is ENU about {msg.latitude:.9f}, {msg.longitude:.9f}, "
                               f"{msg.altitude:.3f} m (estimation/datum)")

    def publish_bias(self, raw: Imu) -> None:
        """The IMU bias estimate in sensor_msgs/Imu form (see ros.runtime.upstream.FusionImuBias)."""
        ekf = self.ekf
        # orientation: the IMU mounting, imu_link -> base_link (REP-145 IMUs report in
        # imu_link); consumers rotate bias-corrected samples with it.
        mount_cov = np.zeros((3, 3))
        mount_cov[1:, 1:] = ekf.mounting_covariance
        values = np.concatenate((rotmat_to_quat(ekf.mounting_rotation), mount_cov.ravel(),
                                 ekf.gyro_bias, np.ravel(ekf.gyro_bias_covariance),
                                 ekf.accel_bias, np.ravel(ekf.accel_bias_covariance)))
        self.publish(self.pub_bias, self._imu_layout.pack(stamp_ns(raw.header.stamp), values.tolist()))
        if ekf.config.estimate_speed_scale:
            # what the wheels and the CAN speed read over the true speed; "converged" once GNSS
            # has halved its prior's sigma
            variance = ekf.speed_scale_variance
            observed = variance <= (0.5 * ekf.config.p0_speed_scale_sigma) ** 2
            t = stamp_to_sec(raw.header.stamp)
            self.publish(self.pub_speed_scale, companion_bytes(t, ekf.speed_scale, variance, observed,
                                                               self.base_frame))
            if self.persisted.due(t):
                self.persisted.save(t, {"scale": ekf.speed_scale, "variance": ekf.speed_scale_filter_variance})

    def _resume_speed_scale(self) -> None:
        loaded = self.persisted.resume()
        if loaded is None:
            return
        stamp, state = loaded
        try:
            variance = self.ekf.resume_speed_scale(state["scale"], state["variance"])
        except (KeyError, ValueError) as exc:
            self.persisted.refuse(exc)
            return
        self.note_event(f"resumed the speed scale {state['scale']:.4f} +- {math.sqrt(variance):.4f} "
                        f"(saved at stamp {stamp:.3f})")

    def _base_link(self, cov: np.ndarray) -> np.ndarray:
        Rm = self.ekf.mounting_rotation
        return Rm @ cov @ Rm.T

    def _angular_rate_covariance(self, raw) -> np.ndarray:
        """Of one compensated gyro sample, in base_link: its noise and the bias estimate's."""
        noise = with_floor(stated_covariance(raw.angular_velocity_covariance), self.gyro_noise.variance)
        return self._base_link(noise + self.ekf.gyro_bias_covariance)

    def _specific_force_covariance(self, raw) -> np.ndarray:
        """Of one compensated accelerometer sample, in base_link: its stated noise and the bias
        estimate's; unknown (all zeros, sensor_msgs/Imu) when the IMU states none."""
        stated = stated_covariance(raw.linear_acceleration_covariance)
        if stated is None or not stated.any():
            return np.zeros((3, 3))
        return self._base_link(stated + self.ekf.accel_bias_covariance)

    def publish_odometry(self, t: float, rate_covariance: np.ndarray) -> None:
        ekf = self.ekf
        p, v_body, q = ekf.position_enu, ekf.velocity_body, ekf.quaternion
        if not (np.isfinite(p).all() and np.isfinite(v_body).all() and np.isfinite(q).all()):
            self.reject("fusion:non_finite_state")
            self.note_event("fusion state became non-finite: resetting")
            self.reset_estimators()
            return
        pose_cov = np.zeros((6, 6))
        pose_cov[:3, :3] = ekf.position_covariance
        pose_cov[3:, 3:] = ekf.pose_attitude_covariance
        _, wc = ekf.compensated_imu(np.zeros(3), self._last_angular_rate)
        twist_cov = np.zeros((6, 6))
        twist_cov[:3, :3] = ekf.velocity_body_covariance
        twist_cov[3:, 3:] = rate_covariance
        values = np.concatenate((p, q, pose_cov.ravel(), v_body, wc, twist_cov.ravel()))
        if ekf.initialized and not self._datum_published and self._origin_fix is not None:
            self.publish_datum(t)
        self.publish(self.pub_odom, self._odom_layout.pack(sec_to_ns(t), values.tolist()))
        grade_var = float(ekf.road_grade_variance)
        self.publish(self.pub_grade, companion_bytes(t, float(ekf.road_grade), grade_var,
                                                     grade_var < (0.5 * math.pi / 180.0) ** 2, self.base_frame))

    # -------------------------------------------------------------- bookkeeping
    def reset_estimators(self) -> None:
        self.ekf.reset()
        self._datum_published = False       # the heading is free again until GNSS fixes it
        self.yaw_check.reset()
        self.gyro_noise.reset()
        self._last_odom_t = -math.inf
        self._last_bias_t = -math.inf
        self._last_imu_pub_t = -math.inf
        self._can_speed_t = -math.inf
        self._wheel_speed_t = -math.inf
        self._imu_t = -math.inf

    @property
    def speed_source(self) -> str:
        """Which speed the filter navigates with now (the IMU's stamp is now)."""
        timeout = self.config.speed_timeout_s
        if self._imu_t - self._can_speed_t <= timeout:
            return SPEED_FROM_CAN
        if self._imu_t - self._wheel_speed_t <= timeout:
            return SPEED_FROM_WHEELS
        if math.isfinite(max(self._can_speed_t, self._wheel_speed_t)):
            return "none now (the velocity is the IMU's integral)"
        return "none yet"

    def status_values(self) -> dict[str, str]:
        ekf = self.ekf
        values = {"filter status": ekf.status, "initialized": str(ekf.initialized),
                  "heading source": "GNSS motion" if ekf.initialized else "free (no GNSS heading yet)",
                  "position source": "GNSS" if self.origin is not None else "dead reckoning (no GNSS fix)",
                  "speed source": self.speed_source, "IMU yaw check": self.yaw_check.status()}
        if ekf.navigating:
            values.update({
                "road grade [deg]": f"{math.degrees(ekf.road_grade):.3f}",
                "accel bias [m/s^2]": np.array2string(ekf.accel_bias, precision=4),
                # Without GNSS the bias and the grade are one unobservable sum (FusionConfig).
                "accel bias estimation": (
                    "GNSS-aided" if ekf.gnss_aided
                    else "held through a GNSS outage" if ekf.accel_bias_observed
                    else "held at its prior (no GNSS yet): the grade is kinematic, its variance "
                         "carries the prior"),
                "gyro bias [rad/s]": np.array2string(ekf.gyro_bias, precision=6),
                "IMU mounting rpy [deg]": np.array2string(np.degrees(ekf.mounting_rpy), precision=3),
            })
            if ekf.config.estimate_mounting:
                pitch, yaw = ekf.mounting_columns()
                values["IMU mounting estimation"] = (
                    "GNSS-aided" if ekf.gnss_aided
                    else "refined by the vehicle constraints (no GNSS)" if pitch
                    else "yaw refined, pitch held in a corner (no GNSS)" if yaw
                    else f"held below {ekf.config.mounting_min_speed_without_gnss:g} m/s without GNSS")
            if ekf.config.estimate_speed_scale:
                values["speed scale (CAN / true)"] = (f"{ekf.speed_scale:.4f} +- "
                                                      f"{math.sqrt(ekf.speed_scale_variance):.4f}")
            sigma = ekf.vertical_constraint_sigma
            values["vertical constraint"] = f"{sigma:g} m/s" + (
                " (loosened after a corner: no GNSS)" if sigma > ekf.config.nh_sigma_z else "")
        for k, v in getattr(ekf, "rejected", {}).items():
            values[f"filter rejected {k}"] = str(v)
        for k, v in getattr(ekf, "events", {}).items():     # imu_gap, align_restart, ...
            values[f"filter event {k}"] = str(v)
        return values


    def status_summary(self) -> tuple[int, str]:
        level, message = super().status_summary()
        if self.yaw_check.mismatched:       # every node reads the IMU in the wrong axes
            return DiagnosticStatus.WARN, self.yaw_check.status() + ("" if level == DiagnosticStatus.OK
                                                                     else "; " + message)
        return level, message


def main(args: list[str] | None = None) -> int:
    return run_node(FusionNode, args)


if __name__ == "__main__":
    raise SystemExit(main())
