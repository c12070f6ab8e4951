"""The fusion's initialisation (paper 003 Sec. 7.1): alignment at standstill or in motion, then
the heading from GNSS motion.

Sec. 7.1 aligns at standstill: roll and pitch from the averaged accelerometer, the gyro bias
the mean of ``init_stationary_samples`` (200) stationary gyro samples, the accelerometer bias
zero, the yaw from GNSS motion once the vehicle moves. A filter started while the car drives
levels itself on the CAN-speed kinematics instead (not in the paper). Until the heading is
fixed the filter navigates with a free heading (:attr:`FusionEKF.navigating`). At every later
standstill a zero-rate update reads the gyro bias again (not in the paper either).

:class:`FusionInitialisation` is a part of
:class:`~vehicle_estimation.estimators.fusion.esekf.FusionEKF`, written apart: it reads and
sets the filter's state, declared below.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from vehicle_estimation.estimators.common.rotations import (quat_from_euler, quat_multiply, quat_normalize,
                                                            quat_to_rotmat, rot_z)
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.error_state import (IA, IBA, IBG, IK, IP, IV, N_ERR, STATUS_ALIGNING,
                                                              STATUS_RUNNING, STATUS_WAIT_HEADING,
                                                              STATUS_WAIT_STANDSTILL)

__all__ = ["FusionInitialisation"]

#: The zero-rate update's Jacobian: the angular rate at standstill is the gyro bias (read only).
_ZERO_RATE_H = np.zeros((3, N_ERR))
_ZERO_RATE_H[:, IBG:IBG + 3] = np.eye(3)
_ZERO_RATE_H.flags.writeable = False


class FusionInitialisation:
    """The alignment and heading steps of :class:`FusionEKF` (a mixin of it)."""

    config: FusionConfig
    status: str
    events: dict[str, int]
    heading_sigma_at_init: float | None
    _p: np.ndarray
    _v: np.ndarray
    _q: np.ndarray
    _R: np.ndarray
    _Rm: np.ndarray
    _ba: np.ndarray
    _bg: np.ndarray
    _P: np.ndarray
    _p0_diag: np.ndarray
    _k0: float
    _speed_scale_error: np.ndarray
    _t: float | None
    _hint: bool | None
    _last_speed: float | None
    _last_gnss: np.ndarray | None
    _align_f: list
    _align_w: list
    _motion: list
    _heading_fixes: list
    _stationary_source: Callable[[float], bool | None]
    _w_prev: np.ndarray | None
    _held_direction: Callable[..., np.ndarray]
    t_heading_fixed: float
    _update: Callable[..., int]

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
        gives in base_link as [dv/dt, v r, 0] (no sideslip, no vertical motion), turned into
        imu_link by the mounting: f = R_m^T a_b + R^T g_up + b.  The gyro bias cannot be
        averaged out while turning, so it starts at zero with ``in_motion_gyro_bias_sigma``."""
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
        Rm = self._Rm
        wb = ws @ Rm.T                                           # the rates about base_link axes
        kinematic = np.array([dvdt, float(np.mean(vs * wb[:, 2])), -float(np.mean(vs * wb[:, 1]))])
        self._align(fs.mean(axis=0) - Rm.T @ kinematic, np.zeros(3))
        self._v = self._R @ (Rm.T @ np.array([float(vs[-1]), 0.0, 0.0]))
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
        # ... and that yaw is base_link's (odom = the start pose, REP-105), not a turned IMU's
        base = self._R @ self._Rm.T
        yaw = math.atan2(base[1, 0], base[0, 0])
        if abs(yaw) > 1e-9:
            self._q = quat_normalize(quat_multiply(np.array([0.0, 0.0, -math.sin(0.5 * yaw), math.cos(0.5 * yaw)]),
                                                   self._q))
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

    def resume_speed_scale(self, scale: float, variance: float) -> float:
        """Start the CAN speed's scale (1 + k) from an earlier drive's estimate, now and after
        every reset: the tyres' rolling radius outlives a drive, and without GNSS nothing in
        this one can learn it (a fusion node persists it, ``persist.path``). The prior variance
        becomes ``variance`` plus ``speed_scale_resume_sigma``^2 for what changed between the
        drives (pressure, temperature), at most ``p0_speed_scale_sigma``^2: the resumed
        variance, returned. Only before the first sample."""
        c = self.config
        if not c.estimate_speed_scale:
            raise ValueError("resume_speed_scale needs estimate_speed_scale")
        if self._t is not None:
            raise ValueError("resume_speed_scale only before the first sample")
        if not (math.isfinite(scale) and abs(scale - 1.0) <= 0.2 and math.isfinite(variance) and variance >= 0.0):
            raise ValueError(f"not a speed scale: {scale} (variance {variance})")
        resumed = min(variance + c.speed_scale_resume_sigma ** 2, c.p0_speed_scale_sigma ** 2)
        self._k0 = scale - 1.0
        self._p0_diag[IK] = resumed
        self._speed_scale_error[0] = self._k0
        self._P[IK, IK] = resumed
        return resumed

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

    def _zero_rate_update(self) -> None:
        """At standstill the gyro reads its bias (and the Earth's rate, which the bias then carries,
        as the alignment's mean does): a zero-rate update observes the bias directly, on every
        axis, from the sample the propagation has just used. Without it the stationary velocity
        update observes the gyro bias only through the tilt it integrates, and nothing of the
        yaw-rate bias, which without GNSS nothing else observes either. The yaw-rate bias is not
        held here (:meth:`_held_direction`): standing, it is observed too, and each stop
        refreshes it (FASTSim's car without GNSS: heading 3.7 -> 0.7 deg RMSE; the pitch-rate
        bias 1.1 -> 0.5 mrad/s off as it pulls away, the pitch over its first 10 s 0.64 -> 0.54
        deg RMSE)."""
        if self._w_prev is None:
            return
        W = np.eye(3) * self.config.stationary_rate_sigma ** 2
        self._update(self._w_prev - self._bg, _ZERO_RATE_H, W, None,
                     held=self._held_direction(yaw_rate_bias=False))

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
        track_scale = math.sqrt(float(np.sum(gc * gc)) / max(spread, 1e-12))
        if abs(track_scale - 1.0) > c.heading_max_scale_error:
            # The GNSS track is not the INS track rotated (a position jump, a fix from
            # elsewhere): its rotation would be arbitrary. Start again from the latest fix.
            self._heading_fixes = [self._heading_fixes[-1]]
            self.events["heading_restarted"] += 1
            return True
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
        self.t_heading_fixed = t
        return True
