"""Speed profiles: the official drive cycles shipped in ``data/`` and a synthetic route generator.

Cycles (1 Hz, see the header of each file for its source):

* ``hwfet``  EPA Highway Fuel Economy Test, 765 s, 16.5 km
* ``udds``   EPA Urban Dynamometer Driving Schedule, 1369 s, 12.0 km
* ``us06``   EPA US06 (aggressive), 600 s, 12.9 km
* ``wltc3``  UNECE WLTC class 3b, 1800 s, 23.3 km

A :class:`SpeedProfile` is resolved into a reference speed sampled at the driver rate
(100 Hz) by :func:`reference_speed`. ``kind="distance"`` profiles (speed as a function of
the position along the road, used by the paper-004 loop) are resolved by the road.
"""

from __future__ import annotations

import dataclasses
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

DATA_DIR = Path(__file__).resolve().parent / "data"

MPH = 0.44704  # m/s per mph

CYCLES = {
    # name: (file, unit factor to m/s, snap grid in m/s or None)
    "hwfet": ("hwfet.csv", MPH, None),
    "udds": ("udds.csv", 1.0, 0.1 * MPH),
    "us06": ("us06.csv", 1.0, 0.1 * MPH),
    "wltc3": ("wltc_class3b.csv", 1.0 / 3.6, None),
}
CYCLE_ALIASES = {"hfet": "hwfet", "wltc": "wltc3", "wltc3b": "wltc3", "wltc_class3": "wltc3",
                 "wltc_class3b": "wltc3", "ftp72": "udds", "la4": "udds"}


@lru_cache(maxsize=None)
def _load_cycle_cached(name: str) -> tuple[float, ...]:
    fname, factor, snap = CYCLES[name]
    values: list[float] = []
    with open(DATA_DIR / fname, "r", encoding="utf-8") as handle:
        for line in handle:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            values.extend(float(tok) for tok in line.split(",") if tok.strip())
    v = np.asarray(values, dtype=float) * factor
    if snap:
        v = np.round(v / snap) * snap
    return tuple(float(x) for x in v)


def load_cycle(name: str) -> np.ndarray:
    """Speed of an official cycle in m/s, one sample per second starting at t = 0."""
    key = CYCLE_ALIASES.get(name.lower(), name.lower())
    if key not in CYCLES:
        raise ValueError(f"unknown drive cycle {name!r}; known: {sorted(CYCLES)}")
    return np.array(_load_cycle_cached(key))


@dataclasses.dataclass(frozen=True)
class SpeedProfile:
    """What the driver tries to follow. Times are measured from the end of the standstill.

    kind:
      ``cycle``     official cycle ``cycle`` (hwfet, udds, us06, wltc3), ``repeat`` to fill the drive
      ``route``     synthetic urban/country/highway mix (seeded), ends with a stop
      ``constant``  hold ``speed_mps``
      ``coast``     hold ``speed_mps`` until ``coast_after_s``, then neutral, no brake (coast-down)
      ``points``    piecewise-linear through ``points`` = ((t, v), ...)
      ``distance``  speed set by the road (curvature-limited; the paper-004 loop)
    """

    kind: str = "route"
    cycle: str = "wltc3"
    speed_mps: float = 15.0
    coast_after_s: float = 20.0
    points: tuple[tuple[float, float], ...] = ()
    repeat: bool = False
    scale: float = 1.0
    route_mix: tuple[str, ...] = ("urban", "country", "highway", "country", "urban")
    max_accel: float = 1.8        # route generator limits [m/s²]
    max_decel: float = 2.0


