"""The mass estimators' update window: the means of every input over one update period.

Paper 003 ran its RLS on 4 Hz CAN data, so the forgetting estimators (RLS, FFRLS) step once per
window on the inputs' means (:class:`UpdateWindow`, filled sample by sample by the mass node).
The offline paths that must feed a core exactly as the node does (paper 003's calibration and
drive campaign) use the batch twins below on whole recordings: :func:`window_edges` applies the
node's closing rule to the powertrain stamps, and :func:`window_mean`, :func:`window_max` and
:func:`window_slope` give the statistics per window. No ROS import.
"""

from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.estimators.common.guard import STAMP_TOLERANCE_S


#: Where the window's acceleration comes from (see :meth:`UpdateWindow.acceleration`).
ACCEL_SOURCES = ("auto", "wheel_speed", "imu", "vehicle_state")


class UpdateWindow:
    """Means of the inputs over one RLS update period (paper 003 ran its RLS on 4 Hz CAN data).

    Averaging the force signals and the IMU acceleration over the *same* window filters both
    sides of Eq. 4 alike, so a transient cannot appear on one side before the other, and it
    keeps the forgetting factor's memory in seconds what the paper's was (lambda = 0.9995 at
    4 Hz: about 500 s). Brake torque: the maximum for ``rls`` (one braking sample spoils the
    window) and the mean for ``ffrls`` (it enters the regression). The gear takes the last
    value, and a gear change inside the window is passed on as NaN so the core treats the
    window as a shift. Speed samples of the vehicle-state node are kept with their stamps so
    that their least-squares slope can serve as the acceleration.
    """

    FIELDS = ("vx", "slope", "bias_variance", "drive_force", "engine_torque", "engine_speed", "engine_load")

    def __init__(self) -> None:
        self.clear()

    def closes(self, t: float, period: float) -> bool:
        """Whether the sample at ``t`` completes the window of length ``period`` [s] (the node
        adds the sample first: the closing sample is in the window)."""
        return not math.isnan(self.start) and t - self.start >= period - STAMP_TOLERANCE_S

    def clear(self) -> None:
        self.start = math.nan
        self.sums = dict.fromkeys(self.FIELDS, 0.0)
        self.counts = dict.fromkeys(self.FIELDS, 0)
        self.accel_sum = 0.0
        self.accel_sq_sum = 0.0
        self.accel_n = 0
        self.wheel_t: list[float] = []
        self.wheel_v: list[float] = []
        self.state_t: list[float] = []
        self.state_v: list[float] = []
        self.brake = 0.0
        self.brake_sum = 0.0
        self.brake_n = 0
        self.gears: set[float] = set()
        self.slope_trusted = True

    def add_accel(self, ax_specific: float) -> None:
        self.accel_sum += ax_specific
        self.accel_sq_sum += ax_specific * ax_specific
        self.accel_n += 1

    def add(self, t: float, brake: float, gear: float, **values: float) -> None:
        if math.isnan(self.start):
            self.start = t
        for key, value in values.items():
            if math.isfinite(value):
                self.sums[key] += value
                self.counts[key] += 1
        self.brake = max(self.brake, brake)
        self.brake_sum += brake
        self.brake_n += 1
        if math.isfinite(gear):
            self.gears.add(gear)

    def add_wheel_speed(self, t: float, v: float) -> None:
        self.wheel_t.append(t)
        self.wheel_v.append(v)

    def add_state_speed(self, t: float, v: float) -> None:
        if not self.state_t or t > self.state_t[-1]:
            self.state_t.append(t)
            self.state_v.append(v)

    @staticmethod
    def speed_fit(t_list: list[float], v_list: list[float]) -> tuple[float, float]:
        """Least-squares slope of the speeds [m/s^2] (NaN below 3 samples) and its variance
        from the fit's residuals [m^2/s^4] (NaN below 4 samples)."""
        if len(t_list) < 3:
            return math.nan, math.nan
        t = np.asarray(t_list) - t_list[0]
        if t[-1] <= 0.0:
            return math.nan, math.nan
        v = np.asarray(v_list)
        slope, offset = np.polyfit(t, v, 1)
        if len(t_list) < 4:
            return float(slope), math.nan
        residual = v - (slope * t + offset)
        spread = float(np.sum((t - t.mean()) ** 2))
        return float(slope), float(np.sum(residual * residual)) / (len(t_list) - 2) / spread

    @classmethod
    def speed_slope(cls, t_list: list[float], v_list: list[float]) -> float:
        return cls.speed_fit(t_list, v_list)[0]

    @property
    def wheel_accel(self) -> float:
        """Least-squares slope of the undriven wheels' speed over the window [m/s^2]."""
        return self.speed_slope(self.wheel_t, self.wheel_v)

    @property
    def brake_mean(self) -> float:
        return self.brake_sum / self.brake_n if self.brake_n else 0.0

    def mean(self, key: str) -> float:
        return self.sums[key] / self.counts[key] if self.counts[key] else math.nan

    @property
    def accel(self) -> float:
        return self.accel_sum / self.accel_n if self.accel_n else math.nan

    @property
    def gear(self) -> float:
        return next(iter(self.gears)) if len(self.gears) == 1 else math.nan

    def _imu_mean_variance(self) -> float:
        """Variance of the mean specific force over this window [m^2/s^4] (NaN below 2 samples)."""
        if self.accel_n < 2:
            return math.nan
        mean = self.accel_sum / self.accel_n
        return max(self.accel_sq_sum / self.accel_n - mean * mean, 0.0) / (self.accel_n - 1)

    def acceleration(self, source: str, slope: float, gravity: float,
                     imu_bias_known: bool) -> tuple[float, float, dict[str, bool]]:
        """Longitudinal acceleration dv/dt over the window [m/s^2] from ``source`` (one of
        :data:`ACCEL_SOURCES`), the variance of its noise [m^2/s^4] (the speed fit's for the
        wheels and the vehicle state, the IMU mean's for the IMU; NaN where it cannot be told),
        and which inputs it found missing (name -> missing).

        ``wheel_speed``: the slope of the undriven wheels' speed. It carries no gravity and no
        body pitch, so neither the accelerometer bias nor the suspension's squat and dive
        (which tilt the IMU by ~0.1 deg per m/s^2) reach the mass. ``imu``: paper 003's choice,
        the mean bias-compensated specific force minus g sin(slope); needs the fusion's bias.
        ``auto`` takes the wheels when they report and the IMU otherwise. ``vehicle_state``:
        the slope of the vehicle-state node's vx (paper 004 Fig. 1: mass <- state).
        """
        if source == "vehicle_state":
            a, variance = self.speed_fit(self.state_t, self.state_v)
            return a, variance, {"vehicle state speed": not math.isfinite(a)}
        missing: dict[str, bool] = {}
        if source in ("wheel_speed", "auto"):
            a, variance = self.speed_fit(self.wheel_t, self.wheel_v)
            missing["undriven wheel speeds"] = not math.isfinite(a) and source == "wheel_speed"
            if math.isfinite(a) or source == "wheel_speed":
                return a, variance, missing
        missing["IMU bias (estimation/imu_bias)"] = not imu_bias_known
        variance = self._imu_mean_variance()
        if not imu_bias_known:
            return math.nan, variance, missing
        return self.accel - gravity * math.sin(slope), variance, missing


