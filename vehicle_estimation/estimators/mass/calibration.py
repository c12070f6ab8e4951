"""Training phase of paper 003 (Jensen et al. 2022, Sec. 6): gear ratios, engine torque map and
longitudinal model parameters from one drive with a known mass. Plain NumPy/SciPy, no ROS.

Equation map (paper 003):

* Eq. (10)  measured effective gearing G = (pi/30) N_e / v = omega_e / v  [1/m].
* Eq. (50)  gear ratios from the sample count N_i in the interval [(1-w) G_i, (1+w) G_i] for a
  grid of candidate gearings G_low <= G_i <= G_upp. The interval *widens* with G_i (its width is
  relative, 2 w G_i) because the spread of the measured ratio grows with it. The paper's Fig. 6
  uses w = 0.02 and finds the peaks with ``scipy.signal.find_peaks`` (Sec. 7.3):
  :func:`gear_ratio_histogram`, :func:`estimate_gear_ratios`. Only the products
  i_t,j i_d / r are observable (Sec. 6.2).
* Eq. (3)   engine torque from the longitudinal dynamics with the mass known and eta_dt = 1
  (Sec. 6.1: the efficiency is absorbed by the torque fit)::

      T_e = ([m + I_w / r^2 + I_e G^2] a + 1/2 rho C_a v^2 + [C_r cos(alpha) + sin(alpha)] m g) / G

  It is *linear* in (C_a, C_r, I_e, I_w): T_e = b0 + C_a b_a + C_r b_r + I_e b_e + I_w b_w
  (:func:`dynamics_torque_basis`).
* Eq. (49)  T_load = w0 + w1 L + w2 N_e + ... + w_n N_e^(n-1) (N_e in rpm as Table 6):
  :func:`torque_features`.
* Eq. (48)  min over w, C_a, C_r, I_e, I_w of sum (T_load - T_e)^2, by a grid search over the
  ranges of Table 5 (:data:`TABLE5_GRID`) with linear regression for every grid point
  (:func:`grid_search`). Here the inner regression is solved in closed form for the whole grid at
  once: with P the projection onto the columns of the Eq.-49 design matrix X, the minimum over w
  for one grid point theta is ||(I - P)(b0 + B theta)||^2 = [1, theta]^T M [1, theta] with the
  5 x 5 matrix M = [b0, B]^T (I - P) [b0, B]. The 123 750 points of Table 5 are one einsum.

The 4 Hz update windows the data is prepared on are the mass node's own
(:mod:`~vehicle_estimation.estimators.mass.update_window`). :func:`debias_grade` removes a
constant offset of a kinematic grade signal so that it integrates to the height change of the
drive (an engineering choice for bags without a fusion grade, not from the paper).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np
from scipy.signal import find_peaks, lfilter

RPM_PER_RAD_S = 30.0 / math.pi

#: Table 5 of paper 003: (lower, upper, step) of C_d A_0 [m^2], C_r [-], I_e [kg m^2], I_w [kg m^2].
TABLE5_GRID: dict[str, tuple[float, float, float]] = {
    "drag_area": (0.30, 1.00, 0.05),
    "rolling_resistance": (0.002, 0.030, 0.002),
    "engine_inertia": (0.02, 1.00, 0.02),
    "wheel_inertia": (2.0, 12.0, 1.0),
}
GRID_PARAMETERS = ("drag_area", "rolling_resistance", "engine_inertia", "wheel_inertia")


# ---------------------------------------------------------------------------- grade
def debias_grade(sin_grade: np.ndarray, distance_step: np.ndarray, height_change: float) -> tuple[np.ndarray, float]:
    """Remove the constant offset c of a kinematic grade signal sin(alpha) = (f_x - dv/dt)/g
    (accelerometer bias and mounting pitch: c = b_x/g - pitch_mount) so that
    sum(sin(alpha) ds) equals the drive's ``height_change`` [m] (e.g. from GNSS altitude).

    Returns (corrected sin(alpha), c). Samples with a non-finite grade or step are ignored.
    """
    s = np.asarray(sin_grade, dtype=float)
    ds = np.asarray(distance_step, dtype=float)
    ok = np.isfinite(s) & np.isfinite(ds) & (ds > 0.0)
    total = float(np.sum(ds[ok]))
    if total <= 0.0 or not math.isfinite(height_change):
        return s.copy(), 0.0
    offset = (float(np.sum(s[ok] * ds[ok])) - float(height_change)) / total
    return s - offset, offset


# ---------------------------------------------------------------------------- gear ratios
def speed_ratios(engine_speed: np.ndarray, vehicle_speed: np.ndarray, *, idle_speed: float,
                 min_vehicle_speed: float = 2.0, idle_margin: float = 1.05) -> np.ndarray:
    """Measured effective gearings omega_e / v [1/m] (Eq. 10) of the samples that can be in gear.

    ``engine_speed`` [rad/s] and ``vehicle_speed`` [m/s]. As for the paper's Fig. 7, samples at
    idle engine speed (below ``idle_margin`` x ``idle_speed``: clutch open, coasting, launch) and
    at standstill or crawling (v < ``min_vehicle_speed``) are left out.
    """
    w = np.asarray(engine_speed, dtype=float)
    v = np.asarray(vehicle_speed, dtype=float)
    ok = np.isfinite(w) & np.isfinite(v) & (v >= min_vehicle_speed) & (w > idle_margin * idle_speed)
    return w[ok] / v[ok]


def gear_ratio_histogram(ratios: np.ndarray, g_low: float, g_upp: float, width: float = 0.02,
                         resolution: float = 0.001) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (50): for candidate gearings G_i spaced by the relative step ``resolution`` in
    [g_low, g_upp], the number of ratios inside [(1 - width) G_i, (1 + width) G_i].

    Returns (G_i, N_i). The candidates are geometrically spaced so that every interval (whose
    width grows with G_i) is sampled equally finely.
    """
    if not (0.0 < width < 1.0):
        raise ValueError(f"width must be in (0, 1), got {width!r}")
    if not (0.0 < g_low < g_upp):
        raise ValueError(f"need 0 < g_low < g_upp, got {g_low!r}, {g_upp!r}")
    if not resolution > 0.0:
        raise ValueError(f"resolution must be > 0, got {resolution!r}")
    r = np.sort(np.asarray(ratios, dtype=float)[np.isfinite(ratios)])
    n = int(math.floor(math.log(g_upp / g_low) / math.log1p(resolution))) + 1
    grid = g_low * (1.0 + resolution) ** np.arange(n)
    counts = np.searchsorted(r, (1.0 + width) * grid, side="right") - np.searchsorted(r, (1.0 - width) * grid, side="left")
    return grid, counts.astype(np.int64)


