"""Adaptive anti-outlier UKF on the 3-DOF Magic-Formula vehicle model (paper 002).

Liu, Cui, Peng 2023, "Vehicle state and parameter estimation based on adaptive anti-outlier
unscented Kalman filter and GA-BPNN method", J. Vibroengineering, doi 10.21595/jve.2023.23441.

Contents
--------
* :class:`UnscentedKalmanFilter`: generic additive-noise UKF with scaled sigma points
  (Julier's ``alpha, beta, kappa``). All ``2n + 1`` sigma points go through ``f`` and ``h`` in
  ONE vectorised call (``(2n+1, n)`` array in, ``(2n+1, .)`` out); the square root is a
  Cholesky factor with an eigenvalue-clipped fallback when ``P`` is not positive definite.
  The correction accepts a per-component gain scaling and uses the covariance update that is
  exact for any gain (``P - K Pxz^T - Pxz K^T + K Pzz K^T``), so a down-weighted or zeroed
  gain column never over-shrinks ``P``.
* :class:`AntiOutlierUKF`: the UKF with the anti-outlier measurement update of Sec. 3.3
  (innovation Eq. 6, per-component test ``|e_i| <= C sigma_ii`` Eq. 7, gain scaling
  ``K <- m K`` for isolated outliers, replacement of speckled outliers by the prediction,
  Steps 1-5), see :meth:`AntiOutlierUKF.update`.
* :class:`ExtendedKalmanFilter`: the EKF the paper contrasts (Table 2), same model, Jacobians
  by central differences evaluated in one vectorised call.
* :class:`ThreeDofModel`: Sec. 2, state ``x = [vx, vy, r]``, input ``u = ax``, observation
  ``y = [ay, r]`` (Sec. 2.3), Eq. 1 dynamics, Magic-Formula lateral tyre forces (Sec. 2.2) with
  the axle loads of Eq. 3.
* :class:`VehicleStateAOUKF`: the node-facing estimator, API of
  :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateCKF` (``step``, ``x``, ``P``, ``sideslip``,
  ``sideslip_variance``, ``initialised``, ``reset``, ``rejected``), with the optional GA-BPNN
  output correction of Eq. 5 (:class:`~vehicle_estimation.estimators.state.gabpnn.BPCorrection`).

Choices where the paper is not explicit (all in :class:`AOUKFConfig`)
-------------------------------------------------------------------
* Tyre: the paper gives ``B = 0.237, C = 1.65, D = 3610.5, E = 0.707`` (Sec. 2.2, for its
  Table-1 car, slip angle in degrees, ``D`` in N per tyre). ``D`` follows the axle load of
  Eq. 3 as ``D = mf_d F_z / mf_reference_load`` (the linear term ``a2 F_z`` of the paper's
  ``D = a1 F_z^2 + a2 F_z``; the reference load is the mean tyre load of the paper's Table-1
  car, ``1522 g / 4``). With ``mf_match_cornering_stiffness`` (default) ``B`` is set per axle
  so that the cornering stiffness ``B C D`` equals ``VehicleParams.cornering_stiffness_*``:
  the paper's numbers describe the paper's car, the vehicle file describes ours. ``False``
  uses the paper's ``B`` as is.
* Innovation standard deviation (Sec. 3.3): ``sigma_ii`` is the larger of the UKF's
  ``sqrt(P_zz,ii)`` (the paper's formula) and a robust running estimate over the last
  ``innovation_window`` innovations, each clipped at ``C sigma`` before it enters the window.
  The running estimate lets ``sigma`` follow a time-varying noise level (a fixed ``R`` would
  flag a whole noisy segment as outliers); the clipping keeps outliers out of it and still
  lets ``sigma`` grow by up to ``C`` per window when the noise really rises.
* Gain factor ``m`` (Sec. 3.3, "depends on the size of the innovation"): ``m = 1`` for
  ``|e_i| <= C sigma_ii``, ``m = C sigma_ii / |e_i|`` up to ``zero_gain_ratio C sigma_ii``,
  and ``m = 0`` beyond (the "very high innovation" case).
* Isolated vs speckled (Steps 1-5): online, the first flagged sample of a channel is an
  isolated outlier (gain scaling); from the ``speckle_min_run``-th consecutive flagged
  sample on it is part of a speckled outlier and is replaced by the prediction
  ``(Z)_i <- (Z_hat)_i`` (innovation 0, no information: its gain column is zeroed). A run
  longer than ``max_outlier_run_s`` is taken as a real change of the signal, not an outlier:
  the channel's window is restarted and the channel is accepted until its innovation passes
  Eq. 7 again (``resyncs``).

Extension beyond the paper: the undriven wheels' mean speed times the wheel radius observes
``vx`` when the wheel speeds are finite (``wheel_speed_update``, default on); without it ``vx``
is the integral of the measured ``ax`` and drifts with its bias. The start value of ``vx``
comes from the same wheels when they are available, as in ``VehicleStateCKF``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Any, Callable, Optional

import numpy as np

from vehicle_estimation.estimators.state.ckf import valid_moments
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.contract.vehicle import VehicleParams

if TYPE_CHECKING:   # gabpnn imports nothing from here at run time either; no cycle
    from vehicle_estimation.estimators.state.gabpnn import BPCorrection

__all__ = [
    "AOUKFConfig", "AntiOutlierUKF", "ExtendedKalmanFilter", "OutlierDecision", "ThreeDofModel",
    "UnscentedKalmanFilter", "VehicleStateAOUKF", "FILTER_KINDS", "OBSERVATIONS",
]

#: Observation channels of the vehicle model, in the order of :meth:`ThreeDofModel.measurement`.
OBSERVATIONS = ("ay", "r", "vx_wheels")
#: Filters :class:`VehicleStateAOUKF` can run on the model (paper Table 2 contrasts).
FILTER_KINDS = ("aoukf", "ukf", "ekf")
#: Mean tyre load of the paper's Table-1 car (1522 kg), the load the paper's D refers to [N].
PAPER_REFERENCE_LOAD = 1522.0 * 9.81 / 4.0


def _matrix(value, n: int, name: str) -> np.ndarray:
    m = np.asarray(value, dtype=float)
    if m.ndim == 1:
        m = np.diag(m)
    if m.shape != (n, n):
        raise ValueError(f"{name} must be {n}x{n} (or a length-{n} diagonal), got shape {m.shape}")
    return m


def sqrt_psd(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of ``P``; for a ``P`` that is not positive definite (round-off),
    ``V sqrt(max(w, 1e-12))`` from its symmetric eigen-decomposition."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(0.5 * (P + P.T))
        return v * np.sqrt(np.maximum(w, 1e-12))


# ========================================================================================
class _AdditiveNoiseFilter:
    """State handling shared by :class:`UnscentedKalmanFilter` and
    :class:`ExtendedKalmanFilter`: models ``f``/``h`` on batches of states, additive ``Q``/``R``,
    the mean and covariance (read as copies), and the last prior for the GA-BPNN features."""

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0):
        self._x = np.array(x0, dtype=float).reshape(-1)
        self.n = self._x.size
        self._P = _matrix(P0, self.n, "P0").copy()
        self.Q = _matrix(Q, self.n, "Q")
        self.R = np.atleast_2d(np.diag(R) if np.ndim(R) == 1 else np.asarray(R, dtype=float))
        self.m = self.R.shape[0]
        self.f, self.h = f, h
        self.x_prior = self._x.copy()
        self.P_prior = self._P.copy()
        self.last_innovation: Optional[np.ndarray] = None

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._P.copy()

    def reset(self, x0, P0) -> None:
        self._x = np.array(x0, dtype=float).reshape(self.n)
        self._P = _matrix(P0, self.n, "P0").copy()
        self.x_prior, self.P_prior = self._x.copy(), self._P.copy()


class UnscentedKalmanFilter(_AdditiveNoiseFilter):
    """Generic UKF, additive noise: ``x_k = f(x_k-1, dt, *args) + v``, ``z = h(x, *args) + w``.

    Scaled sigma points ``X_0 = x``, ``X_i = x +- gamma S_i`` (``S S^T = P``,
    ``gamma = sqrt(n + lambda)``, ``lambda = alpha^2 (n + kappa) - n``) with the weights
    ``Wm_0 = lambda / (n + lambda)``, ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``,
    ``Wm_i = Wc_i = 1 / (2 (n + lambda))``.

    Args:
        f: process model, called ONCE per prediction with the ``(2n+1, n)`` sigma points,
            ``dt`` and ``*args``; returns ``(2n+1, n)``.
        h: measurement model, called once with ``(2n+1, n)`` points and ``*args``; returns
            ``(2n+1, m)``.
        Q: process noise per :meth:`predict` (override with ``Q=``); R: measurement noise.
        x0, P0: initial mean and covariance.
        alpha, beta, kappa: sigma-point scaling (defaults 1, 2, 0: points at ``sqrt(n) S``).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, alpha: float = 1.0,
                 beta: float = 2.0, kappa: float = 0.0):
        super().__init__(f, h, Q, R, x0, P0)
        n = self.n
        lam = alpha * alpha * (n + kappa) - n
        if not n + lam > 0.0:
            raise ValueError("alpha, kappa give n + lambda <= 0")
        self.gamma = math.sqrt(n + lam)
        self.Wm = np.full(2 * n + 1, 0.5 / (n + lam))
        self.Wc = self.Wm.copy()
        self.Wm[0] = lam / (n + lam)
        self.Wc[0] = self.Wm[0] + 1.0 - alpha * alpha + beta
        self.last_innovation_covariance: Optional[np.ndarray] = None
        self.last_gain: Optional[np.ndarray] = None

    def sigma_points(self, x: Optional[np.ndarray] = None, P: Optional[np.ndarray] = None) -> np.ndarray:
        """The ``2n + 1`` scaled sigma points as a ``(2n+1, n)`` array."""
        x = self._x if x is None else x
        S = self.gamma * sqrt_psd(self._P if P is None else P)
        return np.concatenate((x[None, :], x + S.T, x - S.T))

    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        """Time update; keeps the prior in :attr:`x_prior`, :attr:`P_prior`."""
        Xp = np.asarray(self.f(self.sigma_points(), dt, *args), dtype=float)
        x = self.Wm @ Xp
        d = Xp - x
        P = (d.T * self.Wc) @ d + (self.Q if Q is None else Q)
        self._x, self._P = x, 0.5 * (P + P.T)
        self.x_prior, self.P_prior = self._x.copy(), self._P.copy()

    def measurement_moments(self, *args, select=None):
        """``(z_hat, P_zz - R, P_xz)`` of ``h`` at the current moments (columns ``select``)."""
        X = self.sigma_points()
        Z = np.asarray(self.h(X, *args), dtype=float)
        if select is not None:
            Z = Z[:, select]
        z_hat = self.Wm @ Z
        dz = Z - z_hat
        dxw = (X - self._x).T * self.Wc
        return z_hat, (dz.T * self.Wc) @ dz, dxw @ dz

    def correct(self, innovation: np.ndarray, Pzz: np.ndarray, Pxz: np.ndarray,
                gain_scale: Optional[np.ndarray] = None) -> np.ndarray:
        """Correction with ``K = Pxz Pzz^-1``, columns scaled by ``gain_scale`` (the paper's
        ``m``); covariance by the update that holds for any gain. Returns the gain used."""
        K = np.linalg.solve(Pzz, Pxz.T).T
        if gain_scale is not None:
            K = K * gain_scale
            KPxz = K @ Pxz.T
            P = self._P - KPxz - KPxz.T + K @ Pzz @ K.T
        else:
            P = self._P - K @ Pzz @ K.T
        self._x = self._x + K @ innovation
        self._P = 0.5 * (P + P.T)
        self.last_gain, self.last_innovation, self.last_innovation_covariance = K, innovation, Pzz
        return K

    def _R(self, R: Optional[np.ndarray], select) -> np.ndarray:
        R = self.R if R is None else np.asarray(R, dtype=float)
        return R if select is None else R[np.ix_(select, select)]

    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> np.ndarray:
        """Plain UKF update with ``z`` (the ``select``-ed components); returns ``z - z_hat``."""
        z = np.asarray(z, dtype=float).reshape(-1)
        z_hat, Pzz0, Pxz = self.measurement_moments(*args, select=select)
        innovation = z - z_hat
        self.correct(innovation, Pzz0 + self._R(R, select), Pxz)
        return innovation


