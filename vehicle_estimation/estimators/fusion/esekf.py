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

Beyond the paper: IMU mounting states.  The paper's IMU was calibrated to the body; a
car's IMU sits in ``imu_link``, rotated from ``base_link`` by a mounting rotation known
only to a degree or so (REP-145).  The filter's attitude is the IMU's (what the gyros
integrate), and two extra error states, the mounting pitch and yaw (about imu_link y and
z), map it to the vehicle: the non-holonomic and CAN-speed constraints hold in
``base_link``, not in ``imu_link``, and they make the two angles observable once the car
moves (pitch through the vertical constraint and the GNSS height, yaw through the lateral
one).  Without them a 0.5 deg mounting pitch is 0.5 deg of grade error, and a 0.4 deg
mounting roll leaks yaw rate into pitch rate in every curve.  The states need a tight
vertical constraint (``nh_sigma_z`` <= 1 m/s; Table 3's 15 m/s leaves the mounting pitch
unobservable), so they are off by default, as in the paper, and on in the shipped
``params/estimation.yaml``.  Mounting roll is not
observable from the constraints; ``mounting_rpy`` gives the nominal mounting (roll
included) and the states refine pitch and yaw from there.  Every output (orientation,
grade, body velocity, compensated IMU) is in ``base_link``.

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
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from vehicle_estimation.contract.vehicle import GRAVITY
from vehicle_estimation.estimators.common.rotations import (euler_from_rotmat, quat_from_euler, quat_from_rotvec,
                                                            quat_multiply, quat_normalize, quat_to_rotmat, rot_z,
                                                            rotmat_to_quat, skew)

# Error-state layout, Eq. (32): z = [dp, dv, eps, dba, dbg], then the mounting pitch and
# yaw corrections dm (about imu_link y, z; R_vi_true = R_vi_hat (I + S([0, dm]))).
IP, IV, IA, IBA, IBG, IM = 0, 3, 6, 9, 12, 15
N_ERR = 17

STATUS_WAIT_STANDSTILL = "waiting_for_standstill"
STATUS_ALIGNING = "aligning"
STATUS_WAIT_HEADING = "waiting_for_heading"
STATUS_RUNNING = "running"


def _vec3(x) -> np.ndarray | None:
    try:
        a = np.array(x, dtype=float).reshape(3)   # copy: never keep a reference to the caller's buffer
    except (TypeError, ValueError):
        return None
    if not math.isfinite(a[0] + a[1] + a[2]):      # NaN/inf propagate through the sum
        return None
    return a


def _inv_small(S: np.ndarray) -> np.ndarray | None:
    """Inverse of a small SPD innovation covariance (closed form for 1x1 / 2x2)."""
    m = S.shape[0]
    if m == 1:
        s = S[0, 0]
        return np.array([[1.0 / s]]) if s > 0.0 and math.isfinite(s) else None
    if m == 2:
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        det = a * d - b * c
        if not (det > 0.0 and math.isfinite(det)):
            return None
        return np.array([[d, -b], [-c, a]]) / det
    try:
        inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    return inv if math.isfinite(float(inv.sum())) else None