@dataclasses.dataclass(frozen=True)
class GearRatioEstimate:
    """Result of :func:`estimate_gear_ratios`."""

    gearings: tuple[float, ...]     # G_j = i_t,j i_d / r [1/m], first (largest) gear first
    peak_counts: tuple[int, ...]    # N_i at each peak
    grid: np.ndarray                # candidate G_i of Eq. (50)
    counts: np.ndarray              # N_i of Eq. (50)
    width: float

    def transmission_ratios(self, final_drive: float, wheel_radius: float) -> tuple[float, ...]:
        """i_t,j = G_j r / i_d for a given final drive and radius (only G_j is observable)."""
        return tuple(g * wheel_radius / final_drive for g in self.gearings)


def estimate_gear_ratios(ratios: np.ndarray, *, n_gears: int | None = None, width: float = 0.02,
                         g_low: float | None = None, g_upp: float | None = None,
                         resolution: float = 0.001, min_prominence: float = 0.02) -> GearRatioEstimate:
    """Gear ratios from the Eq.-(50) distribution of measured speed ratios and peak finding.

    Peaks closer than ``width`` (relative) to a higher peak are suppressed (``distance`` of
    ``find_peaks`` in grid steps); a peak must stand out by ``min_prominence`` x the highest
    count. With ``n_gears`` the ``n_gears`` most prominent peaks are kept (``ValueError`` when
    fewer are found). Each peak is refined to the median of the ratios inside its Eq.-(50)
    interval [(1 - width/2) G, (1 + width/2) G] (the grid itself only resolves ``resolution``).
    """
    r = np.asarray(ratios, dtype=float)
    r = r[np.isfinite(r) & (r > 0.0)]
    if r.size < 10:
        raise ValueError(f"need at least 10 in-gear samples to estimate gear ratios, got {r.size}")
    lo = float(np.percentile(r, 0.1)) * 0.9 if g_low is None else float(g_low)
    hi = float(np.percentile(r, 99.9)) * 1.1 if g_upp is None else float(g_upp)
    grid, counts = gear_ratio_histogram(r, lo, hi, width, resolution)
    step = math.log1p(resolution)
    distance = max(1, int(round(math.log1p(width) / step)))
    # Pad with zeros so that a cluster at the edge of the range still forms a peak.
    padded = np.concatenate([[0], counts, [0]])
    peaks, props = find_peaks(padded, distance=distance, prominence=min_prominence * float(counts.max()))
    peaks = peaks - 1
    prominence = props["prominences"]
    if n_gears is not None:
        if peaks.size < n_gears:
            raise ValueError(f"found {peaks.size} gear peaks, expected {n_gears}: the drive does not "
                             "cover every gear (or the width is too large)")
        keep = np.sort(np.argsort(prominence)[::-1][:n_gears])
        peaks = peaks[keep]
    rs = np.sort(r)
    gearings = []
    for p in peaks:
        g = grid[p]
        inside = rs[np.searchsorted(rs, (1 - width / 2) * g):np.searchsorted(rs, (1 + width / 2) * g, side="right")]
        gearings.append(float(np.median(inside)) if inside.size else float(g))
    order = np.argsort(gearings)[::-1]
    return GearRatioEstimate(
        gearings=tuple(gearings[i] for i in order),
        peak_counts=tuple(int(counts[peaks[i]]) for i in order),
        grid=grid, counts=counts, width=float(width))


