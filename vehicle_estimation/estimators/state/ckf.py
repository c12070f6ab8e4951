"""Cubature Kalman filter and the paper-004 vehicle-state estimator (Sec. 4, Sec. 7.1).

:class:`CubatureKalmanFilter` is the generic third-degree spherical-radial CKF
(Arasaratnam & Haykin 2009) with ``2n`` equally weighted points
``X_i = x + S xi_i``, ``S S^T = P``, ``xi = sqrt(n) [I, -I]``. It is the "CKF" of the
contrasted strategy of paper 004 Sec. 7; the measurement update is split into
:meth:`CubatureKalmanFilter.measurement_moments` (cubature moments without ``R``) and
:meth:`CubatureKalmanFilter.correct` (gain and correction for a given ``R``) so that a
VB-ACKF subclass can replace :meth:`update` by the variational inverse-Wishart iterations
of Eqs. 11-13 (predict ``nu``, ``V`` in :meth:`predict`, iterate ``moments -> R ->
correct``) without touching the rest.

:class:`VehicleStateCKF` wraps the model of :mod:`vehicle_model` (Eqs. 1-9) with the
Sec. 7.1 tuning and handles stamps, rejection and re-initialisation.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import numpy as np

from vehicle_estimation.estimators.state import vehicle_model as vm
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.contract.vehicle import VehicleParams

__all__ = ["CubatureKalmanFilter", "VehicleStateConfig", "VehicleStateCKF"]


def _as_matrix(value, n: int, name: str) -> np.ndarray:
    m = np.asarray(value, dtype=float)
    if m.ndim == 1:
        m = np.diag(m)
    if m.shape != (n, n):
        raise ValueError(f"{name} must be {n}x{n} (or a length-{n} diagonal), got shape {m.shape}")
    return m


def _sqrt_psd(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor; eigen-decomposition with clipped eigenvalues if not PD."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(0.5 * (P + P.T))
        return v * np.sqrt(np.maximum(w, 1e-12))


class CubatureKalmanFilter:
    """Generic CKF, additive noise: ``x_k = f(x_{k-1}, dt, *args) + v``, ``z = h(x, *args) + w``.

    Args:
        f: process model. With ``vectorized=True`` (default) it is called once with the
            ``(2n, n)`` array of cubature points and must return ``(2n, n)``; otherwise
            it is called per point with ``(n,)``.
        h: measurement model, same calling convention, returning ``(2n, m)`` / ``(m,)``.
        Q: process-noise covariance added per :meth:`predict` (override with ``Q=``).
        R: measurement-noise covariance (``m x m``).
        x0, P0: initial mean and covariance.
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, vectorized: bool = True):
        self._x = np.array(x0, dtype=float).reshape(-1)
        self.n = self._x.size
        self._P = _as_matrix(P0, self.n, "P0").copy()
        self.Q = _as_matrix(Q, self.n, "Q")
        R = np.asarray(R, dtype=float)
        self.R = np.diag(R) if R.ndim == 1 else R
        self.m = self.R.shape[0]
        self.f = f
        self.h = h
        self.vectorized = vectorized
        self._xi = math.sqrt(self.n) * np.concatenate((np.eye(self.n), -np.eye(self.n)), axis=1)
        self._w = 1.0 / (2 * self.n)
        self.last_innovation: Optional[np.ndarray] = None
        self.last_innovation_covariance: Optional[np.ndarray] = None
        self.last_gain: Optional[np.ndarray] = None

    # -- state ---------------------------------------------------------------------------
    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._P.copy()

    def reset(self, x0, P0) -> None:
        self._x = np.array(x0, dtype=float).reshape(self.n)
        self._P = _as_matrix(P0, self.n, "P0").copy()

    # -- cubature ------------------------------------------------------------------------
    def cubature_points(self, x: Optional[np.ndarray] = None, P: Optional[np.ndarray] = None) -> np.ndarray:
        """The ``2n`` points ``x + S xi_i`` as a ``(2n, n)`` array."""
        x = self._x if x is None else x
        P = self._P if P is None else P
        return x + (_sqrt_psd(P) @ self._xi).T

    def _apply(self, fun: Callable, X: np.ndarray, *args) -> np.ndarray:
        if self.vectorized:
            return np.asarray(fun(X, *args), dtype=float)
        return np.array([np.asarray(fun(xi, *args), dtype=float) for xi in X])

    # -- time update ---------------------------------------------------------------------
    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        """Time update: propagate the cubature points through ``f(X, dt, *args)``."""
        X = self.cubature_points()
        Xp = self._apply(self.f, X, dt, *args)
        x = Xp.mean(axis=0)
        d = Xp - x
        P = self._w * (d.T @ d) + (self.Q if Q is None else Q)
        self._x = x
        self._P = 0.5 * (P + P.T)

    # -- measurement update --------------------------------------------------------------
    def measurement_moments(self, *args, x: Optional[np.ndarray] = None,
                            P: Optional[np.ndarray] = None):
        """Cubature moments of ``h`` at ``(x, P)`` (default: current): ``(z_hat, P_zz - R, P_xz)``."""
        x = self._x if x is None else x
        P = self._P if P is None else P
        X = self.cubature_points(x, P)
        Z = self._apply(self.h, X, *args)
        z_hat = Z.mean(axis=0)
        dz = Z - z_hat
        dx = X - x
        return z_hat, self._w * (dz.T @ dz), self._w * (dx.T @ dz)

    def correct(self, innovation: np.ndarray, Pzz: np.ndarray, Pxz: np.ndarray) -> None:
        """Kalman correction with innovation ``z - z_hat`` and ``P_zz`` (including ``R``)."""
        K = np.linalg.solve(Pzz, Pxz.T).T
        self._x = self._x + K @ innovation
        P = self._P - K @ Pzz @ K.T
        self._P = 0.5 * (P + P.T)
        self.last_gain = K
        self.last_innovation = innovation
        self.last_innovation_covariance = Pzz

    def update(self, z, *args, R: Optional[np.ndarray] = None) -> np.ndarray:
        """Measurement update with ``z``; returns the innovation ``z - z_hat``."""
        z = np.asarray(z, dtype=float).reshape(self.m)
        z_hat, Pzz0, Pxz = self.measurement_moments(*args)
        innovation = z - z_hat
        self.correct(innovation, Pzz0 + (self.R if R is None else R), Pxz)
        return innovation

    def normalised_innovation_squared(self) -> float:
        """NIS of the last update, ``nu^T P_zz^-1 nu`` (chi-square with m dof if consistent)."""
        nu, S = self.last_innovation, self.last_innovation_covariance
        if nu is None or S is None:   # set together by correct()
            return float("nan")
        return float(nu @ np.linalg.solve(S, nu))


