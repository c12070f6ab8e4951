"""Cubature Kalman filter and the paper-004 vehicle-state estimator (Sec. 4, Sec. 7.1).

:class:`CubatureKalmanFilter` is the generic third-degree spherical-radial CKF
(Arasaratnam & Haykin 2009): the sigma-point filter of
:mod:`vehicle_estimation.estimators.common.sigma_points` on its
:class:`~vehicle_estimation.estimators.common.sigma_points.CubaturePoints` (``2n`` equally
weighted points ``X_i = x + S xi_i``, ``S S^T = P``, ``xi = sqrt(n) [I, -I]``). It is the
"CKF" of the contrasted strategy of paper 004 Sec. 7; the VB-ACKF of :mod:`.vbackf` replaces
its :meth:`~CubatureKalmanFilter.update` by the variational inverse-Wishart iterations of
Eqs. 11-13.

:class:`VehicleStateCKF` wraps the model of :mod:`.vehicle_model` (Eqs. 1-9) with the
Sec. 7.1 tuning and handles stamps, rejection and re-initialisation.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common.sigma_points import (
    CubaturePoints,
    SigmaPointKalmanFilter,
    is_positive_definite,
)
from vehicle_estimation.estimators.state import vehicle_model as vm
from vehicle_estimation.estimators.state.core import VehicleStateCore
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs

__all__ = ["CubatureKalmanFilter", "VehicleStateConfig", "VehicleStateCKF"]


class CubatureKalmanFilter(SigmaPointKalmanFilter):
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
        super().__init__(f, h, Q, R, x0, P0, CubaturePoints(np.size(x0)), vectorized=vectorized)


# ----------------------------------------------------------------------------------------
@dataclasses.dataclass
class VehicleStateConfig:
    """Tuning of :class:`VehicleStateCKF`; defaults are paper 004 Sec. 7.1.

    The matrices are not ROS parameters (the state node declares their diagonals):
    ``P0`` the initial state covariance (``10 I5``), ``Q`` the process-noise covariance per
    nominal step ``nominal_dt`` (``0.1 I5``), ``R`` the measurement noise of
    ``[ax_imu, ay_imu, r]`` (``diag[4e-2, 4e-2, 6e-5]``). A length-n vector is a diagonal.
    """

    P0: np.ndarray = dataclasses.field(default_factory=lambda: 10.0 * np.eye(5))
    Q: np.ndarray = dataclasses.field(default_factory=lambda: 0.1 * np.eye(5))
    R: np.ndarray = dataclasses.field(default_factory=lambda: np.diag([4e-2, 4e-2, 6e-5]))
    initial_vx: float = setting(80.0 / 3.6, "Initial longitudinal speed [m/s] (paper 004: 80/3.6)")
    init_vx_from_wheel_speeds: bool = setting(
        False, "Initialise (and re-initialise) vx from the mean of omega R of the rear wheels when "
        "their speeds are valid (for a start at stand-still; false = paper)")
    nominal_dt: float = setting(0.01, "The paper's sampling time tau that Q refers to [s]",
                                low=0.0, low_open=True)
    scale_q_with_dt: bool = setting(True, "Use Q dt / nominal_dt for a step of length dt")
    max_gap_s: float = setting(0.5, "Stamp gap above which the filter re-initialises [s]",
                               low=0.0, low_open=True)
    max_substep: float = setting(vm.DEFAULT_MAX_SUBSTEP, "Euler sub-step of the process model [s]",
                                 low=0.0, low_open=True)
    min_speed: float = setting(vm.DEFAULT_MIN_SPEED, "Speed floor v_min of the slip definitions [m/s]",
                               low=0.0, low_open=True)

    def __post_init__(self) -> None:
        for name, n in (("P0", 5), ("Q", 5), ("R", 3)):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim == 1 and value.size == n:
                value = np.diag(value)
            setattr(self, name, value)

    @classmethod
    def from_diagonals(cls, p0_diag, q_diag, r_diag, **fields) -> "VehicleStateConfig":
        """The config with diagonal ``P0``, ``Q``, ``R`` (how the state node declares them);
        ``ValueError`` naming the diagonal that is not 5, 5 or 3 positive numbers."""
        for name, values, n in (("p0_diag", p0_diag, 5), ("q_diag", q_diag, 5), ("r_diag", r_diag, 3)):
            if len(values) != n or not all(math.isfinite(v) and v > 0.0 for v in values):
                raise ValueError(f"{name} must be {n} positive numbers, got {list(values)}")
        return cls(P0=np.diag(p0_diag), Q=np.diag(q_diag), R=np.diag(r_diag), **fields)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        for name, n in (("P0", 5), ("Q", 5), ("R", 3)):
            m = np.asarray(getattr(self, name), dtype=float)
            if m.shape != (n, n):
                raise ValueError(f"{name} must be {n}x{n}, got shape {m.shape}")
            if not np.all(np.isfinite(m)) or not np.allclose(m, m.T):
                raise ValueError(f"{name} must be finite and symmetric")
            if not is_positive_definite(m):
                raise ValueError(f"{name} must be positive definite")
        check_settings(self)


class VehicleStateCKF(VehicleStateCore):
    """Vehicle state ``[vx, vy, r, ax, ay]`` by CKF on the paper-004 model (Sec. 4).

    Feed one :meth:`step` per IMU sample: ``z = [ax, ay, r]`` is the IMU specific force
    (x, y) and yaw rate in the body frame; ``inputs`` carries steer angle, wheel speeds,
    the current slope estimate and mass estimate (paper Fig. 1 information interaction).
    """

    _filter: CubatureKalmanFilter

    def __init__(self, params: VehicleParams, config: Optional[VehicleStateConfig] = None):
        params.validate()
        cfg = VehicleStateConfig() if config is None else config
        cfg.validate()
        super().__init__(params, cfg.initial_vx, cfg.P0, (2, 3), cfg.max_gap_s)
        self.config = cfg

        def f(X, dt, inputs):
            return vm.transition(X, inputs, params, dt, min_speed=cfg.min_speed,
                                 max_substep=cfg.max_substep)

        def h(X, inputs):
            return vm.measurement(X, inputs, params)

        self._filter = self._make_filter(f, h)

    def _make_filter(self, f: Callable, h: Callable) -> CubatureKalmanFilter:
        """Factory hook: the filter on the model closures ``f``, ``h`` (called once by
        ``__init__`` after ``params``/``config`` are validated). Default: the plain CKF with
        the configured ``Q``, ``R``, ``x0`` and ``P0``."""
        cfg = self.config
        return CubatureKalmanFilter(f, h, cfg.Q, cfg.R, self._x0(None), cfg.P0)

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
        sample = self._begin_step(t, inputs, z)
        if sample is None:
            return False
        t, z, dt = sample
        cfg = self.config
        if not self.initialised:
            vx0 = self._vx_from_wheels(inputs) if cfg.init_vx_from_wheel_speeds else None
            if vx0 is not None:
                self._filter.reset(self._x0(vx0), cfg.P0)
            self.initialised = True
        else:
            Q = cfg.Q * (dt / cfg.nominal_dt) if cfg.scale_q_with_dt else self._filter.Q
            Q = self._with_extra_vx_noise(Q, dt)
            try:
                with np.errstate(all="ignore"):
                    self._filter.predict(dt, inputs, Q=Q)
            except np.linalg.LinAlgError:
                self._filter._x[:] = np.nan   # handled as a numerical failure below
        self.t = t
        if not np.all(np.isfinite(z)):
            if self._reinitialised_after_failure(inputs):
                return False
            self.rejected["nonfinite_measurement"] += 1
            self.last_event = "non-finite measurement"
            return False
        if np.all(np.isfinite(self._filter._x)) and np.all(np.isfinite(self._filter._P)):
            try:
                with np.errstate(all="ignore"):
                    self._filter.update(z, inputs)
            except np.linalg.LinAlgError:
                self._filter._x[:] = np.nan   # handled as a numerical failure below
        if self._reinitialised_after_failure(inputs):
            return False
        self.updates += 1
        return True

    def _vx_after_gap(self, inputs: VehicleInputs) -> Optional[float]:
        vx0 = self._vx_now()
        if self.config.init_vx_from_wheel_speeds:
            vx0 = self._vx_from_wheels(inputs) or vx0
        return vx0

    def _correct_speed(self, vx: float, variance: float) -> None:
        P = self._filter.P
        self._filter.correct(np.array([vx - self._filter.x[0]]), np.array([[P[0, 0] + variance]]),
                             P[:, :1].copy())
