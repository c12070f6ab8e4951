"""Error metrics for estimates against ground truth (pure NumPy, no ROS).

Accuracy metrics follow Zhang et al. 2023 (paper 000) Eqs. (37)-(39): RMSE, MAE and MAPE of
an estimate ``est`` against the truth ``true``; the stability metric is its convergence rate
(CR) of Eqs. (40)-(41), see :func:`convergence_rate`. Non-finite pairs are ignored everywhere.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

ArrayLike = Sequence[float] | np.ndarray | float


def _pairs(est: ArrayLike, true: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    e = np.atleast_1d(np.asarray(est, dtype=float))
    t = np.broadcast_to(np.atleast_1d(np.asarray(true, dtype=float)), e.shape)
    ok = np.isfinite(e) & np.isfinite(t)
    return e[ok], t[ok]


def errors(est: ArrayLike, true: ArrayLike) -> np.ndarray:
    """est - true over the finite pairs."""
    e, t = _pairs(est, true)
    return e - t


def mae(est: ArrayLike, true: ArrayLike) -> float:
    """Mean absolute error, paper 000 Eq. (38). NaN when there is no finite pair."""
    err = errors(est, true)
    return float(np.mean(np.abs(err))) if err.size else math.nan


def rmse(est: ArrayLike, true: ArrayLike) -> float:
    """Root mean square error, paper 000 Eq. (37)."""
    err = errors(est, true)
    return float(np.sqrt(np.mean(err * err))) if err.size else math.nan


def bias(est: ArrayLike, true: ArrayLike) -> float:
    """Mean signed error est - true."""
    err = errors(est, true)
    return float(np.mean(err)) if err.size else math.nan


def max_abs_error(est: ArrayLike, true: ArrayLike) -> float:
    err = errors(est, true)
    return float(np.max(np.abs(err))) if err.size else math.nan


def percent_errors(est: ArrayLike, true: ArrayLike) -> np.ndarray:
    """100·(est - true)/|true| over finite pairs with true != 0."""
    e, t = _pairs(est, true)
    ok = t != 0.0
    return 100.0 * (e[ok] - t[ok]) / np.abs(t[ok])


def mape(est: ArrayLike, true: ArrayLike) -> float:
    """Mean absolute percentage error [%], paper 000 Eq. (39); pairs with true == 0 skipped."""
    pe = percent_errors(est, true)
    return float(np.mean(np.abs(pe))) if pe.size else math.nan


def share_within(est: ArrayLike, true: ArrayLike, percent: float) -> float:
    """Fraction (0..1) of samples whose absolute percentage error is <= ``percent``."""
    pe = percent_errors(est, true)
    return float(np.mean(np.abs(pe) <= percent)) if pe.size else math.nan


def summary(est: ArrayLike, true: ArrayLike) -> dict[str, float]:
    """n, MAE, RMSE, bias and max |error| of one quantity."""
    err = errors(est, true)
    return {
        "n": int(err.size),
        "mae": mae(est, true),
        "rmse": rmse(est, true),
        "bias": bias(est, true),
        "max_abs_error": max_abs_error(est, true),
    }


# --------------------------------------------------------------------- convergence (CR)
def rolling_cv(values: ArrayLike, window: int) -> np.ndarray:
    """Coefficient of variation c_v = sigma/mu (paper 000 Eq. 40) over a trailing window.

    ``out[k]`` = std(values[k-window+1 : k+1]) / mean(same), with the population standard
    deviation (ddof = 0); NaN for k < window - 1 (window not yet full) and where the mean
    is 0. c_v uses |mean| so a negative signal gives a positive c_v.
    """
    x = np.asarray(values, dtype=float)
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    out = np.full(x.shape, np.nan)
    if x.size < window:
        return out
    view = np.lib.stride_tricks.sliding_window_view(x, window)
    mean = view.mean(axis=1)
    std = view.std(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cv = np.where(mean != 0.0, std / np.abs(mean), np.nan)
    out[window - 1:] = cv
    return out


def convergence_rate(est: ArrayLike, true: ArrayLike, *, window: int = 50,
                     cv_threshold: float = 0.02, error_threshold: float = 0.02) -> int | None:
    """Convergence rate CR of paper 000 Eqs. (40)-(41), in steps (samples).

    Sample k is "converged" when both hold:

    * Eq. (40): c_v = sigma/mu of the estimates in the trailing window of ``window`` samples
      ending at k (population std, see :func:`rolling_cv`) is below ``cv_threshold`` (0.02);
    * Eq. (41): |est_k - true_k| / |true_k| < ``error_threshold`` (2 %).

    The paper says CR is "the calculation steps cost when c_v converges to lower than c_v0";
    here CR = k* + 1, the number of samples processed up to and including the first sample
    k* from which every later sample is converged (so it never leaves the band again).
    Returns ``None`` when the last sample is not converged. Non-finite samples count as not
    converged. With a full window needed, CR >= ``window``.
    """
    e = np.asarray(est, dtype=float)
    t = np.broadcast_to(np.asarray(true, dtype=float), e.shape)
    if e.size == 0:
        return None
    cv = rolling_cv(e, window)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(e - t) / np.abs(t)
    ok = (cv < cv_threshold) & (rel < error_threshold)      # NaN compares False
    if not ok[-1]:
        return None
    bad = np.flatnonzero(~ok)
    first = int(bad[-1]) + 1 if bad.size else 0
    return first + 1


def convergence_time(t: ArrayLike, est: ArrayLike, true: ArrayLike, **kwargs) -> float:
    """Time [s] from the first sample to the sample at which :func:`convergence_rate` is
    reached (t[CR-1] - t[0]); NaN when not converged."""
    tt = np.asarray(t, dtype=float)
    cr = convergence_rate(est, true, **kwargs)
    if cr is None:
        return math.nan
    return float(tt[cr - 1] - tt[0])


# --------------------------------------------------------------------- time alignment
def _sorted_unique(t: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    if t.shape != y.shape:
        raise ValueError(f"time and value arrays differ in shape: {t.shape} vs {y.shape}")
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    order = np.argsort(t, kind="stable")
    t, y = t[order], y[order]
    if t.size:
        keep = np.ones(t.size, dtype=bool)           # keep the last of duplicate stamps
        keep[:-1] = t[1:] != t[:-1]
        t, y = t[keep], y[keep]
    return t, y


def align(t_est: ArrayLike, y_est: ArrayLike, t_true: ArrayLike, y_true: ArrayLike, *,
          mode: str = "linear", hold_last: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth at the estimate stamps, within the overlap of both time spans.

    Returns ``(t, est, true_at_t)`` for the estimate samples with
    t_true[0] <= t <= t_true[-1] (``hold_last``: no upper limit, the last truth is held).
    ``mode="linear"`` interpolates linearly; ``"previous"`` holds the latest truth sample
    at or before t (zero-order hold, for piecewise-constant truths such as mass).
    Non-finite samples are dropped; both inputs may be unsorted.
    """
    te, ye = _sorted_unique(t_est, y_est)
    tt, yt = _sorted_unique(t_true, y_true)
    empty = np.zeros(0)
    if te.size == 0 or tt.size == 0:
        return empty, empty, empty
    upper = np.inf if hold_last else tt[-1]
    sel = (te >= tt[0]) & (te <= upper)
    te, ye = te[sel], ye[sel]
    if mode == "linear":
        truth = np.interp(te, tt, yt)
    elif mode == "previous":
        idx = np.searchsorted(tt, te, side="right") - 1
        truth = yt[np.clip(idx, 0, tt.size - 1)]
    else:
        raise ValueError(f"mode must be 'linear' or 'previous', got {mode!r}")
    return te, ye, truth