def window_edges(powertrain_t: np.ndarray, period: float) -> np.ndarray:
    """The stamps at which the mass node closes its update windows on a drive whose powertrain
    samples (the node's trigger) have the stamps ``powertrain_t``: :meth:`UpdateWindow.closes`
    applied sample by sample, as the node does. A window ends with (and includes) the sample
    that closes it; the last, incomplete window is not in the list."""
    edges: list[float] = []
    window = UpdateWindow()
    for t in np.asarray(powertrain_t, dtype=float):
        if math.isnan(window.start):
            window.start = float(t)
        if window.closes(float(t), period):
            edges.append(float(t))
            window.start = math.nan
    return np.asarray(edges)


def window_ids(t: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Index of the update window each stamp falls in (windows as :func:`window_edges` gives
    them: a stamp belongs to the first window that closes at or after it); ``len(edges)`` for
    the stamps after the last complete window."""
    return np.searchsorted(np.asarray(edges, dtype=float), np.asarray(t, dtype=float), side="left").astype(np.int64)


def window_mean(ids: np.ndarray, x: np.ndarray, n_windows: int) -> np.ndarray:
    """Mean of the finite ``x`` per window id (NaN for a window without finite samples)."""
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x) & (ids >= 0) & (ids < n_windows)
    s = np.bincount(ids[ok], weights=x[ok], minlength=n_windows)
    n = np.bincount(ids[ok], minlength=n_windows).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1.0), np.nan)


def window_max(ids: np.ndarray, x: np.ndarray, n_windows: int, empty: float = 0.0) -> np.ndarray:
    """Maximum of the finite ``x`` per window id (``empty`` for a window without samples)."""
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x) & (ids >= 0) & (ids < n_windows)
    out = np.full(n_windows, -np.inf)
    np.maximum.at(out, ids[ok], x[ok])
    return np.where(np.isfinite(out), out, empty)


def window_slope(ids: np.ndarray, t: np.ndarray, x: np.ndarray, n_windows: int, min_samples: int = 3) -> np.ndarray:
    """Least-squares slope dx/dt per window (NaN with fewer than ``min_samples`` samples), the
    vectorised twin of :meth:`UpdateWindow.speed_slope`."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    ok = np.isfinite(x) & np.isfinite(t) & (ids >= 0) & (ids < n_windows)
    i, tt, xx = ids[ok], t[ok], x[ok]
    n = np.bincount(i, minlength=n_windows).astype(float)
    nn = np.maximum(n, 1.0)
    mt = np.bincount(i, weights=tt, minlength=n_windows) / nn
    mx = np.bincount(i, weights=xx, minlength=n_windows) / nn
    dt = tt - mt[i]
    sxy = np.bincount(i, weights=dt * (xx - mx[i]), minlength=n_windows)
    sxx = np.bincount(i, weights=dt * dt, minlength=n_windows)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((n >= min_samples) & (sxx > 0.0), sxy / np.where(sxx > 0.0, sxx, 1.0), np.nan)
