"""Compiled linear algebra on the small matrices of the filters (n <= 20), as loops over scalars.

LAPACK through numpy costs microseconds of dispatch per call on a 3x3 or 5x5 matrix, more than
the arithmetic; these kernels do the same work inline in other kernels. The numpy calls they
stand for (``np.linalg.cholesky``, ``solve``, :func:`sigma_points.valid_moments`) are their test
oracles (``test_model_kernels``).
"""

from __future__ import annotations

import math

from vehicle_estimation.estimators.common.compiled import kernel

__all__ = ["all_finite", "cholesky_lower", "cholesky_solve_rows", "valid_moments"]


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
