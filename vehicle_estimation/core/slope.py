"""Road-slope observers (paper 004 Sec. 5 and Sec. 7; paper 003 Sec. 7.2).

Slope ``theta`` [rad] is positive uphill. Two methods, selectable by name through
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
    does not give values). The same base class is meant to host the slope-prediction +
    cubic observer (Eqs. 15-27: ``Phi = I``, ``u2 = 2 a2`` from a quadratic road fit)
    by overriding :meth:`_SlopeObserverBase._input_vector`.

``"fusion_pitch"`` -- :class:`PitchGradeSlope`, paper 003 Sec. 7.2: the road grade is the
    (negated) pitch of the IMU/GNSS fusion; here it arrives already as ``road_grade``
    (+uphill) with its variance, and is optionally smoothed by a linearly weighted moving
    average (LWMA, 25 samples in paper 003 Sec. 7.1).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Optional

import numpy as np

from vehicle_estimation.vehicle import GRAVITY

__all__ = [
    "ClassicalSlopeConfig",
    "ClassicalSlopeObserver",
    "PitchGradeConfig",
    "PitchGradeSlope",
    "SLOPE_METHODS",
    "grade_from_pitch",
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
        self._x = self._x + K * innov
        if self._cubic_dir is not None:
            # Eq. 24: - (e^T C^T kappa C e) N_c C e with C e ~ innovation
            self._x = self._x + dt * self._cubic_dir * self.config.cubic_kappa * innov ** 3
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


SLOPE_METHODS = {"classical": ClassicalSlopeObserver, "fusion_pitch": PitchGradeSlope}
