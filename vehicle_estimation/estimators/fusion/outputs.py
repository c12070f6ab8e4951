"""What the fusion publishes, in REP-103 terms: pose, velocity, grade, biases and their covariances,
and what its measurements observe now (GNSS aiding, the mounting's angles).

The filter's own attitude is the IMU's (``imu_link``, what the gyros integrate); every output
here is in ``base_link``, through the mounting rotation the filter refines (see
:mod:`vehicle_estimation.estimators.fusion.esekf`).

:class:`FusionOutputs` is a part of
:class:`~vehicle_estimation.estimators.fusion.esekf.FusionEKF`, written apart: it reads the
filter's state, declared below, and changes nothing.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from vehicle_estimation.estimators.common.rotations import euler_from_rotmat, rotmat_to_quat
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.error_state import IA, IBA, IBG, IK, IM, IP, IV, N_ERR, STATUS_RUNNING
from vehicle_estimation.estimators.fusion.lasting_speed_offset import LastingSpeedOffset

__all__ = ["FusionOutputs"]


def _copy_of(attribute: str, doc: str) -> Any:
    """A read-only property: a copy of the state array ``attribute``."""
    return property(lambda self: getattr(self, attribute).copy(), doc=doc)


def _covariance_block(start: int, size: int, doc: str) -> Any:
    """A read-only property: a copy of the diagonal block of P from ``start``."""
    return property(lambda self: self._P[start:start + size, start:start + size].copy(), doc=doc)


class FusionOutputs:
    """The outputs of :class:`FusionEKF` (a mixin of it)."""

    config: FusionConfig
    status: str
    t_heading_fixed: float
    _v: np.ndarray
    _w_lp: np.ndarray
    _w_nh: np.ndarray
    _w_nh_cornering: np.ndarray
    _t_cornering: float
    _R: np.ndarray
    _Rm: np.ndarray
    _ba: np.ndarray
    _bg: np.ndarray
    _speed_scale_error: np.ndarray
    _P: np.ndarray
    _eye3: np.ndarray
    _t: float | None
    _t_gnss: float | None
    _t_gnss_applied: float | None
    _speed_variance: float | None
    _lasting_speed: LastingSpeedOffset
    _is_stationary: Callable[[float], bool]
    _body_speed_rows: Callable[..., tuple]

    position_enu = _copy_of("_p", "Position in the ENU frame [m].")
    velocity_enu = _copy_of("_v", "Velocity in the ENU frame [m/s].")
    imu_rotation_matrix = _copy_of("_R", "imu_link -> ENU (the filter's own attitude).")
    mounting_rotation = _copy_of("_Rm", "imu_link -> base_link: the nominal mounting refined online.")
    accel_bias = _copy_of("_ba", "Accelerometer bias in imu_link [m/s^2] (measured = true + bias).")
    gyro_bias = _copy_of("_bg", "Gyro bias in imu_link [rad/s] (measured = true + bias).")
    covariance = _copy_of("_P", "18x18 error-state covariance, order [dp(ENU), dv(ENU), eps(ENU), "
                                "dba(imu_link), dbg(imu_link), dm (mounting pitch, yaw), dk (speed scale)].")
    velocity_covariance = _covariance_block(IV, 3, "ENU velocity covariance [m^2/s^2].")
    gyro_bias_covariance = _covariance_block(IBG, 3, "Gyro bias covariance [rad^2/s^2].")
    mounting_covariance = _covariance_block(IM, 2, "2x2 covariance of the mounting pitch and yaw "
                                                   "refinement [rad^2].")

    @property
    def speed_scale(self) -> float:
        """1 + k: the CAN speed over the body's forward speed (``estimate_speed_scale``; else 1)."""
        return 1.0 + float(self._speed_scale_error[0])

    @property
    def speed_scale_filter_variance(self) -> float:
        """The filter's own variance of the scale, without the floor that publishing adds (what a
        later drive resumes from, :meth:`resume_speed_scale`)."""
        return float(self._P[IK, IK]) if self.config.estimate_speed_scale else 0.0

    @property
    def speed_scale_variance(self) -> float:
        """Variance of :attr:`speed_scale` [-]: its prior until GNSS observes it, and always the
        quantised speed's lasting offset (``speed_scale_floor_sigma``); 0 when not estimated."""
        if not self.config.estimate_speed_scale:
            return 0.0
        return float(self._P[IK, IK]) + self.config.speed_scale_floor_sigma ** 2

    @property
    def position_covariance(self) -> np.ndarray:
        """ENU position covariance [m^2]; without GNSS with the speed's lasting offsets
        (``FusionConfig.lasting_speed_offset``)."""
        cov = self._P[IP:IP + 3, IP:IP + 3].copy()
        if not self.gnss_aided:
            if self.config.lasting_speed_offset:
                cov += self._lasting_speed.covariance
            if self.speed_scale_held:      # k d, d the distance since the last fix
                d = self._lasting_speed.distance
                cov += self.speed_scale_variance * np.outer(d, d)
        return cov

    @property
    def speed_scale_held(self) -> bool:
        """Whether the filter takes the speed's scale as known, its variance a consider term of the
        published velocity and position (``estimate_speed_scale`` while no GNSS position aids,
        and for ``speed_scale_after_s`` after GNSS fixed the heading)."""
        c = self.config
        settled = self._t is not None and self._t - self.t_heading_fixed >= c.speed_scale_after_s
        return c.estimate_speed_scale and not (self.gnss_aided and self.status == STATUS_RUNNING and settled)

    def _note_speed(self, t: float, speed: float, variance: float) -> None:
        """A CAN speed at stamp ``t`` as reported, once aligned (before, the forward axis is not
        yet in the position's frame), for the lasting offsets; a fix forgets them. Standing, the
        stationary update holds the position, not the speed: nothing accrues."""
        if self.gnss_aided:
            self._lasting_speed.reset()
        elif self.config.lasting_speed_offset or self.config.estimate_speed_scale:
            forward = np.zeros(3) if self._is_stationary(t) else self.rotation_matrix[:, 0]
            self._lasting_speed.add(t, speed, variance, forward)

    @property
    def gnss_aided(self) -> bool:
        """A valid fix has arrived within ``gnss_aiding_timeout_s``: the bias walks as in the
        paper (while the first fixes fix the heading too: they update the state seconds later)."""
        return (self._t_gnss is not None and self._t is not None
                and self._t - self._t_gnss <= self.config.gnss_aiding_timeout_s)

    def mounting_columns(self) -> tuple[bool, bool]:
        """Whether the body-velocity measurements refine the mounting pitch and yaw now: with
        GNSS always; without it only from ``mounting_min_speed_without_gnss`` up, and the pitch
        only while the low-passed yaw rate stays below ``mounting_max_yaw_rate_without_gnss``.

        The mounting enters them as the body velocity times its angle. Pulling away, that
        product is millimetres per second, less than what the constraints' model misses there
        (the body pitching under the first acceleration, the CAN speed's quantisation), and
        without GNSS nothing takes back what the mounting then learnt: on a 36 t truck without
        GNSS the mounting pitch took the start's errors and kept them (slope RMSE 0.24 deg, mass
        11 % low; with the gate 0.12 deg and 5.4 %). The mounting keeps its covariance and its
        correlations below that speed, so what other states learn still reaches it.

        In a corner the constraints miss the sideslip and the roll, and without GNSS nothing
        pins the lateral velocity: on CommonRoad's lane change without GNSS the mounting pitch
        took +0.4 deg there, one to one in the slope node's bias-corrected specific force (a
        slope 0.38 deg off on a level road, beyond its 2 sigma on 16 % of the drive). Its yaw
        keeps learning: held too, the step steer's slope RMSE was 0.37 deg instead of 0.24.
        """
        if not self.config.estimate_mounting:
            return False, False
        v = self._v
        speed_sq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        pitch, yaw = self._mounting_min_speeds()
        return bool(speed_sq >= pitch * pitch), bool(speed_sq >= yaw * yaw)

    def _mounting_min_speeds(self) -> tuple[float, float]:
        """The speeds from which the constraints refine the mounting pitch and yaw now
        (:meth:`mounting_columns`); infinite: not at all (so the compiled kernels gate alike)."""
        if self.gnss_aided:
            return 0.0, 0.0
        speed = self.config.mounting_min_speed_without_gnss
        return (math.inf if self._cornering() else speed), speed

    def _cornering(self) -> bool:
        """The low-passed yaw rate about base_link z is above ``mounting_max_yaw_rate_without_gnss``:
        the sideslip and the body roll, which the vehicle constraints do not model, are more
        than they can tell apart from the state without GNSS."""
        return abs(float(self._Rm[2] @ self._w_lp)) > self.config.mounting_max_yaw_rate_without_gnss

    def _moving_constraint_noise(self) -> np.ndarray:
        """W of the lateral and vertical constraints of a moving vehicle at the current IMU
        stamp: without GNSS, in a corner and ``nh_cornering_hold_s`` after it (``_t_cornering``,
        the last IMU stamp that ended in a corner), the vertical one at
        ``nh_sigma_z_cornering_without_gnss``.

        The tight vertical constraint is there for the pitch and the mounting pitch (on a
        straight, the body's vertical velocity is the pitch error times the speed). In a corner
        it also sees the roll error times the filter's lateral velocity, and that velocity is
        off by the sideslip and the roll sway the lateral constraint does not model; without
        GNSS nothing else pins it, and the filter took what the two constraints missed for a
        roll it was sure of: on CommonRoad's lane change without GNSS the roll was 1.6 deg off
        (RMS) at a sigma of 0.7 deg, 52 % within 2 sigma, NEES 38. With the looser constraint
        there: 0.40 deg, 100 %, 0.20 (GNSS: 100 %, 0.25, unchanged)."""
        if self.gnss_aided or self._t is None:
            return self._w_nh
        return self._w_nh_cornering if self._t - self._t_cornering <= self.config.nh_cornering_hold_s else self._w_nh

    @property
    def vertical_constraint_sigma(self) -> float:
        """The vertical non-holonomic constraint's std for a moving vehicle now [m/s]: above
        ``nh_sigma_z`` while it is loosened after a corner without GNSS."""
        return math.sqrt(float(self._moving_constraint_noise()[1, 1]))

    @property
    def accel_bias_observed(self) -> bool:
        """GNSS has aided the filter since the alignment, so its accelerometer bias is more than
        the prior (and held at what it learned through a later outage)."""
        return self._t_gnss_applied is not None

    @property
    def velocity_body(self) -> np.ndarray:
        """Velocity in base_link (FLU) [m/s]."""
        return self._Rm @ (self._R.T @ self._v)

    @property
    def rotation_matrix(self) -> np.ndarray:
        """base_link -> ENU."""
        return self._R @ self._Rm.T

    @property
    def quaternion(self) -> np.ndarray:
        """(x, y, z, w), base_link FLU -> ENU."""
        return rotmat_to_quat(self.rotation_matrix)

    @property
    def mounting_rpy(self) -> np.ndarray:
        """Roll, pitch, yaw of imu_link in base_link [rad]."""
        return np.asarray(euler_from_rotmat(self._Rm), float)

    @property
    def roll(self) -> float:
        return euler_from_rotmat(self.rotation_matrix)[0]

    @property
    def pitch(self) -> float:
        """REP-103 pitch of base_link about its y axis (positive = nose DOWN)."""
        return euler_from_rotmat(self.rotation_matrix)[1]

    @property
    def yaw(self) -> float:
        return euler_from_rotmat(self.rotation_matrix)[2]

    @property
    def road_grade(self) -> float:
        """Angle of the base_link x axis above the horizontal [rad], positive nose-up/uphill."""
        return math.asin(max(-1.0, min(1.0, float(self._R[2] @ self._Rm[0]))))

    @property
    def velocity_body_covariance(self) -> np.ndarray:
        """base_link (FLU) velocity covariance, including the attitude and mounting
        uncertainty (for nav_msgs/Odometry twist, which is in the child/body frame).

        Without GNSS the CAN speed is the only absolute velocity, and its error (a quantisation
        offset) lasts while the speed stays in one step: no averaging removes it, so the forward
        variance is not published below the speed's own stated variance. (The filter weighs that
        speed as correlated over ``speed_error_correlation_s`` and computed 0.045 m/s on FASTSim's
        car without GNSS, where a 1 km/h step leaves 0.07 m/s: NEES 2.5.)"""
        v_body, H = self._body_speed_rows([0, 1, 2], (self.config.estimate_mounting,) * 2)
        cov = H @ self._P @ H.T
        if self._speed_variance is not None and not self.gnss_aided and cov[0, 0] < self._speed_variance:
            cov[0, 0] = self._speed_variance
        if self.speed_scale_held:          # the speed's held scale error, k v_x
            cov[0, 0] += self.speed_scale_variance * float(v_body[0]) ** 2
        return cov

    def _base_attitude_jacobian(self) -> np.ndarray:
        """J with eps_base = J z: R_wb,true = (I - S(eps_base)) R_wb,hat.

        R_wb = R R_m^T; R_m,true^T = R_m^T (I - S(dm)), so eps_base = eps + R_wb [0, dm]."""
        J = np.zeros((3, N_ERR))
        J[:, IA:IA + 3] = self._eye3
        J[:, IM:IM + 2] = (self._R @ self._Rm.T)[:, 1:3]
        return J

    @property
    def attitude_covariance(self) -> np.ndarray:
        """base_link attitude error covariance about the fixed ENU x, y, z axes [rad^2]
        (the sensor_msgs/Imu and nav_msgs/Odometry convention)."""
        J = self._base_attitude_jacobian()
        return J @ self._P @ J.T

    @property
    def pose_attitude_covariance(self) -> np.ndarray:
        """:attr:`attitude_covariance` of the attitude as ``estimation/odometry`` publishes it, with
        what P cannot know about the vehicle's tilt. Until GNSS has observed the accelerometer bias,
        its prior along base_link x enters as a pitch and along y as a roll (a bias b reads as a
        tilt of b / g), as in :attr:`road_grade_variance`; and the nominal mounting roll, which no
        constraint refines, enters the roll by ``mounting_roll_sigma`` (P's attitude is the IMU's;
        the car's differs from it by the mounting error). ``estimation/imu`` keeps
        :attr:`attitude_covariance` whole: its orientation goes with its compensated specific
        force, where the tilt's and the bias's errors cancel (P knows their sum), and the
        vehicle-state node removes gravity from the lateral force with that pair."""
        axes = self.rotation_matrix                     # base_link x (roll) and y (pitch) in ENU
        tilt = self._unaided_bias_variance / self.config.gravity ** 2
        roll = tilt + self.config.mounting_roll_sigma ** 2
        return (self.attitude_covariance + tilt * np.outer(axes[:, 1], axes[:, 1])
                + roll * np.outer(axes[:, 0], axes[:, 0]))

    @property
    def _unaided_bias_variance(self) -> float:
        return 0.0 if self.accel_bias_observed else self.config.unaided_accel_bias_sigma ** 2

    @property
    def accel_bias_covariance(self) -> np.ndarray:
        """In imu_link, including, until GNSS has observed it, the unaided term on every axis
        (see ``FusionConfig.unaided_accel_bias_sigma``): on the horizontal ones the prior no
        constraint tells from the tilt; on the vertical one what the held bias misses, which the
        vertical constraint would let P learn ever more surely (a bias that drifts, a gravity
        a little off: P 2e-4 m/s^2 for a 0.007 m/s^2 error on our demo, NEES 840)."""
        P = self._P[IBA:IBA + 3, IBA:IBA + 3].copy()
        return P + self._unaided_bias_variance * self._eye3

    @property
    def road_grade_variance(self) -> float:
        """Variance of ``road_grade`` [rad^2] from the attitude covariance.

        grade = asin(e_z . R_wb e_x);  with R_wb,true = (I - S(eps_b)) R_wb,hat,
        d(grade) = -(eps_b,x b_y - eps_b,y b_x) / cos(grade),  b = R_wb,hat e_x.
        """
        b = self.rotation_matrix[:, 0]
        cg = max(math.sqrt(max(0.0, 1.0 - b[2] * b[2])), 1e-6)
        j = np.array([-b[1], b[0], 0.0]) / cg
        j = j @ self._base_attitude_jacobian()
        # Without GNSS the grade is the kinematic one, (f_x - b_x - dv/dt) / g: the unobserved
        # bias is in it one to one.
        return float(j @ self._P @ j) + self._unaided_bias_variance / (self.config.gravity * cg) ** 2

    @property
    def pitch_variance(self) -> float:
        """Variance of REP-103 pitch (= variance of road_grade, pitch = -grade)."""
        return self.road_grade_variance

    def compensated_imu(self, specific_force, angular_rate) -> tuple:
        """Bias-removed (specific force, angular rate), Eq. (22), rotated into base_link."""
        return (self._Rm @ (np.asarray(specific_force, float) - self._ba),
                self._Rm @ (np.asarray(angular_rate, float) - self._bg))