# ----------------------------------------------------------------------------------------
def valid_moments(x: np.ndarray, P: np.ndarray) -> bool:
    """Finite mean and positive-definite covariance. Absurd inputs (the model driven at
    thousands of m/s) can leave a finite P that rounding has made indefinite (negative
    variances) or make a factorisation fail: a numerical failure like a NaN."""
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return True


@dataclasses.dataclass
class VehicleStateConfig:
    """Tuning of :class:`VehicleStateCKF`; defaults are paper 004 Sec. 7.1.

    Attributes:
        P0: initial state covariance (``10 I5``).
        Q: process-noise covariance per nominal step ``nominal_dt`` (``0.1 I5``).
        R: measurement noise for ``[ax_imu, ay_imu, r]`` (``diag[4e-2, 4e-2, 6e-5]``).
        initial_vx: initial longitudinal speed [m/s] (``80/3.6``).
        init_vx_from_wheel_speeds: if True, initialise (and re-initialise) ``vx`` from the
            mean of ``omega R`` of the rear wheels when the wheel speeds are valid
            (recommended for a node that may start at stand-still; False = paper).
        nominal_dt: the paper's sampling time ``tau`` [s] that ``Q`` refers to.
        scale_q_with_dt: use ``Q dt / nominal_dt`` for a step of length ``dt``.
        max_gap_s: stamp gap above which the filter re-initialises [s].
        max_substep: Euler sub-step of the process model [s].
        min_speed: speed floor ``v_min`` of the slip definitions [m/s].
    """

    P0: np.ndarray = dataclasses.field(default_factory=lambda: 10.0 * np.eye(5))
    Q: np.ndarray = dataclasses.field(default_factory=lambda: 0.1 * np.eye(5))
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.diag([4e-2, 4e-2, 6e-5]))
    initial_vx: float = 80.0 / 3.6
    init_vx_from_wheel_speeds: bool = False
    nominal_dt: float = 0.01
    scale_q_with_dt: bool = True
    max_gap_s: float = 0.5
    max_substep: float = vm.DEFAULT_MAX_SUBSTEP
    min_speed: float = vm.DEFAULT_MIN_SPEED

    def __post_init__(self) -> None:
        for name, n in (("P0", 5), ("Q", 5), ("R", 3)):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim == 1 and value.size == n:
                value = np.diag(value)
            setattr(self, name, value)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        for name, n in (("P0", 5), ("Q", 5), ("R", 3)):
            m = np.asarray(getattr(self, name), dtype=float)
            if m.shape != (n, n):
                raise ValueError(f"{name} must be {n}x{n}, got shape {m.shape}")
            if not np.all(np.isfinite(m)) or not np.allclose(m, m.T):
                raise ValueError(f"{name} must be finite and symmetric")
            try:
                np.linalg.cholesky(m)
            except np.linalg.LinAlgError:
                raise ValueError(f"{name} must be positive definite") from None
        for name in ("nominal_dt", "max_gap_s", "max_substep", "min_speed"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")
        if not (isinstance(self.initial_vx, (int, float)) and math.isfinite(self.initial_vx)):
            raise ValueError(f"initial_vx must be finite, got {self.initial_vx!r}")


class VehicleStateCKF:
    """Vehicle state ``[vx, vy, r, ax, ay]`` by CKF on the paper-004 model (Sec. 4).

    Feed one :meth:`step` per IMU sample: ``z = [ax, ay, r]`` is the IMU specific force
    (x, y) and yaw rate in the body frame; ``inputs`` carries steer angle, wheel speeds,
    the current slope estimate and mass estimate (paper Fig. 1 information interaction).
    """

    def __init__(self, params: VehicleParams, config: Optional[VehicleStateConfig] = None):
        params.validate()
        self.params = params
        self.config = VehicleStateConfig() if config is None else config
        self.config.validate()
        cfg = self.config

        def f(X, dt, inputs):
            return vm.transition(X, inputs, params, dt, min_speed=cfg.min_speed,
                                 max_substep=cfg.max_substep)

        def h(X, inputs):
            return vm.measurement(X, inputs, params)

        self._ckf = self._make_filter(f, h)
        self.t: Optional[float] = None
        self.initialised = False
        self.rejected = {"nonfinite_measurement": 0, "invalid_input": 0, "stamp_not_increasing": 0}
        self.reinitialisations = 0
        self.last_event = ""
        self.updates = 0
        self.speed_updates = 0
        #: Extra process noise on vx [(m/s^2)^2 s], added as ``density * dt`` per step: the
        #: owner sets it while an input is unknown (the node: no slope estimate, so the grade's
        #: g sin(theta) acts on vx as a correlated acceleration error).
        self.extra_vx_noise_density = 0.0

    def _make_filter(self, f: Callable, h: Callable) -> CubatureKalmanFilter:
        """Factory hook: the filter on the model closures ``f``, ``h`` (called once by
        ``__init__`` after ``params``/``config`` are validated). Default: the plain CKF with
        the configured ``Q``, ``R``, ``x0`` and ``P0``."""
        cfg = self.config
        return CubatureKalmanFilter(f, h, cfg.Q, cfg.R, self._x0(None), cfg.P0)

    # -- helpers -------------------------------------------------------------------------
    def _x0(self, vx0: Optional[float]) -> np.ndarray:
        return np.array([self.config.initial_vx if vx0 is None else float(vx0), 0.0, 0.0, 0.0, 0.0])

    def _vx_from_wheels(self, inputs: VehicleInputs) -> Optional[float]:
        ws = inputs.wheel_speeds[2:]
        if np.all(np.isfinite(ws)):
            return float(np.mean(ws) * self.params.wheel_radius)
        return None

    def reset(self, vx0: Optional[float] = None) -> None:
        """Back to ``x0 = [vx0, 0, 0, 0, 0]`` (``vx0`` default ``initial_vx``), ``P0``; forget stamp."""
        self._ckf.reset(self._x0(vx0), self.config.P0)
        self.t = None
        self.initialised = False

    # -- main entry ----------------------------------------------------------------------
    def step(self, t: float, inputs: VehicleInputs, z) -> bool:
        """Predict to stamp ``t`` with ``inputs`` and update with ``z = [ax, ay, r]``.

        Returns True if a measurement update was applied. False if the sample was
        rejected: non-finite ``t``/inputs or stamp not increasing (nothing changes), or
        non-finite ``z`` (the state is still predicted to ``t``). A gap above
        ``max_gap_s`` re-initialises the filter (``reinitialisations``, ``last_event``)
        and the sample is then used as the first one. So does a numerical failure (moments
        not finite, or a covariance no longer positive definite, after absurd inputs); the
        step then returns False.
        """
        t = float(t)
        z = np.asarray(z, dtype=float).reshape(-1)
        if not math.isfinite(t) or not inputs.is_valid() or z.shape != (3,):
            self.rejected["invalid_input"] += 1
            self.last_event = "invalid input"
            return False
        if self.t is not None and t <= self.t:
            self.rejected["stamp_not_increasing"] += 1
            self.last_event = f"stamp not increasing ({t:.6f} <= {self.t:.6f})"
            return False
        if self.t is not None and t - self.t > self.config.max_gap_s:
            gap = t - self.t
            vx0 = float(self._ckf.x[0]) if math.isfinite(self._ckf.x[0]) else None
            if self.config.init_vx_from_wheel_speeds:
                vx0 = self._vx_from_wheels(inputs) or vx0
            self.reset(vx0)
            self.reinitialisations += 1
            self.last_event = f"re-initialised after a {gap:.3f} s gap"
        if not self.initialised:
            vx0 = self._vx_from_wheels(inputs) if self.config.init_vx_from_wheel_speeds else None
            if vx0 is not None:
                self._ckf.reset(self._x0(vx0), self.config.P0)
            self.initialised = True
        else:
            assert self.t is not None   # initialised implies a stamp
            dt = t - self.t
            Q = self.config.Q * (dt / self.config.nominal_dt) if self.config.scale_q_with_dt else None
            if self.extra_vx_noise_density > 0.0:
                Q = np.array(self._ckf.Q if Q is None else Q, dtype=float)
                Q[0, 0] += self.extra_vx_noise_density * dt
            try:
                with np.errstate(all="ignore"):
                    self._ckf.predict(dt, inputs, Q=Q)
            except np.linalg.LinAlgError:
                self._ckf._x[:] = np.nan   # handled as a numerical failure below
        self.t = t
        if not np.all(np.isfinite(z)):
            if self._reinitialised_after_failure():
                return False
            self.rejected["nonfinite_measurement"] += 1
            self.last_event = "non-finite measurement"
            return False
        if np.all(np.isfinite(self._ckf._x)) and np.all(np.isfinite(self._ckf._P)):
            try:
                with np.errstate(all="ignore"):
                    self._ckf.update(z, inputs)
            except np.linalg.LinAlgError:
                self._ckf._x[:] = np.nan   # handled as a numerical failure below
        if self._reinitialised_after_failure():
            return False
        self.updates += 1
        return True

    def _reinitialised_after_failure(self) -> bool:
        """Re-initialise (and count it) if the moments are no longer valid; True if it did."""
        if self._valid_moments():
            return False
        self.reset(None)
        self.reinitialisations += 1
        self.last_event = "re-initialised after numerical failure"
        return True

    def _valid_moments(self) -> bool:
        return valid_moments(self._ckf._x, self._ckf._P)

    def update_speed(self, vx: float, variance: float) -> bool:
        """Update with a direct measurement of the longitudinal speed ``vx`` [m/s].

        Not in paper 004, whose model observes vx through the wheel speeds only: without them
        (a car whose bus reports only the vehicle speed, a log without wheel speeds) vx would
        be dead-reckoned from the accelerometer and drift with its bias. The measurement is
        linear (``H = [1, 0, 0, 0, 0]``), so this is the exact Kalman update on the current
        moments. Returns False (nothing changes) for a non-finite value or variance <= 0, or
        before the filter has started.
        """
        vx, variance = float(vx), float(variance)
        if not (self.initialised and math.isfinite(vx) and math.isfinite(variance) and variance > 0.0):
            return False
        P = self._ckf.P
        self._ckf.correct(np.array([vx - self._ckf.x[0]]), np.array([[P[0, 0] + variance]]),
                          P[:, :1].copy())
        self.speed_updates += 1
        return True

    # -- outputs -------------------------------------------------------------------------
    @property
    def filter(self) -> CubatureKalmanFilter:
        return self._ckf

    @property
    def x(self) -> np.ndarray:
        return self._ckf.x

    @property
    def P(self) -> np.ndarray:
        return self._ckf.P

    @property
    def sideslip(self) -> float:
        """``beta = arctan(vy/vx)`` (Eq. 14) [rad]."""
        return vm.sideslip(self._ckf._x)

    @property
    def sideslip_variance(self) -> float:
        """First-order variance of Eq. 14 from the ``(vx, vy)`` block of ``P`` [rad^2]."""
        vx, vy = self._ckf._x[0], self._ckf._x[1]
        s = vx * vx + vy * vy
        if s < 1e-6:
            return float("inf")
        J = np.array([-vy / s, vx / s])
        return float(J @ self._ckf._P[:2, :2] @ J)