def _rate_limited_route(rng: np.random.Generator, mix: tuple[str, ...], drive_s: float,
                        a_up: float, a_dn: float, dt: float) -> np.ndarray:
    """Synthetic speed trace: phases of (target, hold) drawn per road class."""
    classes = {
        "urban": [(50, 20), (0, 8), (40, 15), (50, 20), (30, 8), (0, 10)],
        "country": [(80, 35), (70, 20), (90, 35)],
        "highway": [(110, 40), (125, 35), (100, 25)],
    }
    phases: list[tuple[float, float]] = []
    for cls in mix:
        for v_kmh, hold in classes[cls]:
            v = v_kmh * (1.0 + 0.08 * rng.standard_normal()) if v_kmh > 0 else 0.0
            phases.append((max(v, 0.0) / 3.6, hold * (0.7 + 0.6 * rng.random())))
    # scale holds so that the whole drive roughly fits, ending with a stop
    n = int(round(drive_s / dt))
    out = np.zeros(n)
    v = 0.0
    k = 0
    i_phase = 0
    hold_left = None
    target, hold = phases[0]
    wobble_phase = rng.random() * 2 * math.pi
    stop_reserve = 0.0
    while k < n:
        t = k * dt
        # reserve time at the end to stop
        stop_reserve = v / a_dn + 6.0
        if t > drive_s - stop_reserve:
            target = 0.0
            hold_left = None
        if abs(v - target) < 1e-9:
            if hold_left is None:
                hold_left = hold
            hold_left -= dt
            if hold_left <= 0 and t <= drive_s - stop_reserve:
                i_phase = (i_phase + 1) % len(phases)
                target, hold = phases[i_phase]
                hold_left = None
        # speed-dependent acceleration ability of an ordinary driver
        up = a_up * max(0.25, 1.0 - v / 45.0)
        if v < target:
            v = min(target, v + up * dt)
        elif v > target:
            v = max(target, v - a_dn * dt)
        # small cruise fluctuation
        wob = 0.25 * math.sin(0.21 * t + wobble_phase) if v > 3.0 and abs(v - target) < 1e-9 else 0.0
        out[k] = max(0.0, v + wob)
        k += 1
    return out


def _smooth(x: np.ndarray, width: int) -> np.ndarray:
    if width <= 1:
        return x.copy()
    kernel = np.ones(width) / width
    pad = width // 2
    xp = np.concatenate([np.full(pad, x[0]), x, np.full(width - 1 - pad, x[-1])])
    return np.convolve(xp, kernel, mode="valid")


def reference_speed(profile: SpeedProfile, duration_s: float, standstill_s: float,
                    initial_speed: float, rng: np.random.Generator, dt: float = 0.01) -> np.ndarray:
    """Reference speed [m/s] at ``t = k*dt`` for ``k = 0..ceil(duration/dt)``.

    NaN means "coast" (driver releases everything, neutral). The standstill period is zero
    unless ``initial_speed > 0`` (then there is no standstill).
    """
    n = int(math.ceil(duration_s / dt)) + 1
    t = np.arange(n) * dt
    stand = 0.0 if initial_speed > 0 else standstill_s
    tau = t - stand
    drive_s = max(duration_s - stand, dt)
    kind = profile.kind
    if kind == "cycle":
        cyc = load_cycle(profile.cycle) * profile.scale
        tc = np.arange(cyc.size, dtype=float)
        if profile.repeat and cyc.size > 1:
            period = cyc.size - 1
            tau_c = np.mod(np.maximum(tau, 0.0), period)
        else:
            tau_c = tau
        v = np.interp(tau_c, tc, cyc, left=0.0, right=0.0)
    elif kind == "route":
        vr = _rate_limited_route(rng, profile.route_mix, drive_s, profile.max_accel,
                                 profile.max_decel, dt) * profile.scale
        vr = _smooth(vr, int(round(1.0 / dt)))
        v = np.interp(tau, np.arange(vr.size) * dt, vr, left=0.0, right=0.0)
    elif kind == "constant":
        v = np.full(n, profile.speed_mps * profile.scale)
    elif kind == "coast":
        v = np.full(n, profile.speed_mps * profile.scale)
        v[tau >= profile.coast_after_s] = np.nan
    elif kind == "points":
        pts = np.asarray(profile.points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError("SpeedProfile.points must be ((t, v), ...)")
        v = np.interp(tau, pts[:, 0], pts[:, 1] * profile.scale)
    elif kind == "distance":
        v = np.full(n, np.nan)  # resolved by the road at run time; marker only
    else:
        raise ValueError(f"unknown SpeedProfile.kind {kind!r}")
    if kind not in ("constant", "coast", "distance") and initial_speed <= 0:
        v[tau < 0] = 0.0
    return v


def reference_distance(v: np.ndarray, dt: float) -> np.ndarray:
    """Distance travelled along the reference (NaN counted as zero)."""
    vv = np.nan_to_num(v, nan=0.0)
    return np.concatenate([[0.0], np.cumsum(0.5 * (vv[1:] + vv[:-1]) * dt)])
