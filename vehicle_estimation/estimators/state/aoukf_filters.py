"""The filters paper 002 runs on its 3-DOF model: UKF, anti-outlier UKF, EKF.

Liu, Cui, Peng 2023, "Vehicle state and parameter estimation based on adaptive anti-outlier
unscented Kalman filter and GA-BPNN method", J. Vibroengineering, doi 10.21595/jve.2023.23441.

* :class:`UnscentedKalmanFilter`: the sigma-point filter of
  :mod:`vehicle_estimation.estimators.common.sigma_points` on the scaled unscented set
  (Julier's ``alpha, beta, kappa``); all ``2n + 1`` points go through ``f`` and ``h`` in ONE
  vectorised call.
* :class:`AntiOutlierUKF`: the UKF with the anti-outlier measurement update of Sec. 3.3
  (innovation Eq. 6, per-component test ``|e_i| <= C sigma_ii`` Eq. 7, gain scaling
  ``K <- m K`` for isolated outliers, replacement of speckled outliers by the prediction,
  Steps 1-5), see :meth:`AntiOutlierUKF.update`. The choices where the paper is not
  explicit are listed in :mod:`.aoukf`.
* :class:`ExtendedKalmanFilter`: the EKF the paper contrasts (Table 2), same model, Jacobians
  by central differences evaluated in one vectorised call.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import numpy as np

from vehicle_estimation.estimators.common.sigma_points import (
    AdditiveNoiseFilter,
    SigmaPointKalmanFilter,
    UnscentedPoints,
)

__all__ = ["AntiOutlierUKF", "ExtendedKalmanFilter", "OutlierDecision", "UnscentedKalmanFilter"]


class UnscentedKalmanFilter(SigmaPointKalmanFilter):
    """Generic UKF, additive noise: ``x_k = f(x_k-1, dt, *args) + v``, ``z = h(x, *args) + w``.

    Args:
        f: process model, called ONCE per prediction with the ``(2n+1, n)`` sigma points,
            ``dt`` and ``*args``; returns ``(2n+1, n)``.
        h: measurement model, called once with ``(2n+1, n)`` points and ``*args``; returns
            ``(2n+1, m)``.
        Q: process noise per :meth:`predict` (override with ``Q=``); R: measurement noise.
        x0, P0: initial mean and covariance.
        alpha, beta, kappa: sigma-point scaling (:class:`UnscentedPoints`; defaults 1, 2, 0:
            points at ``sqrt(n) S``).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, *, alpha: float = 1.0,
                 beta: float = 2.0, kappa: float = 0.0):
        super().__init__(f, h, Q, R, x0, P0, UnscentedPoints(np.size(x0), alpha, beta, kappa))


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

    def reset(self, x0, P0) -> None:
        """New moments; the innovation windows and the outlier runs are forgotten too."""
        super().reset(x0, P0)
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
        Pzz = Pzz0 + self._noise(R, sel)
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
class ExtendedKalmanFilter(AdditiveNoiseFilter):
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
        R_sel = self._noise(R, sel)
        S = H @ self._P @ H.T + R_sel
        PHt = self._P @ H.T
        K = np.linalg.solve(S, PHt.T).T
        innovation = np.asarray(z, dtype=float).reshape(-1) - z_hat
        self._x = self._x + K @ innovation
        IKH = np.eye(self.n) - K @ H
        P = IKH @ self._P @ IKH.T + K @ R_sel @ K.T    # Joseph form
        self._P = 0.5 * (P + P.T)
        self.last_innovation = innovation
        return innovation
