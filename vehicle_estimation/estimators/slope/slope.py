"""Road-slope observers (paper 004 Sec. 5 and Sec. 7; paper 003 Sec. 7.2).

Slope ``theta`` [rad] is positive uphill. Three methods, selectable by name through
:data:`SLOPE_METHODS`:

``"classical"`` -- :class:`ClassicalSlopeObserver`, the contrasted strategy of paper 004
    (Eqs. 32-33): state ``x_r = [vx, theta]``, ``x_r' = A x_r + Phi u_r``, ``y_r = vx``
    with ``A = [[0, -g], [0, 0]]``, ``Phi_con = diag(1, 0)``, ``u_r = [u1, 0]`` and
    ``u1 = a_x,acc + r vy`` from the accelerometer model Eq. 21
    (``a_x,acc ~ vx' - r vy + g theta``). The paper prints ``u1 = a_x,acc + r vy'``;
    Eq. 21 requires ``r vy`` and that is what is implemented. ``theta' = 0`` is the
    classical slope model; the observer gain is either a discrete Kalman gain with a
    random-walk process noise on ``theta`` (default, gives a consistent variance) or
    the paper's fixed Luenberger gain ``L_c = [1, -2]^T`` (Sec. 7.1), optionally with the
    cubic correction term of Eq. 24 (``kappa_c``, ``gamma``; off by default as the paper
    does not give values).

``"cubic_prediction"`` -- :class:`CubicPredictionSlopeObserver`, the proposed strategy of
    paper 004 Sec. 5: the same state space with ``Phi = I`` and ``u2`` the slope change
    rate from the slope prediction model (Eqs. 15-20, :class:`SlopePredictionModel`: a
    second-order road fitted over the recently travelled distance to the observer's own
    past slope estimates), observed by the cubic observer of Eqs. 24-27
    (:func:`cubic_observer_design`). It removes the ramp lag of ``theta' = 0``
    (``L1 / (-L2 g)`` for a fixed gain) and propagates the error covariance of its fixed
    gain so that ``variance`` and ``converged`` mean what they mean for the others.

``"fusion_pitch"`` -- :class:`PitchGradeSlope`, paper 003 Sec. 7.2: the road grade is the
    (negated) pitch of the IMU/GNSS fusion; here it arrives already as ``road_grade``
    (+uphill) with its variance, and is optionally smoothed by a linearly weighted moving
    average (LWMA, 25 samples in paper 003 Sec. 7.1).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import NamedTuple, Optional

import numpy as np

from vehicle_estimation.contract.vehicle import GRAVITY

__all__ = [
    "ClassicalSlopeConfig",
    "ClassicalSlopeObserver",
    "CubicPredictionSlopeConfig",
    "CubicObserverDesign",
    "CubicPredictionSlopeObserver",
    "PAPER_LUENBERGER_GAIN",
    "PitchGradeConfig",
    "PitchGradeSlope",
    "SLOPE_METHODS",
    "SlopePredictionModel",
    "cubic_observer_design",
    "grade_from_pitch",
    "luenberger_gain_for_poles",
]


def grade_from_pitch(pitch: float) -> float:
    """Road grade from a REP-103 pitch angle: nose-up is negative pitch about +y, so
    ``theta = -pitch`` (paper 003 Sec. 7.2: "the sign of the road gradient is opposite to
    the vehicle pitch angle"). Dynamic pitch from acceleration is not compensated."""
    return -float(pitch)


def _check_positive(obj, names) -> None:
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be a finite positive number, got {value!r}")


@dataclasses.dataclass
class ClassicalSlopeConfig:
    """Tuning of :class:`ClassicalSlopeObserver`.

    Attributes:
        gain_mode: ``"kalman"`` (time-varying Kalman gain on Eqs. 32-33 with a random
            walk on ``theta``) or ``"luenberger"`` (fixed ``L_c`` of paper 004 Sec. 7.1,
            Euler-discretised, ``K = L_c dt``; the variance is then propagated for that
            gain in Joseph form).
        gravity: ``g`` [m/s^2] (paper Table 1: 9.8).
        accel_noise_std: accelerometer noise ``sigma_a`` [m/s^2] driving ``vx`` in the
            prediction (per sample; default ``sqrt(4e-2)``, paper R for ``ax``).
        speed_noise_std: noise of the measured ``vx`` [m/s] (overridable per step).
        slope_rate_std: random-walk density of ``theta`` [rad/sqrt(s)]; the
            ``theta' = 0`` model plus this noise. Larger = faster, noisier.
        initial_slope, initial_slope_std: prior on ``theta`` [rad].
        luenberger_gain: ``L_c`` (paper: ``[1, -2]^T``), continuous-time [1/s, rad/m].
        cubic_kappa, cubic_gamma: Eq. 24 cubic term ``kappa_c``, ``gamma`` (0 = off).
        cubic_max_step_gain: the explicit-Euler step of the cubic term is capped so that the
            total correction of ``v_x`` per step is at most this fraction of the innovation
            (the continuous Eq. 24 has no such limit; its Euler discretisation diverges for
            gains above 2, e.g. on a speed that jumps while an upstream filter starts).
        max_gap_s: stamp gap that re-initialises the observer [s].
        converged_std: ``converged`` once ``sqrt(variance)`` is below this [rad] ...
        min_converge_time: ... and at least this long since (re)initialisation [s].
    """

    gain_mode: str = "kalman"
    gravity: float = GRAVITY
    accel_noise_std: float = 0.2
    speed_noise_std: float = 0.05
    slope_rate_std: float = 0.003
    initial_slope: float = 0.0
    initial_slope_std: float = 0.1
    luenberger_gain: tuple = (1.0, -2.0)
    cubic_kappa: float = 0.0
    cubic_gamma: float = 1.0
    cubic_max_step_gain: float = 0.5
    max_gap_s: float = 0.5
    converged_std: float = 0.005
    min_converge_time: float = 2.0

    def validate(self) -> None:
        if self.gain_mode not in ("kalman", "luenberger"):
            raise ValueError(f"gain_mode must be 'kalman' or 'luenberger', got {self.gain_mode!r}")
        _check_positive(self, ("gravity", "accel_noise_std", "speed_noise_std", "slope_rate_std",
                               "initial_slope_std", "cubic_gamma", "max_gap_s", "converged_std"))
        if not (math.isfinite(self.initial_slope) and abs(self.initial_slope) < 0.5 * math.pi):
            raise ValueError(f"initial_slope must be finite and within +-pi/2, got {self.initial_slope!r}")
        if not (math.isfinite(self.cubic_kappa) and self.cubic_kappa >= 0.0):
            raise ValueError(f"cubic_kappa must be finite and >= 0, got {self.cubic_kappa!r}")
        if not (math.isfinite(self.cubic_max_step_gain) and 0.0 < self.cubic_max_step_gain < 1.0):
            raise ValueError(f"cubic_max_step_gain must be in (0, 1), got {self.cubic_max_step_gain!r}")
        if not (math.isfinite(self.min_converge_time) and self.min_converge_time >= 0.0):
            raise ValueError(f"min_converge_time must be finite and >= 0, got {self.min_converge_time!r}")
        L = np.asarray(self.luenberger_gain, dtype=float)
        if L.shape != (2,) or not np.all(np.isfinite(L)):
            raise ValueError(f"luenberger_gain must be 2 finite numbers, got {self.luenberger_gain!r}")
        if self.gain_mode == "luenberger":
            g = self.gravity
            Acl = np.array([[-L[0], -g], [-L[1], 0.0]])
            if np.any(np.linalg.eigvals(Acl).real >= 0.0):
                raise ValueError("luenberger_gain gives an unstable A - L_c C")


class _SlopeObserverBase:
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
        self.rejected = {"nonfinite_input": 0, "stamp_not_increasing": 0, "nonfinite_speed": 0}
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

    def _predict(self, dt: float, u: np.ndarray) -> None:
        g = self.config.gravity
        w = self.PHI @ u
        F = np.array([[1.0, -g * dt], [0.0, 1.0]])
        self._x = F @ self._x + np.array([dt * w[0] - 0.5 * g * dt * dt * w[1], dt * w[1]])
        qv = (self.config.accel_noise_std * dt) ** 2
        qt = self.config.slope_rate_std ** 2 * dt
        Qd = np.array([[qv + g * g * qt * dt * dt / 3.0, -0.5 * g * qt * dt],
                       [-0.5 * g * qt * dt, qt]])
        self._P = F @ self._P @ F.T + Qd

    def _correct(self, dt: float, vx: float, r_vx: float) -> None:
        P = self._P
        innov = vx - self._x[0]
        if self.config.gain_mode == "kalman":
            S = P[0, 0] + r_vx
            K = P[:, 0] / S
        else:
            K = np.asarray(self.config.luenberger_gain, dtype=float) * dt
            if self._cubic_dir is not None:
                # Eq. 24's cubic term -(e^T C^T kappa_c C e) N_c C e, C e ~ innovation, as a
                # gain on the innovation: dt (-N_c kappa_c) innov^2, capped where the explicit
                # Euler step would overshoot the measurement (cubic_max_step_gain).
                d = self._cubic_dir
                room = max(self.config.cubic_max_step_gain - K[0], 0.0)
                innov_sq = min(innov * innov, room / (dt * d[0])) if d[0] > 0.0 else innov * innov
                K = K + dt * d * innov_sq
        self._x = self._x + K * innov
        IKC = np.eye(2) - np.outer(K, [1.0, 0.0])
        P = IKC @ P @ IKC.T + r_vx * np.outer(K, K)
        self._P = 0.5 * (P + P.T)

    # -- main entry ----------------------------------------------------------------------
    def _step(self, t: float, ax_measured: float, vx: float, yaw_rate: float, vy: float,
              vx_variance: Optional[float]) -> bool:
        t = float(t)
        if not all(math.isfinite(v) for v in (t, ax_measured, yaw_rate, vy)):
            self.rejected["nonfinite_input"] += 1
            self.last_event = "non-finite input"
            return False
        if self.t is not None and t <= self.t:
            self.rejected["stamp_not_increasing"] += 1
            self.last_event = "stamp not increasing"
            return False
        vx_ok = math.isfinite(vx)
        if self.t is not None and t - self.t > self.config.max_gap_s:
            self.last_event = f"re-initialised after a {t - self.t:.3f} s gap"
            slope = self.slope
            self.reset()
            self._x[1] = slope  # keep the last slope as prior, with the initial variance
            self.reinitialisations += 1
        if self.t is None:
            if not vx_ok:
                self.rejected["nonfinite_speed"] += 1
                return False
            self._x[0] = vx
            self._P[0, 0] = self._r_vx(vx_variance)
            self.t = self._t0 = t
            return True
        dt = t - self.t
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


class ClassicalSlopeObserver(_SlopeObserverBase):
    """Classical slope observer, paper 004 Eqs. 32-33 (``theta' = 0``, ``Phi_con = diag(1, 0)``)."""

    PHI = np.diag([1.0, 0.0])

    def step(self, t: float, ax_measured: float, vx: float, vx_dot: Optional[float] = None,
             yaw_rate: float = 0.0, vy: float = 0.0, vx_variance: Optional[float] = None) -> bool:
        """One sample at stamp ``t`` [s].

        Args:
            ax_measured: longitudinal accelerometer specific force ``a_x,acc`` [m/s^2]
                (IMU, body x, gravity component included, bias-compensated if possible).
            vx: measured longitudinal speed ``y_r`` [m/s] (wheel speeds / CAN speed or
                the vehicle-state estimate); NaN -> predict only.
            vx_dot: not used by Eqs. 32-33 (``vx'`` is implicit in the observer);
                accepted for API compatibility and ignored.
            yaw_rate, vy: ``r`` [rad/s] and ``vy`` [m/s] for ``u1 = a_x,acc + r vy``
                (Eq. 21); 0 when unknown (straight driving).
            vx_variance: variance of ``vx`` [m^2/s^2]; default ``speed_noise_std^2``.

        Returns True if ``vx`` corrected the state; False if the sample was rejected
        (non-finite input, stamp not increasing) or only predicted (``vx`` NaN).
        A gap above ``max_gap_s`` re-initialises (keeping the last slope as prior).
        """
        del vx_dot
        return self._step(t, ax_measured, vx, yaw_rate, vy, vx_variance)


class CubicObserverDesign(NamedTuple):
    """Matrices of the cubic observer, Eqs. 23-27 (scalar output, so ``kappa_c`` is 1x1).

    Attributes:
        A, C: Eq. 23.
        L: ``L_c``: ``[1/s, rad/(m/s)/s]`` per unit speed innovation.
        A_cl: ``A - L_c C``.
        P: ``P_c``, from ``A_cl^T P_c + P_c A_cl = -Q_c`` (the first of Eqs. 27, with
            ``Q_c`` positive definite; this module uses ``Q_c = I``).
        kappa, gamma: ``kappa_c >= 0`` and the arbitrary ``gamma > 0``.
        N: ``N_c = -gamma P_c^-1 C^T kappa_c`` (the choice after Eq. 27), shape (2,).
        lyapunov_linear: ``A_cl^T P_c + P_c A_cl`` (first of Eqs. 27, ``= -Q_c < 0``).
        lyapunov_cubic: ``P_c N_c C + C^T N_c^T P_c`` (second of Eqs. 27,
            ``= -2 gamma kappa_c C^T C``).
    """

    A: np.ndarray
    C: np.ndarray
    L: np.ndarray
    A_cl: np.ndarray
    P: np.ndarray
    kappa: float
    gamma: float
    N: np.ndarray
    lyapunov_linear: np.ndarray
    lyapunov_cubic: np.ndarray


def cubic_observer_design(luenberger_gain, gravity: float = GRAVITY, kappa: float = 1.0,
                          gamma: float = 1.0, lyapunov_q=None) -> CubicObserverDesign:
    """Design the cubic observer of Eqs. 24-27 for a given ``L_c``.

    ``P_c`` solves ``(A - L_c C)^T P_c + P_c (A - L_c C) = -Q_c`` (default ``Q_c = I``), so the
    first of Eqs. 27 holds with margin ``Q_c`` whenever ``A - L_c C`` is Hurwitz. Then
    ``N_c = -gamma P_c^-1 C^T kappa_c`` makes the second

        ``P_c N_c C + C^T N_c^T P_c = -2 gamma kappa_c C^T C``,

    negative *semi*-definite (``C^T C`` has rank 1, so the strict ``< 0`` printed in Eq. 27
    cannot hold for a scalar output). That is enough: along Eq. 25,
    ``V_c' = -e^T Q_c e - 2 gamma kappa_c^2 (C e)^4 <= -e^T Q_c e < 0`` for ``e != 0``, and
    the cubic term only ever makes ``V_c`` fall faster (the claim of Sec. 5.2).
    """
    from scipy.linalg import solve_continuous_lyapunov

    L = np.asarray(luenberger_gain, dtype=float).reshape(2)
    A = np.array([[0.0, -float(gravity)], [0.0, 0.0]])
    C = np.array([[1.0, 0.0]])
    A_cl = A - np.outer(L, C[0])
    if np.any(np.linalg.eigvals(A_cl).real >= 0.0):
        raise ValueError(f"luenberger_gain {tuple(L)} gives an unstable A - L_c C")
    Q = np.eye(2) if lyapunov_q is None else np.asarray(lyapunov_q, dtype=float)
    P = solve_continuous_lyapunov(A_cl.T, -Q)
    P = 0.5 * (P + P.T)
    N = -gamma * np.linalg.solve(P, C[0]) * kappa
    lin = A_cl.T @ P + P @ A_cl
    cub = P @ np.outer(N, C[0]) + np.outer(C[0], N) @ P
    return CubicObserverDesign(A=A, C=C, L=L, A_cl=A_cl, P=P, kappa=float(kappa), gamma=float(gamma),
                               N=N, lyapunov_linear=0.5 * (lin + lin.T), lyapunov_cubic=0.5 * (cub + cub.T))


class SlopePredictionModel:
    """Slope prediction model of paper 004 Sec. 5.1 (Eqs. 15-20): the slope change rate from
    a local second-order fit of the road over the recently travelled distance.

    Reading of the paper (Fig. 4): the points ``P_{k-n}`` are the vehicle's past positions
    along the road, in a vertical plane whose ``x`` is the horizontal distance travelled and
    ``y`` the height. Eq. 15 gives the path length between two samples, ``tau v_x``; Eq. 16
    splits it into ``tau v_x cos(theta)`` (horizontal) and ``tau v_x sin(theta)`` (vertical);
    Eq. 17 sums these backwards from ``P_{k-1}`` to place the past points. The road through
    them is the parabola ``y = a1 x + a2 x^2`` (Eq. 18); since ``theta ~ tan(theta) = dy/dx``
    (Eq. 19, ``theta = a1 + 2 a2 x``) and the slopes ``theta_{k-n}`` at the past points are
    "known" (they are the observer's own past estimates), the paper fits Eq. 19 -- a
    straight line of slope against horizontal distance -- rather than Eq. 18. Eq. 20 then
    gives the change rate as the second derivative of Eq. 18, ``2 a2``.

    ``2 a2 = d theta / d x`` is a rate *per metre* (the curvature of the vertical profile),
    although Eq. 20 writes it with a time dot and Eq. 22 uses it as ``theta'``. The time rate
    follows by the chain rule, ``theta' = 2 a2 dx/dt = 2 a2 v_x cos(theta)``, which is what
    :meth:`slope_rate` returns by default (``rate_mode="distance"``); ``"as_printed"``
    uses ``2 a2`` as a rate per second, as printed (too small by the factor ``v_x``).

    Only ``x`` is needed for the Eq. 19 fit (``y``, from Eq. 17's second column, would be
    needed for Eq. 18 only). Points are stored every ``sample_period_s`` (the paper's points
    are one sample time apart, ``tau = 0.01 s``; thinning them bounds the cost of a fit over
    a window of seconds and changes nothing else); the ordinary least-squares slope is

        ``2 a2 = sum((x_i - x_bar)(theta_i - theta_bar)) / sum((x_i - x_bar)^2)``.
    """

    def __init__(self, window_s: float, sample_period_s: float, min_points: int,
                 min_span_m: float, max_curvature: float, rate_mode: str = "distance"):
        self.window_s = float(window_s)
        self.sample_period_s = float(sample_period_s)
        self.min_points = int(min_points)
        self.min_span_m = float(min_span_m)
        self.max_curvature = float(max_curvature)
        self.rate_mode = rate_mode
        self.reset()

    def reset(self) -> None:
        self._t: collections.deque = collections.deque()
        self._x: collections.deque = collections.deque()
        self._theta: collections.deque = collections.deque()
        self.distance = 0.0           # horizontal distance since reset, Eq. 17's x (shifted) [m]
        self._last: Optional[tuple] = None   # (t, v, theta) of the previous call
        self.curvature = 0.0          # 2 a2 [rad/m], Eq. 20

    def update(self, t: float, speed: float, theta: float) -> None:
        """Advance to stamp ``t`` with the current speed ``v_x`` [m/s] and slope estimate.

        The distance from the previous call is ``dt v_{x,k-1} cos(theta_{k-1})`` (Eqs. 15-16,
        rectangle rule, as Eq. 17). A point ``(x, theta)`` is stored when ``sample_period_s``
        has elapsed since the last one; the fit is redone then.
        """
        if self._last is not None:
            t_prev, v_prev, th_prev = self._last
            self.distance += (t - t_prev) * v_prev * math.cos(th_prev)
        self._last = (t, speed, theta)
        if self._t and t - self._t[-1] < self.sample_period_s - 1e-6:   # float stamps near 1.7e9 s
            return
        self._t.append(t)
        self._x.append(self.distance)
        self._theta.append(theta)
        while self._t and t - self._t[0] > self.window_s + 1e-6:
            self._t.popleft()
            self._x.popleft()
            self._theta.popleft()
        self.curvature = self._fit()

    def _fit(self) -> float:
        """``2 a2`` of Eq. 19 by least squares over the window, clamped; 0 if ill-posed."""
        if len(self._x) < self.min_points:
            return 0.0
        x = np.fromiter(self._x, dtype=float)
        th = np.fromiter(self._theta, dtype=float)
        # Eq. 17 puts the origin at P_{k-1}; the fitted slope 2 a2 does not depend on the
        # origin, and centring on the mean keeps the sums well conditioned
        dx = x - x.mean()
        sxx = float(dx @ dx)
        # a short span (slow or stopped) makes the fit ill-conditioned; the rate is then ~0 anyway
        if abs(x[-1] - x[0]) < self.min_span_m or sxx <= 0.0:
            return 0.0
        curvature = float(dx @ (th - th.mean())) / sxx
        return min(max(curvature, -self.max_curvature), self.max_curvature)

    def slope_rate(self, speed: float, theta: float) -> float:
        """``u2``: the slope change rate [rad/s] (Eq. 20 with the chain rule, see class doc)."""
        if self.rate_mode == "as_printed":
            return self.curvature
        return self.curvature * speed * math.cos(theta)


#: ``L_c`` of paper 004 Sec. 7.1 [1/s, rad/(m/s)/s]: poles of ``A - L_c C`` at
#: ``-0.5 +- 4.40j`` (omega_n = sqrt(2 g) = 4.43 rad/s, damping 0.11).
PAPER_LUENBERGER_GAIN = (1.0, -2.0)


def luenberger_gain_for_poles(natural_frequency: float, damping: float,
                              gravity: float = GRAVITY) -> tuple:
    """``L_c`` placing the poles of ``A - L_c C`` (Eq. 23) at ``s^2 + 2 zeta w s + w^2``:
    ``det(sI - A + L_c C) = s^2 + L1 s - g L2``, so ``L1 = 2 zeta w`` and ``L2 = -w^2 / g``."""
    return (2.0 * damping * natural_frequency, -natural_frequency ** 2 / gravity)


@dataclasses.dataclass
class CubicPredictionSlopeConfig(ClassicalSlopeConfig):
    """Tuning of :class:`CubicPredictionSlopeObserver`.

    All fields of :class:`ClassicalSlopeConfig` keep their meaning; ``gain_mode`` defaults to
    ``"luenberger"`` (the paper's fixed-gain cubic observer) and ``cubic_kappa`` to a value
    > 0 (the cubic term on). ``luenberger_gain`` is ``L_c``, ``cubic_kappa`` is ``kappa_c``
    and ``cubic_gamma`` is ``gamma``; ``N_c`` follows from them and ``Q_c = I``
    (:func:`cubic_observer_design`). ``slope_rate_std`` is now the error of the *predicted*
    rate ``u2``, not of ``theta' = 0``; it only shapes the reported variance in
    ``"luenberger"`` mode (and the gain in ``"kalman"`` mode).

    Default gain: ``L_c = [4.2, -0.92]^T`` (:func:`luenberger_gain_for_poles` with
    ``omega = 3 rad/s``, ``zeta = 0.7``) instead of the paper's ``[1, -2]^T``
    (:data:`PAPER_LUENBERGER_GAIN`, see :meth:`paper_gain`). The paper's gain is stable and
    nearly lag-free (ramp lag of the ``theta' = 0`` observer ``L1 / (-L2 g) = 0.05 s``) but its
    poles are damped at 0.11: every jolt of the accelerometer (gear shifts, brake onsets)
    rings at 0.7 Hz for seconds. On the ``paper004_loop`` simulation with the node's inputs
    it gives slope RMSE 0.23 deg and peak error 1.4 deg against 0.14 deg / 0.6 deg for the
    default, and its propagated std (0.4 deg) never gets below ``converged_std``.

    ``cubic_kappa = 1.5``: the cubic term's speed gain ``gamma kappa_c^2 (P_c^-1 C^T)_v e^2``
    equals ``L1`` at an innovation ``e = 0.5 m/s``, i.e. it stays out of the way of speed
    noise (a few cm/s) and acts on gross errors. With ``N_c = -gamma P_c^-1 C^T kappa_c`` its
    direction is almost pure ``v_x`` (``theta``/``v_x`` component ratio -0.03 against
    ``L_c``'s -0.22), so it speeds up the recovery of the speed error and barely touches the
    slope.

    Attributes (new):
        fit_window_s: span of the sliding window of past ``(x, theta_hat)`` points fitted by
            Eq. 19 [s]. The rate fitted from the observer's own estimates feeds back into
            them; windows below ~2 s make that loop unstable for the paper's gain, and
            3-6 s give the best errors in simulation.
        fit_sample_period_s: spacing of the stored points [s].
        fit_min_points: fewer points than this -> ``u2 = 0``.
        fit_min_span_m: horizontal span of the window below which ``u2 = 0`` [m].
        max_slope_curvature: clamp on ``|2 a2|`` [rad/m] (road vertical curves have radii
            of hundreds of metres and more, i.e. ``|d theta/dx| < ~0.005 rad/m``).
        rate_mode: ``"distance"`` (``u2 = 2 a2 v_x cos(theta)``, default) or ``"as_printed"``
            (``u2 = 2 a2`` taken as a rate per second, as Eq. 22 prints; dimensionally a rate
            per metre, so the prediction is ``v_x`` times too weak).
        prediction_warmup_s: after (re)initialisation the observer runs with ``u2 = 0`` and
            collects no fit points for this long [s], so that its own initial convergence is
            not taken for a slope change and extrapolated.
    """

    gain_mode: str = "luenberger"
    luenberger_gain: tuple = (4.2, -0.92)
    cubic_kappa: float = 1.5
    cubic_gamma: float = 1.0
    slope_rate_std: float = 0.002
    fit_window_s: float = 4.0
    fit_sample_period_s: float = 0.05
    fit_min_points: int = 5
    fit_min_span_m: float = 2.0
    max_slope_curvature: float = 0.01
    rate_mode: str = "distance"
    prediction_warmup_s: float = 2.0

    @classmethod
    def paper_gain(cls, **overrides) -> "CubicPredictionSlopeConfig":
        """The paper-literal observer gain ``L_c = [1, -2]^T`` (Sec. 7.1)."""
        overrides.setdefault("luenberger_gain", PAPER_LUENBERGER_GAIN)
        return cls(**overrides)

    def validate(self) -> None:
        super().validate()
        _check_positive(self, ("fit_window_s", "fit_sample_period_s", "fit_min_span_m",
                               "max_slope_curvature"))
        if not (isinstance(self.fit_min_points, (int, np.integer)) and self.fit_min_points >= 3):
            raise ValueError(f"fit_min_points must be an integer >= 3, got {self.fit_min_points!r}")
        if self.fit_sample_period_s * (self.fit_min_points - 1) > self.fit_window_s:
            raise ValueError(f"fit_window_s ({self.fit_window_s!r}) holds fewer than fit_min_points "
                             f"({self.fit_min_points!r}) points of fit_sample_period_s "
                             f"({self.fit_sample_period_s!r})")
        if self.rate_mode not in ("distance", "as_printed"):
            raise ValueError(f"rate_mode must be 'distance' or 'as_printed', got {self.rate_mode!r}")
        if not (math.isfinite(self.prediction_warmup_s) and self.prediction_warmup_s >= 0.0):
            raise ValueError(f"prediction_warmup_s must be finite and >= 0, got {self.prediction_warmup_s!r}")


class CubicPredictionSlopeObserver(_SlopeObserverBase):
    """Slope prediction model + cubic observer, paper 004 Sec. 5 (Eqs. 15-27).

    State ``x_r = [v_x, theta]``, ``x_r' = A x_r + Phi u_r`` with ``Phi = I`` (Eq. 23) and
    ``u_r = [u1, u2]``: ``u1 = a_x,acc + r v_y`` (Eq. 21) and ``u2`` the slope change rate from
    :class:`SlopePredictionModel` (Eqs. 15-20) fitted to this observer's own past estimates.
    The observer is Eq. 24,

        ``x_hat' = (A - L_c C) x_hat + L_c y + Phi u - (e^T C^T kappa_c C e) N_c C e``,

    where ``C e = v_x - v_x_hat`` is the innovation, discretised per step ``dt`` as
    ``x_hat += dt (L_c + gamma kappa_c^2 P_c^-1 C^T innov^2) innov`` after the exact prediction
    of the base class, with the cubic factor capped (``cubic_max_step_gain``).

    Variance: the paper's observer is fixed-gain and has no covariance. This class propagates
    the error covariance of exactly that fixed-gain observer alongside, ``P <- F P F^T + Q``
    and the Joseph form ``(I - K C) P (I - K C)^T + K R K^T`` with the gain ``K`` actually
    applied this step (the linear ``L_c dt`` plus the cubic term's secant gain), for the
    modelled accelerometer, speed and slope-rate-prediction noises. ``gain_mode="kalman"``
    instead uses the Kalman gain with the same prediction model (no cubic term).
    """

    config: CubicPredictionSlopeConfig

    def __init__(self, config: Optional[CubicPredictionSlopeConfig] = None):
        config = CubicPredictionSlopeConfig() if config is None else config
        self.config = config
        config.validate()
        self.design = cubic_observer_design(config.luenberger_gain, config.gravity,
                                            config.cubic_kappa, config.cubic_gamma)
        super().__init__(config)

    def reset(self) -> None:
        super().reset()
        c = self.config
        predictor = getattr(self, "prediction", None)
        if predictor is None:
            self.prediction = SlopePredictionModel(c.fit_window_s, c.fit_sample_period_s, c.fit_min_points,
                                                   c.fit_min_span_m, c.max_slope_curvature, c.rate_mode)
        else:
            predictor.reset()
        self.slope_rate = 0.0     # last u2 [rad/s]

    def _cubic_direction(self) -> np.ndarray:
        # -N_c kappa_c: the update direction of Eq. 24's cubic term per innovation^3
        return -self.design.N * self.design.kappa

    def _input_vector(self, ax_measured: float, yaw_rate: float, vy: float) -> np.ndarray:
        """``u_r = [a_x,acc + r v_y, u2]`` (Eqs. 21-22); called once per prediction with the
        posterior of the previous step in ``self._x`` and its stamp in ``self.t``."""
        speed, theta = float(self._x[0]), float(self._x[1])
        assert self.t is not None and self._t0 is not None   # only called after the first sample
        if self.t - self._t0 < self.config.prediction_warmup_s:
            self.slope_rate = 0.0
        else:
            self.prediction.update(self.t, speed, theta)
            self.slope_rate = self.prediction.slope_rate(speed, theta)
        return np.array([ax_measured + yaw_rate * vy, self.slope_rate])

    def step(self, t: float, ax_measured: float, vx: float, vx_dot: Optional[float] = None,
             yaw_rate: float = 0.0, vy: float = 0.0, vx_variance: Optional[float] = None) -> bool:
        """One sample; same signature and semantics as :meth:`ClassicalSlopeObserver.step`.

        ``vx`` both corrects the state (``y_r``) and, through the filtered speed, advances
        the travelled distance of the prediction model (Eq. 15). ``vx_dot`` is ignored.
        """
        del vx_dot
        return self._step(t, ax_measured, vx, yaw_rate, vy, vx_variance)


@dataclasses.dataclass
class PitchGradeConfig:
    """Tuning of :class:`PitchGradeSlope`.

    Attributes:
        lwma_window: LWMA length in samples (1 = pass-through; paper 003 uses 25).
        max_gap_s: stamp gap that clears the LWMA buffer [s].
        converged_std: ``converged`` once the buffer is full and ``sqrt(variance)`` is
            below this [rad].
    """

    lwma_window: int = 1
    max_gap_s: float = 0.5
    converged_std: float = 0.02

    def validate(self) -> None:
        if not (isinstance(self.lwma_window, (int, np.integer)) and self.lwma_window >= 1):
            raise ValueError(f"lwma_window must be an integer >= 1, got {self.lwma_window!r}")
        _check_positive(self, ("max_gap_s", "converged_std"))


class PitchGradeSlope:
    """Road grade from the fusion pitch (paper 003 Sec. 7.2), optional LWMA low-pass.

    With weights ``w_i = i`` (newest ``N``) the LWMA delays a ramp by ``(N - 1)/3``
    samples (8 samples = 40 ms for ``N = 25`` at 200 Hz). The reported variance is the
    weighted mean of the input variances, i.e. the fully-correlated (conservative) case,
    since consecutive fusion pitch estimates are strongly correlated.
    """

    def __init__(self, config: Optional[PitchGradeConfig] = None):
        self.config = PitchGradeConfig() if config is None else config
        self.config.validate()
        n = int(self.config.lwma_window)
        self._weights = np.arange(1, n + 1, dtype=float)
        self.rejected = {"nonfinite_input": 0, "stamp_not_increasing": 0}
        self.reinitialisations = 0
        self.last_event = ""
        self.reset()

    def reset(self) -> None:
        n = int(self.config.lwma_window)
        self._grades: collections.deque = collections.deque(maxlen=n)
        self._vars: collections.deque = collections.deque(maxlen=n)
        self.t: Optional[float] = None
        self._slope = float("nan")
        self._variance = float("inf")

    def step(self, t: float, road_grade: float, variance: float) -> bool:
        """Add a grade sample [rad, +uphill] with its variance [rad^2] at stamp ``t``."""
        t = float(t)
        if not (math.isfinite(t) and math.isfinite(road_grade) and math.isfinite(variance)
                and variance >= 0.0):
            self.rejected["nonfinite_input"] += 1
            self.last_event = "non-finite input"
            return False
        if self.t is not None and t <= self.t:
            self.rejected["stamp_not_increasing"] += 1
            self.last_event = "stamp not increasing"
            return False
        if self.t is not None and t - self.t > self.config.max_gap_s:
            self.last_event = f"re-initialised after a {t - self.t:.3f} s gap"
            self.reset()
            self.reinitialisations += 1
        self.t = t
        self._grades.append(float(road_grade))
        self._vars.append(float(variance))
        w = self._weights[: len(self._grades)]
        self._slope = float(np.dot(w, self._grades) / w.sum())
        self._variance = float(np.dot(w, self._vars) / w.sum())
        return True

    @property
    def slope(self) -> float:
        return self._slope

    @property
    def variance(self) -> float:
        return self._variance

    @property
    def converged(self) -> bool:
        return (len(self._grades) == self._grades.maxlen
                and math.sqrt(self._variance) < self.config.converged_std)


SLOPE_METHODS = {
    "classical": ClassicalSlopeObserver,
    "cubic_prediction": CubicPredictionSlopeObserver,
    "fusion_pitch": PitchGradeSlope,
}
