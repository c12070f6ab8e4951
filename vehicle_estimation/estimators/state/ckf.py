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
from vehicle_estimation.estimators.common import compiled, small_linalg
from vehicle_estimation.estimators.state import model_kernels
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
        h_affine: ``(H, c)`` of an affine ``h``, for closed-form moments (see
            :class:`~vehicle_estimation.estimators.common.sigma_points.SigmaPointKalmanFilter`).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, vectorized: bool = True,
                 h_affine: Optional[Callable] = None):
        super().__init__(f, h, Q, R, x0, P0, CubaturePoints(np.size(x0)), vectorized=vectorized,
                         h_affine=h_affine)


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
    wheel_slip_forces: bool = setting(
        True, "Longitudinal tyre forces from the measured wheel slip (Eqs. 8-9, paper). False: the "
        "undriven wheels measure only the speed (their free-rolling v_t, Eq. 7) and the tyre model "
        "runs without longitudinal slip, so a 1 % rolling-radius error is 1 % of speed, not "
        "~800 N of phantom force per wheel")
    wheel_radius_std: float = setting(
        0.01, "Relative uncertainty of the effective rolling radius (wear, pressure, load): the "
        "std of the vx the wheel speeds measure when wheel_slip_forces is false [-]", low=0.0, high=0.2)
    front_axle_force_std: float = setting(
        0.0, "Process noise on the front axle's lateral force, as a density [N/sqrt(s)]: the "
        "steering angle behind it (ratio, compliance steer, toe) is the least certain input of "
        "the tyre model. It moves vy and r together, so the measured yaw rate corrects vy "
        "(0 = paper: only the diagonal Q)", low=0.0, high=1.0e6)
    rear_axle_force_std: float = setting(
        0.0, "Process noise on the rear axle's lateral force, as a density [N/sqrt(s)] (see "
        "front_axle_force_std)", low=0.0, high=1.0e6)

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
            if not np.isfinite(m).all() or not np.allclose(m, m.T):
                raise ValueError(f"{name} must be finite and symmetric")
            if not is_positive_definite(m):
                raise ValueError(f"{name} must be positive definite")
        check_settings(self)


_VX_ROW = np.array([1.0, 0.0, 0.0, 0.0, 0.0])   # H of a measured vx
#: vx std of the wheel-speed measurement at stand-still (encoder resolution) [m/s].
WHEEL_SPEED_FLOOR_STD = 0.05


