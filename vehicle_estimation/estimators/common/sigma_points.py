"""Sigma-point Kalman filtering: point sets, and one filter that propagates them.

The cubature Kalman filter of paper 004 (Sec. 4) and the unscented Kalman filter of paper 002
(Sec. 3.3) differ only in where they place the points around ``N(x, P)`` and how they weight
them; the time update, the measurement moments and the correction are the same. As in
filterpy, the point set is an object of its own and the filter takes one:

* :class:`CubaturePoints`: the third-degree spherical-radial rule (Arasaratnam & Haykin
  2009), ``2n`` equally weighted points ``X_i = x + S xi_i``, ``S S^T = P``,
  ``xi = sqrt(n) [I, -I]``;
* :class:`UnscentedPoints`: Julier's scaled set, ``X_0 = x``, ``X_i = x +- gamma S_i`` with
  ``gamma = sqrt(n + lambda)``, ``lambda = alpha^2 (n + kappa) - n``, and the weights
  ``Wm_0 = lambda / (n + lambda)``, ``Wc_0 = Wm_0 + 1 - alpha^2 + beta``,
  ``Wm_i = Wc_i = 1 / (2 (n + lambda))``.

:class:`SigmaPointKalmanFilter` passes all points through the models in ONE call (an
``(N, n)`` array in, ``(N, .)`` out) and splits the measurement update into
:meth:`~SigmaPointKalmanFilter.measurement_moments` (the moments without ``R``) and
:meth:`~SigmaPointKalmanFilter.correct` (gain and correction for a given ``P_zz``), so that a
subclass can replace :meth:`~SigmaPointKalmanFilter.update` (the variational iterations of
the VB-ACKF, the anti-outlier gain scaling of the AO-UKF) without touching the rest.

Also here, the matrix helpers every filter of the package uses: :func:`as_matrix`,
:func:`sqrt_psd`, :func:`is_positive_definite`, :func:`valid_moments`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any, Callable, Optional, Protocol

import numpy as np

__all__ = [
    "AdditiveNoiseFilter", "CubaturePoints", "PointSet", "SigmaPointKalmanFilter", "UnscentedPoints",
    "as_matrix", "is_positive_definite", "sqrt_psd", "valid_moments",
]


def as_matrix(value, n: int, name: str) -> np.ndarray:
    """``value`` as an ``n x n`` float matrix; a length-``n`` vector is its diagonal."""
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


def is_positive_definite(M: np.ndarray) -> bool:
    """Finite and Cholesky-factorisable."""
    if not np.isfinite(M).all():
        return False
    try:
        np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return False
    return True


def valid_moments(x: np.ndarray, P: np.ndarray) -> bool:
    """Finite mean and positive-definite covariance. Absurd inputs (a model driven at
    thousands of m/s) can leave a finite P that rounding has made indefinite (negative
    variances) or make a factorisation fail: a numerical failure like a NaN."""
    return bool(np.isfinite(x).all()) and is_positive_definite(P)


# ----------------------------------------------------------------------------------------
class PointSet(Protocol):
    """Where the points of ``N(x, P)`` lie and how their images are averaged."""

    def points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The points as an ``(N, n)`` array."""

    def mean(self, Y: np.ndarray) -> np.ndarray:
        """Weighted mean of the images ``Y`` (``(N, k)``)."""

    def covariance(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """Weighted ``sum_i w_i A_i B_i^T`` of deviations ``A`` (``(N, a)``), ``B`` (``(N, b)``)."""


class CubaturePoints:
    """Spherical-radial cubature rule: ``2n`` points ``x + S xi_i``, weight ``1 / (2n)`` each."""

    def __init__(self, n: int):
        self.n = n
        self.xi = math.sqrt(n) * np.concatenate((np.eye(n), -np.eye(n)), axis=1)
        self.weight = 1.0 / (2 * n)

    def points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        return x + (sqrt_psd(P) @ self.xi).T

    def mean(self, Y: np.ndarray) -> np.ndarray:
        return Y.mean(axis=0)

    def covariance(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return self.weight * (A.T @ B)


class UnscentedPoints:
    """Scaled unscented set: ``2n + 1`` points with Julier's ``alpha``, ``beta``, ``kappa``
    (defaults 1, 2, 0: points at ``sqrt(n) S``)."""

    def __init__(self, n: int, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0):
        lam = alpha * alpha * (n + kappa) - n
        if not n + lam > 0.0:
            raise ValueError("alpha, kappa give n + lambda <= 0")
        self.n = n
        self.gamma = math.sqrt(n + lam)
        self.Wm = np.full(2 * n + 1, 0.5 / (n + lam))
        self.Wc = self.Wm.copy()
        self.Wm[0] = lam / (n + lam)
        self.Wc[0] = self.Wm[0] + 1.0 - alpha * alpha + beta

    def points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        S = self.gamma * sqrt_psd(P)
        return np.concatenate((x[None, :], x + S.T, x - S.T))

    def mean(self, Y: np.ndarray) -> np.ndarray:
        return self.Wm @ Y

    def covariance(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        return (A.T * self.Wc) @ B


# ----------------------------------------------------------------------------------------
class AdditiveNoiseFilter(ABC):
    """State of a filter on ``x_k = f(x_k-1, dt, *args) + v``, ``z = h(x, *args) + w``:
    the models, additive ``Q``/``R``, the mean and covariance (read as copies) and the last
    prior (:attr:`x_prior`, :attr:`P_prior`: the GA-BPNN features of paper 002 use it)."""

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0):
        self._x = np.array(x0, dtype=float).reshape(-1)
        self.n = self._x.size
        self._P = as_matrix(P0, self.n, "P0").copy()
        self.Q = as_matrix(Q, self.n, "Q")
        R = np.asarray(R, dtype=float)
        self.R = np.atleast_2d(np.diag(R) if R.ndim == 1 else R)
        self.m = self.R.shape[0]
        self.f, self.h = f, h
        self.x_prior = self._x.copy()
        self.P_prior = self._P.copy()
        self.last_innovation: Optional[np.ndarray] = None
        #: A measurement noise the caller knows and that changes with time (an input's own
        #: uncertainty, e.g. the attitude a measurement was compensated with): added to ``R``
        #: (or to a learnt ``R``) at every update while set; None = nothing added.
        self.known_noise: Optional[np.ndarray] = None

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._P.copy()

    def reset(self, x0, P0) -> None:
        self._x = np.array(x0, dtype=float).reshape(self.n)
        self._P = as_matrix(P0, self.n, "P0").copy()
        self.x_prior, self.P_prior = self._x.copy(), self._P.copy()

    @abstractmethod
    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        """Time update over ``dt`` with ``f(x, dt, *args)`` and ``Q`` (default: :attr:`Q`)."""

    @abstractmethod
    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> Any:
        """Measurement update with ``z``, the ``select``-ed channels of ``h(x, *args)``."""

    def _noise(self, R: Optional[np.ndarray], select) -> np.ndarray:
        """``R`` (default: :attr:`R`) plus :attr:`known_noise`, restricted to the ``select``-ed
        channels."""
        R = self.R if R is None else np.asarray(R, dtype=float)
        if self.known_noise is not None:
            R = R + self.known_noise
        return R if select is None else R[np.ix_(select, select)]


class SigmaPointKalmanFilter(AdditiveNoiseFilter):
    """Additive-noise sigma-point Kalman filter on a :class:`PointSet`.

    Args:
        f: process model. With ``vectorized=True`` (default) it is called ONCE per prediction
            with the ``(N, n)`` array of points, ``dt`` and ``*args`` and returns ``(N, n)``;
            otherwise it is called per point with ``(n,)``.
        h: measurement model, same calling convention, returning ``(N, m)`` / ``(m,)``.
        Q: process-noise covariance added per :meth:`predict` (override with ``Q=``).
        R: measurement-noise covariance (``m x m``, or its diagonal).
        x0, P0: initial mean and covariance.
        points: the point set (:class:`CubaturePoints`, :class:`UnscentedPoints`).
        h_affine: optional ``h_affine(*args) -> (H, c)`` for a measurement that is affine in the
            state, ``h(x, *args) = H x + c``. The point rule is exact for it, so the moments
            are taken in closed form (``H x + c``, ``H P H^T``, ``P H^T``) without points: the
            same numbers to rounding, at a fraction of the cost. ``h`` stays the definition
            (tests compare both).
    """

    def __init__(self, f: Callable, h: Callable, Q, R, x0, P0, points: PointSet, *,
                 vectorized: bool = True, h_affine: Optional[Callable] = None):
        super().__init__(f, h, Q, R, x0, P0)
        self.points = points
        self.vectorized = vectorized
        self.h_affine = h_affine
        # Optional compiled steps, the same rules on the same model: the time update
        # ``(x, P, Q, dt, *args) -> (x, P)`` and, for an affine ``h``, the update
        # ``(z, x, P, H, c, R) -> (x, P, K, innovation, P_zz)``; None where they return None.
        # ``compiled_scalar_correct``: :meth:`correct_scalar`'s update
        # (``small_linalg.scalar_correct``).
        self.compiled_predict: Optional[Callable] = None
        self.compiled_update: Optional[Callable] = None
        self.compiled_scalar_correct: Optional[Callable] = None
        self.last_innovation_covariance: Optional[np.ndarray] = None
        self.last_gain: Optional[np.ndarray] = None

    def sigma_points(self, x: Optional[np.ndarray] = None, P: Optional[np.ndarray] = None) -> np.ndarray:
        """The points of ``N(x, P)`` (default: the current moments) as an ``(N, n)`` array."""
        return self.points.points(self._x if x is None else x, self._P if P is None else P)

    def _apply(self, fun: Callable, X: np.ndarray, *args) -> np.ndarray:
        if self.vectorized:
            return np.asarray(fun(X, *args), dtype=float)
        return np.array([np.asarray(fun(xi, *args), dtype=float) for xi in X])

    # -- time update ---------------------------------------------------------------------
    def predict(self, dt: float, *args, Q: Optional[np.ndarray] = None) -> None:
        """Time update through ``f(X, dt, *args)``; keeps the prior in :attr:`x_prior`, :attr:`P_prior`."""
        Q = self.Q if Q is None else Q
        moments = None if self.compiled_predict is None else self.compiled_predict(self._x, self._P, Q, dt, *args)
        if moments is not None:
            self._x, self._P = moments
        else:
            Xp = self._apply(self.f, self.sigma_points(), dt, *args)
            x = self.points.mean(Xp)
            d = Xp - x
            P = self.points.covariance(d, d) + Q
            self._x, self._P = x, 0.5 * (P + P.T)
        self.x_prior, self.P_prior = self._x.copy(), self._P.copy()

    # -- measurement update --------------------------------------------------------------
    def measurement_moments(self, *args, x: Optional[np.ndarray] = None, P: Optional[np.ndarray] = None,
                            select=None):
        """``(z_hat, P_zz - R, P_xz)`` of ``h`` at ``(x, P)`` (default: current), for the
        columns ``select`` of ``h``'s output (default: all)."""
        x = self._x if x is None else x
        if self.h_affine is not None:
            H, c = self.h_affine(*args)
            if select is not None:
                H, c = H[select], c[select]
            Pxz = (self._P if P is None else P) @ H.T
            Czz = H @ Pxz
            return H @ x + c, 0.5 * (Czz + Czz.T), Pxz
        X = self.sigma_points(x, P)
        Z = self._apply(self.h, X, *args)
        if select is not None:
            Z = Z[:, select]
        z_hat = self.points.mean(Z)
        dz = Z - z_hat
        return z_hat, self.points.covariance(dz, dz), self.points.covariance(X - x, dz)

    def correct(self, innovation: np.ndarray, Pzz: np.ndarray, Pxz: np.ndarray,
                gain_scale: Optional[np.ndarray] = None) -> np.ndarray:
        """Kalman correction with ``K = P_xz P_zz^-1`` (``P_zz`` including ``R``), its columns
        scaled by ``gain_scale`` if given; the covariance then by the update that holds for
        any gain (``P - K P_xz^T - P_xz K^T + K P_zz K^T``), so a down-weighted or zeroed
        gain column never over-shrinks ``P``. Returns the gain used."""
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

    def correct_scalar(self, H: np.ndarray, value: float, variance: float) -> None:
        """The exact Kalman update with one linear measurement ``value = H x + noise`` of
        ``variance`` (:meth:`correct` with a 1 x 1 ``P_zz``)."""
        if self.compiled_scalar_correct is not None:
            x, P, K = np.empty_like(self._x), np.empty_like(self._P), np.empty_like(self._x)
            innovation, s = self.compiled_scalar_correct(self._x, self._P, H, value, variance, x, P, K)
            self._x, self._P = x, P
            self.last_gain, self.last_innovation = K[:, None], np.array([innovation])
            self.last_innovation_covariance = np.array([[s]])
            return
        PHt = self._P @ H
        self.correct(np.array([value - H @ self._x]), np.array([[H @ PHt + variance]]), PHt[:, None])

    def update(self, z, *args, R: Optional[np.ndarray] = None, select=None) -> np.ndarray:
        """Measurement update with ``z`` (the ``select``-ed channels); returns ``z - z_hat``."""
        z = np.asarray(z, dtype=float).reshape(self.m if select is None else -1)
        if self.compiled_update is not None and self.h_affine is not None and select is None:
            result = self.compiled_update(z, self._x, self._P, *self.h_affine(*args), self._noise(R, None))
            if result is not None:
                self._x, self._P, K, innovation, Pzz = result
                self.last_gain, self.last_innovation, self.last_innovation_covariance = K, innovation, Pzz
                return innovation
        z_hat, Pzz0, Pxz = self.measurement_moments(*args, select=select)
        innovation = z - z_hat
        self.correct(innovation, Pzz0 + self._noise(R, select), Pxz)
        return innovation

    def normalised_innovation_squared(self) -> float:
        """NIS of the last update, ``nu^T P_zz^-1 nu`` (chi-square with m dof if consistent)."""
        nu, S = self.last_innovation, self.last_innovation_covariance
        if nu is None or S is None:   # set together by correct()
            return float("nan")
        return float(nu @ np.linalg.solve(S, nu))