# ========================================================================================
@dataclasses.dataclass
class OutlierDecision:
    """Per-channel outcome of one anti-outlier update (arrays over the selected channels)."""

    innovation: np.ndarray       # e = Z - Z_hat (Eq. 6)
    sigma: np.ndarray            # innovation standard deviation used in Eq. 7
    gain_scale: np.ndarray       # m per channel (1 normal, (0,1) down-weighted, 0 zero gain/replaced)
    flagged: np.ndarray          # Eq. 7 violated
    replaced: np.ndarray         # speckled outlier replaced by the prediction


class AntiOutlierUKF(UnscentedKalmanFilter):
    """UKF with the adaptive anti-outlier measurement update of paper 002 Sec. 3.3.

    Channel bookkeeping (window, run length) is per column of ``h``'s output, so ``select``
    may change from step to step (a channel that is absent is simply not updated).

    Args:
        f, h, Q, R, x0, P0, alpha, beta, kappa: as :class:`UnscentedKalmanFilter`.
        C: the constant of Eq. 7. zero_gain_ratio: ``m = 0`` above ``zero_gain_ratio C sigma``.
        window: number of innovations in the running standard deviation (0 = Eq. 7 with the
            UKF's ``P_zz`` only). speckle_min_run: consecutive flagged samples from which a
            run is speckled. max_run: consecutive flagged samples after which the channel is
            accepted again (0 = never).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, C: float = 3.0,
                 zero_gain_ratio: float = 2.0, window: int = 100, speckle_min_run: int = 2,
                 max_run: int = 50, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        super().__init__(f, h, Q, R, x0, P0, alpha=alpha, beta=beta, kappa=kappa)
        self.C, self.zero_gain_ratio = float(C), float(zero_gain_ratio)
        self.window, self.speckle_min_run, self.max_run = int(window), int(speckle_min_run), int(max_run)
        self.counts = {"isolated_downweighted": 0, "isolated_zero_gain": 0, "speckled_replaced": 0,
                       "resyncs": 0}
        self.reset_statistics()

    def reset_statistics(self) -> None:
        """Forget the innovation windows and the outlier runs (counters are kept)."""
        self._e2 = np.zeros((max(self.window, 1), self.m))      # clipped e^2, ring buffer per channel
        self._e2_next = np.zeros(self.m, dtype=int)
        self._e2_sum = np.zeros(self.m)
        self._e2_count = np.zeros(self.m, dtype=int)
        self.run_length = np.zeros(self.m, dtype=int)
        self.following = np.zeros(self.m, dtype=bool)

    def innovation_sigma(self, Pzz_diag: np.ndarray, select: np.ndarray) -> np.ndarray:
        """``sigma_ii``: max of ``sqrt(P_zz,ii)`` and the running RMS of the channel's window."""
        sigma2 = Pzz_diag
        if self.window > 0:
            count = self._e2_count[select]
            running = np.where(count >= min(10, self.window), self._e2_sum[select] / np.maximum(count, 1), 0.0)
            sigma2 = np.maximum(sigma2, running)
        return np.sqrt(sigma2)

    def _forget(self, channels: np.ndarray) -> None:
        self._e2[:, channels] = 0.0
        self._e2_sum[channels] = 0.0
        self._e2_count[channels] = 0
        self._e2_next[channels] = 0

    def _remember(self, select: np.ndarray, e: np.ndarray, sigma: np.ndarray) -> None:
        if self.window <= 0:
            return
        clipped = np.minimum(np.abs(e), self.C * sigma)
        rows = self._e2_next[select]
        new = clipped * clipped
        # running sum: add the new value, drop the one it overwrites (0 while the ring fills)
        self._e2_sum[select] = np.maximum(self._e2_sum[select] + new - self._e2[rows, select], 0.0)
        self._e2[rows, select] = new
        self._e2_count[select] = np.minimum(self._e2_count[select] + 1, self.window)
        self._e2_next[select] = (rows + 1) % self.window

    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> OutlierDecision:  # type: ignore[override]
        """Anti-outlier update (Sec. 3.3) with ``z`` = the ``select``-ed channels of ``h``.

        1. ``e = Z - Z_hat`` (Eq. 6), ``sigma`` (see :meth:`innovation_sigma`).
        2. Eq. 7 per component; flagged components extend their channel's run.
        3. Isolated (run < ``speckle_min_run``): ``m = C sigma / |e|`` or 0 above
           ``zero_gain_ratio C sigma``. Speckled (longer run): ``Z_i <- Z_hat_i``, ``m = 0``.
           A run beyond ``max_run`` is accepted as a real change (window restarted).
        4. ``K <- K diag(m)``, state and covariance updated with that gain.
        """
        sel = np.arange(self.m) if select is None else np.asarray(select, dtype=int).reshape(-1)
        z = np.asarray(z, dtype=float).reshape(-1)
        z_hat, Pzz0, Pxz = self.measurement_moments(*args, select=sel)
        Pzz = Pzz0 + self._R(R, sel)
        e = z - z_hat
        sigma = self.innovation_sigma(np.diag(Pzz).copy(), sel)
        limit = self.C * sigma
        flagged = np.abs(e) > limit
        # a channel accepted after a long run stays accepted until it passes Eq. 7 again
        following = self.following[sel]
        self.following[sel] = following & flagged
        flagged = flagged & ~following
        runs = np.where(flagged, self.run_length[sel] + 1, 0)
        resync = flagged & (self.max_run > 0) & (runs > self.max_run)
        if np.any(resync):
            self._forget(sel[resync])
            self.counts["resyncs"] += int(resync.sum())
            self.following[sel[resync]] = True
            flagged = flagged & ~resync
            runs = np.where(resync, 0, runs)
        self.run_length[sel] = runs
        replaced = flagged & (runs >= self.speckle_min_run)
        isolated = flagged & ~replaced
        ratio = np.abs(e) / np.maximum(limit, 1e-300)
        m = np.ones(sel.size)
        m[isolated] = np.where(ratio[isolated] > self.zero_gain_ratio, 0.0, 1.0 / np.maximum(ratio[isolated], 1.0))
        m[replaced] = 0.0
        e_used = np.where(replaced, 0.0, e)    # Step 4: the prediction replaces the outlier
        self.counts["isolated_downweighted"] += int(np.sum(isolated & (m > 0.0)))
        self.counts["isolated_zero_gain"] += int(np.sum(isolated & (m == 0.0)))
        self.counts["speckled_replaced"] += int(replaced.sum())
        self.correct(e_used, Pzz, Pxz, gain_scale=None if not flagged.any() else m)
        self._remember(sel, np.where(resync | following, e, e_used), sigma)
        return OutlierDecision(e, sigma, m, flagged, replaced)


