"""IMU / GNSS / CAN-speed / vehicle-model fusion: error-state EKF (pure numpy, no ROS).

Implements paper 003 (Jensen, Nielsen, Pedersen, Hansen, Stoustrup 2022, "Online
estimation of vehicle mass ...", MSSP 171, 108925), Sec. 5 and Alg. 1:

* Sec. 5.2 INS mechanisation: bias calibration Eq. (22), quaternion attitude
  propagation Eqs. (23)-(24), specific force to navigation frame Eqs. (25)-(26),
  gravity compensation Eq. (27), position/velocity integration Eqs. (28)-(29).
* Sec. 5.3 error-state EKF: 15-state error vector [dp, dv, eps, dba, dbg], Eq. (30)-(32),
  small-angle attitude error R_true = (I - S(eps)) R_hat, Eq. (31); discrete error
  dynamics F, G, Eq. (33)-(34); covariance propagation Eq. (35)-(36); gain Eq. (37);
  error injection and reset Eqs. (40)-(43); covariance update Eq. (44) (here in
  Joseph form, which is algebraically identical for the optimal gain).
* Sec. 5.4 measurements, Eqs. (45)-(47): GNSS position (navigation frame), CAN-bus
  longitudinal speed (body x), non-holonomic (NH) pseudo-measurements of zero lateral
  and vertical body speed applied at every IMU sample, and stationary updates (NH
  variances greatly reduced when CAN speed says the vehicle stands still).
* Sec. 7.1 initialisation: roll/pitch from the averaged accelerometer at standstill,
  gyro bias = mean of ``init_stationary_samples`` (200) stationary gyro samples,
  accelerometer bias zero, yaw from GNSS motion once the vehicle moves. Until then (for
  ever without GNSS) the filter navigates with a free heading (:attr:`FusionEKF.navigating`).
  It is :class:`~vehicle_estimation.estimators.fusion.initialisation.FusionInitialisation`,
  the outputs in REP-103 terms are
  :class:`~vehicle_estimation.estimators.fusion.outputs.FusionOutputs` and the tuning is
  :class:`~vehicle_estimation.estimators.fusion.config.FusionConfig`; this module is the
  filter itself.

Beyond the paper: IMU mounting states.  The paper's IMU was calibrated to the body; a
car's IMU sits in ``imu_link``, rotated from ``base_link`` by a mounting rotation known
only to a degree or so (REP-145).  The filter's attitude is the IMU's (what the gyros
integrate), and two extra error states, the mounting pitch and yaw (about base_link y and
z, whichever way the IMU is turned), map it to the vehicle: the non-holonomic and
CAN-speed constraints hold in ``base_link``, not in ``imu_link``, and they make the two
angles observable once the car moves (pitch through the vertical constraint and the GNSS
height, yaw through the lateral one).  Without them a 0.5 deg mounting pitch is 0.5 deg of
grade error, and a 0.4 deg mounting roll leaks yaw rate into pitch rate in every curve.
The states need a tight vertical constraint (``nh_sigma_z`` <= 1 m/s; Table 3's 15 m/s
leaves the mounting pitch unobservable), so they are off by default, as in the paper, and
on in the shipped ``params/estimation.yaml``.  Mounting roll is not observable from the
constraints; ``mounting_rpy`` (the node's ``vehicle.imu_mounting_rpy``) gives the nominal
mounting (roll included) and the states refine pitch and yaw from there.  Every output (orientation,
grade, body velocity, compensated IMU) is in ``base_link``.

Beyond the paper: the CAN speed's scale error k, speed = (1 + k) v_x (``estimate_speed_scale``).
The bus speed is the wheels' rate times a nominal rolling radius, off by a few per cent with
tyre wear, pressure or another tyre; taken as exact it pulls the velocity off GNSS's by that
share, and every acceleration derived from it (the mass) with it. GNSS positions observe k;
without them it is held, a consider state (:meth:`FusionEKF._held_direction`).

Frames and conventions (REP-103): body = FLU (x forward, y left, z up); world = ENU.
The paper's NED equations are frame-agnostic except for the gravity vector, so the
filter runs directly in ENU with gravity (0, 0, -g).  Quaternions are (x, y, z, w),
body -> ENU.  The IMU specific force reads +g on body z when level at rest.

Biases are reported in the conventional sense: ``measured = true + bias + noise``;
the paper's delta-u (Eq. (21)-(22)) is the negative of this.

Stationary detection: CAN speed (``update_speed``) with ``|speed| <=
stationary_speed_threshold`` means stationary (as in the paper), unless the caller
overrides with ``set_stationary_hint(True/False)``; ``set_stationary_hint(None)``
returns to speed-based detection.  If neither is available, alignment falls back on
an IMU-variance test only.
"""
from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.estimators.common import compiled
from vehicle_estimation.estimators.common.noise import white_equivalent_variance
from vehicle_estimation.estimators.common.rotations import (quat_from_euler, quat_from_rotvec, quat_multiply,
                                                            quat_to_rotmat, skew)
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.error_state import (IA, IBA, IBG, IK, IM, IP, IV, N_ERR, STATUS_ALIGNING,
                                                              STATUS_RUNNING, STATUS_WAIT_HEADING,
                                                              STATUS_WAIT_STANDSTILL, innovation_inverse,
                                                              invariant_reset, scaled_speed_row)
