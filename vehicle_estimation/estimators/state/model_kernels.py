"""Compiled forms of the CKF/VB-ACKF step on the paper-004 model (see ``common.compiled``).

:func:`cubature_predict` is :meth:`SigmaPointKalmanFilter.predict` with the cubature points
through :func:`vehicle_model.transition` (Eqs. 1-9: the same sub-steps, load transfer, Dugoff
tyres and fallbacks); :func:`affine_update` is :meth:`SigmaPointKalmanFilter.update` for the
affine IMU measurement; :func:`vb_update` is :meth:`VariationalBayesCKF.update` with its fixed
``N`` variational iterations (Eqs. 11-13). They are written per point and per wheel over
scalars; the numpy code they replace is their test oracle (``test_model_kernels``).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common import small_linalg
from vehicle_estimation.estimators.common.compiled import kernel
from vehicle_estimation.estimators.common.small_linalg import (affine_moments, cholesky_lower, cholesky_solve_rows,
                                                               kalman_correct, times_transpose)
from vehicle_estimation.estimators.state import vehicle_model as vm

__all__ = ["affine_update", "cubature_predict", "vb_step", "vb_update", "STEP_NO_FACTOR",
           "STEP_PREDICTION_NOT_FINITE", "CompiledModel", "VB_OK", "VB_REJECTED", "VB_FAILED", "warm_up"]

# Rows of the per-wheel constants (the fields of vehicle_model._WheelGeometry, in order).
_X_FROM_R, _Y_FROM_VY, _Y_FROM_R, _STEERED, _ALPHA_SIGN, _C_ALPHA, _LOAD_STATIC, _FZ_NOMINAL, \
    _LOAD_AX, _LOAD_AY = range(10)
# Entries of the scalar constants.
_GRAVITY, _RADIUS, _C_SIGMA, _LOAD_EXPONENT, _FRICTION, _DRAG, _YAW_INERTIA, _LF, _LR, _HF, _HR = range(11)


@kernel
def _accelerations(vx, vy, r, ax, ay, delta, cd, sd, sin_t, cos_t, mass, omega, wheel_torque, mx, my,
                   from_slip, torque_known, G, S, min_speed):
    """Eqs. 2-9 at one state: the model ``(ax, ay, r')`` (``vehicle_model._body_accelerations``)."""
    g = S[_GRAVITY]
    ax_spec = ax + g * sin_t
    n_exp = S[_LOAD_EXPONENT]
    sum_x = 0.0
    sum_y = 0.0
    sum_z = 0.0
    for i in range(4):
        # Eqs. 6-7: slip angle and forward speed of the wheel.
        vxw = vx + G[_X_FROM_R, i] * r
        vyw = G[_Y_FROM_VY, i] * vy + G[_Y_FROM_R, i] * r
        den = vxw if (vxw > min_speed or vxw != vxw) else min_speed
        alpha = G[_STEERED, i] * delta + G[_ALPHA_SIGN, i] * math.atan(vyw / den)
        front = G[_STEERED, i]
        vt = vxw * (front * (cd - 1.0) + 1.0) + vyw * (front * sd)
        # Eq. 5, with the specific force.
        fz = mass * (G[_LOAD_STATIC, i] * (g * cos_t) + G[_LOAD_AX, i] * ax_spec + G[_LOAD_AY, i] * ay)
        if not fz > 0.0:
            fz = 0.0 if fz == fz else fz
        # Eq. 9, Dugoff.
        c_sigma = S[_C_SIGMA]
        c_alpha = G[_C_ALPHA, i]
        if n_exp != 0.0:
            load = (fz / G[_FZ_NOMINAL, i]) ** n_exp
            c_sigma = c_sigma * load
            c_alpha = c_alpha * load
        mu_fz = S[_FRICTION] * fz
        if from_slip:
            avt = abs(vt)
            slip = (omega[i] * S[_RADIUS] - vt) / (avt if (avt > min_speed or avt != avt) else min_speed)
            mu_lateral = mu_fz
        else:   # quasi-static fallback (torques or the drive force), clipped to the friction limit
            slip = 0.0
            fx = wheel_torque[i] / S[_RADIUS]
            fx = min(max(fx, -mu_fz), mu_fz)
            mu_lateral = math.sqrt(max(mu_fz * mu_fz - fx * fx, 0.0))   # the friction ellipse
        one_p = 1.0 + slip
        if not one_p > 1e-6:
            one_p = 1e-6 if one_p == one_p else one_p
        kx = c_sigma * slip
        ky = c_alpha * math.tan(alpha)
        d = math.sqrt(kx * kx + ky * ky)
        if not d > 1e-9:
            d = 1e-9 if d == d else d
        lam = mu_lateral * one_p / (2.0 * d)
        scale = (2.0 - lam) * mu_lateral / (2.0 * d) if lam < 1.0 else 1.0 / one_p
        fy = ky * scale
        if from_slip:
            fx = kx * scale
        sum_x += fx * mx[i, 0] + fy * my[i, 0]
        sum_y += fx * mx[i, 1] + fy * my[i, 1]
        sum_z += fx * mx[i, 2] + fy * my[i, 2]
    drag = S[_DRAG] * vx * abs(vx)
    return (sum_x - drag) / mass - g * sin_t, sum_y / mass, sum_z / S[_YAW_INERTIA]


@kernel
def _transition_point(X, j, dt, n_sub, delta, sin_t, cos_t, mass, omega, wheel_torque, mx, my,
                      from_slip, torque_known, G, S, min_speed):
    """``vehicle_model.transition`` of point ``X[j]``, in place."""
    vx, vy, r, ax, ay = X[j, 0], X[j, 1], X[j, 2], X[j, 3], X[j, 4]
    known = from_slip or torque_known
    h = dt / n_sub
    cd, sd = math.cos(delta), math.sin(delta)
    for _ in range(n_sub):
        ax_m, ay_m, rdot = _accelerations(vx, vy, r, ax, ay, delta, cd, sd, sin_t, cos_t, mass, omega,
                                          wheel_torque, mx, my, from_slip, torque_known, G, S, min_speed)
        ax_used = ax_m if known else ax
        vx_new = vx + h * (ax_used + r * vy)
        vy = vy + h * (ay_m - r * vx)
        vx = vx_new
        r = r + h * rdot
        ax = ax_used
        ay = ay_m
    ax_m, ay_m, rdot = _accelerations(vx, vy, r, ax, ay, delta, cd, sd, sin_t, cos_t, mass, omega,
                                      wheel_torque, mx, my, from_slip, torque_known, G, S, min_speed)
    if known:
        ax = ax_m
    X[j, 0], X[j, 1], X[j, 2], X[j, 3], X[j, 4] = vx, vy, r, ax, ay_m


@kernel
def _force_to_body(delta, S, mx, my):
    """``vehicle_model._force_to_body`` in place: Eqs. 2-4 as ``Fx @ mx + Fy @ my``."""
    cd, sd = math.cos(delta), math.sin(delta)
    lf, lr, hf, hr = S[_LF], S[_LR], S[_HF], S[_HR]
    mx[0, 0], mx[0, 1], mx[0, 2] = cd, sd, lf * sd - hf * cd
    mx[1, 0], mx[1, 1], mx[1, 2] = cd, sd, lf * sd + hf * cd
    mx[2, 0], mx[2, 1], mx[2, 2] = 1.0, 0.0, -hr
    mx[3, 0], mx[3, 1], mx[3, 2] = 1.0, 0.0, hr
    my[0, 0], my[0, 1], my[0, 2] = -sd, cd, lf * cd + hf * sd
    my[1, 0], my[1, 1], my[1, 2] = -sd, cd, lf * cd - hf * sd
    my[2, 0], my[2, 1], my[2, 2] = 0.0, 1.0, -lr
    my[3, 0], my[3, 1], my[3, 2] = 0.0, 1.0, -lr


@kernel
def cubature_predict(x, P, Q, dt, n_sub, delta, sin_t, cos_t, mass, omega, wheel_torque,
                     slip_forces, torque_known, G, S, min_speed, x_out, P_out):
    """The CKF time update through the vehicle model: ``2n`` points ``x +- sqrt(n) L e_i``,
    each through the transition, then their mean and ``(1/2n) sum d d^T + Q``, symmetrised.
    Returns False (outputs untouched) where ``P`` has no Cholesky factor; the caller then
    takes the numpy path, whose eigen-decomposition handles it."""
    n = x.shape[0]
    L = np.empty((n, n))
    if not cholesky_lower(P, L):
        return False
    from_slip = slip_forces
    for i in range(4):
        if not math.isfinite(omega[i]):
            from_slip = False
    mx = np.empty((4, 3))
    my = np.empty((4, 3))
    _force_to_body(delta, S, mx, my)
    root = math.sqrt(n)
    X = np.empty((2 * n, n))
    for i in range(n):
        for k in range(n):
            X[i, k] = x[k] + root * L[k, i]
            X[n + i, k] = x[k] - root * L[k, i]
    for j in range(2 * n):
        _transition_point(X, j, dt, n_sub, delta, sin_t, cos_t, mass, omega, wheel_torque, mx, my,
                          from_slip, torque_known, G, S, min_speed)
    w = 1.0 / (2 * n)
    for k in range(n):
        s = 0.0
        for j in range(2 * n):
            s += X[j, k]
        x_out[k] = s * w
    for j in range(2 * n):
        for k in range(n):
            X[j, k] -= x_out[k]
    for a in range(n):
        for b in range(a, n):
            s = 0.0
            for j in range(2 * n):
                s += X[j, a] * X[j, b]
            P_out[a, b] = w * s + 0.5 * (Q[a, b] + Q[b, a])
            P_out[b, a] = P_out[a, b]
    return True


VB_OK, VB_REJECTED, VB_FAILED = 0, 1, 2


@kernel
def vb_update(z, x_pred, P_pred, dof_pred, scale_pred, H, c, R_known, iterations, r_mean, diagonal,
              innovation, Czz, Pxz, x_out, P_out, scale_out, K_out, Pzz_out):
    """``VariationalBayesCKF.update`` for an affine ``h = H x + c`` and a fixed ``N``: the
    closed-form moments of the prediction, then ``N`` times the residual moment
    ``B = e e^T + H P H^T``, ``V = V_pred + B``, ``R = V / (nu - d - 1)`` (``r_mean``) or
    ``V / nu`` (Eq. 11; ``nu`` per channel, ``dof_pred`` of shape ``(m,)``), only its diagonal
    where ``diagonal``, ``P_zz = C_zz + R + R_known``
    (``R_known``: a noise the caller knows, not learnt), the gain and the correction (Eqs. 12-13).

    Returns ``VB_OK``; ``VB_REJECTED`` where the moments are not finite (nothing written but
    the moments); ``VB_FAILED`` where ``V_pred`` or a ``P_zz`` is not positive definite or a
    result is not finite (the caller falls back to the plain correction)."""
    n = x_pred.shape[0]
    m = z.shape[0]
    if not affine_moments(z, x_pred, P_pred, H, c, innovation, Pxz, Czz):
        return VB_REJECTED
    L = np.empty((m, m))
    if not cholesky_lower(scale_pred, L):
        return VB_FAILED
    divisor = np.empty(m)
    for i in range(m):
        if not math.isfinite(dof_pred[i]):
            return VB_FAILED
        dof = dof_pred[i] + 1.0
        divisor[i] = dof - m - 1.0 if r_mean else dof
        for k in range(m):
            if not math.isfinite(scale_pred[i, k]):
                return VB_FAILED
    x = x_pred.copy()
    P = P_pred.copy()
    e = np.empty(m)
    HP = np.empty((m, n))
    HPHt = np.empty((m, m))
    for _ in range(iterations):
        for a in range(m):
            s = c[a]
            for k in range(n):
                s += H[a, k] * x[k]
            e[a] = z[a] - s
        times_transpose(H, P, HP)        # H P (P is symmetric)
        times_transpose(HP, H, HPHt)
        for a in range(m):
            for b in range(m):
                scale_out[a, b] = e[a] * e[b] + HPHt[a, b]
        for a in range(m):
            for b in range(a, m):
                v = scale_pred[a, b] + 0.5 * (scale_out[a, b] + scale_out[b, a])
                scale_out[a, b] = v
                scale_out[b, a] = v
        for a in range(m):
            for b in range(m):
                Pzz_out[a, b] = (Czz[a, b] + (scale_out[a, b] / divisor[b] if a == b or not diagonal else 0.0)
                                 + R_known[a, b])
        if not cholesky_lower(Pzz_out, L):
            return VB_FAILED
        cholesky_solve_rows(L, Pxz, K_out)          # K = P_xz P_zz^-1
        kalman_correct(x_pred, P_pred, K_out, Pzz_out, innovation, x, P)
    for i in range(n):
        x_out[i] = x[i]
        if not math.isfinite(x[i]):
            return VB_FAILED
        for j in range(n):
            P_out[i, j] = P[i, j]
            if not math.isfinite(P[i, j]):
                return VB_FAILED
    for a in range(m):
        for b in range(m):
            if not math.isfinite(scale_out[a, b]):
                return VB_FAILED
    return VB_OK


STEP_NO_FACTOR, STEP_PREDICTION_NOT_FINITE = 3, 4


@kernel
def vb_step(x, P, Q, dt, n_sub, delta, sin_t, cos_t, mass, omega, wheel_torque, slip_forces, torque_known,
            G, S, min_speed, rho, z, H, c, R_known, dof, scale, iterations, r_mean, diagonal, x_prior, P_prior,
            scale_pred,
            innovation, Czz, Pxz, x_out, P_out, scale_out, K_out, Pzz_out):
    """One VB-ACKF step in one call: :func:`cubature_predict` into ``x_prior``, ``P_prior``; the
    inverse-Wishart prediction ``nu = rho (nu - d - 1) + d + 1``, ``V = rho V`` (Fig. 3; ``rho``
    and ``nu`` per channel, ``V_ab`` times ``sqrt(rho_a rho_b)``) into ``scale_pred`` (its ``nu``
    is recomputed by the caller);
    then :func:`vb_update`. Returns its outcome, or ``STEP_NO_FACTOR`` (``P`` has no Cholesky
    factor: nothing written) or ``STEP_PREDICTION_NOT_FINITE`` (the prediction is written, no
    update)."""
    if not cubature_predict(x, P, Q, dt, n_sub, delta, sin_t, cos_t, mass, omega, wheel_torque, slip_forces,
                            torque_known, G, S, min_speed, x_prior, P_prior):
        return STEP_NO_FACTOR
    m = z.shape[0]
    d1 = m + 1.0
    dof_pred = np.empty(m)
    for a in range(m):
        dof_pred[a] = rho[a] * (dof[a] - d1) + d1
        for b in range(m):
            factor = rho[a] if rho[a] == rho[b] else math.sqrt(rho[a] * rho[b])
            scale_pred[a, b] = factor * scale[a, b]
    if not small_linalg.all_finite(x_prior, P_prior):
        return STEP_PREDICTION_NOT_FINITE
    return vb_update(z, x_prior, P_prior, dof_pred, scale_pred, H, c, R_known, iterations, r_mean,
                     diagonal, innovation, Czz, Pxz, x_out, P_out, scale_out, K_out, Pzz_out)


@kernel
def affine_update(z, x_pred, P_pred, H, c, R, innovation, x_out, P_out, K_out, Pzz_out):
    """``SigmaPointKalmanFilter.update`` for an affine ``h = H x + c`` and a fixed ``R``: the
    closed-form moments, ``P_zz = H P H^T + R``, ``K = P_xz P_zz^-1``, ``x + K (z - z_hat)``,
    ``P - K P_zz K^T`` (symmetrised). False where ``P_zz`` is not positive definite or a moment
    is not finite (outputs then undefined; the caller runs the numpy update)."""
    n, m = x_pred.shape[0], z.shape[0]
    Pxz = np.empty((n, m))
    if not affine_moments(z, x_pred, P_pred, H, c, innovation, Pxz, Pzz_out):
        return False
    for a in range(m):
        for b in range(m):
            Pzz_out[a, b] += R[a, b]
    L = np.empty((m, m))
    if not cholesky_lower(Pzz_out, L):
        return False
    cholesky_solve_rows(L, Pxz, K_out)
    kalman_correct(x_pred, P_pred, K_out, Pzz_out, innovation, x_out, P_out)
    return True


class CompiledModel:
    """The per-parameter-set constants of the kernels and the per-step inputs they take."""

    def __init__(self, params: VehicleParams, min_speed: float, max_substep: float, slip_forces: bool):
        g = vm._geometry(params)
        self.G = np.ascontiguousarray(np.stack(list(g)), dtype=float)
        self.S = np.array([params.gravity, params.wheel_radius, params.longitudinal_stiffness,
                           params.tyre_load_exponent, params.road_friction,
                           0.5 * params.drag_coefficient * params.frontal_area * params.air_density,
                           params.yaw_inertia, params.lf, params.lr,
                           0.5 * params.track_front, 0.5 * params.track_rear])
        self.params = params
        self.min_speed = float(min_speed)
        self.max_substep = float(max_substep)
        self.slip_forces = bool(slip_forces)

    def predict(self, x: np.ndarray, P: np.ndarray, Q: np.ndarray, dt: float,
                inputs: vm.VehicleInputs) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The predicted ``(x, P)`` (``Q`` included), or None where the numpy path must run
        (``dt <= 0``, or a ``P`` without a Cholesky factor)."""
        if not dt > 0.0:
            return None
        x_out = np.empty_like(x)
        P_out = np.empty_like(P)
        arguments = (x, P, Q, *self.model_arguments(dt, inputs), x_out, P_out)
        ok = cubature_predict(*arguments)
        return (x_out, P_out) if ok else None

    def model_arguments(self, dt: float, inputs: vm.VehicleInputs) -> tuple:
        """The arguments of :func:`cubature_predict` from ``dt`` to ``min_speed``: the step's
        inputs and this parameter set's constants."""
        params = self.params
        torque_known = inputs.torques_valid
        wheel_torque = vm.wheel_torques(inputs, params)
        theta = float(inputs.slope)
        n_sub = max(1, int(math.ceil(dt / self.max_substep - 1e-9)))
        return (float(dt), n_sub, float(inputs.steer_angle), math.sin(theta), math.cos(theta),
                inputs.mass_or(params), inputs.wheel_speeds, wheel_torque, self.slip_forces, torque_known,
                self.G, self.S, self.min_speed)

    @staticmethod
    def update(z: np.ndarray, x: np.ndarray, P: np.ndarray, H: np.ndarray, c: np.ndarray,
               R: np.ndarray) -> Optional[tuple[np.ndarray, ...]]:
        """:func:`affine_update`: ``(x, P, K, innovation, P_zz)``, or None where the numpy
        update must run (``P_zz`` not positive definite, a moment not finite)."""
        n, m = x.shape[0], z.shape[0]
        innovation, x_out, P_out, K, Pzz = np.empty(m), np.empty(n), np.empty((n, n)), np.empty((n, m)), np.empty((m, m))
        if not affine_update(z, x, P, H, c, R, innovation, x_out, P_out, K, Pzz):
            return None
        return x_out, P_out, K, innovation, Pzz


_warm = False


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module now, with the argument types
    the filters use, so that the first sample of a drive does not wait for the compiler."""
    global _warm
    if _warm:
        return
    model = CompiledModel(VehicleParams(), vm.DEFAULT_MIN_SPEED, vm.DEFAULT_MAX_SUBSTEP, True)
    x, P = np.array([10.0, 0.0, 0.0, 0.0, 0.0]), np.eye(5)
    model.predict(x, P, 0.01 * np.eye(5), 0.01, vm.VehicleInputs(wheel_speeds=np.full(4, 30.0)))
    H, c = vm.measurement_affine(vm.VehicleInputs(), model.params)
    vb_update(np.zeros(3), x, P, np.full(3, 8.0), np.eye(3), H, c, np.zeros((3, 3)), 1, True, False, np.empty(3), np.empty((3, 3)),
              np.empty((5, 3)), np.empty(5), np.empty((5, 5)), np.empty((3, 3)), np.empty((5, 3)), np.empty((3, 3)))
    affine_update(np.zeros(3), x, P, H, c, np.eye(3), np.empty(3), np.empty(5), np.empty((5, 5)),
                  np.empty((5, 3)), np.empty((3, 3)))
    step_arguments = (x, P, 0.01 * np.eye(5), *model.model_arguments(0.01, vm.VehicleInputs(wheel_speeds=np.full(4, 30.0))),
                      np.full(3, 0.9), np.zeros(3), H, c, np.zeros((3, 3)), np.full(3, 8.0), np.eye(3), 1, True, False, np.empty(5), np.empty((5, 5)), np.empty((3, 3)),
                      np.empty(3), np.empty((3, 3)), np.empty((5, 3)), np.empty(5), np.empty((5, 5)), np.empty((3, 3)),
                      np.empty((5, 3)), np.empty((3, 3)))
    vb_step(*step_arguments)
    small_linalg.valid_moments(x, P, np.empty_like(P))
    small_linalg.all_finite(x, P)
    _warm = True