@dataclass
class FusionConfig:
    """Filter tuning.  Defaults are paper 003 Tables 2-3 (SI units) where the paper
    gives a value; the remaining fields are implementation choices documented here.

    The paper's process noise is in discrete "per IMU sample" form, Eq. (34): velocity
    and attitude noise enter as ``Ts * R * w`` (variance ``Ts^2 sigma^2`` per step) and
    the bias random walks as ``I * w`` (variance ``sigma^2`` per step).  The bias terms
    are scaled by ``dt * imu_rate_hz`` so that they equal the paper at the nominal rate
    and stay consistent under timing jitter.
    """
    gravity: float = GRAVITY                 # [m/s^2] (paper uses 9.81, Eq. (27))
    imu_rate_hz: float = 200.0               # nominal rate the per-sample Q values refer to
    # --- Table 2: initial state standard deviations (P0) ---
    p0_position_sigma: float = 2.0           # [m]
    p0_velocity_sigma: float = 0.5           # [m/s]
    p0_attitude_sigma: tuple = (5e-3, 5e-3, 10e-3)  # [rad] about world x, y, z
    p0_accel_bias_sigma: float = 0.005       # [m/s^2]
    p0_gyro_bias_sigma: float = 0.0008       # [rad/s]
    # --- Table 3 (left): process noise Q ---
    q_accel_sigma: float = 0.03              # [m/s^2]
    q_gyro_sigma: float = 1e-5               # [rad/s]
    q_accel_bias_sigma: float = 1e-3         # [m/s^2] per sample
    q_gyro_bias_sigma: float = 1e-6          # [rad/s] per sample
    # --- Table 3 (right): measurement noise W ---
    gnss_sigma: tuple = (2.0, 2.0, 5.0)      # [m] E, N, U (used when no covariance given)
    speed_sigma: float = 0.5                 # [m/s]
    nh_sigma_y: float = 5.0                  # [m/s] lateral NH constraint
    nh_sigma_z: float = 15.0                 # [m/s] vertical NH constraint
    # --- stationary updates (paper: "greatly reduced" NH variances; value not given) ---
    stationary_sigma: float = 0.02           # [m/s] NH sigma while stationary
    stationary_update_longitudinal: bool = True  # also pseudo-measure body-x speed 0 at standstill
    stationary_speed_threshold: float = 0.05     # [m/s] |CAN speed| <= this -> stationary
    # A CAN speed of 0 is only trusted while the IMU agrees (quantised / low-rate CAN
    # reads 0 for a while after the car starts to roll): low-passed gravity-free
    # acceleration and angular rate below these limits (not in the paper).
    stationary_max_accel: float = 0.15           # [m/s^2]
    stationary_max_rate: float = 0.03            # [rad/s]
    stationary_imu_tau_s: float = 0.1            # low-pass time constant
    speed_timeout_s: float = 0.5             # CAN speed older than this -> stationarity unknown
    speed_unsigned: bool = False             # CAN speed is |v_x| (sign taken from the estimate)
    # --- non-holonomic update cadence (None: every IMU sample, as in the paper) ---
    nh_update_rate_hz: float | None = None
    full_velocity_jacobian: bool = True      # include the attitude term -R^T S(v) in body-speed H
    # --- initialisation (Sec. 7.1) ---
    init_stationary_samples: int = 200
    init_max_accel_std: float = 0.3          # [m/s^2] per-axis std over the alignment window
    init_max_gyro_std: float = 0.02          # [rad/s]
    heading_min_baseline_m: float = 15.0     # GNSS travel before yaw is fixed
    # In-motion alignment (not in the paper, which starts at standstill): a filter started
    # while the car drives (a node restart, a bag cut mid-drive) levels itself on the mean
    # specific force minus the CAN-speed kinematics over this window, with these priors.
    in_motion_alignment: bool = True
    in_motion_window_s: float = 5.0          # [s] of continuous motion
    in_motion_tilt_sigma: float = 0.0175     # [rad] (1 deg) tilt prior after it
    in_motion_gyro_bias_sigma: float = 0.005  # [rad/s] gyro-bias prior (no standstill mean)
    heading_max_fixes: int = 600
    # --- robustness ---
    gnss_gate_chi2: float | None = 16.27     # chi2(3) 99.9 %; None disables
    speed_gate_chi2: float | None = 10.83    # chi2(1) 99.9 %; None disables
    max_consecutive_rejections: int = 10     # then the position covariance is re-opened
    max_measurement_delay_s: float = 0.5     # measurements older than the filter by more: rejected
    max_imu_dt_s: float = 0.5                # larger IMU gaps are propagated but counted
    # --- IMU mounting (imu_link in base_link; not in the paper, see the module docstring) ---
    mounting_rpy: tuple = (0.0, 0.0, 0.0)    # nominal roll, pitch, yaw of imu_link in base_link [rad]
    estimate_mounting: bool = False          # refine mounting pitch and yaw online (needs nh_sigma_z <= 1)
    p0_mounting_sigma: float = 0.035         # [rad] (2 deg) prior on the pitch and yaw refinement
    q_mounting_sigma: float = 1e-7           # [rad] per sample: a mounting does not move
    # --- without GNSS (not in the paper, which always has it) ---
    # Without GNSS the along-track (and lateral) accelerometer bias and the pitch (roll) enter
    # every measurement only as the sum g*tilt + bias: one direction of the error state is
    # unobservable. The paper's bias random walk then lets the split wander with whatever the
    # model gets wrong (on FASTSim's hilly drive the x bias reached +2 m/s^2 and the grade
    # -10 deg in 600 s; the true bias is 0.05). So the accelerometer bias is held while no
    # valid fix has come for gnss_aiding_timeout_s, and every correction of the sum goes
    # into the tilt, which the gyro carries between corrections.
    accel_bias_walk_without_gnss: bool = False  # let the accel bias random-walk without GNSS too (paper Q)
    gnss_aiding_timeout_s: float = 5.0       # [s] no valid fix for this long -> the accel bias is held
    # A bias that no fix has ever observed is only known to its prior; the turn-on bias of a
    # MEMS accelerometer is typically this large. It enters the grade variance, and the
    # published bias covariance, as a 'consider' term: it is not in the filter's P, because a
    # large P there would move corrections of the sum into the bias (the drift above).
    unaided_accel_bias_sigma: float = 0.05   # [m/s^2] accel bias prior in the grade variance until GNSS observes it
    # Without GNSS nothing observes the heading, so nothing observes the z gyro bias either
    # (the alignment's standstill mean set it), yet the non-holonomic constraint couples it to
    # the lateral accelerometer bias (v_y' = a_y - r v_x: a yaw-rate error looks like b_y / v_x)
    # and the filter trades one for the other (on FASTSim's drive the z bias went from -2 to
    # +2 mrad/s). Held: a 'consider' state while no fix aids (a Schmidt update: its gain is
    # zero, its covariance and cross-covariances are kept, Joseph form), corrected by GNSS.
    hold_yaw_rate_bias_without_gnss: bool = True

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        pos = ["gravity", "imu_rate_hz", "p0_position_sigma", "p0_velocity_sigma",
               "p0_accel_bias_sigma", "p0_gyro_bias_sigma", "q_accel_sigma", "q_gyro_sigma",
               "q_accel_bias_sigma", "q_gyro_bias_sigma", "speed_sigma", "nh_sigma_y",
               "nh_sigma_z", "stationary_sigma", "speed_timeout_s", "init_max_accel_std",
               "init_max_gyro_std", "heading_min_baseline_m", "stationary_max_accel",
               "stationary_max_rate", "stationary_imu_tau_s", "max_measurement_delay_s",
               "max_imu_dt_s", "in_motion_window_s", "in_motion_tilt_sigma", "in_motion_gyro_bias_sigma",
               "gnss_aiding_timeout_s"]
        for name in pos:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"FusionConfig.{name} must be a finite positive number, got {v!r}")
        v = self.stationary_speed_threshold
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"FusionConfig.stationary_speed_threshold must be >= 0, got {v!r}")
        for name in ("p0_mounting_sigma", "q_mounting_sigma", "unaided_accel_bias_sigma"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"FusionConfig.{name} must be a finite number >= 0, got {v!r}")
        try:
            m = np.asarray(self.mounting_rpy, dtype=float)
        except (TypeError, ValueError):
            m = np.full(1, np.nan)
        if m.shape != (3,) or not np.all(np.isfinite(m)) or np.any(np.abs(m) > math.pi):
            raise ValueError(f"FusionConfig.mounting_rpy must be 3 angles in [-pi, pi] rad, "
                             f"got {self.mounting_rpy!r}")
        if self.estimate_mounting and self.nh_sigma_z > 1.0:
            raise ValueError(
                "FusionConfig.estimate_mounting needs FusionConfig.nh_sigma_z <= 1 m/s: the "
                f"mounting pitch is observed through the vertical constraint (nh_sigma_z={self.nh_sigma_z!r})")
        for name in ("p0_attitude_sigma", "gnss_sigma"):
            v = getattr(self, name)
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"FusionConfig.{name} must be 3 positive numbers, got {v!r}") from None
            if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a <= 0):
                raise ValueError(f"FusionConfig.{name} must be 3 positive numbers, got {v!r}")
        for name in ("gnss_gate_chi2", "speed_gate_chi2", "nh_update_rate_hz"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))
                                  or not math.isfinite(v) or v <= 0):
                raise ValueError(f"FusionConfig.{name} must be None or a positive number, got {v!r}")
        for name in ("init_stationary_samples", "heading_max_fixes", "max_consecutive_rejections"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"FusionConfig.{name} must be an int >= 1, got {v!r}")
        if self.heading_max_fixes < 2:
            raise ValueError("FusionConfig.heading_max_fixes must be >= 2")
        for name in ("stationary_update_longitudinal", "speed_unsigned", "full_velocity_jacobian",
                     "estimate_mounting", "in_motion_alignment", "accel_bias_walk_without_gnss",
                     "hold_yaw_rate_bias_without_gnss"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"FusionConfig.{name} must be a bool")

    @classmethod
    def from_dict(cls, d: dict) -> "FusionConfig":
        """Build from a (ROS parameter) dict; unknown keys raise ValueError."""
        names = {f.name for f in fields(cls)}
        bad = set(d) - names
        if bad:
            raise ValueError(f"unknown FusionConfig field(s): {sorted(bad)}")
        kwargs: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}
        cfg = cls(**kwargs)
        cfg.validate()
        return cfg


