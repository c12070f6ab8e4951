"""Compiled linear algebra on the small matrices of the filters (n <= 20), as loops over scalars.

LAPACK through numpy costs microseconds of dispatch per call on a 3x3 or 5x5 matrix, more than
the arithmetic; these kernels do the same work inline in other kernels. The numpy calls they
stand for (``np.linalg.cholesky``, ``solve``, :func:`sigma_points.valid_moments`) are their test
oracles (``test_model_kernels``).
"""

from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.estimators.common.compiled import kernel

__all__ = ["affine_moments", "all_finite", "cholesky_lower", "cholesky_solve_rows", "kalman_correct",
           "scalar_correct", "times_transpose", "valid_moments"]


@kernel
def cholesky_lower(P, L):
    """``L L^T = P`` (``L`` lower, written in place); False where ``P`` is not positive
    definite or not finite (the upper triangle of ``P`` is not read)."""
    n = P.shape[0]
    for i in range(n):
        for k in range(i + 1):
            s = P[i, k]
            for m in range(k):
                s -= L[i, m] * L[k, m]
            if i == k:
                if not s > 0.0:   # also False for NaN
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, k] = s / L[k, k]
        for k in range(i + 1, n):
            L[i, k] = 0.0
    return True


@kernel
def cholesky_solve_rows(L, B, X):
    """``X = B S^-1`` for ``S = L L^T`` symmetric (each row ``b`` of ``B`` gives ``S^-1 b``):
    the gain ``K = P_xz P_zz^-1`` from the factor of ``P_zz``."""
    m = L.shape[0]
    for r in range(B.shape[0]):
        for i in range(m):            # forward: L y = b
            s = B[r, i]
            for k in range(i):
                s -= L[i, k] * X[r, k]
            X[r, i] = s / L[i, i]
        for i in range(m - 1, -1, -1):  # backward: L^T x = y
            s = X[r, i]
            for k in range(i + 1, m):
                s -= L[k, i] * X[r, k]
            X[r, i] = s / L[i, i]


@kernel
def valid_moments(x, P, work):
    """Finite mean and a finite, Cholesky-factorisable covariance (``work``: an ``n x n``
    scratch matrix)."""
    return all_finite(x, P) and cholesky_lower(P, work)


@kernel
def all_finite(x, P):
    """Every entry of the vector ``x`` and the matrix ``P`` finite."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return False
    for i in range(P.shape[0]):
        for k in range(P.shape[1]):
            if not math.isfinite(P[i, k]):
                return False
    return True


@kernel
def times_transpose(A, B, out):
    """``out = A B^T``."""
    for i in range(A.shape[0]):
        for a in range(B.shape[0]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[a, k]
            out[i, a] = s


@kernel
def affine_moments(z, x, P, H, c, innovation, Pxz, Czz):
    """The moments of ``h = H x + c`` at ``N(x, P)``: ``P_xz = P H^T``, ``C_zz = H P H^T``
    (symmetrised) and the innovation ``z - H x - c``; False where any is not finite."""
    n, m = x.shape[0], z.shape[0]
    times_transpose(P, H, Pxz)
    finite = True
    for a in range(m):
        zh = c[a]
        for k in range(n):
            zh += H[a, k] * x[k]
        innovation[a] = z[a] - zh
        finite = finite and math.isfinite(innovation[a])
        for b in range(m):
            s = 0.0
            for k in range(n):
                s += H[a, k] * Pxz[k, b]
            Czz[a, b] = s
    for a in range(m):
        for b in range(a, m):
            v = 0.5 * (Czz[a, b] + Czz[b, a])
            Czz[a, b] = v
            Czz[b, a] = v
            finite = finite and math.isfinite(v)
        for i in range(n):
            finite = finite and math.isfinite(Pxz[i, a])
    return finite


@kernel
def kalman_correct(x_pred, P_pred, K, Pzz, innovation, x_out, P_out):
    """``x_out = x + K nu`` and ``P_out = P - K P_zz K^T`` (symmetric by construction)."""
    n, m = K.shape[0], K.shape[1]
    KPzz = np.empty((n, m))
    for i in range(n):
        for b in range(m):
            s = 0.0
            for a in range(m):
                s += K[i, a] * Pzz[a, b]
            KPzz[i, b] = s
    for i in range(n):
        s = x_pred[i]
        for a in range(m):
            s += K[i, a] * innovation[a]
        x_out[i] = s
        for j in range(i, n):
            kpk = 0.0
            for a in range(m):
                kpk += KPzz[i, a] * K[j, a]
            P_out[i, j] = P_pred[i, j] - kpk
            P_out[j, i] = P_out[i, j]


@kernel
def scalar_correct(x, P, H, value, variance, x_out, P_out, K_out):
    """The exact Kalman update with one measurement ``value = H x + noise`` of ``variance``:
    ``K = P H^T / s`` with ``s = H P H^T + variance``, ``x_out = x + K (value - H x)``,
    ``P_out = P - K s K^T`` (symmetric by construction). Returns ``(innovation, s)``.
    The numpy update it stands for: :meth:`SigmaPointKalmanFilter.correct` with a 1 x 1 ``P_zz``."""
    n = x.shape[0]
    s = variance
    predicted = 0.0
    for i in range(n):
        pht = 0.0
        for j in range(n):
            pht += P[i, j] * H[j]
        K_out[i] = pht
        s += H[i] * pht
        predicted += H[i] * x[i]
    innovation = value - predicted
    for i in range(n):
        K_out[i] = K_out[i] / s
    for i in range(n):
        x_out[i] = x[i] + K_out[i] * innovation
        for j in range(i, n):
            P_out[i, j] = P[i, j] - K_out[i] * s * K_out[j]
            P_out[j, i] = P_out[i, j]
    return innovation, s