def resample_uniform(t: ArrayLike, y: ArrayLike, dt: float, start: float, stop: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of (t, y) onto start, start+dt, ... <= stop."""
    ts, ys = _sorted_unique(t, y)
    n = int(math.floor((stop - start) / dt + 1e-9)) + 1
    grid = start + dt * np.arange(max(n, 0))
    return grid, np.interp(grid, ts, ys) if ts.size else np.full(grid.shape, np.nan)


def estimate_lag(t_est: ArrayLike, y_est: ArrayLike, t_true: ArrayLike, y_true: ArrayLike, *,
                 max_lag: float = 2.0, dt: float | None = None, refine: bool = True) -> float:
    """Time shift [s] that best aligns the estimate to the truth: est(t) ~ true(t - lag).

    Positive lag = the estimate is delayed behind the truth. Both signals are linearly
    resampled onto one uniform grid of step ``dt`` (default: the median estimate sample
    interval) over their overlap; every integer shift s in [-max_lag/dt, max_lag/dt] is
    scored by the RMSE of est[i] - true[i - s] over the samples both cover (a grid search,
    insensitive to a constant bias only through the RMSE floor). The best shift (ties: the
    smallest |s|, within a relative 1e-9) is refined by a parabola through the mean square
    errors of the neighbouring shifts when ``refine``. NaN when the overlap has fewer than 4
    samples or the truth is constant over it (no timing information).
    """
    te, ye = _sorted_unique(t_est, y_est)
    tt, yt = _sorted_unique(t_true, y_true)
    if te.size < 3 or tt.size < 3:
        return math.nan
    if dt is None:
        dt = float(np.median(np.diff(te)))
    if not (dt > 0.0 and math.isfinite(dt)):
        return math.nan
    start, stop = max(te[0], tt[0]), min(te[-1], tt[-1])
    if stop <= start:
        return math.nan
    _, e = resample_uniform(te, ye, dt, start, stop)
    _, tr = resample_uniform(tt, yt, dt, start, stop)
    n = e.size
    if n < 4 or not np.std(tr) > 1e-12 * (1.0 + abs(float(np.mean(tr)))):
        return math.nan     # a constant truth carries no timing information
    smax = min(int(round(max_lag / dt)), n - 4)
    if smax < 0:
        return math.nan
    shifts = np.arange(-smax, smax + 1)
    mse = np.empty(shifts.size)
    for i, s in enumerate(shifts):
        if s >= 0:
            d = e[s:] - tr[:n - s]
        else:
            d = e[:n + s] - tr[-s:]
        mse[i] = np.mean(d * d)
    best = np.flatnonzero(mse <= mse.min() * (1.0 + 1e-9) + 1e-300)   # ties: smallest |shift|
    k = int(best[np.argmin(np.abs(shifts[best]))])
    lag = float(shifts[k])
    if refine and 0 < k < shifts.size - 1:
        a, b, c = mse[k - 1], mse[k], mse[k + 1]
        denom = a - 2.0 * b + c
        if denom > 0.0:
            lag += float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5))
    return lag * dt


# --------------------------------------------------------------------- consistency
#: Shares of a Gaussian within 1, 2 and 3 sigma: what an honest variance gives.
GAUSSIAN_WITHIN = {1: 0.6827, 2: 0.9545, 3: 0.9973}


def consistency(error: ArrayLike, variance: ArrayLike, converged: ArrayLike | None = None) -> dict[str, float]:
    """Is a published variance honest? Errors against their own sigma.

    For the finite samples with a positive variance: the shares of ``|error|`` within 1, 2 and
    3 sigma (an honest Gaussian estimate: 68 / 95 / 99.7 %) and the mean normalised estimation
    error squared, NEES = mean(error^2 / variance) (honest: 1; above: the variance is too small).
    With ``converged`` (the estimate's own flag), the same over the flagged samples
    (``converged_*``) and the share flagged (``converged_share``); a flagged sample beyond 3 sigma
    is what a controller must never get (``converged_beyond_3sigma``).
    """
    e = np.atleast_1d(np.asarray(error, dtype=float))
    v = np.broadcast_to(np.atleast_1d(np.asarray(variance, dtype=float)), e.shape)
    ok = np.isfinite(e) & np.isfinite(v) & (v > 0.0)
    c = (np.ones(e.shape, dtype=bool) if converged is None
         else np.broadcast_to(np.atleast_1d(np.asarray(converged, dtype=float)) > 0.5, e.shape))

    def shares(sel: np.ndarray, prefix: str) -> dict[str, float]:
        n = int(sel.sum())
        if n == 0:
            return {f"{prefix}n": 0, **{f"{prefix}within_{k}sigma": math.nan for k in GAUSSIAN_WITHIN},
                    f"{prefix}nees": math.nan}
        z2 = e[sel] ** 2 / v[sel]
        return {f"{prefix}n": n, **{f"{prefix}within_{k}sigma": float(np.mean(z2 <= k * k)) for k in GAUSSIAN_WITHIN},
                f"{prefix}nees": float(np.mean(z2))}

    out = shares(ok, "")
    if converged is not None:
        flagged = ok & c
        out.update(shares(flagged, "converged_"))
        out["converged_share"] = float(flagged.sum() / ok.sum()) if ok.any() else math.nan
        out["converged_beyond_3sigma"] = (float(np.mean(e[flagged] ** 2 > 9.0 * v[flagged]))
                                          if flagged.any() else math.nan)
    return out
