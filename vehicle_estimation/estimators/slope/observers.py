"""The slope observers of paper 004 on ``x_r = [v_x, theta]``: the shared base and the classical one.

Slope ``theta`` [rad] is positive uphill. :class:`ClassicalSlopeObserver` is the contrasted
strategy of paper 004 (Eqs. 32-33): state ``x_r = [vx, theta]``, ``x_r' = A x_r + Phi u_r``,
``y_r = vx`` with ``A = [[0, -g], [0, 0]]``, ``Phi_con = diag(1, 0)``, ``u_r = [u1, 0]`` and
``u1 = a_x,acc + r vy`` from the accelerometer model Eq. 21 (``a_x,acc ~ vx' - r vy + g theta``).
The paper prints ``u1 = a_x,acc + r vy'``; Eq. 21 requires ``r vy`` and that is what is
implemented. ``theta' = 0`` is the classical slope model; the observer gain is either a discrete
Kalman gain with a random-walk process noise on ``theta`` (default, gives a consistent variance)
or the paper's fixed Luenberger gain ``L_c = [1, -2]^T`` (Sec. 7.1), optionally with the cubic
correction term of Eq. 24 (``kappa_c``, ``gamma``; off by default as the paper does not give
values).

The proposed strategy, with the slope prediction model, is
:class:`~vehicle_estimation.estimators.slope.cubic_prediction.CubicPredictionSlopeObserver`,
a subclass of :class:`SlopeObserver`.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from typing import Optional

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import GRAVITY
from vehicle_estimation.estimators.common.guard import StepGuard

__all__ = ["ClassicalSlopeConfig", "ClassicalSlopeObserver", "SlopeObserver"]

GAIN_MODES = ("kalman", "luenberger")


@dataclasses.dataclass
class ClassicalSlopeConfig:
    """Tuning of :class:`ClassicalSlopeObserver` (each field's doc gives its unit and meaning).

    ``gain_mode="luenberger"`` Euler-discretises the fixed ``L_c`` of paper 004 Sec. 7.1 as
    ``K = L_c dt`` and propagates the variance for that gain in Joseph form. The explicit-Euler
    step of the cubic term is capped by ``cubic_max_step_gain``: the continuous Eq. 24 has no
    such limit, but its Euler discretisation diverges for gains above 2 (e.g. on a speed that
    jumps while an upstream filter starts).

    ``slope_rate_std`` (the Kalman gain's random walk; the paper gives none) is 0.006 rad/sqrt(s):
    real roads change grade at 0.5-0.7 deg/s, and at 0.003 the model's lag there lay beyond
    3 sigma (FASTSim's car through the nodes: 89 % of the errors within 2 sigma, 1.5 % of the
    flagged beyond 3 sigma, RMSE 0.176 deg; at 0.006: 99.5 %, 0.4 %, 0.135 deg; without GNSS
    0.166 -> 0.121 deg). On a level road with 4 m/s^2 of IMU vibration it costs 8 % of RMSE
    (CommonRoad's lane change, 0.192 -> 0.208 deg) and halves the share beyond 3 sigma.
    """

    gain_mode: str = setting(
        "kalman", "Observer gain: kalman (time-varying Kalman gain on Eqs. 32-33 with a random walk "
        "on theta) or luenberger (the fixed L_c of paper 004 Sec. 7.1)", choices=GAIN_MODES)
    gravity: float = setting(GRAVITY, "Gravitational acceleration g [m/s^2] (paper 004 Table 1: 9.8)",
                             low=0.0, low_open=True)
    accel_noise_std: float = setting(
        0.2, "Accelerometer noise sigma_a driving vx in the prediction, per sample [m/s^2]",
        low=0.0, low_open=True)
    speed_noise_std: float = setting(0.05, "Noise of the measured vx when the sample gives no variance [m/s]",
                                     low=0.0, low_open=True)
    slope_rate_std: float = setting(
        0.006, "Random-walk density of theta on the theta' = 0 model [rad/sqrt(s)]; larger is faster "
        "and noisier", low=0.0, low_open=True)
    initial_slope: float = setting(0.0, "Prior on theta [rad]", low=-0.5 * math.pi, high=0.5 * math.pi,
                                   low_open=True, high_open=True)
    initial_slope_std: float = setting(0.1, "Prior standard deviation of theta [rad]", low=0.0, low_open=True)
    luenberger_gain: tuple = setting(
        (1.0, -2.0), "Observer gain L_c, continuous time [1/s, rad/(m/s)/s] (paper 004 Sec. 7.1: [1, -2])")
    cubic_kappa: float = setting(0.0, "Eq. 24 cubic term kappa_c (0 = off)", low=0.0)
    cubic_gamma: float = setting(1.0, "Eq. 24 cubic term gamma", low=0.0, low_open=True)
    cubic_max_step_gain: float = setting(
        0.5, "Cap on the correction of vx per step, as a fraction of the innovation (Euler step of "
        "the cubic term)", low=0.0, high=1.0, low_open=True, high_open=True)
    max_gap_s: float = setting(0.5, "Stamp gap that re-initialises the observer [s]", low=0.0, low_open=True)
    converged_std: float = setting(0.005, "Converged once sqrt(variance) is below this (and min_converge_time "
                                   "has passed) [rad]", low=0.0, low_open=True)
    min_converge_time: float = setting(2.0, "Converged no sooner than this after (re)initialisation [s]", low=0.0)
    uncompensated_accel_bias_std: float = setting(
        0.05, "Std of an accelerometer bias the observer cannot remove while the fusion's bias estimate "
        "is missing [m/s^2]; enters the published variance as (std / g)^2 (0.05: a typical MEMS "
        "turn-on bias)", low=0.0)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        check_settings(self)
        L = np.asarray(self.luenberger_gain, dtype=float)
        if L.shape != (2,):
            raise ValueError(f"luenberger_gain must be 2 finite numbers, got {self.luenberger_gain!r}")
        if self.gain_mode == "luenberger":
            g = self.gravity
            Acl = np.array([[-L[0], -g], [-L[1], 0.0]])
            if np.any(np.linalg.eigvals(Acl).real >= 0.0):
                raise ValueError("luenberger_gain gives an unstable A - L_c C")


class SlopeObserver(StepGuard):
    """Observer on ``x_r = [vx, theta]``, ``x_r' = A x_r + Phi u_r``, ``y_r = C x_r``.

    ``A = [[0, -g], [0, 0]]`` and ``C = [1, 0]`` are shared by Eqs. 22-23 and 32-33;
    subclasses choose ``Phi`` and the input vector ``u_r``. Discretisation over a step of
    length ``dt`` is exact for the linear part (``A^2 = 0``): ``F = I + A dt``, with the
    inputs held constant over the step: ``B u = [dt u1 - g dt^2 u2 / 2, dt u2]`` (after
    ``Phi``).
    """

    PHI = np.diag([1.0, 1.0])

    def __init__(self, config: Optional[ClassicalSlopeConfig] = None):
        self.config = ClassicalSlopeConfig() if config is None else config
        self.config.validate()
        self._cubic_dir: Optional[np.ndarray] = None
        if self.config.gain_mode == "luenberger" and self.config.cubic_kappa > 0.0:
            self._cubic_dir = self._cubic_direction()
        self.rejected: Counter[str] = Counter(
            {"nonfinite_input": 0, "stamp_not_increasing": 0, "nonfinite_speed": 0})
        self.reinitialisations = 0
        self.last_event = ""
        self.reset()

    # -- state -----------------------------------------------------------------------------
    def reset(self) -> None:
        self._x = np.array([0.0, self.config.initial_slope])
        self._P = np.diag([1.0, self.config.initial_slope_std ** 2])
        self.t: Optional[float] = None
        self._t0: Optional[float] = None

    @property
    def slope(self) -> float:
        return float(self._x[1])

    @property
    def variance(self) -> float:
        return float(self._P[1, 1])

    @property
    def speed(self) -> float:
        """The observer's filtered ``vx`` [m/s]."""
        return float(self._x[0])

    @property
    def converged(self) -> bool:
        if self.t is None or self._t0 is None:
            return False
        return (self.t - self._t0 >= self.config.min_converge_time
                and math.sqrt(max(self.variance, 0.0)) < self.config.converged_std)

    # -- model ---------------------------------------------------------------------------
    def _input_vector(self, ax_measured: float, yaw_rate: float, vy: float) -> np.ndarray:
        """``u_r`` before ``Phi``: ``[u1, u2]`` with ``u1 = a_x,acc + r vy`` (Eq. 21)."""
        return np.array([ax_measured + yaw_rate * vy, 0.0])

    def _cubic_direction(self) -> np.ndarray:
        """``-N_c = gamma P_c^-1 C^T kappa_c`` of Eqs. 24-27 with ``P_c`` from the Lyapunov
        equation ``(A - L_c C)^T P_c + P_c (A - L_c C) = -I``."""
        from scipy.linalg import solve_continuous_lyapunov

        g = self.config.gravity
        L = np.asarray(self.config.luenberger_gain, dtype=float)
        Acl = np.array([[-L[0], -g], [-L[1], 0.0]])
        Pc = solve_continuous_lyapunov(Acl.T, -np.eye(2))
        return self.config.cubic_gamma * np.linalg.solve(Pc, np.array([1.0, 0.0])) * self.config.cubic_kappa

    # The 2-state maths below is written out in scalars: numpy's per-call cost on 2x2 arrays
    # was 10x the arithmetic, at 200 Hz. The matrix form is in each comment.
    def _predict(self, dt: float, u: np.ndarray) -> None:
        """``x = F x + [dt w1 - g dt^2 w2 / 2, dt w2]``, ``P = F P F^T + Q_d`` with ``w = Phi u``
        and ``F = [[1, -g dt], [0, 1]]``."""
        g = self.config.gravity
        phi = self.PHI
        u0, u1 = float(u[0]), float(u[1])
        w0 = float(phi[0, 0]) * u0 + float(phi[0, 1]) * u1
        w1 = float(phi[1, 0]) * u0 + float(phi[1, 1]) * u1
        f = -g * dt
        x0, x1 = float(self._x[0]), float(self._x[1])
        self._x = np.array([x0 + f * x1 + (dt * w0 - 0.5 * g * dt * dt * w1), x1 + dt * w1])
        qv = (self.config.accel_noise_std * dt) ** 2
        qt = self.config.slope_rate_std ** 2 * dt
        q01 = -0.5 * g * qt * dt
        P = self._P
        a00, a01 = float(P[0, 0]) + f * float(P[1, 0]), float(P[0, 1]) + f * float(P[1, 1])   # F P
        a10, a11 = float(P[1, 0]), float(P[1, 1])
        self._P = np.array([[a00 + a01 * f + (qv + g * g * qt * dt * dt / 3.0), a01 + q01],   # (F P) F^T + Q_d
                            [a10 + a11 * f + q01, a11 + qt]])

    def _correct(self, dt: float, vx: float, r_vx: float) -> None:
        """``x + K (vx - x_1)``; ``P = (I - K C) P (I - K C)^T + r K K^T`` (symmetrised), with
        ``C = [1, 0]`` and the Kalman gain or the (cubic) Luenberger gain of Eqs. 24-27."""
        P = self._P
        p00, p01, p10, p11 = float(P[0, 0]), float(P[0, 1]), float(P[1, 0]), float(P[1, 1])
        innov = vx - float(self._x[0])
        if self.config.gain_mode == "kalman":
            S = p00 + r_vx
            k0, k1 = p00 / S, p10 / S
        else:
            L = self.config.luenberger_gain
            k0, k1 = float(L[0]) * dt, float(L[1]) * dt
            if self._cubic_dir is not None:
                # Eq. 24's cubic term -(e^T C^T kappa_c C e) N_c C e, C e ~ innovation, as a
                # gain on the innovation: dt (-N_c kappa_c) innov^2, capped where the explicit
                # Euler step would overshoot the measurement (cubic_max_step_gain).
                d0, d1 = float(self._cubic_dir[0]), float(self._cubic_dir[1])
                room = max(self.config.cubic_max_step_gain - k0, 0.0)
                innov_sq = min(innov * innov, room / (dt * d0)) if d0 > 0.0 else innov * innov
                k0, k1 = k0 + dt * d0 * innov_sq, k1 + dt * d1 * innov_sq
        self._x = np.array([float(self._x[0]) + k0 * innov, float(self._x[1]) + k1 * innov])
        c00, c01 = (1.0 - k0) * p00, (1.0 - k0) * p01                  # (I - K C) P
        c10, c11 = -k1 * p00 + p10, -k1 * p01 + p11
        d00, d01 = c00 * (1.0 - k0) + r_vx * k0 * k0, c00 * -k1 + c01 + r_vx * k0 * k1
        d10, d11 = c10 * (1.0 - k0) + r_vx * k1 * k0, c10 * -k1 + c11 + r_vx * k1 * k1
        off = 0.5 * (d01 + d10)
        self._P = np.array([[d00, off], [off, d11]])

    # -- main entry ----------------------------------------------------------------------
    def step(self, t: float, ax_measured: float, vx: float, vx_dot: Optional[float] = None,
             yaw_rate: float = 0.0, vy: float = 0.0, vx_variance: Optional[float] = None) -> bool:
        """One sample at stamp ``t`` [s].

        Args:
            ax_measured: longitudinal accelerometer specific force ``a_x,acc`` [m/s^2]
                (IMU, body x, gravity component included, bias-compensated if possible).
            vx: measured longitudinal speed ``y_r`` [m/s] (wheel speeds / CAN speed or
                the vehicle-state estimate); NaN -> predict only.
            vx_dot: not used (``vx'`` is implicit in the observer); accepted for API
                compatibility and ignored.
            yaw_rate, vy: ``r`` [rad/s] and ``vy`` [m/s] for ``u1 = a_x,acc + r vy``
                (Eq. 21); 0 when unknown (straight driving).
            vx_variance: variance of ``vx`` [m^2/s^2]; default ``speed_noise_std^2``.

        Returns True if ``vx`` corrected the state; False if the sample was rejected
        (non-finite input, stamp not increasing) or only predicted (``vx`` NaN).
        A gap above ``max_gap_s`` re-initialises (keeping the last slope as prior).
        """
        del vx_dot
        t = float(t)
        gap = self.admit(t, all(math.isfinite(v) for v in (ax_measured, yaw_rate, vy)),
                         invalid="nonfinite_input", invalid_event="non-finite input", show_stamps=False)
        if gap is None:
            return False
        vx_ok = math.isfinite(vx)
        if self.t is not None and gap > self.config.max_gap_s:
            slope = self.slope
            self.reset()
            self._x[1] = slope  # keep the last slope as prior, with the initial variance
            self.note_reinitialised(gap)
        if self.t is None:
            if not vx_ok:
                self.rejected["nonfinite_speed"] += 1
                return False
            self._x[0] = vx
            self._P[0, 0] = self._r_vx(vx_variance)
            self.t = self._t0 = t
            return True
        dt = gap
        self._predict(dt, self._input_vector(ax_measured, yaw_rate, vy))
        self.t = t
        if not vx_ok:
            self.rejected["nonfinite_speed"] += 1
            self.last_event = "non-finite vx: predicted only"
            return False
        self._correct(dt, vx, self._r_vx(vx_variance))
        return True

    def _r_vx(self, vx_variance: Optional[float]) -> float:
        if vx_variance is not None and math.isfinite(vx_variance) and vx_variance > 0.0:
            return float(vx_variance)
        return self.config.speed_noise_std ** 2


class ClassicalSlopeObserver(SlopeObserver):
    """Classical slope observer, paper 004 Eqs. 32-33 (``theta' = 0``, ``Phi_con = diag(1, 0)``)."""

    PHI = np.diag([1.0, 0.0])