class FusionEKF:
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
            np.full(2, c.p0_mounting_sigma ** 2 if c.estimate_mounting else 0.0)])
        self._Rm0 = quat_to_rotmat(quat_from_euler(*(float(a) for a in c.mounting_rpy)))  # imu_link -> base_link
        self._w_gnss = np.diag(np.asarray(c.gnss_sigma, float) ** 2)
        self._g_vec = np.array([0.0, 0.0, -c.gravity])
        self._eye15 = np.eye(N_ERR)
        self._eye3 = np.eye(3)
        self._di = np.arange(N_ERR)
        self._qd_dt: float | None = None
        self._qd_walk: bool | None = None
        self._qd = np.zeros(N_ERR)
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
        self._P = np.diag(self._p0_diag)
        self._F = np.eye(N_ERR)
        self._t: float | None = None  # last IMU stamp
        self._f_prev: np.ndarray | None = None  # last raw IMU sample (used over the next interval, Eq. (28))
        self._w_prev: np.ndarray | None = None
        self._t_gnss: float | None = None
        self._t_gnss_applied: float | None = None   # last fix that updated the navigation state
        self._t_speed: float | None = None
        self._last_speed: float | None = None
        self._last_gnss: np.ndarray | None = None
        self._t_nh = -math.inf
        self._a_lp = np.zeros(3)      # low-passed gravity-free acceleration (ENU)
        self._w_lp = np.zeros(3)      # low-passed compensated angular rate (FLU)
        self._hint: bool | None = None
        self._align_f: list = []
        self._align_w: list = []
        self._motion: list = []          # (t, f, w, CAN speed) while moving, for in-motion alignment
        self._heading_fixes: list = []   # (gnss_enu, ins_enu, variance_h)
        self._consec = {"gnss": 0, "speed": 0}
        self.rejected = {"imu_nonfinite": 0, "imu_out_of_order": 0,
                         "gnss_nonfinite": 0, "gnss_out_of_order": 0, "gnss_stale": 0, "gnss_gate": 0,
                         "speed_nonfinite": 0, "speed_out_of_order": 0, "speed_stale": 0, "speed_gate": 0,
                         "update_numerical": 0}
        self.events = {"imu_gap": 0, "align_restart": 0, "aligned_in_motion": 0, "gnss_covariance_reopened": 0,
                       "speed_covariance_reopened": 0, "heading_initialised": 0}
        self.heading_sigma_at_init: float | None = None

    @property
    def initialized(self) -> bool:
        """Aligned and the heading fixed by GNSS motion: the pose is in ENU."""
        return self.status == STATUS_RUNNING

    @property
    def gnss_aided(self) -> bool:
        """A valid fix has arrived within ``gnss_aiding_timeout_s``: the bias walks as in the
        paper (while the first fixes fix the heading too: they update the state seconds later)."""
        return (self._t_gnss is not None and self._t is not None
                and self._t - self._t_gnss <= self.config.gnss_aiding_timeout_s)

    @property
    def accel_bias_observed(self) -> bool:
        """GNSS has aided the filter since the alignment, so its accelerometer bias is more than
        the prior (and held at what it learned through a later outage)."""
        return self._t_gnss_applied is not None

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
        try:
            t = float(t)
        except (TypeError, ValueError):
            t = math.nan
        if f is None or w is None or not math.isfinite(t):
            self.rejected["imu_nonfinite"] += 1
            return False
        if self._t is not None and not t > self._t:
            self.rejected["imu_out_of_order"] += 1
            return False

        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            self._align_step(t, f, w)
        else:
            assert self._t is not None   # set by the first sample (alignment)
            dt = t - self._t
            if dt > self.config.max_imu_dt_s:
                self.events["imu_gap"] += 1
            self._propagate(dt)
            self._t = t
            rate = self.config.nh_update_rate_hz
            if rate is None or t - self._t_nh >= 1.0 / rate - 1e-6:   # float stamps near 1.7e9 s
                self._t_nh = t
                self._nh_update(t)
        self._t = t
        self._f_prev = f
        self._w_prev = w
        return True

    def _align_step(self, t: float, f: np.ndarray, w: np.ndarray) -> None:
        c = self.config
        static = self._stationary_source(t)
        if static is False:
            if self._align_f:
                self.events["align_restart"] += 1
            self._align_f.clear()
            self._align_w.clear()
            self.status = STATUS_WAIT_STANDSTILL
            if c.in_motion_alignment and self._hint is None:
                self._motion_align_step(t, f, w)
            return
        self._motion.clear()
        self._align_f.append(f)
        self._align_w.append(w)
        self.status = STATUS_ALIGNING
        n = c.init_stationary_samples
        if len(self._align_f) < n:
            return
        fa = np.array(self._align_f[-n:])
        wa = np.array(self._align_w[-n:])
        if fa.std(axis=0).max() > c.init_max_accel_std or wa.std(axis=0).max() > c.init_max_gyro_std:
            # Not quiet enough (e.g. no speed source and the car moves): slide the window.
            self.events["align_restart"] += 1
            del self._align_f[: n // 2]
            del self._align_w[: n // 2]
            return
        self._align(fa.mean(axis=0), wa.mean(axis=0))

    def _motion_align_step(self, t: float, f: np.ndarray, w: np.ndarray) -> None:
        """Level the filter while driving: over ``in_motion_window_s`` of motion the mean
        specific force is gravity plus the mean kinematic acceleration, which the CAN speed
        gives in the body frame as [dv/dt, v r, 0] (no sideslip, no vertical motion):
        f = a_b + R^T g_up + b.  The gyro bias cannot be averaged out while turning, so it
        starts at zero with ``in_motion_gyro_bias_sigma``."""
        c = self.config
        assert self._last_speed is not None   # only called on a fresh CAN speed
        self._motion.append((t, f, w, float(self._last_speed)))
        if t - self._motion[0][0] < c.in_motion_window_s:
            return
        data = self._motion
        ts = np.array([d[0] for d in data])
        fs = np.array([d[1] for d in data])
        ws = np.array([d[2] for d in data])
        vs = np.array([d[3] for d in data])
        self._motion = []
        tc = ts - ts.mean()
        dvdt = float(tc @ (vs - vs.mean()) / (tc @ tc))          # least-squares slope of CAN speed
        kinematic = np.array([dvdt, float(np.mean(vs * ws[:, 2])), -float(np.mean(vs * ws[:, 1]))])
        self._align(fs.mean(axis=0) - kinematic, np.zeros(3))
        self._v = self._R @ np.array([float(vs[-1]), 0.0, 0.0])
        tilt = c.in_motion_tilt_sigma ** 2
        P = self._P
        P[IA:IA + 2, IA:IA + 2] += np.eye(2) * tilt
        P[IBG:IBG + 3, IBG:IBG + 3] = np.eye(3) * max(c.in_motion_gyro_bias_sigma, c.p0_gyro_bias_sigma) ** 2
        P[IV:IV + 3, IV:IV + 3] = np.eye(3) * max(c.p0_velocity_sigma, c.speed_sigma) ** 2
        self.events["aligned_in_motion"] += 1

    def _align(self, f_mean: np.ndarray, w_mean: np.ndarray) -> None:
        """Sec. 7.1: roll/pitch from gravity, gyro bias = mean rate, accel bias = 0."""
        roll = math.atan2(f_mean[1], f_mean[2])
        pitch = math.atan2(-f_mean[0], math.hypot(f_mean[1], f_mean[2]))
        self._q = quat_from_euler(roll, pitch, 0.0)       # yaw provisional until GNSS heading
        self._R = quat_to_rotmat(self._q)
        self._bg = w_mean.copy()
        self._ba = np.zeros(3)
        self._v = np.zeros(3)
        self._p = self._last_gnss.copy() if self._last_gnss is not None else np.zeros(3)
        self._P = self._aligned_covariance()
        self._align_f.clear()
        self._align_w.clear()
        self._heading_fixes = []
        self.status = STATUS_WAIT_HEADING

    def _aligned_covariance(self) -> np.ndarray:
        """P0 after the accelerometer alignment, with the tilt/bias correlation it creates.

        The alignment takes the mean specific force as gravity and sets the accelerometer
        bias to zero, so whatever bias b the sensor has (turn-on bias, and the g·sin(delta)
        a mounting misalignment delta adds) goes into the tilt: from
        f = R^T (g_up + S(g_up)... ) the tilt error is eps = A b with
        R_hat b = S(g_up) eps, i.e. eps_x = (R_hat b)_y / g, eps_y = -(R_hat b)_x / g.
        Table 2 gives independent sigmas; with them the filter believes the aligned tilt to
        within p0_attitude_sigma while it is really off by |b|/g (0.1 m/s^2 is 0.6 deg), and
        it has no way to move a later-observed bias error back into the tilt. Here the tilt
        and bias errors start fully correlated (eps = A dba) plus Table 2's independent tilt
        term, so observing the bias corrects the grade at once and the grade variance is
        honest from the start.
        """
        P = np.diag(self._p0_diag)
        g = self.config.gravity
        # eps = A dba (x, y rows; yaw is unaffected by gravity)
        A = np.zeros((3, 3))
        A[0] = self._R[1] / g
        A[1] = -self._R[0] / g
        Pbb = P[IBA:IBA + 3, IBA:IBA + 3]
        P[IA:IA + 3, IA:IA + 3] += A @ Pbb @ A.T
        P[IA:IA + 3, IBA:IBA + 3] = A @ Pbb
        P[IBA:IBA + 3, IA:IA + 3] = (A @ Pbb).T
        return P

    def _propagate(self, dt: float) -> None:
        """INS mechanisation (Sec. 5.2) and covariance propagation (Eqs. (33)-(36))."""
        c = self.config
        R = self._R
        assert self._f_prev is not None and self._w_prev is not None   # only after the first sample
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
        # G Qc G^T (Eqs. (34), (36)): R diag(sigma^2) R^T = sigma^2 I for isotropic sigma,
        # so the discrete process noise is diagonal; cached per dt.
        walk = self.gnss_aided or c.accel_bias_walk_without_gnss
        if dt != self._qd_dt or walk != self._qd_walk:
            kb = dt * c.imu_rate_hz
            self._qd = np.concatenate([
                np.zeros(3), np.full(3, (dt * c.q_accel_sigma) ** 2),
                np.full(3, (dt * c.q_gyro_sigma) ** 2),
                np.full(3, kb * c.q_accel_bias_sigma ** 2 if walk else 0.0),
                np.full(3, kb * c.q_gyro_bias_sigma ** 2),
                np.full(2, kb * c.q_mounting_sigma ** 2 if c.estimate_mounting else 0.0)])
            self._qd_dt, self._qd_walk = dt, walk
        P[self._di, self._di] += self._qd
        self._P = P

    # ------------------------------------------------------------------ measurement helpers
    def _body_speed_rows(self, rows) -> tuple:
        """Prediction v_b[rows] = (R_m R^T v)[rows] in base_link and its Jacobian H (Eq. (46)).

        With R_true = (I - S(eps)) R_hat:  v_i = R^T v - R^T S(v) eps  (the attitude
        term is dropped when ``full_velocity_jacobian`` is False, as in Eq. (46)); the
        mounting R_m (imu_link -> base_link) with R_m,true = R_m (I + S(dm)) adds
        v_b = R_m v_i - R_m S(v_i) dm.
        """
        Rt = self._R.T
        Rm = self._Rm
        vi = Rt @ self._v
        vb = Rm @ vi
        H = np.zeros((len(rows), N_ERR))
        RmRt = Rm @ Rt
        H[:, IV:IV + 3] = RmRt[rows]
        if self.config.full_velocity_jacobian:
            H[:, IA:IA + 3] = -(RmRt[rows] @ skew(self._v))
        if self.config.estimate_mounting:
            H[:, IM:IM + 2] = -(Rm[rows] @ skew(vi))[:, 1:3]
        return vb[rows], H

    def _nh_update(self, t: float) -> None:
        """NH constraints / stationary update (Sec. 5.4, rows (3) of Eq. (45))."""
        c = self.config
        if self._is_stationary(t):
            rows = [0, 1, 2] if c.stationary_update_longitudinal else [1, 2]
            r = np.full(len(rows), c.stationary_sigma ** 2)
        else:
            rows = [1, 2]
            r = np.array([c.nh_sigma_y ** 2, c.nh_sigma_z ** 2])
        pred, H = self._body_speed_rows(rows)
        self._update(-pred, H, np.diag(r), None)

    def _update(self, y: np.ndarray, H: np.ndarray, W: np.ndarray, gate) -> int:
        """Eqs. (37)-(44): gain, error-state estimate, injection, covariance (Joseph form).

        Returns 1 if applied, 0 if gated out, -1 on numerical failure.
        """
        P = self._P
        PHt = P @ H.T
        S = H @ PHt + W
        S_inv = _inv_small(S)
        if S_inv is None:
            self.rejected["update_numerical"] += 1
            return -1
        if gate is not None:
            d2 = float(y @ S_inv @ y)
            if not d2 <= gate:
                return 0
        K = PHt @ S_inv                                   # Eq. (37)
        if self.config.hold_yaw_rate_bias_without_gnss and not self.gnss_aided:
            K[IBG + 2, :] = 0.0                           # Schmidt: a consider state keeps its value
        dz = K @ y                                        # Eq. (40), with the previous error reset to 0
        if not math.isfinite(float(dz.sum())):
            self.rejected["update_numerical"] += 1
            return -1
        A = self._eye15 - K @ H
        P = A @ P @ A.T + K @ W @ K.T                     # Eq. (44), Joseph form
        self._P = 0.5 * (P + P.T)
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
        if self.config.estimate_mounting:
            self._Rm = self._Rm @ quat_to_rotmat(quat_from_rotvec([0.0, dz[IM], dz[IM + 1]]))

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
        try:
            t = float(t)
        except (TypeError, ValueError):
            t = math.nan
        W = self._w_gnss
        if covariance is not None:
            try:
                Wc = np.asarray(covariance, dtype=float).reshape(3, 3)
            except (TypeError, ValueError):
                Wc = None
            if Wc is None or not np.all(np.isfinite(Wc)) or np.any(np.diag(Wc) <= 0):
                z = None
            else:
                W = 0.5 * (Wc + Wc.T)
        if z is None or not math.isfinite(t):
            self.rejected["gnss_nonfinite"] += 1
            return False
        if self._t_gnss is not None and not t > self._t_gnss:
            self.rejected["gnss_out_of_order"] += 1
            return False
        if self._t is not None and t < self._t - self.config.max_measurement_delay_s:
            self.rejected["gnss_stale"] += 1
            return False
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

    def _heading_step(self, t: float, z: np.ndarray, W: np.ndarray) -> bool:
        """Yaw initialisation from GNSS motion (Sec. 7.1).

        The paper takes the course between the first two fixes after the vehicle starts
        moving.  At 10 Hz that baseline is centimetres, so here all fixes from the first
        one after moving are paired with the (yaw-provisional) INS positions at the same
        stamps (the INS keeps running with the yaw-free speed/NH/stationary updates), and
        once the GNSS baseline exceeds ``heading_min_baseline_m`` the 2-D rotation +
        translation that best maps the INS track onto the GNSS track (least squares,
        Procrustes) gives the yaw.  Its standard deviation sigma_h / sqrt(sum |r_i|^2)
        seeds P.
        """
        c = self.config
        if not self._heading_fixes and self._stationary_source(t):
            # Still standing: keep the provisional position on the latest fix.
            self._p = z.copy()
            return True
        ins = self._p + (t - self._t) * self._v if self._t is not None else self._p.copy()
        var_h = 0.5 * (W[0, 0] + W[1, 1])
        self._heading_fixes.append((z, ins, var_h))
        if len(self._heading_fixes) > c.heading_max_fixes:
            self._heading_fixes.pop(0)
        g0 = self._heading_fixes[0][0]
        if math.hypot(z[0] - g0[0], z[1] - g0[1]) < c.heading_min_baseline_m:
            return True
        G = np.array([f[0] for f in self._heading_fixes])
        I = np.array([f[1] for f in self._heading_fixes])
        var_h = float(np.mean([f[2] for f in self._heading_fixes]))
        gm, im = G.mean(axis=0), I.mean(axis=0)
        gc, ic = G[:, :2] - gm[:2], I[:, :2] - im[:2]
        num = float(np.sum(ic[:, 0] * gc[:, 1] - ic[:, 1] * gc[:, 0]))
        den = float(np.sum(ic[:, 0] * gc[:, 0] + ic[:, 1] * gc[:, 1]))
        dpsi = math.atan2(num, den)
        spread = float(np.sum(ic * ic))
        sig_psi = max(math.sqrt(var_h / max(spread, 1e-6)), c.p0_attitude_sigma[2])
        Rz = rot_z(dpsi)
        # Rotate the whole navigation solution about the vertical.
        self._q = quat_normalize(quat_multiply(np.array([0.0, 0.0, math.sin(0.5 * dpsi),
                                                         math.cos(0.5 * dpsi)]), self._q))
        self._R = quat_to_rotmat(self._q)
        self._v = Rz @ self._v
        p = self._p.copy()
        p[:2] = gm[:2] + Rz[:2, :2] @ (p[:2] - im[:2])
        p[2] = p[2] + (gm[2] - im[2])
        self._p = p
        T = np.eye(N_ERR)
        for b in (IP, IV, IA):
            T[b:b + 3, b:b + 3] = Rz
        P = T @ self._P @ T.T
        P[IP:IP + 3, :] = 0.0
        P[:, IP:IP + 3] = 0.0
        P[IP:IP + 3, IP:IP + 3] = W
        P[IA + 2, :] = 0.0
        P[:, IA + 2] = 0.0
        P[IA + 2, IA + 2] = sig_psi ** 2
        self._P = 0.5 * (P + P.T)
        self._heading_fixes = []
        self.heading_sigma_at_init = sig_psi
        self.events["heading_initialised"] += 1
        self.status = STATUS_RUNNING
        return True

    # ------------------------------------------------------------------ CAN speed
    def update_speed(self, t: float, speed: float, variance: float | None = None) -> bool:
        """CAN-bus longitudinal speed update (row (2) of Eqs. (45)-(47), body x).

        Also drives stationary detection (|speed| <= stationary_speed_threshold).
        Before alignment the speed is only stored for stationarity.  Returns True
        when the measurement was used.
        """
        try:
            t = float(t)
            s = float(speed)
            r = self.config.speed_sigma ** 2 if variance is None else float(variance)
        except (TypeError, ValueError):
            t = s = r = math.nan
        if not (math.isfinite(t) and math.isfinite(s) and math.isfinite(r)) or r <= 0:
            self.rejected["speed_nonfinite"] += 1
            return False
        if self._t_speed is not None and not t > self._t_speed:
            self.rejected["speed_out_of_order"] += 1
            return False
        if self._t is not None and t < self._t - self.config.max_measurement_delay_s:
            self.rejected["speed_stale"] += 1
            return False
        self._t_speed = t
        self._last_speed = s
        if self.status in (STATUS_WAIT_STANDSTILL, STATUS_ALIGNING):
            return True
        pred, H = self._body_speed_rows([0])
        if self.config.speed_unsigned and pred[0] < 0.0:
            s = -abs(s)
        y = np.array([s - pred[0]])
        W = np.array([[r]])
        res = self._update(y, H, W, self.config.speed_gate_chi2)
        return self._after_gated("speed", res, y, H, W, slice(IV, IV + 3))

    # ------------------------------------------------------------------ outputs
    @property
    def position_enu(self) -> np.ndarray:
        return self._p.copy()

    @property
    def velocity_enu(self) -> np.ndarray:
        return self._v.copy()

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
    def imu_rotation_matrix(self) -> np.ndarray:
        """imu_link -> ENU (the filter's own attitude)."""
        return self._R.copy()

    @property
    def mounting_rotation(self) -> np.ndarray:
        """imu_link -> base_link: the nominal mounting refined online."""
        return self._Rm.copy()

    @property
    def mounting_rpy(self) -> np.ndarray:
        """Roll, pitch, yaw of imu_link in base_link [rad]."""
        return np.asarray(euler_from_rotmat(self._Rm), float)

    @property
    def mounting_covariance(self) -> np.ndarray:
        """2x2 covariance of the mounting pitch and yaw refinement [rad^2]."""
        return self._P[IM:IM + 2, IM:IM + 2].copy()

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
    def accel_bias(self) -> np.ndarray:
        return self._ba.copy()

    @property
    def gyro_bias(self) -> np.ndarray:
        return self._bg.copy()

    @property
    def covariance(self) -> np.ndarray:
        """17x17 error-state covariance, order [dp(ENU), dv(ENU), eps(ENU), dba(imu_link),
        dbg(imu_link), dm (mounting pitch, yaw)]."""
        return self._P.copy()

    @property
    def position_covariance(self) -> np.ndarray:
        return self._P[IP:IP + 3, IP:IP + 3].copy()

    @property
    def velocity_covariance(self) -> np.ndarray:
        """ENU velocity covariance."""
        return self._P[IV:IV + 3, IV:IV + 3].copy()

    @property
    def velocity_body_covariance(self) -> np.ndarray:
        """base_link (FLU) velocity covariance, including the attitude and mounting
        uncertainty (for nav_msgs/Odometry twist, which is in the child/body frame)."""
        _, H = self._body_speed_rows([0, 1, 2])
        return H @ self._P @ H.T

    def _base_attitude_jacobian(self) -> np.ndarray:
        """J with eps_base = J z: R_wb,true = (I - S(eps_base)) R_wb,hat.

        R_wb = R R_m^T; R_m,true^T = (I - S(dm)) R_m^T, so eps_base = eps + R [0, dm]."""
        J = np.zeros((3, N_ERR))
        J[:, IA:IA + 3] = self._eye3
        J[:, IM:IM + 2] = self._R[:, 1:3]
        return J

    @property
    def attitude_covariance(self) -> np.ndarray:
        """base_link attitude error covariance about the fixed ENU x, y, z axes [rad^2]
        (the sensor_msgs/Imu and nav_msgs/Odometry convention)."""
        J = self._base_attitude_jacobian()
        return J @ self._P @ J.T

    @property
    def _unaided_bias_variance(self) -> float:
        return 0.0 if self.accel_bias_observed else self.config.unaided_accel_bias_sigma ** 2

    @property
    def accel_bias_covariance(self) -> np.ndarray:
        """Including, until GNSS has observed it, the bias prior on x and y (see
        ``FusionConfig.unaided_accel_bias_sigma``)."""
        P = self._P[IBA:IBA + 3, IBA:IBA + 3].copy()
        P[0, 0] += self._unaided_bias_variance
        P[1, 1] += self._unaided_bias_variance
        return P

    @property
    def gyro_bias_covariance(self) -> np.ndarray:
        return self._P[IBG:IBG + 3, IBG:IBG + 3].copy()

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
