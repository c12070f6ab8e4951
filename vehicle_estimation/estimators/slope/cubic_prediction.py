"""Paper 004's proposed slope observer: the slope prediction model with the cubic observer (Sec. 5).

:class:`CubicPredictionSlopeObserver` uses the state space of the classical observer
(:class:`~vehicle_estimation.estimators.slope.observers.SlopeObserver`) with ``Phi = I`` and
``u2`` the slope change rate from the slope prediction model (Eqs. 15-20,
:class:`SlopePredictionModel`: a second-order road fitted over the recently travelled distance to
the observer's own past slope estimates), observed by the cubic observer of Eqs. 24-27
(:func:`cubic_observer_design`). It removes the ramp lag of ``theta' = 0`` (``L1 / (-L2 g)`` for
a fixed gain) and propagates the error covariance of its fixed gain so that ``variance`` and
``converged`` mean what they mean for the other slope cores.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import NamedTuple, Optional

import numpy as np

from vehicle_estimation.contract.settings import setting
from vehicle_estimation.contract.vehicle import GRAVITY
from vehicle_estimation.estimators.slope.observers import GAIN_MODES, ClassicalSlopeConfig, SlopeObserver

__all__ = [
    "CubicObserverDesign",
    "CubicPredictionSlopeConfig",
    "CubicPredictionSlopeObserver",
    "PAPER_LUENBERGER_GAIN",
    "SlopePredictionModel",
    "cubic_observer_design",
    "luenberger_gain_for_poles",
]

RATE_MODES = ("distance", "as_printed")


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

    ``fit_window_s``: the rate fitted from the observer's own estimates feeds back into them;
    windows below ~2 s make that loop unstable for the paper's gain, and 3-6 s give the best
    errors in simulation. ``max_slope_curvature``: road vertical curves have radii of hundreds
    of metres and more, i.e. ``|d theta/dx| < ~0.005 rad/m``. ``rate_mode="as_printed"`` takes
    ``2 a2`` as a rate per second, as Eq. 22 prints; dimensionally it is a rate per metre, so
    that prediction is ``v_x`` times too weak.
    """

    gain_mode: str = setting(
        "luenberger", "Observer gain: luenberger (the fixed-gain cubic observer of paper 004 Eqs. 24-27) "
        "or kalman (Kalman gain on the same prediction model, no cubic term)", choices=GAIN_MODES)
    slope_rate_std: float = setting(
        0.002, "Error density of the predicted slope rate u2 [rad/sqrt(s)]; shapes the reported variance "
        "(and the gain with kalman)", low=0.0, low_open=True)
    luenberger_gain: tuple = setting(
        (4.2, -0.92), "Observer gain L_c [1/s, rad/(m/s)/s] (paper 004 Sec. 7.1: [1, -2]; default: poles "
        "at omega 3 rad/s, damping 0.7)")
    cubic_kappa: float = setting(1.5, "Eq. 24 cubic term kappa_c (0 = off)", low=0.0)
    fit_window_s: float = setting(4.0, "Span of the sliding window of past (x, theta) points fitted by "
                                  "Eq. 19 [s]", low=0.0, low_open=True)
    fit_sample_period_s: float = setting(0.05, "Spacing of the stored fit points [s]", low=0.0, low_open=True)
    fit_min_points: int = setting(5, "Fewer fit points than this: u2 = 0", low=3)
    fit_min_span_m: float = setting(2.0, "Horizontal span of the fit window below which u2 = 0 [m]",
                                    low=0.0, low_open=True)
    max_slope_curvature: float = setting(0.01, "Clamp on |2 a2|, the road's vertical curvature [rad/m]",
                                         low=0.0, low_open=True)
    rate_mode: str = setting(
        "distance", "u2 from 2 a2: distance (2 a2 v_x cos(theta), the chain rule) or as_printed (2 a2 "
        "as a rate per second, as Eq. 22 prints)", choices=RATE_MODES)
    prediction_warmup_s: float = setting(
        2.0, "After (re)initialisation u2 = 0 and no fit points for this long [s], so that the "
        "observer's own convergence is not extrapolated", low=0.0)

    @classmethod
    def paper_gain(cls, **overrides) -> "CubicPredictionSlopeConfig":
        """The paper-literal observer gain ``L_c = [1, -2]^T`` (Sec. 7.1)."""
        overrides.setdefault("luenberger_gain", PAPER_LUENBERGER_GAIN)
        return cls(**overrides)

    def validate(self) -> None:
        super().validate()
        if self.fit_sample_period_s * (self.fit_min_points - 1) > self.fit_window_s:
            raise ValueError(f"fit_window_s ({self.fit_window_s!r}) holds fewer than fit_min_points "
                             f"({self.fit_min_points!r}) points of fit_sample_period_s "
                             f"({self.fit_sample_period_s!r})")


class CubicPredictionSlopeObserver(SlopeObserver):
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

    :meth:`step` is the base class's: ``vx`` both corrects the state (``y_r``) and, through the
    filtered speed, advances the travelled distance of the prediction model (Eq. 15).
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