from vehicle_estimation.estimators.fusion import ins_kernels
from vehicle_estimation.estimators.fusion.compiled_steps import FusionCompiledSteps
from vehicle_estimation.estimators.fusion.initialisation import FusionInitialisation
from vehicle_estimation.estimators.fusion.lasting_speed_offset import LastingSpeedOffset
from vehicle_estimation.estimators.fusion.outputs import FusionOutputs

__all__ = ["FusionEKF"]


def _vec3(x) -> np.ndarray | None:
    try:
        a = np.array(x, dtype=float).reshape(3)   # copy: never keep a reference to the caller's buffer
    except (TypeError, ValueError):
        return None
    if not math.isfinite(a[0] + a[1] + a[2]):      # NaN/inf propagate through the sum
        return None
    return a


def _float_or_nan(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


class FusionEKF(FusionInitialisation, FusionOutputs, FusionCompiledSteps):
    """Error-state EKF of paper 003 Alg. 1 with the API in REP-103 terms.

    Call order: ``process_imu`` for every IMU sample, ``update_gnss`` /
    ``update_speed`` whenever a message arrives (stamps in float seconds from the
    message headers).  Measurements are applied to the state at the latest IMU
    stamp; the GNSS prediction is extrapolated by ``v * (t_meas - t_imu)``.
    """

    def __init__(self, config: FusionConfig | None = None):
        self.config = config if config is not None else FusionConfig()
        self.config.validate()
        c = self.config
        self._p0_diag = np.concatenate([
            np.full(3, c.p0_position_sigma ** 2), np.full(3, c.p0_velocity_sigma ** 2),
            np.asarray(c.p0_attitude_sigma, float) ** 2,
            np.full(3, c.p0_accel_bias_sigma ** 2), np.full(3, c.p0_gyro_bias_sigma ** 2),
            np.full(2, c.p0_mounting_sigma ** 2 if c.estimate_mounting else 0.0),
            [c.p0_speed_scale_sigma ** 2 if c.estimate_speed_scale else 0.0]])
        self._k0 = 0.0                     # k's prior mean (resume_speed_scale)
        self._Rm0 = quat_to_rotmat(quat_from_euler(*(float(a) for a in c.mounting_rpy)))  # imu_link -> base_link
        # Schmidt consider directions, rows (:meth:`_held_direction`): none, the yaw-rate bias
        # (the gyro bias along base_link z, in the IMU's axes by the nominal mounting), the scale
        yaw_bias, scale = np.zeros(N_ERR), np.zeros(N_ERR)
        yaw_bias[IBG:IBG + 3], scale[IK] = self._Rm0[2], 1.0
        self._holds = {(False, False): np.zeros((1, N_ERR)), (True, False): yaw_bias[None], (False, True): scale[None],
                       (True, True): np.stack([yaw_bias, scale])}
        self._w_gnss = np.diag(np.asarray(c.gnss_sigma, float) ** 2)
        self._g_vec = np.array([0.0, 0.0, -c.gravity])
        self._w_nh = np.diag([c.nh_sigma_y ** 2, c.nh_sigma_z ** 2])   # read only
        self._w_nh_cornering = np.diag([c.nh_sigma_y ** 2,                # read only
                                        max(c.nh_sigma_z, c.nh_sigma_z_cornering_without_gnss) ** 2])
        self._eye_n, self._eye3 = np.eye(N_ERR), np.eye(3)
        self._di = np.arange(N_ERR)
        self._qd_dt: float | None = None
        self._qd_walk: bool | None = None
        self._qd = np.zeros(N_ERR)
        #: Propagation, updates and injection by the compiled kernels of :mod:`.ins_kernels` (the
        #: same numbers to 1e-12; the numpy methods below are their definition and test oracle).
        self.compiled = compiled.enabled()
        if self.compiled:
            ins_kernels.warm_up(N_ERR)
        self.reset()

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        """Forget everything; back to 'waiting_for_standstill'."""
        self.status = STATUS_WAIT_STANDSTILL
        self._p = np.zeros(3)
        self._v = np.zeros(3)
        self._q = np.array([0.0, 0.0, 0.0, 1.0])
        self._R = np.eye(3)
        self._ba = np.zeros(3)
        self._bg = np.zeros(3)
        self._Rm = self._Rm0.copy()   # imu_link -> base_link (mounting)
        self._speed_scale_error = np.full(1, self._k0)   # k: CAN speed = (1 + k) v_x (kernels add in place)
        self._P = np.diag(self._p0_diag)
        self._F = np.eye(N_ERR)
        self._t: float | None = None  # last IMU stamp
        self._f_prev: np.ndarray | None = None  # last raw IMU sample (used over the next interval, Eq. (28))
        self._w_prev: np.ndarray | None = None
        self._t_gnss: float | None = None
        self._t_gnss_applied: float | None = None   # last fix that updated the navigation state
        self._t_speed: float | None = None
        self._last_speed: float | None = None
        self._speed_variance: float | None = None   # the last CAN speed's stated variance
        self._lasting_speed = LastingSpeedOffset()
        self._last_gnss: np.ndarray | None = None
        self._t_nh = -math.inf
        self._t_cornering = -math.inf   # the last IMU stamp whose step ended in a corner
        self._a_lp = np.zeros(3)      # low-passed gravity-free acceleration (ENU)
        self._w_lp = np.zeros(3)      # low-passed compensated angular rate (FLU)
        self._hint: bool | None = None
        self._align_f: list = []
        self._align_w: list = []
        self._motion: list = []          # (t, f, w, CAN speed) while moving, for in-motion alignment
        self._heading_fixes: list = []   # (gnss_enu, ins_enu, variance_h)
        self._consec = {"gnss": 0, "speed": 0}
        self.rejected = {"imu_nonfinite": 0, "imu_out_of_order": 0, "imu_range": 0,
                         "gnss_nonfinite": 0, "gnss_out_of_order": 0, "gnss_stale": 0, "gnss_gate": 0,
                         "speed_nonfinite": 0, "speed_out_of_order": 0, "speed_stale": 0, "speed_gate": 0,
                         "update_numerical": 0}
        self.events = {"imu_gap": 0, "align_restart": 0, "aligned_in_motion": 0, "gnss_covariance_reopened": 0,
                       "speed_covariance_reopened": 0, "heading_initialised": 0,
                       "heading_restarted": 0}
        self.heading_sigma_at_init: float | None = None
        self.t_heading_fixed = math.inf      # stamp of the fix that fixed the heading

    @property
    def initialized(self) -> bool:
        """Aligned and the heading fixed by GNSS motion: the pose is in ENU."""
        return self.status == STATUS_RUNNING

    @property
    def navigating(self) -> bool:
        """Aligned: attitude, velocity, biases and grade are estimated.

        Until GNSS fixes the heading (never, on a car without GNSS) the filter runs with a free
        heading: its yaw and position are relative to the pose at alignment (the heading taken
        as zero, the position as the latest fix or the origin), dead-reckoned with the CAN speed
        and the vehicle constraints, and the position covariance grows with the distance. Roll,
        pitch, the grade, the body velocity and the biases do not depend on the heading, so
        they are as good as with GNSS.
        """
        return self.status in (STATUS_WAIT_HEADING, STATUS_RUNNING)

    @property
    def time(self) -> float | None:
        """Stamp of the last processed IMU sample."""
        return self._t

    def set_stationary_hint(self, stationary: bool | None) -> None:
        """Override stationarity (True/False); None returns to CAN-speed detection."""
        self._hint = None if stationary is None else bool(stationary)

    def _stationary_source(self, t: float):
        """True/False from the hint or a fresh CAN speed; None when unknown."""
        if self._hint is not None:
            return self._hint
        if (self._t_speed is not None and self._last_speed is not None   # set together
                and t - self._t_speed <= self.config.speed_timeout_s):
            return abs(self._last_speed) <= self.config.stationary_speed_threshold
        return None

    def _imu_quiet(self) -> bool:
        c = self.config
        a, w = self._a_lp, self._w_lp
        return (a[0] * a[0] + a[1] * a[1] + a[2] * a[2] <= c.stationary_max_accel ** 2
                and w[0] * w[0] + w[1] * w[1] + w[2] * w[2] <= c.stationary_max_rate ** 2)

    def _is_stationary(self, t: float) -> bool:
        """Stationary-update condition: the hint if set, else CAN speed ~ 0 and a quiet IMU."""
        if self._hint is not None:
            return self._hint
        return bool(self._stationary_source(t)) and self._imu_quiet()

    @property
    def stationary(self) -> bool:
        """Whether the stationary (zero-velocity) update is currently applied."""
        t = self._t if self._t is not None else (self._t_speed if self._t_speed is not None else 0.0)
        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            return bool(self._stationary_source(t))
        return self._is_stationary(t)

    def _admit(self, kind: str, t: float, valid: bool, last: float | None) -> bool:
        """Whether a sample of stream ``kind`` (imu, gnss, speed) may be used: ``valid`` values
        and a finite stamp, newer than the stream's ``last``, and not older than the filter
        by more than ``max_measurement_delay_s``; else counted as ``<kind>_nonfinite``,
        ``_out_of_order`` or ``_stale``."""
        if not valid or not math.isfinite(t):
            self.rejected[f"{kind}_nonfinite"] += 1
            return False
        if last is not None and not t > last:
            self.rejected[f"{kind}_out_of_order"] += 1
            return False
        if self._t is not None and t < self._t - self.config.max_measurement_delay_s:
            self.rejected[f"{kind}_stale"] += 1
            return False
        return True

    # ------------------------------------------------------------------ IMU
    def process_imu(self, t: float, specific_force, angular_rate) -> bool:
        """One IMU sample (body FLU, specific force [m/s^2], angular rate [rad/s]).

        Before alignment the sample is collected for initialisation (Sec. 7.1).  Then
        Alg. 1: the previous sample, bias-calibrated (Eq. (22)), propagates the nominal
        state over [t_prev, t] (Eqs. (23)-(29)) and the error covariance (Eq. (35)); the
        NH / stationary pseudo-measurements (Eqs. (45)-(47)) are then applied.
        Returns False (and changes nothing) for non-finite input or t <= last stamp.
        """
        f = _vec3(specific_force)
        w = _vec3(angular_rate)
        t = _float_or_nan(t)
        if not self._admit("imu", t, f is not None and w is not None, self._t):
            return False
        assert f is not None and w is not None
        c = self.config
        if (max(abs(f[0]), abs(f[1]), abs(f[2])) > c.imu_max_specific_force
                or max(abs(w[0]), abs(w[1]), abs(w[2])) > c.imu_max_angular_rate):
            # Beyond the sensor's range the value is a bus or scaling fault, not a motion; one
            # such sample integrated over its dt would corrupt the state for good.
            self.rejected["imu_range"] += 1
            return False

        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            self._align_step(t, f, w)
        else:
            assert self._t is not None   # set by the first sample (alignment)
            dt = t - self._t
            if dt > self.config.max_imu_dt_s:
                self.events["imu_gap"] += 1
            rate = self.config.nh_update_rate_hz
            nh_due = rate is None or t - self._t_nh >= 1.0 / rate - 1e-6   # float stamps near 1.7e9 s
            # Moving for sure (no stationary source): propagation and constraint in one call.
            if self.compiled and nh_due and not self._stationary_source(t):
                self._t_nh = t
                self._imu_step_compiled(t, dt)
            else:
                self._propagate(dt)
                self._t = t
                if nh_due:
                    self._t_nh = t
                    self._nh_update(t)
            if self._cornering():
                self._t_cornering = t
        self._t = t
        self._f_prev = f
        self._w_prev = w
        return True

    def _propagate(self, dt: float) -> None:
        """INS mechanisation (Sec. 5.2) and covariance propagation (Eqs. (33)-(36))."""
        c = self.config
        R = self._R
        assert self._f_prev is not None and self._w_prev is not None   # only after the first sample
        self._update_process_noise(dt)
        if self.compiled:
            q, R_new, P_new = np.empty(4), np.empty((3, 3)), np.empty((N_ERR, N_ERR))
            ins_kernels.propagate(dt, c.stationary_imu_tau_s, self._f_prev, self._w_prev, self._ba, self._bg,
                                  self._g_vec, self._p, self._v, self._q, R, self._a_lp, self._w_lp, self._P,
                                  self._qd, q, R_new, P_new)
            self._q, self._R, self._P = q, R_new, P_new
            return
        s_b = self._f_prev - self._ba                     # Eq. (22)
        w_b = self._w_prev - self._bg
        s_n = R @ s_b                                     # Eq. (25)
        a = s_n + self._g_vec                             # Eq. (27)
        self._p += dt * self._v + (0.5 * dt * dt) * a     # Eq. (28)
        self._v += dt * a                                 # Eq. (29)
        alpha = min(1.0, dt / c.stationary_imu_tau_s)     # stationarity cross-check (not in paper)
        self._a_lp += alpha * (a - self._a_lp)
        self._w_lp += alpha * (w_b - self._w_lp)
        # Eq. (23): q_k = q_{k-1} (x) [cos(|w|Ts/2), sin(|w|Ts/2) w/|w|]  (body-rate, right product)
        wx, wy, wz = w_b[0] * dt, w_b[1] * dt, w_b[2] * dt
        ang = math.sqrt(wx * wx + wy * wy + wz * wz)
        if ang > 1e-12:
            k = math.sin(0.5 * ang) / ang
            cw = math.cos(0.5 * ang)
        else:
            k, cw = 0.5, 1.0
        bx, by, bz = k * wx, k * wy, k * wz
        qx, qy, qz, qw = self._q
        nx = qw * bx + qx * cw + qy * bz - qz * by
        ny = qw * by - qx * bz + qy * cw + qz * bx
        nz = qw * bz + qx * by - qy * bx + qz * cw
        nw = qw * cw - qx * bx - qy * by - qz * bz
        inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
        self._q = np.array([nx * inv, ny * inv, nz * inv, nw * inv])
        self._R = quat_to_rotmat(self._q)                 # Eq. (26)

        # Eq. (34): F = I + Ts*[..]; signs for conventional biases (measured = true + b):
        #   d(dv)/dt = S(s_n) eps - R dba,  d(eps)/dt = R dbg
        F = self._F
        F[0, 3] = F[1, 4] = F[2, 5] = dt
        F[3:6, 6:9] = dt * np.array([[0.0, -s_n[2], s_n[1]],
                                     [s_n[2], 0.0, -s_n[0]],
                                     [-s_n[1], s_n[0], 0.0]])
        dR = dt * R
        F[3:6, 9:12] = -dR
        F[6:9, 12:15] = dR
        P = F @ self._P @ F.T                             # Eq. (35)
        P[self._di, self._di] += self._qd
        self._P = P

    def _update_process_noise(self, dt: float) -> None:
        """G Qc G^T (Eqs. (34), (36)): R diag(sigma^2) R^T = sigma^2 I for isotropic sigma, so
        the discrete process noise is diagonal; cached per dt."""
        c = self.config
        walk = self.gnss_aided or c.accel_bias_walk_without_gnss
        if dt != self._qd_dt or walk != self._qd_walk:
            kb = dt * c.imu_rate_hz
            qd = np.zeros(N_ERR)   # a new array: the previous one may still be referenced
            qd[IV:IV + 3] = (dt * c.q_accel_sigma) ** 2
            qd[IA:IA + 3] = (dt * c.q_gyro_sigma) ** 2
            qd[IBA:IBA + 3] = kb * c.q_accel_bias_sigma ** 2 if walk else 0.0
            qd[IBG:IBG + 3] = kb * c.q_gyro_bias_sigma ** 2
            qd[IM:IM + 2] = kb * c.q_mounting_sigma ** 2 if c.estimate_mounting else 0.0
            qd[IK] = kb * c.q_speed_scale_sigma ** 2 if c.estimate_speed_scale else 0.0
            self._qd, self._qd_dt, self._qd_walk = qd, dt, walk

    # ------------------------------------------------------------------ measurement helpers
    def _body_speed_rows(self, rows, mounting_columns: tuple[bool, bool] | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Prediction v_b[rows] = (R_m R^T v)[rows] in base_link and its Jacobian H (Eq. (46)).

        With R_true = (I - S(eps)) R_hat:  v_i = R^T v - R^T S(v) eps  (the attitude
        term is dropped when ``full_velocity_jacobian`` is False, as in Eq. (46)); the
        mounting R_m (imu_link -> base_link) with R_m,true = (I + S(dm)) R_m, dm about the
        base_link axes, adds v_b = R_m v_i - S(R_m v_i) dm (``mounting_columns``: the pitch's
        and the yaw's; by default :meth:`mounting_columns`).
        """
        pitch, yaw = self.mounting_columns() if mounting_columns is None else mounting_columns
        if self.compiled:
            pred, H = np.empty(len(rows)), np.empty((len(rows), N_ERR))
            ins_kernels.body_speed_rows(self._R, self._Rm, self._v, np.asarray(rows, dtype=np.int64),
                                        self.config.full_velocity_jacobian, pitch, yaw, pred, H)
            return pred, H
        Rt = self._R.T
        Rm = self._Rm
        vi = Rt @ self._v
        vb = Rm @ vi
        H = np.zeros((len(rows), N_ERR))
        RmRt = Rm @ Rt
        H[:, IV:IV + 3] = RmRt[rows]
        if self.config.full_velocity_jacobian:
            H[:, IA:IA + 3] = -(RmRt[rows] @ skew(self._v))
        if pitch or yaw:
            mounting = -skew(vb)[rows][:, 1:3]
            if pitch:
                H[:, IM] = mounting[:, 0]
            if yaw:
                H[:, IM + 1] = mounting[:, 1]
        return vb[rows], H

    def _nh_update(self, t: float) -> None:
        """NH constraints / stationary update (Sec. 5.4, rows (3) of Eq. (45))."""
        c = self.config
        stationary = self._is_stationary(t)
        if stationary:
            rows = [0, 1, 2] if c.stationary_update_longitudinal else [1, 2]
            W = np.diag(np.full(len(rows), c.stationary_sigma ** 2))
        else:
            rows = [1, 2]
            W = self._moving_constraint_noise()
        if self.compiled:
            self._constraint_update_compiled(rows, W)
        else:
            pred, H = self._body_speed_rows(rows)
            self._update(-pred, H, W, None)
        if stationary and c.stationary_rate_update:
            self._zero_rate_update()

    def _held_direction(self, yaw_rate_bias: bool = True) -> np.ndarray:
        """The error-state directions the gain leaves out, orthonormal rows (zeros: none): Schmidt
        consider states while no GNSS fix aids: the yaw-rate bias, and the speed's scale, which
        only positions observe (the accelerometer would tell it only through its bias: a 36 t
        truck without GNSS learnt 1.18 from its first pull-away, NEES 55)."""
        return self._holds[(yaw_rate_bias and self.config.hold_yaw_rate_bias_without_gnss and not self.gnss_aided,
                            self.speed_scale_held)]

    def _invariant_reset_due(self) -> bool:
        """Whether an update moves P with the estimate (:func:`.error_state.invariant_reset`)."""
        return self.config.invariant_reset_without_gnss and not self.gnss_aided

    def _update(self, y: np.ndarray, H: np.ndarray, W: np.ndarray, gate, held: np.ndarray | None = None) -> int:
        """Eqs. (37)-(44): gain, error-state estimate, injection, covariance (Joseph form);
        ``held``: the consider direction, :meth:`_held_direction`'s when None.

        Returns 1 if applied, 0 if gated out, -1 on numerical failure.
        """
        P = self._P
        held = self._held_direction() if held is None else held
        if self.compiled:
            return self._update_compiled(y, H, W, gate, held)
        PHt = P @ H.T
        S = H @ PHt + W
        S_inv = innovation_inverse(S)
        if S_inv is None:
            self.rejected["update_numerical"] += 1
            return -1
        if gate is not None:
            d2 = float(y @ S_inv @ y)
            if not d2 <= gate:
                return 0
        K = PHt @ S_inv                                   # Eq. (37)
        K -= held.T @ (held @ K)                          # Schmidt: a consider state keeps its value
        dz = K @ y                                        # Eq. (40), with the previous error reset to 0
        if not math.isfinite(float(dz.sum())):
            self.rejected["update_numerical"] += 1
            return -1
        A = self._eye_n - K @ H
        P = A @ P @ A.T + K @ W @ K.T                     # Eq. (44), Joseph form
        self._P = invariant_reset(P, dz) if self._invariant_reset_due() else 0.5 * (P + P.T)
        self._inject(dz)
        return 1

    def _inject(self, dz: np.ndarray) -> None:
        """Eqs. (41)-(43): feed the error estimate back into the nominal state."""
        self._p += dz[IP:IP + 3]                          # Eq. (41)
        self._v += dz[IV:IV + 3]                          # Eq. (42)
        e = dz[IA:IA + 3]
        # Eq. (31): R_new = (I - S(eps)) R_hat, done exactly as q_new = q(-eps) (x) q_hat,
        # which also replaces the DCM -> quaternion conversion of Eq. (43).
        ex, ey, ez = -e[0], -e[1], -e[2]
        ang = math.sqrt(ex * ex + ey * ey + ez * ez)
        if ang > 1e-12:
            k = math.sin(0.5 * ang) / ang
            dq = np.array([k * ex, k * ey, k * ez, math.cos(0.5 * ang)])
        else:
            dq = np.array([0.5 * ex, 0.5 * ey, 0.5 * ez, 1.0])
        q = quat_multiply(dq, self._q)
        self._q = q / math.sqrt(float(q @ q))
        self._R = quat_to_rotmat(self._q)
        self._ba += dz[IBA:IBA + 3]
        self._bg += dz[IBG:IBG + 3]
        self._speed_scale_error += dz[IK]
        if self.config.estimate_mounting:
            self._Rm = quat_to_rotmat(quat_from_rotvec([0.0, dz[IM], dz[IM + 1]])) @ self._Rm

    def _reopen(self, kind: str, block: slice, W: np.ndarray, y: np.ndarray) -> None:
        """After many consecutive gate rejections: the filter is inconsistent; forget the
        cross-correlations of the block and give it the innovation-sized variance."""
        P = self._P
        P[block, :] = 0.0
        P[:, block] = 0.0
        P[block, block] = W + np.diag(y * y)
        self.events[f"{kind}_covariance_reopened"] += 1

    # ------------------------------------------------------------------ GNSS
    def update_gnss(self, t: float, enu_position, covariance=None) -> bool:
        """Loosely coupled GNSS position update (rows (1) of Eqs. (45)-(47)).

        ``enu_position``: antenna position in the ENU frame [m] (see LocalTangentPlane);
        ``covariance``: 3x3 ENU covariance [m^2] or None for ``config.gnss_sigma``.
        Before the heading is known the fixes are used for the yaw initialisation.
        Returns True when the fix was used (applied or consumed for initialisation).
        """
        z = _vec3(enu_position)
        t = _float_or_nan(t)
        W = self._w_gnss
        if covariance is not None:
            try:
                Wc = np.asarray(covariance, dtype=float).reshape(3, 3)
            except (TypeError, ValueError):
                Wc = None
            if Wc is None or not np.isfinite(Wc).all() or np.any(np.diag(Wc) <= 0):
                z = None
            else:
                W = 0.5 * (Wc + Wc.T)
        if not self._admit("gnss", t, z is not None, self._t_gnss):
            return False
        assert z is not None
        self._t_gnss = t
        self._last_gnss = z.copy()
        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            return True
        if self.status == STATUS_WAIT_HEADING:
            return self._heading_step(t, z, W)

        assert self._t is not None   # running: IMU samples were processed
        dt = t - self._t
        H = np.zeros((3, N_ERR))
        H[:, IP:IP + 3] = self._eye3
        H[:, IV:IV + 3] = dt * self._eye3
        y = z - (self._p + dt * self._v)
        res = self._update(y, H, W, self.config.gnss_gate_chi2)
        used = self._after_gated("gnss", res, y, H, W, slice(IP, IP + 3))
        if used:
            self._t_gnss_applied = t
        return used

    def _after_gated(self, kind: str, res: int, y, H, W, block: slice) -> bool:
        if res == 1:
            self._consec[kind] = 0
            return True
        if res == 0:
            self.rejected[f"{kind}_gate"] += 1
            self._consec[kind] += 1
            if self._consec[kind] >= self.config.max_consecutive_rejections:
                self._consec[kind] = 0
                self._reopen(kind, block, W if W.shape[0] == 3 else np.diag(np.full(3, W[0, 0])),
                             np.resize(y, 3))
                return self._update(y, H, W, None) == 1
        return False

    # ------------------------------------------------------------------ CAN speed
    def update_speed(self, t: float, speed: float, variance: float | None = None) -> bool:
        """CAN-bus longitudinal speed update (row (2) of Eqs. (45)-(47), body x).

        Also drives stationary detection (|speed| <= stationary_speed_threshold).
        Before alignment the speed is only stored for stationarity.  Returns True
        when the measurement was used.
        """
        t, s = _float_or_nan(t), _float_or_nan(speed)
        r = self.config.speed_sigma ** 2 if variance is None else _float_or_nan(variance)
        if not self._admit("speed", t, math.isfinite(s) and math.isfinite(r) and r > 0, self._t_speed):
            return False
        spacing = t - self._t_speed if self._t_speed is not None else math.inf
        self._speed_variance = r
        r = white_equivalent_variance(r, self.config.speed_error_correlation_s, spacing)
        self._t_speed = t
        self._last_speed = s
        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            return True
        self._note_speed(t, s, self._speed_variance)
        pred, H = scaled_speed_row(*self._body_speed_rows([0]), float(self._speed_scale_error[0]),
                                   self.speed_scale_held)
        if self.config.speed_unsigned and pred[0] < 0.0:
            s = -abs(s)
        y = np.array([s - pred[0]])
        W = np.array([[r]])
        res = self._update(y, H, W, self.config.speed_gate_chi2)
        return self._after_gated("speed", res, y, H, W, slice(IV, IV + 3))