def assign_gears(measured: np.ndarray, gearings: Sequence[float], tolerance: float = 0.10) -> np.ndarray:
    """Eq. (11) on arrays: the gear (1-based) whose gearing is nearest to each measured ratio, 0
    where the measurement is not finite or mismatches the nearest by more than ``tolerance``
    (relative): clutch open or slipping, neutral."""
    m = np.asarray(measured, dtype=float)
    g = np.asarray(gearings, dtype=float)
    err = np.abs(m[:, None] - g[None, :])
    best = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=1)
    rel = np.abs(m - g[best]) / g[best]
    return np.where(np.isfinite(m) & (rel <= tolerance), best + 1, 0).astype(np.int64)


# ---------------------------------------------------------------------------- torque regression
def torque_features(load: np.ndarray, engine_speed: np.ndarray, speed_order: int = 2) -> np.ndarray:
    """Design matrix of Eq. (49): columns 1, L, N_e, ..., N_e^speed_order with N_e in rpm
    (``engine_speed`` is given in rad/s). ``speed_order`` = n - 1; the paper used 2 (Table 6)."""
    if speed_order < 0:
        raise ValueError(f"speed_order must be >= 0, got {speed_order!r}")
    n_rpm = np.asarray(engine_speed, dtype=float) * RPM_PER_RAD_S
    cols = [np.ones_like(n_rpm), np.asarray(load, dtype=float)]
    cols += [n_rpm ** k for k in range(1, speed_order + 1)]
    return np.stack(cols, axis=1)