def axle_force_noise(params: VehicleParams, config: VehicleStateConfig) -> np.ndarray:
    """The process noise per ``nominal_dt`` that lateral-force errors of the front and rear axle
    put on ``[vx, vy, r, ax, ay]``: a force ``F_f`` moves ``vy' `` by ``F_f/m`` and ``r'`` by
    ``l_f F_f / I_z`` (a rear one by ``F_r/m`` and ``-l_r F_r / I_z``), so the two are
    correlated and the yaw rate, measured to 0.003 rad/s, tells the filter about vy. A diagonal
    Q cannot: its vy and r noise are independent."""
    std_f, std_r = config.front_axle_force_std, config.rear_axle_force_std
    G = np.zeros((5, 2))
    G[1] = 1.0 / params.mass
    G[2] = params.lf / params.yaw_inertia, -params.lr / params.yaw_inertia
    return config.nominal_dt * G @ np.diag([std_f ** 2, std_r ** 2]) @ G.T


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
                                 max_substep=cfg.max_substep, slip_forces=cfg.wheel_slip_forces)

        def h(X, inputs):
            return vm.measurement(X, inputs, params)

        self.process_noise = cfg.Q + axle_force_noise(params, cfg)
        # The IMU measurement is affine in the state: its moments in closed form, not by points.
        self._h_affine = lambda inputs: vm.measurement_affine(inputs, params)
        self._filter = self._make_filter(f, h)
        self.use_compiled(compiled.enabled())

    def use_compiled(self, on: bool) -> None:
        """Run the time update (and the VB iterations) by the compiled kernels, or by numpy.
        Both give the same estimates to 1e-12 (tests); the bench times them side by side."""
        cfg = self.config
        model = None
        if on:
            model_kernels.warm_up()
            model = model_kernels.CompiledModel(self.params, cfg.min_speed, cfg.max_substep, cfg.wheel_slip_forces)
        self._filter.compiled_predict = None if model is None else model.predict
        self._filter.compiled_update = None if model is None else model.update
        self._filter.compiled_scalar_correct = small_linalg.scalar_correct if on else None
        self.compiled_checks = on
        self._compiled_model = model

    def _make_filter(self, f: Callable, h: Callable) -> CubatureKalmanFilter:
        """Factory hook: the filter on the model closures ``f``, ``h`` (called once by
        ``__init__`` after ``params``/``config`` are validated). Default: the plain CKF with
        the configured ``Q``, ``R``, ``x0`` and ``P0``."""
        cfg = self.config
        return CubatureKalmanFilter(f, h, self.process_noise, cfg.R, self._x0(None), cfg.P0, h_affine=self._h_affine)

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
        inputs = self._with_drive_force(inputs)
        z_finite = math.isfinite(z[0]) and math.isfinite(z[1]) and math.isfinite(z[2])
        with np.errstate(all="ignore"):   # absurd inputs end as a numerical failure, handled below
            if not self.initialised:
                vx0 = self._vx_from_wheels(inputs) if cfg.init_vx_from_wheel_speeds else None
                if vx0 is not None:
                    self._filter.reset(*self._initial_moments(vx0))
                self.initialised = True
            else:
                Q = self.process_noise * (dt / cfg.nominal_dt) if cfg.scale_q_with_dt else self._filter.Q
                Q = self._with_extra_vx_noise(Q, dt)
                if z_finite and self._fused_step(dt, inputs, Q, z):
                    self.t = t
                    return self._after_update(inputs)
                try:
                    self._filter.predict(dt, inputs, Q=Q)
                except np.linalg.LinAlgError:
                    self._filter._x[:] = np.nan   # handled as a numerical failure below
            self.t = t
            if not z_finite:
                if self._reinitialised_after_failure(inputs):
                    return False
                self.rejected["nonfinite_measurement"] += 1
                self.last_event = "non-finite measurement"
                return False
            x, P = self._filter._x, self._filter._P
            if small_linalg.all_finite(x, P) if self.compiled_checks else (np.isfinite(x).all() and np.isfinite(P).all()):
                try:
                    self._filter.update(z, inputs)
                except np.linalg.LinAlgError:
                    self._filter._x[:] = np.nan   # handled as a numerical failure below
        return self._after_update(inputs)

    def _with_drive_force(self, inputs: VehicleInputs) -> VehicleInputs:
        """``inputs`` with the drive force that carries the filter's acceleration estimate
        and the drag, ``m (ax + g sin theta) + F_drag`` where positive, for the model's
        fallback (no slip forces, no torques; module docstring of ``vehicle_model``). It is
        taken from the estimate, as an input like a torque, not from each cubature point: the
        points' spread of a vibrating ax, clipped at zero, would add a bias."""
        if vm.longitudinal_forces_known(inputs, self.config.wheel_slip_forces) or not self.initialised:
            return inputs
        p = self.params
        vx, ax = float(self._filter._x[0]), float(self._filter._x[3])
        drag = float(vm.aerodynamic_drag(vx, p))
        force = inputs.mass_or(p) * (ax + p.gravity * math.sin(inputs.slope)) + drag
        if not (math.isfinite(force) and force > 0.0):
            return inputs
        return dataclasses.replace(inputs, drive_force=force)

    def _fused_step(self, dt: float, inputs: VehicleInputs, Q: np.ndarray, z: np.ndarray) -> bool:
        """Predict and update (a finite ``z``) by one compiled call where the filter has one (the
        VB-ACKF); False: the caller runs the two steps."""
        fused = getattr(self._filter, "fused_step", None)
        return fused is not None and bool(fused(dt, inputs, Q, z))

    def _after_update(self, inputs: VehicleInputs) -> bool:
        """After the update: the numerical-failure check, the counter, the wheel-speed update."""
        if self._reinitialised_after_failure(inputs):
            return False
        self.updates += 1
        if not self.config.wheel_slip_forces:
            self._update_speed_from_wheels(inputs)
        return True

    def _update_speed_from_wheels(self, inputs: VehicleInputs) -> None:
        """The mean speed of the undriven wheels (no drive slip) as a measurement of the mean
        of their forward speeds v_t (Eq. 7), free rolling: ``vx`` at the rear,
        ``vx cos(delta) + (vy + l_F r) sin(delta)`` at the front (the track terms cancel
        between left and right). Linear in the state for a given steering angle, so the exact
        Kalman update; the rolling radius's uncertainty is its variance."""
        wheels = self.params.undriven_wheels
        speed = 0.0
        for i in wheels:
            speed += float(inputs.wheel_speeds[i])
        if not math.isfinite(speed):
            return
        speed *= self.params.wheel_radius / len(wheels)
        front = sum(1 for i in wheels if i < 2) / len(wheels)   # share of steered wheels
        cos_d, sin_d = math.cos(inputs.steer_angle), math.sin(inputs.steer_angle)
        H = np.array([1.0 - front + front * cos_d, front * sin_d, front * self.params.lf * sin_d, 0.0, 0.0])
        self._correct_linear(H, speed, (self.config.wheel_radius_std * speed) ** 2 + WHEEL_SPEED_FLOOR_STD ** 2)
        self.speed_updates += 1

    def _vx_after_gap(self, inputs: VehicleInputs) -> Optional[float]:
        vx0 = self._vx_now()
        if self.config.init_vx_from_wheel_speeds:
            vx0 = self._vx_from_wheels(inputs) or vx0
        return vx0

    def _correct_speed(self, vx: float, variance: float) -> None:
        self._correct_linear(_VX_ROW, vx, variance)

    def _correct_linear(self, H: np.ndarray, value: float, variance: float) -> None:
        """The exact Kalman update with a scalar measurement ``value = H x + noise``."""
        self._filter.correct_scalar(H, value, variance)
