"""Variational-Bayes adaptive cubature Kalman filter (VB-ACKF) of paper 004, Sec. 4.

Chen et al. 2021, "An effective joint soft-sensing strategy for multi-information under
diverse vehicle driving scenarios", Electronics 10, 505: Eqs. 10-13 and Fig. 3; the
algorithm is the one of the paper's ref. [30] (Huang et al. 2018, "A novel adaptive Kalman
filter with inaccurate process and measurement noise covariance matrices", IEEE TAC 63)
restricted to the measurement noise, as the paper uses it: only ``R`` is adapted, ``Q`` is
the fixed Sec. 7.1 value.

Model (Eq. 10, discretised as in :mod:`vehicle_model`)::

    x_k = f(x_{k-1}, u_k) + v_k,   v_k ~ N(0, Q)
    z_k = h(x_k, u_k) + w_k,       w_k ~ N(0, R_k),   R_k unknown and slowly time-varying

Prior on ``R_k`` (paper Sec. 4): inverse Wishart ``IW(R_k; nu_k, V_k)`` of dimension ``d``
(density ``~ |R|^-(nu+d+1)/2 exp(-tr(V R^-1)/2)``) whose mean is the noise estimate of
Eq. 11::

    E[R_k] = V_k / (nu_k - d - 1)                                            (Eq. 11)

Time update (Fig. 3, "R is also predicted out in this part"; ref. [30], Algorithm 1), with
the forgetting factor ``rho`` in (0, 1]::

    nu_k|k-1 = rho (nu_k-1 - d - 1) + d + 1,   V_k|k-1 = rho V_k-1

which keeps the mean ``E[R]`` and spreads the distribution (less "data weight"
``nu - d - 1``), so that a change of the noise can be followed.

Variational measurement update (Eqs. 12-13, Fig. 3): ``p(x, R | z_1:k)`` is approximated by
``q(x) q(R)`` minimising the KLD; the coordinate-descent fixed point is iterated ``N``
times starting from ``q(x) = N(x_k|k-1, P_k|k-1)``::

    nu_k = nu_k|k-1 + 1
    for i = 0 .. N-1:
        B^(i)  = E_q(i)(x)[(z - h(x)) (z - h(x))^T]     ("adjustment matrix" of Fig. 3,
                                                          by the cubature rule at x^(i), P^(i))
        V^(i+1) = V_k|k-1 + B^(i)
        R^(i+1) = V^(i+1) / (nu_k - d - 1)              (Eq. 11; see "point estimate" below)
        P_zz = C_zz + R^(i+1),  W = P_xz P_zz^-1         (C_zz, P_xz: cubature moments of the
        x^(i+1) = x_k|k-1 + W (z - z_hat_k|k-1)           prediction, Fig. 3 notation)
        P^(i+1) = P_k|k-1 - W P_zz W^T

Choices where the paper's text is not explicit (Fig. 3 is an image not in the text):

* Point estimate of ``R`` in the gain. Exact mean-field VB uses ``(E[R^-1])^-1 = V/nu``;
  the paper states that "the noise covariance matrix R_k is represented by the mean of the
  IW distribution" (Eq. 11), which is also what common implementations of ref. [30] use
  (``E[R^-1] = (nu - d - 1) V^-1``). Default: the mean, Eq. 11
  (``VBConfig.r_estimate = "mean"``); ``"vb"`` gives
  ``V/nu``. Both are exposed (:attr:`VariationalBayesCKF.R_mean`,
  :attr:`VariationalBayesCKF.R_vb`).
* Iteration order. As ref. [30] Algorithm 1: ``B`` is formed first from the predicted
  density, so the first gain already uses this step's innovation; the returned state and
  ``(nu, V)`` are those of the last iteration (consistent pair).
* ``B`` is evaluated with the cubature points of ``N(x^(i), P^(i))`` as
  ``(1/2n) sum_j (z - h(X_j))(z - h(X_j))^T``, PSD by construction (for a linear ``h`` it
  equals ref. [30]'s ``(z - H x)(z - H x)^T + H P H^T``).
* Sampling times that differ from the paper's ``tau``: with ``VBConfig.nominal_dt`` set,
  a prediction over ``dt`` uses ``rho ** (dt / nominal_dt)`` so that the memory of the
  noise estimate is a time (``nominal_dt / (1 - rho)``, 0.55 s for the defaults) and not a
  number of samples.
* Not in the paper: with the diagonal noise (``VBConfig.noise_structure``), each channel may
  forget at its own rate (``VBConfig.rho_per_channel``): one ``nu`` per channel, and
  ``V_ab`` forgotten by ``sqrt(rho_a rho_b)`` (symmetric; each variance by its own ``rho``).
  An accelerometer's vibration noise changes over seconds to minutes, while the gyro's learnt
  noise, on a nearly exact model, is best kept short (params/estimation.yaml says why).

Limitation (inherent to the method, not to this code): ``R`` is identifiable from the
innovations only where the predicted measurement covariance ``C_zz`` is not much larger
than ``R``. Where ``C_zz >> R`` the gain is ~1 whatever ``R``, the posterior residual is ~0
and ``B`` ~ the current estimate, so ``E[R]`` hardly moves (see
:class:`VehicleStateVBACKF`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common import compiled
from vehicle_estimation.estimators.common.sigma_points import as_matrix, is_positive_definite
from vehicle_estimation.estimators.state.ckf import CubatureKalmanFilter, VehicleStateCKF, VehicleStateConfig
from vehicle_estimation.estimators.state.model_kernels import (STEP_NO_FACTOR, STEP_PREDICTION_NOT_FINITE, VB_FAILED,
                                                               VB_REJECTED, CompiledModel, vb_step, vb_update)
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs

__all__ = ["VBConfig", "VariationalBayesCKF", "VehicleStateVBACKF"]

R_ESTIMATES = ("mean", "vb")
NOISE_STRUCTURES = ("full", "diagonal")


class _NumericalFailure(Exception):
    """A variational iteration produced a non-finite or non-positive-definite matrix."""


@dataclasses.dataclass
class VBConfig:
    """Tuning of the variational inverse-Wishart adaptation of ``R`` (paper 004 Sec. 4).

    Paper 004 Sec. 7.1 gives ``P0``, ``Q``, the initial ``R`` and ``tau`` (those are in
    :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateConfig`) but not the three VB
    parameters; the defaults are those recommended by the paper's ref. [30] (Huang et al.
    2018), which is where the paper points for ``N``.

    ``nominal_dt`` is not a ROS parameter: ``None`` means ``rho`` per
    :meth:`~VariationalBayesCKF.predict` call, and the vehicle estimator fills in the
    paper's ``tau`` (its ``VehicleStateConfig.nominal_dt``, 0.01 s) when it is ``None``.
    """

    rho: float = setting(
        1.0 - math.exp(-4.0),
        "Forgetting factor rho of the nu/V prediction, per nominal_dt (1 - exp(-4) = 0.9817, "
        "ref. [30]); 1 = constant noise [-]", low=0.0, high=1.0, low_open=True)
    iterations: int = setting(10, "Number N of variational iterations per update (10, ref. [30])", low=1)
    prior_weight: float = setting(
        3.0, "nu_0 - d - 1, the number of pseudo-measurements the initial R_0 is worth; V_0 = "
        "prior_weight R_0 so that E[R_0] = R_0 (Eq. 11). 3 as ref. [30]'s reference code. Large = "
        "prior concentrated at R_0 [-]", low=0.0, low_open=True)
    nominal_dt: Optional[float] = None
    r_estimate: str = setting(
        "mean", "The R used in the gain: 'mean' (Eq. 11, V/(nu-d-1), paper) or 'vb' "
        "((E[R^-1])^-1 = V/nu, exact mean-field)", choices=R_ESTIMATES)
    noise_structure: str = setting(
        "full", "Which R is learnt: 'full' (paper, inverse-Wishart: every covariance) or 'diagonal' "
        "(each channel's variance alone: the IW's marginals, the inverse-Gamma of Sarkka & "
        "Nummenmaa 2009). An IMU's axes have independent noise; a full R also learns the "
        "correlation of the model's errors in ay and r as sensor noise", choices=NOISE_STRUCTURES)
    tolerance: float = setting(
        0.0, "Stop the iterations early when the relative change of V is below this (0 = always "
        "`iterations`, as the paper) [-]", low=0.0)
    rho_per_channel: tuple[float, ...] = setting(
        (), "Forgetting factor of each measurement channel's noise, per nominal_dt, in the order of "
        "z ([ax, ay, r] for the vehicle state); empty = rho for every channel. Different values only "
        "with the 'diagonal' noise_structure, where each channel's variance is learnt alone [-]",
        low=0.0, high=1.0, low_open=True, each=True)

    @property
    def diagonal(self) -> bool:
        return self.noise_structure == "diagonal"

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        check_settings(self)
        if len(set(self.rho_per_channel)) > 1 and not self.diagonal:
            raise ValueError("rho_per_channel with different values needs noise_structure 'diagonal': a full "
                             "inverse-Wishart has one number of degrees of freedom")
        if self.nominal_dt is not None and not (
                isinstance(self.nominal_dt, (int, float)) and not isinstance(self.nominal_dt, bool)
                and math.isfinite(self.nominal_dt) and self.nominal_dt > 0.0):
            raise ValueError(f"nominal_dt must be None or a finite positive number, got {self.nominal_dt!r}")


class VariationalBayesCKF(CubatureKalmanFilter):
    """CKF with the measurement-noise covariance learnt by variational Bayes (Eqs. 10-13).

    Same model conventions as :class:`~vehicle_estimation.estimators.state.ckf.CubatureKalmanFilter`;
    ``R`` is the initial noise estimate ``R_0`` (prior mean, Eq. 11). See the module
    docstring for the algorithm.

    Robustness: a measurement with a non-finite entry, or whose cubature moments are not
    finite, is skipped (``rejected_measurements``; the returned innovation is NaN where
    nothing could be computed, the state and the noise statistics are untouched). If a
    variational iteration meets a non-finite or non-positive-definite matrix the step falls
    back to the plain CKF correction with the last valid noise estimate (``vb_fallbacks``)
    and the noise statistics keep their prediction (or go back to the prior if that is
    invalid too). The estimates are never set to NaN by :meth:`update`.

    Args:
        f, h, Q, R, x0, P0, vectorized: as :class:`CubatureKalmanFilter`.
        vb: :class:`VBConfig` (default: ``VBConfig()``).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *,
                 vb: Optional[VBConfig] = None, vectorized: bool = True, h_affine: Optional[Callable] = None):
        super().__init__(f, h, Q, R, x0, P0, vectorized=vectorized, h_affine=h_affine)
        self.vb = VBConfig() if vb is None else vb
        self.vb.validate()
        if not (is_positive_definite(self.R) and np.allclose(self.R, self.R.T)):
            raise ValueError("R must be a finite, symmetric positive-definite matrix")
        self.R0 = self.R.copy()
        if len(self.vb.rho_per_channel) not in (0, self.m):
            raise ValueError(f"rho_per_channel must have one value per measurement channel ({self.m}), "
                             f"got {len(self.vb.rho_per_channel)}")
        # One forgetting factor and one nu per channel; all equal unless rho_per_channel.
        self._rho = np.array(self.vb.rho_per_channel if len(self.vb.rho_per_channel) else [self.vb.rho] * self.m,
                             dtype=float)
        self._no_known_noise = np.zeros((self.m, self.m))
        self.vb_fallbacks = 0
        self.rejected_measurements = 0
        self.last_iterations = 0
        # The fixed-N iterations by the compiled kernel (same numbers to 1e-12; the numpy loop
        # below is its definition and test oracle).
        self.compiled_iterations = compiled.enabled()
        self.compiled_model: Optional[CompiledModel] = None   # for fused_step (set by its owner)
        self.reset_noise_statistics()

    # -- noise statistics ----------------------------------------------------------------
    def reset_noise_statistics(self, R0=None) -> None:
        """Back to the prior ``nu_0 = d + 1 + prior_weight``, ``V_0 = prior_weight R_0``.

        ``R0`` (default: the constructor's ``R``) becomes the new prior mean.
        """
        if R0 is not None:
            R0 = as_matrix(R0, self.m, "R0")
            if not is_positive_definite(R0):
                raise ValueError("R0 must be finite and positive definite")
            self.R0 = 0.5 * (R0 + R0.T)
        self._dof = np.full(self.m, self.m + 1.0 + self.vb.prior_weight)
        self._scale = self.vb.prior_weight * self.R0

    def reset(self, x0, P0, *, reset_noise: bool = False) -> None:
        """Reset the state; the noise statistics only with ``reset_noise=True``.

        The noise is a property of the sensors and survives a state re-initialisation.
        """
        super().reset(x0, P0)
        if reset_noise:
            self.reset_noise_statistics()

    @property
    def dof(self) -> float:
        """Current degrees of freedom ``nu`` of ``IW(R; nu, V)`` (of the first channel's
        inverse-Gamma where the channels forget at different rates: :attr:`dofs`)."""
        return float(self._dof[0])

    @property
    def dofs(self) -> np.ndarray:
        """``nu`` of each channel (equal unless ``VBConfig.rho_per_channel``)."""
        return self._dof.copy()

    @property
    def scale(self) -> np.ndarray:
        """Current inverse scale matrix ``V`` of ``IW(R; nu, V)``."""
        return self._scale.copy()

    @property
    def R_mean(self) -> np.ndarray:
        """``E[R] = V / (nu - d - 1)`` (Eq. 11): the current noise estimate."""
        return self._point_estimate(self._dof, self._scale, "mean")

    @property
    def R_mean_diagonal(self) -> np.ndarray:
        """The diagonal of :attr:`R_mean` without the matrix (the state node reads it every step)."""
        return np.diagonal(self._scale) / (self._dof - self.m - 1.0)

    @property
    def R_vb(self) -> np.ndarray:
        """``(E[R^-1])^-1 = V / nu``, the mean-field VB point estimate."""
        return self._point_estimate(self._dof, self._scale, "vb")

    @property
    def R_estimate(self) -> np.ndarray:
        """The ``R`` the gain uses, by ``VBConfig.r_estimate`` (default: Eq. 11)."""
        return self._point_estimate(self._dof, self._scale, self.vb.r_estimate)

    def _point_estimate(self, dof: np.ndarray, scale: np.ndarray, kind: str) -> np.ndarray:
        """``R`` of ``IW(R; dof, scale)``: its mean (``kind`` "mean") or ``(E[R^-1])^-1`` ("vb");
        only its diagonal with ``VBConfig.noise_structure`` "diagonal" (``dof`` per channel:
        column ``j`` is divided by channel ``j``'s; all equal for a full ``R``)."""
        R = scale / (dof - self.m - 1.0) if kind == "mean" else scale / dof
        return np.diag(np.diag(R)) if self.vb.diagonal else R

    def forgetting_factor(self, dt: float) -> np.ndarray:
        """Each channel's ``rho`` for a prediction over ``dt``: ``rho ** (dt / nominal_dt)``
        or ``rho``."""
        if self.vb.nominal_dt is None:
            return self._rho.copy()
        return self._rho ** (max(float(dt), 0.0) / self.vb.nominal_dt)

    @staticmethod
    def _forget_scale(rho: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """``V_k|k-1``: ``rho V`` (Fig. 3); per channel ``V_ab sqrt(rho_a rho_b)``, which keeps
        ``V`` symmetric and scales each diagonal element by its channel's ``rho`` (``rho_a``
        itself where the two are equal, as ``vb_step`` does)."""
        row, column = rho[:, None], rho[None, :]
        return np.where(row == column, row, np.sqrt(row * column)) * scale

    # -- time update ---------------------------------------------------------------------
    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        """CKF time update, then the IW prediction ``nu_k|k-1``, ``V_k|k-1`` (Fig. 3)."""
        super().predict(dt, *args, Q=Q)
        rho = self.forgetting_factor(dt)
        self._dof = self._predicted_dof(rho)
        self._scale = self._forget_scale(rho, self._scale)

    def _predicted_dof(self, rho: np.ndarray) -> np.ndarray:
        """``nu_k|k-1 = rho (nu_k-1 - d - 1) + d + 1`` (Fig. 3; ``vb_step`` computes the same)."""
        d1 = self.m + 1.0
        return rho * (self._dof - d1) + d1

    def _compiled_h_affine(self) -> Optional[Callable]:
        """``h_affine`` where the compiled update serves (switched on, an affine ``h``, a fixed
        ``N``), else None."""
        return self.h_affine if self.compiled_iterations and self.vb.tolerance == 0.0 else None

    # -- variational measurement update ---------------------------------------------------
    def _known(self) -> np.ndarray:
        """:attr:`known_noise`, or zeros: added to the learnt ``R`` in ``P_zz`` only. The
        residual statistics stay those of every error, so what the known term does not
        explain is still learnt (the two may count some error twice: cautious, not bold)."""
        if self.known_noise is None:
            return self._no_known_noise
        return self.known_noise

    def _residual_second_moment(self, z: np.ndarray, x: np.ndarray, P: np.ndarray, args) -> np.ndarray:
        """``B = E_N(x,P)[(z - h(x))(z - h(x))^T]`` by the cubature rule ("adjustment matrix"),
        in closed form for an affine ``h``: ``e e^T + H P H^T`` with ``e = z - H x - c``."""
        if self.h_affine is not None:
            return _affine_residual_moment(z, x, P, *self.h_affine(*args))
        Z = self._apply(self.h, self.sigma_points(x, P), *args)
        e = z - Z
        B = self.points.covariance(e, e)
        return 0.5 * (B + B.T)

    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> np.ndarray:
        """Variational measurement update with ``z``; returns the innovation ``z - z_hat``.

        ``R=`` given: plain CKF update with that fixed ``R``, noise statistics untouched. The
        noise statistics are those of every channel: ``select`` must be None.
        """
        if select is not None:
            raise ValueError("the variational update takes every measurement channel (select=None)")
        z = np.asarray(z, dtype=float).reshape(self.m)
        if not all(map(math.isfinite, z)):
            self.rejected_measurements += 1
            self.last_iterations = 0
            return np.full(self.m, np.nan)
        if R is not None:
            return super().update(z, *args, R=R)
        h_affine = self._compiled_h_affine()
        if h_affine is not None:
            return self._update_compiled(z, *h_affine(*args))

        x_pred, P_pred = self._x.copy(), self._P.copy()
        dof_pred, scale_pred = self._dof, self._scale.copy()
        with np.errstate(all="ignore"):
            z_hat, Czz, Pxz = self.measurement_moments(*args)
            innovation = z - z_hat
        if not (np.isfinite(innovation).all() and np.isfinite(Czz).all() and np.isfinite(Pxz).all()):
            self.rejected_measurements += 1
            self.last_iterations = 0
            return innovation

        dof = dof_pred + 1.0
        x_i, P_i = x_pred, P_pred
        known = self._known()
        try:
            # V_k|k-1 PD and B PSD (by construction) make every V^(i+1), R^(i+1) PD: check the
            # prediction once, then only that B is finite and P_zz factorises.
            if not (np.isfinite(dof_pred).all() and is_positive_definite(scale_pred)):
                raise _NumericalFailure
            if self.h_affine is not None and self.vb.tolerance == 0.0:
                H, c = self.h_affine(*args)
                self._iterate_affine(z, innovation, Czz, Pxz, x_pred, P_pred, dof, scale_pred, H, c)
                return innovation
            with np.errstate(all="ignore"):
                for i in range(self.vb.iterations):
                    B = self._residual_second_moment(z, x_i, P_i, args)
                    if not np.isfinite(B).all():
                        raise _NumericalFailure
                    scale = scale_pred + B
                    R_i = self._point_estimate(dof, scale, self.vb.r_estimate)
                    Pzz = Czz + R_i + known
                    if not is_positive_definite(Pzz):
                        raise _NumericalFailure
                    self._x, self._P = x_pred, P_pred
                    self.correct(innovation, Pzz, Pxz)
                    if not (np.isfinite(self._x).all() and np.isfinite(self._P).all()):
                        raise _NumericalFailure
                    x_i, P_i = self._x, self._P
                    converged = (i > 0 and self.vb.tolerance > 0.0 and
                                 np.linalg.norm(scale - self._scale) <= self.vb.tolerance * np.linalg.norm(scale))
                    self._dof, self._scale = dof, scale
                    if converged:
                        break
            self.last_iterations = i + 1
        except (_NumericalFailure, np.linalg.LinAlgError):
            self._fallback(innovation, Czz, Pxz, x_pred, P_pred, dof_pred, scale_pred)
        return innovation

    def _update_compiled(self, z: np.ndarray, H: np.ndarray, c: np.ndarray) -> np.ndarray:
        """:meth:`update` by the compiled kernel (affine ``h``, fixed ``N``): the same steps, the
        same outcomes (rejection, fallback), the same numbers to 1e-12."""
        out = self._kernel_outputs()
        x_pred, P_pred, dof_pred, scale_pred = self._x, self._P, self._dof, self._scale
        outcome = vb_update(z, x_pred, P_pred, dof_pred, scale_pred, H, c, self._known(), self.vb.iterations,
                            self.vb.r_estimate == "mean", self.vb.diagonal, *out)
        self._take_outcome(outcome, out, x_pred, P_pred, dof_pred, scale_pred)
        return out[0]

    def fused_step(self, dt: float, inputs, Q: np.ndarray, z: np.ndarray) -> bool:
        """:meth:`predict` and :meth:`update` (finite ``z``) in one compiled call, with their
        outcomes; False, with nothing changed, where that call cannot serve (no compiled model,
        a non-affine ``h``, early stopping, ``dt <= 0``, or a ``P`` without a Cholesky factor):
        the caller then runs the two steps."""
        model = self.compiled_model
        h_affine = self._compiled_h_affine()
        if model is None or h_affine is None or not dt > 0.0:
            return False
        n, m = self.n, self.m
        x_prior, P_prior, scale_pred = np.empty(n), np.empty((n, n)), np.empty((m, m))
        out = self._kernel_outputs()
        rho = self.forgetting_factor(dt)
        arguments = (self._x, self._P, Q, *model.model_arguments(dt, inputs), rho, z, *h_affine(inputs),
                     self._known(), self._dof, self._scale, self.vb.iterations, self.vb.r_estimate == "mean",
                     self.vb.diagonal, x_prior, P_prior, scale_pred, *out)
        outcome = vb_step(*arguments)
        if outcome == STEP_NO_FACTOR:
            return False
        dof_pred = self._predicted_dof(rho)
        self.x_prior, self.P_prior = x_prior.copy(), P_prior.copy()
        if outcome == STEP_PREDICTION_NOT_FINITE:
            self._x, self._P, self._dof, self._scale = x_prior, P_prior, dof_pred, scale_pred
        else:
            self._take_outcome(outcome, out, x_prior, P_prior, dof_pred, scale_pred)
        return True

    def _kernel_outputs(self) -> tuple[np.ndarray, ...]:
        """New arrays for ``(innovation, C_zz, P_xz, x, P, V, K, P_zz)``: each is kept as a state
        or a ``last_*`` attribute, or handed to :meth:`_fallback`."""
        n, m = self.n, self.m
        return (np.empty(m), np.empty((m, m)), np.empty((n, m)), np.empty(n), np.empty((n, n)), np.empty((m, m)),
                np.empty((n, m)), np.empty((m, m)))

    def _take_outcome(self, outcome: int, out: tuple, x_pred, P_pred, dof_pred: np.ndarray, scale_pred) -> None:
        """The state after a compiled update from the prediction ``(x, P, nu, V)_pred``."""
        innovation, Czz, Pxz, x, P, scale, K, Pzz = out
        if outcome == VB_REJECTED:
            self._x, self._P, self._dof, self._scale = x_pred, P_pred, dof_pred, scale_pred
            self.rejected_measurements += 1
            self.last_iterations = 0
        elif outcome == VB_FAILED:
            self._fallback(innovation, Czz, Pxz, x_pred.copy(), P_pred.copy(), dof_pred, scale_pred.copy())
        else:
            self._x, self._P, self._dof, self._scale = x, P, dof_pred + 1.0, scale
            self.last_gain, self.last_innovation, self.last_innovation_covariance = K, innovation, Pzz
            self.last_iterations = self.vb.iterations

    def _iterate_affine(self, z, innovation, Czz, Pxz, x_pred, P_pred, dof, scale_pred, H, c) -> None:
        """The iterations of :meth:`update` for an affine ``h = H x + c`` and a fixed ``N``: the
        same steps as the general loop (so the same numbers), with the residual moment in
        closed form and the checks that only guard against non-finite values done once at the
        end, where a NaN or inf would still show. Raises :class:`_NumericalFailure` or
        ``LinAlgError`` as the general loop does."""
        kind = self.vb.r_estimate
        known = self._known()
        with np.errstate(all="ignore"):
            for _ in range(self.vb.iterations):
                scale = scale_pred + _affine_residual_moment(z, self._x, self._P, H, c)
                Pzz = Czz + self._point_estimate(dof, scale, kind) + known
                np.linalg.cholesky(Pzz)          # LinAlgError: not positive definite
                self._x, self._P = x_pred, P_pred
                self.correct(innovation, Pzz, Pxz)
        if not (np.isfinite(self._x).all() and np.isfinite(self._P).all() and np.isfinite(scale).all()):
            raise _NumericalFailure
        self._dof, self._scale = dof, scale
        self.last_iterations = self.vb.iterations

    def _fallback(self, innovation, Czz, Pxz, x_pred, P_pred, dof_pred, scale_pred) -> None:
        """Plain CKF correction with the last valid noise estimate; noise statistics = prediction."""
        self.vb_fallbacks += 1
        self.last_iterations = 0
        self._dof, self._scale = dof_pred, scale_pred
        if not (np.isfinite(dof_pred).all() and is_positive_definite(scale_pred)):
            self.reset_noise_statistics()
        self._x, self._P = x_pred, P_pred
        R = self._noise(self.R_estimate, None)
        with np.errstate(all="ignore"):
            if not is_positive_definite(Czz + R):
                R = self._noise(self.R0, None)
            try:
                self.correct(innovation, Czz + R, Pxz)
                ok = bool(np.isfinite(self._x).all() and np.isfinite(self._P).all())
            except np.linalg.LinAlgError:
                ok = False
        if not ok:  # not even the plain correction: keep the prediction
            self._x, self._P = x_pred, P_pred
            self.rejected_measurements += 1


def _affine_residual_moment(z, x, P, H, c) -> np.ndarray:
    """``E_N(x,P)[(z - h(x))(z - h(x))^T]`` for ``h(x) = H x + c``: ``e e^T + H P H^T`` with
    ``e = z - H x - c``, symmetrised (what the cubature rule gives exactly, to rounding)."""
    e = z - H @ x - c
    B = np.outer(e, e) + H @ P @ H.T
    return 0.5 * (B + B.T)


# ----------------------------------------------------------------------------------------
class VehicleStateVBACKF(VehicleStateCKF):
    """Vehicle state ``[vx, vy, r, ax, ay]`` by the VB-ACKF (paper 004 Sec. 4, "proposed").

    Everything but the filter is :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateCKF`
    (model, Sec. 7.1 tuning, stamps, gap re-initialisation, rejection counters): the
    filter it builds (:meth:`_make_filter`) is a :class:`VariationalBayesCKF` instead of
    the plain CKF, with the same ``f``, ``h``, ``Q``, ``R`` (= ``R_0``), ``x0`` and ``P0``.

    Defaults (Sec. 7.1): ``P0 = 10 I``, ``Q = 0.1 I`` per ``tau``, ``R_0 = diag[4e-2, 4e-2,
    6e-5]``, ``tau = 0.01`` s; not in the paper: ``rho = 1 - exp(-4)`` per ``tau``,
    ``N = 10``, ``nu_0 = d + 1 + 3`` (:class:`VBConfig`).

    A re-initialisation after a stamp gap keeps the learnt noise (a sensor property); one
    after a numerical failure also resets the noise statistics to the prior.

    Note: with the Sec. 7.1 ``Q = 0.1 I`` per 10 ms the predicted covariance of
    ``[ax_imu, ay_imu, r]`` is ~``diag[6, 4, 0.05]``, two orders of magnitude above ``R``
    (the Dugoff slip stiffness turns the ``vx``/``vy`` process noise into several m/s^2 of
    predicted acceleration uncertainty). The gain is then ~1 on every measurement, ``R`` is
    not identifiable and the filter behaves as the CKF (``E[R]`` stays near ``R_0``). With
    ``Q`` around ``1e-4 I``..``1e-3 I`` the noise is learnt (see the tests).

    Args:
        params: vehicle parameters.
        config: :class:`VehicleStateConfig` (Sec. 7.1 defaults).
        vb: :class:`VBConfig`; ``nominal_dt=None`` (default) takes ``config.nominal_dt``.
    """

    _filter: VariationalBayesCKF   # built by _make_filter
    learns_measurement_noise = True

    def __init__(self, params: VehicleParams, config: Optional[VehicleStateConfig] = None,
                 vb: Optional[VBConfig] = None):
        # Read by _make_filter, which super().__init__ calls once the config is validated.
        self._vb_requested = VBConfig() if vb is None else vb
        super().__init__(params, config)

    def _make_filter(self, f: Callable, h: Callable) -> VariationalBayesCKF:
        """The :class:`VariationalBayesCKF` on the model closures, with the configured ``Q``,
        ``R`` (= ``R_0``), ``x0`` and ``P0``; sets :attr:`vb_config`."""
        vb = self._vb_requested
        if vb.nominal_dt is None:
            vb = dataclasses.replace(vb, nominal_dt=self.config.nominal_dt)
        vb.validate()
        self.vb_config = vb
        cfg = self.config
        return VariationalBayesCKF(f, h, self.process_noise, cfg.R, self._x0(None), cfg.P0, vb=vb,
                                   h_affine=self._h_affine)

    def use_compiled(self, on: bool) -> None:
        """As the CKF's, and the variational iterations and the fused step too."""
        super().use_compiled(on)
        self._filter.compiled_iterations = on
        self._filter.compiled_model = self._compiled_model

    def _reinitialised_after_failure(self, inputs: VehicleInputs) -> bool:
        """As the CKF's, and the noise statistics go back to the prior too: a failure may
        come from them."""
        if not super()._reinitialised_after_failure(inputs):
            return False
        self._filter.reset_noise_statistics()
        return True

    @property
    def measurement_noise(self) -> np.ndarray:
        """Current estimate ``E[R]`` (Eq. 11) of the covariance of ``[ax_imu, ay_imu, r]``."""
        return self._filter.R_mean

    @property
    def measurement_noise_diagonal(self) -> np.ndarray:
        """The diagonal of :attr:`measurement_noise`."""
        return self._filter.R_mean_diagonal

    @property
    def vb_fallbacks(self) -> int:
        """Updates where the variational iteration failed and the plain CKF was used."""
        return self._filter.vb_fallbacks

    def status(self) -> dict[str, str]:
        """The learnt measurement noise (diagonal of ``E[R]``) and the VB fallbacks."""
        return {"learnt R diagonal": np.array2string(np.diag(self.measurement_noise), precision=6),
                "VB fallbacks": str(self.vb_fallbacks)}