def dynamics_torque_basis(mass: float, v: np.ndarray, a: np.ndarray, slope: np.ndarray, gearing: np.ndarray,
                          *, wheel_radius: float, air_density: float, gravity: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (3) with eta_dt = 1 written as T_e = b0 + B @ [C_a, C_r, I_e, I_w] [N m].

    b0 = m (a + g sin alpha) / G; columns of B: 1/2 rho v^2 / G, m g cos(alpha) / G, G a,
    a / (r^2 G). ``gearing`` is G [1/m] of each sample's gear.
    """
    v, a, al, G = (np.asarray(x, dtype=float) for x in (v, a, slope, gearing))
    b0 = mass * (a + gravity * np.sin(al)) / G
    B = np.stack([0.5 * air_density * v * v / G,
                  mass * gravity * np.cos(al) / G,
                  G * a,
                  a / (wheel_radius ** 2 * G)], axis=1)
    return b0, B


def _grid_values(spec: tuple[float, float, float]) -> np.ndarray:
    lo, hi, step = spec
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    return lo + step * np.arange(n)


@dataclasses.dataclass(frozen=True)
class TorqueModelFit:
    """Result of :func:`grid_search` (Eqs. 48-49)."""

    drag_area: float               # C_a = C_d A_0 [m^2]
    rolling_resistance: float      # C_r [-]
    engine_inertia: float          # I_e [kg m^2]
    wheel_inertia: float           # I_w [kg m^2]
    coefficients: tuple[float, ...]  # w0..wn of Eq. (49), N_e in rpm, L in the unit given
    r2: float                      # coefficient of determination of T_load vs T_e
    rmse: float                    # [N m]
    n_samples: int
    on_grid_edge: tuple[str, ...]  # parameters whose optimum is at a limit of the grid
    #: Relative std of the fitted torque at the mean operating point of the fit (the
    #: coefficients' covariance, widened by the residuals' correlation between consecutive
    #: samples): how well the map is known, a scale error that every drive on it shares [-]
    relative_std: float = math.nan
    #: Joint covariance of [w0..wn, C_a, C_r, I_e, I_w], row by row (:func:`joint_covariance`):
    #: the map and the vehicle values trade against each other (w0 against C_r, C_a against C_r),
    #: so what a drive at other speeds and loads inherits is known only from all of it together
    covariance: tuple[float, ...] = ()

    def parameters(self) -> dict[str, float]:
        return {name: float(getattr(self, name)) for name in GRID_PARAMETERS}


def grid_search(X: np.ndarray, b0: np.ndarray, B: np.ndarray,
                grid: dict[str, tuple[float, float, float]] | None = None) -> TorqueModelFit:
    """Eq. (48) over the grid (default Table 5) with the Eq.-(49) regression solved in closed form.

    ``X`` (n, k) is the Eq.-(49) design matrix (:func:`torque_features`), ``b0`` (n,) and ``B``
    (n, 4) the Eq.-(3) basis (:func:`dynamics_torque_basis`). Returns the best grid point, the
    regression coefficients there, and R^2 = 1 - SS_res / SS_tot of the fit to T_e.
    """
    X = np.asarray(X, dtype=float)
    b0 = np.asarray(b0, dtype=float)
    B = np.asarray(B, dtype=float)
    ok = np.all(np.isfinite(X), axis=1) & np.isfinite(b0) & np.all(np.isfinite(B), axis=1)
    X, b0, B = X[ok], b0[ok], B[ok]
    n, k = X.shape
    if n <= k + 4:
        raise ValueError(f"need more than {k + 4} valid samples for the torque regression, got {n}")
    spec = dict(TABLE5_GRID if grid is None else grid)
    axes = [_grid_values(spec[name]) for name in GRID_PARAMETERS]
    # Column scaling keeps the QR well conditioned (N_e^2 in rpm^2 is ~1e7).
    scale = np.maximum(np.max(np.abs(X), axis=0), 1e-12)
    Q, _ = np.linalg.qr(X / scale, mode="reduced")
    A = np.column_stack([b0, B])                       # T_e = A @ [1, theta]
    A_res = A - Q @ (Q.T @ A)                          # (I - P) A
    M = A_res.T @ A_res                                # 5 x 5
    mesh = np.meshgrid(*axes, indexing="ij")
    theta = np.stack([np.ones(mesh[0].size)] + [m.ravel() for m in mesh], axis=1)
    objective = np.einsum("ki,ij,kj->k", theta, M, theta)
    best = int(np.argmin(objective))
    th = theta[best]
    target = A @ th
    w_scaled, *_ = np.linalg.lstsq(X / scale, target, rcond=None)
    w = w_scaled / scale
    residual = target - X @ w
    ss_res = float(residual @ residual)
    ss_tot = float(np.sum((target - target.mean()) ** 2))
    idx = np.unravel_index(best, mesh[0].shape)
    edge = tuple(name for name, i, ax in zip(GRID_PARAMETERS, idx, axes) if ax.size > 1 and i in (0, ax.size - 1))
    return TorqueModelFit(
        drag_area=float(th[1]), rolling_resistance=float(th[2]), engine_inertia=float(th[3]),
        wheel_inertia=float(th[4]), coefficients=tuple(float(x) for x in w),
        r2=1.0 - ss_res / ss_tot if ss_tot > 0.0 else float("nan"),
        rmse=math.sqrt(ss_res / n), n_samples=int(n), on_grid_edge=edge,
        relative_std=map_relative_std(X / scale, w_scaled, residual),
        covariance=tuple(float(c) for c in joint_covariance(
            X, B, residual, [spec[name][2] for name in GRID_PARAMETERS]).ravel()))


def _lag1_correlation(residual: np.ndarray) -> float:
    """Lag-1 correlation of a residual sequence in time order, clipped to [0, 0.99]."""
    lagged = float(residual[:-1] @ residual[:-1])
    rho = float(residual[1:] @ residual[:-1]) / lagged if lagged > 0.0 else 0.0
    return min(max(rho, 0.0), 0.99)


def joint_covariance(X: np.ndarray, B: np.ndarray, residual: np.ndarray, steps: Sequence[float]) -> np.ndarray:
    """Covariance of [w (Eq. 49, X's units), C_a, C_r, I_e, I_w] of the fit T_e = b0 + B theta =
    X w (Eq. 48 is linear in all of them: b0 = [X, -B] [w, theta]), with Z = [X, -B] and the
    fit's residuals (rows in time order) taken as an AR(1) sequence of variance s^2 and lag-1
    correlation rho: the sandwich ``(Z^T Z)^-1 Z^T Omega Z (Z^T Z)^-1``, Omega_ij = s^2
    rho^|i-j|. A column that changes slowly (the speed's drag, the map's offset) is known
    (1 + rho) / (1 - rho) times less well than white residuals would say, one that changes from
    window to window (the acceleration's inertias) hardly less. Plus the grid's own rounding,
    step^2 / 12, on each vehicle value (``steps``, Table 5's)."""
    Z = np.column_stack([np.asarray(X, dtype=float), -np.asarray(B, dtype=float)])
    n, k = Z.shape
    if n <= k:
        return np.full((k, k), math.nan)
    scale = np.maximum(np.max(np.abs(Z), axis=0), 1e-12)
    Zs = Z / scale
    rho = _lag1_correlation(residual)
    s2 = float(residual @ residual) / (n - k)
    # sum_j rho^|i-j| z_j = forward + backward exponential sums - z_i
    forward = lfilter([1.0], [1.0, -rho], Zs, axis=0)
    backward = lfilter([1.0], [1.0, -rho], Zs[::-1], axis=0)[::-1]
    middle = s2 * Zs.T @ (forward + backward - Zs)
    bread = np.linalg.pinv(Zs.T @ Zs)
    covariance = bread @ middle @ bread / np.outer(scale, scale)
    covariance[-len(steps):, -len(steps):] += np.diag([step * step / 12.0 for step in steps])
    return 0.5 * (covariance + covariance.T)


def map_relative_std(X: np.ndarray, w: np.ndarray, residual: np.ndarray) -> float:
    """Relative std of the least-squares fit ``X w`` at the mean row of ``X`` (rows in time
    order): ``sqrt(x_mean^T C x_mean) / |x_mean^T w|`` with the coefficient covariance
    ``C = s^2 (X^T X)^-1 (1 + rho) / (1 - rho)``. A torque map's error depends on the
    operating point, which changes over seconds, so consecutive residuals correlate (rho, their
    lag-1 correlation, clipped to [0, 0.99]) and the fit knows its coefficients by that much
    less than white residuals would say (an AR(1) sequence's effective sample count)."""
    n, k = X.shape
    if n <= k:
        return math.nan
    s2 = float(residual @ residual) / (n - k)
    rho = _lag1_correlation(residual)
    covariance = s2 * (1.0 + rho) / (1.0 - rho) * np.linalg.pinv(X.T @ X)
    x_mean = X.mean(axis=0)
    torque = float(x_mean @ w)
    spread = float(x_mean @ covariance @ x_mean)
    return math.sqrt(max(spread, 0.0)) / abs(torque) if torque != 0.0 else math.nan


def fit_torque_model(mass: float, v: np.ndarray, a: np.ndarray, slope: np.ndarray, gearing: np.ndarray,
                     load: np.ndarray, engine_speed: np.ndarray, *, wheel_radius: float, air_density: float,
                     gravity: float, speed_order: int = 2,
                     grid: dict[str, tuple[float, float, float]] | None = None) -> TorqueModelFit:
    """Eqs. (48)-(49) on prepared driving samples (a > 0, in gear, no braking: the caller's
    selection, Sec. 7.1). ``engine_speed`` in rad/s, ``load`` as the vehicle reports it."""
    b0, B = dynamics_torque_basis(mass, v, a, slope, gearing, wheel_radius=wheel_radius,
                                  air_density=air_density, gravity=gravity)
    X = torque_features(load, engine_speed, speed_order)
    return grid_search(X, b0, B, grid)