# ========================================================================================
class ExtendedKalmanFilter(_AdditiveNoiseFilter):
    """EKF with central-difference Jacobians (the paper's contrast, Table 2).

    ``f``/``h`` follow the calling convention of :class:`UnscentedKalmanFilter` (batches of
    states), so ``F = df/dx`` and ``H = dh/dx`` come from ONE call each on the ``2n + 1``
    points ``x, x +- eps_j e_j``.
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, rel_step: float = 1e-5):
        super().__init__(f, h, Q, R, x0, P0)
        self.rel_step = rel_step

    def _points(self) -> tuple[np.ndarray, np.ndarray]:
        eps = self.rel_step * np.maximum(np.abs(self._x), 1.0)
        D = np.diag(eps)
        return np.concatenate((self._x[None, :], self._x + D, self._x - D)), eps

    def _jacobian(self, Y: np.ndarray, eps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.n
        return Y[0], ((Y[1:n + 1] - Y[n + 1:]) / (2.0 * eps[:, None])).T

    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        X, eps = self._points()
        x, F = self._jacobian(np.asarray(self.f(X, dt, *args), dtype=float), eps)
        P = F @ self._P @ F.T + (self.Q if Q is None else Q)
        self._x, self._P = x, 0.5 * (P + P.T)
        self.x_prior, self.P_prior = self._x.copy(), self._P.copy()

    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> np.ndarray:
        sel = np.arange(self.m) if select is None else np.asarray(select, dtype=int).reshape(-1)
        X, eps = self._points()
        z_hat, H = self._jacobian(np.asarray(self.h(X, *args), dtype=float)[:, sel], eps)
        Rm = self.R if R is None else np.asarray(R, dtype=float)
        S = H @ self._P @ H.T + Rm[np.ix_(sel, sel)]
        PHt = self._P @ H.T
        K = np.linalg.solve(S, PHt.T).T
        innovation = np.asarray(z, dtype=float).reshape(-1) - z_hat
        self._x = self._x + K @ innovation
        IKH = np.eye(self.n) - K @ H
        P = IKH @ self._P @ IKH.T + K @ Rm[np.ix_(sel, sel)] @ K.T    # Joseph form
        self._P = 0.5 * (P + P.T)
        self.last_innovation = innovation
        return innovation


# ========================================================================================
@dataclasses.dataclass(frozen=True)
class AOUKFConfig:
    """Tuning of :class:`VehicleStateAOUKF`. Noise values refer to ``nominal_dt``.

    Attributes:
        filter: ``"aoukf"`` (paper Sec. 3.3), ``"ukf"`` (plain UKF) or ``"ekf"`` (the contrast).
        mf_b: Magic-Formula B of Sec. 2.2 [1/deg] (0.237).
        mf_c: Magic-Formula C of Sec. 2.2 (1.65).
        mf_d: Magic-Formula D of Sec. 2.2 [N per tyre at ``mf_reference_load``] (3610.5).
        mf_e: Magic-Formula E of Sec. 2.2 (0.707).
        mf_reference_load: tyre load [N] at which the tyre has peak ``mf_d``; D scales with
            the Eq.-3 load (default: mean tyre load of the paper's 1522 kg car).
        mf_match_cornering_stiffness: set B per axle so that ``B C D`` equals the vehicle's
            ``cornering_stiffness_front/rear`` (False: the paper's B for both axles).
        q_diag: process noise ``[vx, vy, r]`` per ``nominal_dt`` [(m/s)^2, (m/s)^2, (rad/s)^2].
        r_ay: measurement variance of ay [(m/s^2)^2].
        r_yaw_rate: measurement variance of the yaw rate [(rad/s)^2].
        r_wheel_speed: measurement variance of the wheel-speed vx [(m/s)^2].
        p0_diag: initial covariance diagonal of ``[vx, vy, r]``.
        initial_vx: start speed without wheel speeds [m/s].
        wheel_speed_update: observe vx by the undriven wheels' mean speed x radius
            (extension, see module docstring).
        init_vx_from_wheel_speeds: start vx from the undriven wheels when they report.
        outlier_c: C of Eq. 7 (a component is an outlier when ``|e_i| > C sigma_ii``).
        zero_gain_ratio: the gain factor m is 0 above this multiple of ``C sigma``.
        innovation_window_s: length of the running innovation std [s] (0: ``P_zz`` only).
        speckle_min_run: consecutive outliers from which they are speckled (replaced).
        max_outlier_run_s: a run longer than this is accepted as a real change [s].
        max_abs_accel: |ax| input above this is clipped (an ax spike goes straight into vx)
            [m/s^2].
        ukf_alpha: sigma-point spread alpha.
        ukf_beta: sigma-point prior-distribution weight beta (2: Gaussian).
        ukf_kappa: sigma-point secondary scaling kappa.
        nominal_dt: step the noise values refer to [s]; Q scales with ``dt / nominal_dt``.
        max_gap_s: a stamp gap above this re-initialises [s].
        max_substep: Euler sub-step of Eq. 1 [s].
        min_speed: vx floor in the slip angles [m/s].
    """

    filter: str = "aoukf"
    mf_b: float = 0.237
    mf_c: float = 1.65
    mf_d: float = 3610.5
    mf_e: float = 0.707
    mf_reference_load: float = PAPER_REFERENCE_LOAD
    mf_match_cornering_stiffness: bool = True
    q_diag: tuple[float, float, float] = (2e-4, 2e-4, 1e-5)
    r_ay: float = 0.04
    r_yaw_rate: float = 1e-4
    r_wheel_speed: float = 4e-3
    p0_diag: tuple[float, float, float] = (1.0, 0.25, 0.01)
    initial_vx: float = 0.0
    wheel_speed_update: bool = True
    init_vx_from_wheel_speeds: bool = True
    outlier_c: float = 3.0
    zero_gain_ratio: float = 2.0
    innovation_window_s: float = 1.0
    speckle_min_run: int = 2
    max_outlier_run_s: float = 0.5
    max_abs_accel: float = 15.0
    ukf_alpha: float = 1.0
    ukf_beta: float = 2.0
    ukf_kappa: float = 0.0
    nominal_dt: float = 0.01
    max_gap_s: float = 0.5
    max_substep: float = 0.01
    min_speed: float = 1.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        if self.filter not in FILTER_KINDS:
            raise ValueError(f"filter must be one of {FILTER_KINDS}, got {self.filter!r}")
        for name in ("mf_b", "mf_c", "mf_d", "mf_reference_load", "r_ay", "r_yaw_rate", "r_wheel_speed",
                     "outlier_c", "nominal_dt", "max_gap_s", "max_substep", "min_speed", "max_abs_accel",
                     "ukf_alpha"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite positive number, got {value!r}")
        for name in ("mf_e", "ukf_beta", "ukf_kappa", "initial_vx"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if self.mf_e >= 1.0:
            raise ValueError(f"mf_e must be < 1 (a curvature factor >= 1 folds the curve), got {self.mf_e!r}")
        for name in ("q_diag", "p0_diag"):
            value = tuple(getattr(self, name))
            if len(value) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in value):
                raise ValueError(f"{name} must be 3 finite positive numbers, got {value!r}")
        if not self.zero_gain_ratio >= 1.0 or not math.isfinite(self.zero_gain_ratio):
            raise ValueError(f"zero_gain_ratio must be a finite number >= 1, got {self.zero_gain_ratio!r}")
        for name in ("innovation_window_s", "max_outlier_run_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if isinstance(self.speckle_min_run, bool) or not isinstance(self.speckle_min_run, int) or self.speckle_min_run < 1:
            raise ValueError(f"speckle_min_run must be an integer >= 1, got {self.speckle_min_run!r}")
        for name in ("wheel_speed_update", "init_vx_from_wheel_speeds", "mf_match_cornering_stiffness"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be a bool, got {getattr(self, name)!r}")
        lam = self.ukf_alpha ** 2 * (3 + self.ukf_kappa) - 3
        if not 3 + lam > 0:
            raise ValueError(f"ukf_kappa must give n + lambda > 0, got {self.ukf_kappa!r}")


# ========================================================================================
@dataclasses.dataclass(frozen=True)
class ThreeDofModel:
    """The 3-DOF model of Sec. 2 on batches of states ``X = [vx, vy, r]`` (shape ``(..., 3)``).

    Eq. 1 with ``F_T / m`` = the measured longitudinal acceleration less gravity along the
    slope (the model's input ``u = ax``, Sec. 2.3)::

        vx' = vy r + (ax_imu - g sin(theta))
        vy' = -vx r + 2 (F_yf + F_yr) / m
        r'  = 2 (a F_yf - b F_yr) / I_z

    ``F_y = D sin(C atan(B alpha - E (B alpha - atan(B alpha))))`` per tyre (Sec. 2.2) with
    ``alpha_f = delta - (vy + a r) / vx``, ``alpha_r = (b r - vy) / vx`` and ``D`` from the
    axle load of Eq. 3, ``F_zf = m g b / (a + b)``, ``F_zr = m g a / (a + b)`` (per tyre: half).
    Observation (Sec. 2.3) ``[ay, r]`` with ``ay = 2 (F_yf + F_yr) / m``, plus ``vx`` (the
    wheel-speed extension).
    """

    mass: float
    a: float
    b: float
    yaw_inertia: float
    gravity: float
    B_front: float      # [1/rad]
    B_rear: float
    C: float
    D_front: float      # [N per tyre]
    D_rear: float
    E: float
    min_speed: float
    max_substep: float

    @classmethod
    def from_params(cls, params: VehicleParams, config: AOUKFConfig) -> "ThreeDofModel":
        m, a, b, g = params.mass, params.lf, params.lr, params.gravity
        fz_front = 0.5 * m * g * b / (a + b)      # Eq. 3, per tyre
        fz_rear = 0.5 * m * g * a / (a + b)
        d_front = config.mf_d * fz_front / config.mf_reference_load
        d_rear = config.mf_d * fz_rear / config.mf_reference_load
        if config.mf_match_cornering_stiffness:
            b_front = params.cornering_stiffness_front / (config.mf_c * d_front)
            b_rear = params.cornering_stiffness_rear / (config.mf_c * d_rear)
        else:
            b_front = b_rear = config.mf_b * 180.0 / math.pi
        return cls(m, a, b, params.yaw_inertia, g, b_front, b_rear, config.mf_c, d_front, d_rear,
                   config.mf_e, config.min_speed, config.max_substep)

    def tyre_force(self, alpha, B: float, D: float):
        """Magic Formula (Sec. 2.2), lateral force per tyre [N] for slip angle ``alpha`` [rad]."""
        ba = B * alpha
        return D * np.sin(self.C * np.arctan(ba - self.E * (ba - np.arctan(ba))))

    def lateral_forces(self, X: np.ndarray, delta: float):
        vx = np.maximum(X[..., 0], self.min_speed)
        vy, r = X[..., 1], X[..., 2]
        alpha_f = delta - (vy + self.a * r) / vx
        alpha_r = (self.b * r - vy) / vx
        return self.tyre_force(alpha_f, self.B_front, self.D_front), self.tyre_force(alpha_r, self.B_rear, self.D_rear)

    def derivative(self, X: np.ndarray, ax_kin: float, delta: float) -> np.ndarray:
        """Eq. 1 for a batch of states; ``ax_kin = ax_imu - g sin(theta)`` [m/s^2]."""
        fyf, fyr = self.lateral_forces(X, delta)
        out = np.empty_like(X)
        out[..., 0] = X[..., 1] * X[..., 2] + ax_kin
        out[..., 1] = -X[..., 0] * X[..., 2] + 2.0 * (fyf + fyr) / self.mass
        out[..., 2] = 2.0 * (self.a * fyf - self.b * fyr) / self.yaw_inertia
        return out

    def transition(self, X: np.ndarray, dt: float, ax_kin: float, delta: float) -> np.ndarray:
        """``x_k+1`` by ``ceil(dt / max_substep)`` explicit Euler sub-steps of Eq. 1."""
        X = np.array(X, dtype=float)
        if dt <= 0.0:
            return X
        n = max(1, int(math.ceil(dt / self.max_substep - 1e-9)))
        h = dt / n
        for _ in range(n):
            X = X + h * self.derivative(X, ax_kin, delta)
        return X

    def measurement(self, X: np.ndarray, delta: float) -> np.ndarray:
        """``[ay, r, vx]`` (Sec. 2.3 plus the wheel-speed vx), shape ``(..., 3)``."""
        fyf, fyr = self.lateral_forces(X, delta)
        out = np.empty(X.shape[:-1] + (3,))
        out[..., 0] = 2.0 * (fyf + fyr) / self.mass
        out[..., 1] = X[..., 2]
        out[..., 2] = X[..., 0]
        return out


# ========================================================================================
class VehicleStateAOUKF:
    """Vehicle state ``[vx, vy, r]`` by the anti-outlier UKF (+ GA-BPNN) of paper 002.

    API of :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateCKF`: one :meth:`step` per IMU
    sample with ``z = [ax, ay, r]`` (bias-compensated IMU in base_link); ``ax`` is the model's
    input, ``[ay, r]`` the observation; ``inputs`` carries the road-wheel steer angle, the wheel
    speeds (vx observation), the slope (removes gravity from ``ax``) and the mass (model mass;
    ``None``: ``VehicleParams.mass``).

    With a ``correction`` (:class:`~vehicle_estimation.estimators.state.gabpnn.BPCorrection`) :attr:`x`
    is the corrected output of Eq. 5, ``X' = X_k|k + B_perr``; the filter itself never sees
    the correction (:attr:`x_filter` is the UKF estimate).
    """

    def __init__(self, params: VehicleParams, config: Optional[AOUKFConfig] = None,
                 correction: Optional["BPCorrection"] = None):
        params.validate()
        self.params = params
        self.config = AOUKFConfig() if config is None else config
        self.config.validate()
        self.correction = correction
        cfg = self.config
        self.model = ThreeDofModel.from_params(params, cfg)
        self._models: dict[float, ThreeDofModel] = {params.mass: self.model}
        # An all-wheel drive has no undriven axle: the rear wheels stand in (less drive slip).
        self._undriven = [2, 3] if params.driven_axle == "all" else list(params.undriven_wheels)
        self._Q = np.diag(np.asarray(cfg.q_diag, dtype=float))
        R = np.diag([cfg.r_ay, cfg.r_yaw_rate, cfg.r_wheel_speed])
        x0 = self._x0(None)
        f, h = self._f, self._h
        self._filter: Any
        if cfg.filter == "ekf":
            self._filter = ExtendedKalmanFilter(f, h, self._Q, R, x0, np.diag(cfg.p0_diag))
        elif cfg.filter == "ukf":
            self._filter = UnscentedKalmanFilter(f, h, self._Q, R, x0, np.diag(cfg.p0_diag), alpha=cfg.ukf_alpha,
                                                 beta=cfg.ukf_beta, kappa=cfg.ukf_kappa)
        else:
            window = int(round(cfg.innovation_window_s / cfg.nominal_dt))
            max_run = int(round(cfg.max_outlier_run_s / cfg.nominal_dt))
            self._filter = AntiOutlierUKF(f, h, self._Q, R, x0, np.diag(cfg.p0_diag), C=cfg.outlier_c,
                                          zero_gain_ratio=cfg.zero_gain_ratio, window=window,
                                          speckle_min_run=cfg.speckle_min_run, max_run=max_run,
                                          alpha=cfg.ukf_alpha, beta=cfg.ukf_beta, kappa=cfg.ukf_kappa)
        self.t: Optional[float] = None
        self.initialised = False
        self.rejected = {"nonfinite_measurement": 0, "invalid_input": 0, "stamp_not_increasing": 0,
                         "accel_clipped": 0}
        self.reinitialisations = 0
        self.last_event = ""
        self.updates = 0
        self.speed_updates = 0
        self._ax = 0.0
        self._correction_output = np.zeros(3)
        self.last_decision: Optional[OutlierDecision] = None
        #: Extra process noise on vx [(m/s^2)^2 s] (as ``VehicleStateCKF.extra_vx_noise_density``).
        self.extra_vx_noise_density = 0.0

    # -- model closures ------------------------------------------------------------------
    def _model_for(self, mass: Optional[float]) -> ThreeDofModel:
        key = self.params.mass if mass is None else float(mass)
        model = self._models.get(key)
        if model is None:
            if len(self._models) > 16:
                self._models.clear()
            model = ThreeDofModel.from_params(self.params.with_mass(key), self.config)
            self._models[key] = model
        return model

    def _f(self, X, dt, model: ThreeDofModel, ax_kin: float, delta: float):
        return model.transition(X, dt, ax_kin, delta)

    def _h(self, X, model: ThreeDofModel, delta: float):
        return model.measurement(X, delta)

    # -- helpers -------------------------------------------------------------------------
    def _x0(self, vx0: Optional[float]) -> np.ndarray:
        return np.array([self.config.initial_vx if vx0 is None else float(vx0), 0.0, 0.0])

    def _vx_from_wheels(self, inputs: VehicleInputs) -> Optional[float]:
        ws = inputs.wheel_speeds[self._undriven]
        if np.all(np.isfinite(ws)):
            return float(np.mean(ws) * self.params.wheel_radius)
        return None

    def reset(self, vx0: Optional[float] = None) -> None:
        """Back to ``[vx0, 0, 0]`` (``vx0`` default ``initial_vx``), ``P0``; forget the stamp,
        the outlier windows and the correction's feature history."""
        self._filter.reset(self._x0(vx0), np.diag(self.config.p0_diag))
        if isinstance(self._filter, AntiOutlierUKF):
            self._filter.reset_statistics()
        if self.correction is not None:
            self.correction.reset()
        self._correction_output = np.zeros(3)
        self.t = None
        self.initialised = False

    # -- main entry ----------------------------------------------------------------------
    def step(self, t: float, inputs: VehicleInputs, z) -> bool:
        """Predict to ``t`` with ``ax = z[0]`` and update with ``[ay, r] = z[1:]`` (+ wheels).

        Returns True if a measurement update was applied. Rejected (nothing changes, counted
        in :attr:`rejected`): non-finite ``t``, invalid ``inputs``, ``z`` not 3 values, stamp
        not increasing. A non-finite ``ax`` predicts with the last valid one; a non-finite
        ``ay``/``r`` is left out of the update (both non-finite and no wheels: no update). An
        ``|ax|`` above ``max_abs_accel`` is clipped. A gap above ``max_gap_s`` re-initialises.
        """
        try:
            t = float(t)
            z = np.asarray(z, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            self.rejected["invalid_input"] += 1
            self.last_event = "invalid input"
            return False
        if not math.isfinite(t) or not isinstance(inputs, VehicleInputs) or not inputs.is_valid() or z.shape != (3,):
            self.rejected["invalid_input"] += 1
            self.last_event = "invalid input"
            return False
        if self.t is not None and t <= self.t:
            self.rejected["stamp_not_increasing"] += 1
            self.last_event = f"stamp not increasing ({t:.6f} <= {self.t:.6f})"
            return False
        cfg = self.config
        if self.t is not None and t - self.t > cfg.max_gap_s:
            gap = t - self.t
            vx_now = float(self._filter.x[0])
            vx0 = self._vx_from_wheels(inputs) if cfg.init_vx_from_wheel_speeds else None
            self.reset(vx0 if vx0 is not None else (vx_now if math.isfinite(vx_now) else None))
            self.reinitialisations += 1
            self.last_event = f"re-initialised after a {gap:.3f} s gap"
        if math.isfinite(z[0]):
            ax = float(z[0])
            if abs(ax) > cfg.max_abs_accel:
                ax = math.copysign(cfg.max_abs_accel, ax)
                self.rejected["accel_clipped"] += 1
            self._ax = ax
        model = self._model_for(inputs.mass)
        delta = float(inputs.steer_angle)
        if not self.initialised:
            vx0 = self._vx_from_wheels(inputs) if cfg.init_vx_from_wheel_speeds else None
            self._filter.reset(self._x0(vx0), np.diag(cfg.p0_diag))
            self.initialised = True
        else:
            assert self.t is not None   # initialised implies a stamp
            dt = t - self.t
            ax_kin = self._ax - self.params.gravity * math.sin(float(inputs.slope))
            Q = self._Q * (dt / cfg.nominal_dt)
            if self.extra_vx_noise_density > 0.0:
                Q[0, 0] += self.extra_vx_noise_density * dt
            self._filter.predict(dt, model, ax_kin, delta, Q=Q)
        self.t = t
        x_prior = self._filter.x
        obs = np.array([z[1], z[2], np.nan])
        if cfg.wheel_speed_update:
            vx_wheels = self._vx_from_wheels(inputs)
            if vx_wheels is not None:
                obs[2] = vx_wheels
        select = np.nonzero(np.isfinite(obs))[0]
        if not np.all(np.isfinite(z)):
            self.rejected["nonfinite_measurement"] += 1
            self.last_event = "non-finite measurement"
        if select.size == 0:
            if self._reinitialised_after_failure(inputs):
                return False
            self._after_update(x_prior, t)
            return False
        with np.errstate(all="ignore"):
            try:
                result = self._filter.update(obs[select], model, delta, select=select)
            except np.linalg.LinAlgError:
                result = None
        if result is None:
            self._filter._x[:] = np.nan        # handled as a numerical failure below
        if self._reinitialised_after_failure(inputs):
            return False
        self.last_decision = result if isinstance(result, OutlierDecision) else None
        self.updates += 1
        self._after_update(x_prior, t)
        return True

    def _reinitialised_after_failure(self, inputs: VehicleInputs) -> bool:
        """Re-initialise (and count it) when the mean is not finite or the covariance is no
        longer positive definite (absurd inputs, rounding); True if it did."""
        if valid_moments(self._filter._x, self._filter._P):
            return False
        self.reset(self._vx_from_wheels(inputs) if self.config.init_vx_from_wheel_speeds else None)
        self.reinitialisations += 1
        self.last_event = "re-initialised after numerical failure"
        return True

    def _after_update(self, x_prior: np.ndarray, t: float) -> None:
        if self.correction is None:
            return
        out = self.correction.step(t, self._filter.x - x_prior)
        self._correction_output = out if np.all(np.isfinite(out)) else np.zeros(3)

    def update_speed(self, vx: float, variance: float) -> bool:
        """Linear update with a measured ``vx`` [m/s] (e.g. the vehicle speed on the bus when
        there are no wheel speeds); as :meth:`VehicleStateCKF.update_speed`."""
        vx, variance = float(vx), float(variance)
        if not (self.initialised and math.isfinite(vx) and math.isfinite(variance) and variance > 0.0):
            return False
        f = self._filter
        P = f._P
        K = P[:, 0] / (P[0, 0] + variance)
        f._x = f._x + K * (vx - f._x[0])
        P = P - np.outer(K, P[0, :])
        f._P = 0.5 * (P + P.T)
        self.speed_updates += 1
        return True

    # -- outputs -------------------------------------------------------------------------
    @property
    def filter(self):
        return self._filter

    @property
    def x_filter(self) -> np.ndarray:
        """The UKF/EKF estimate ``X_k|k`` (no GA-BPNN correction)."""
        return self._filter.x

    @property
    def correction_output(self) -> np.ndarray:
        """The last ``B_perr`` of Eq. 5 (zeros without a correction)."""
        return self._correction_output.copy()

    @property
    def x(self) -> np.ndarray:
        """``[vx, vy, r]``: ``X_k|k + B_perr`` (Eq. 5) with a correction, else ``X_k|k``."""
        return self._filter.x + self._correction_output

    @property
    def P(self) -> np.ndarray:
        return self._filter.P

    @property
    def sideslip(self) -> float:
        """``beta = arctan(vy / vx)`` [rad] of :attr:`x`; 0 below 1 mm/s."""
        x = self.x
        return 0.0 if abs(x[0]) < 1e-3 else math.atan(x[1] / x[0])

    @property
    def sideslip_variance(self) -> float:
        """First-order variance of ``beta`` from the ``(vx, vy)`` block of ``P`` [rad^2]."""
        x, P = self.x, self._filter._P
        s = x[0] * x[0] + x[1] * x[1]
        if s < 1e-6:
            return float("inf")
        J = np.array([-x[1] / s, x[0] / s])
        return float(J @ P[:2, :2] @ J)

    @property
    def outlier_counts(self) -> dict[str, int]:
        """Anti-outlier counters: isolated_downweighted, isolated_zero_gain, speckled_replaced,
        resyncs (all zero for the plain UKF/EKF)."""
        if isinstance(self._filter, AntiOutlierUKF):
            return dict(self._filter.counts)
        return {"isolated_downweighted": 0, "isolated_zero_gain": 0, "speckled_replaced": 0, "resyncs": 0}

    @property
    def counters(self) -> dict[str, int]:
        """Everything a diagnostics message needs: outliers, rejected inputs, updates."""
        out = {**self.outlier_counts, **{f"rejected_{k}": v for k, v in self.rejected.items()}}
        out.update(updates=self.updates, reinitialisations=self.reinitialisations,
                   speed_updates=self.speed_updates)
        return out
