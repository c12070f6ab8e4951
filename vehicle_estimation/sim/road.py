"""Roads: a 2-D path with curvature and an elevation profile, sampled every ``DS`` metres.

The path starts at the ENU origin (0, 0, 0), heading east unless the kind fixes it.
Grade is dz/ds (s is horizontal arc length); the road slope angle is atan(grade),
positive uphill.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

DS = 0.5  # path sampling [m]


@dataclasses.dataclass(frozen=True)
class RoadSpec:
    """Road / path description.

    kind:
      ``random``   curves sized for the reference speed (lateral acceleration ``lat_acc``) and
                   smooth hills (sum of sinusoids over distance, max |grade| = ``grade_max``)
      ``loop004``  closed ~2328 m hilly, curvy loop like paper 004 Fig. 6 (``length``)
      ``straight`` straight road, hills as ``random`` (``grade_max``) plus ``constant_grade``
      ``circle``   circle of ``radius`` (counter-clockwise, i.e. left turn), ``constant_grade``
      ``dlc3888``  ISO 3888-2 obstacle-avoidance double lane change (paper 002 Sec. 4.2):
                   ``dlc_lead_in`` m straight, then the 61 m track (sections 12, 13.5, 11,
                   12.5, 12 m; lane 3 moved left so that its right edge is 1 m left of lane
                   1's left edge; lane widths from ``dlc_vehicle_width``), then straight;
                   repeated every ``dlc_repeat_m`` m if > 0; hills as ``random``
    """

    kind: str = "random"
    grade_max: float = 0.06
    constant_grade: float = 0.0
    hill_wavelengths: tuple[float, ...] = (1800.0, 800.0, 380.0)
    curves: bool = True
    lat_acc: float = 2.5           # design lateral acceleration of the curves [m/s²]
    min_radius: float = 25.0
    radius: float = 100.0          # circle
    length: float = 2328.0         # loop004 length; other kinds: auto from the speed profile
    loop_speed_max: float = 80.0 / 3.6
    loop_speed_min: float = 30.0 / 3.6
    loop_lat_acc: float = 1.0      # tuned: ~148 s per lap, ~57 km/h average
    dlc_vehicle_width: float = 1.85  # ISO 3888-2 lane widths are set from the vehicle width [m]
    dlc_lead_in: float = 100.0       # straight before the first double lane change [m]
    dlc_repeat_m: float = 0.0        # > 0: a double lane change every this many metres


@dataclasses.dataclass
class Road:
    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    psi: np.ndarray
    kappa: np.ndarray
    z: np.ndarray
    grade: np.ndarray        # dz/ds
    closed: bool
    v_of_s: np.ndarray | None = None   # distance-based speed profile (loop004)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def slope(self) -> np.ndarray:
        return np.arctan(self.grade)


def _hills(rng: np.random.Generator, s: np.ndarray, grade_max: float, wavelengths, periodic_len=None):
    if grade_max <= 0:
        return np.zeros_like(s), np.zeros_like(s)
    z = np.zeros_like(s)
    dz = np.zeros_like(s)
    for lam in wavelengths:
        if periodic_len:
            k = max(1, round(periodic_len / lam))
            lam = periodic_len / k
        w = 2 * math.pi / lam
        phase = rng.random() * 2 * math.pi
        amp = (0.6 + 0.8 * rng.random()) / w   # equal grade contribution per component
        z += amp * np.sin(w * s + phase)
        dz += amp * w * np.cos(w * s + phase)
    scale = grade_max / max(np.max(np.abs(dz)), 1e-12)
    return z * scale, dz * scale


def _integrate_path(kappa: np.ndarray, psi0: float = 0.0):
    psi = psi0 + np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * DS)])
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(psi[1:]) + np.cos(psi[:-1])) * DS)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(psi[1:]) + np.sin(psi[:-1])) * DS)])
    return x, y, psi


def _moving_average(x: np.ndarray, width: int, wrap: bool = False) -> np.ndarray:
    if width <= 1:
        return x.copy()
    kernel = np.ones(width) / width
    if wrap:
        xp = np.concatenate([x[-width:], x, x[:width]])
        return np.convolve(xp, kernel, mode="same")[width:-width]
    pad = width // 2
    xp = np.concatenate([np.full(pad, x[0]), x, np.full(width - 1 - pad, x[-1])])
    return np.convolve(xp, kernel, mode="valid")


def build_road(spec: RoadSpec, rng: np.random.Generator, needed_length: float,
               v_ref_dist: tuple[np.ndarray, np.ndarray] | None = None) -> Road:
    """Build the road. ``v_ref_dist`` = (distance, speed) of the reference, to size the curves."""
    kind = spec.kind
    if kind == "loop004":
        return _loop004(spec, rng)
    length = max(needed_length * 1.15 + 400.0, 600.0)
    n = int(math.ceil(length / DS)) + 1
    s = np.arange(n) * DS
    if kind == "dlc3888":
        z, dz = _hills(rng, s, spec.grade_max, spec.hill_wavelengths)
        kappa = _dlc3888_curvature(spec, s)
        x, y, psi = _integrate_path(kappa)
        return Road(s, x, y, psi, kappa, z - z[0], dz, False)
    if kind == "circle":
        kappa = np.full(n, 1.0 / spec.radius)
        x, y, psi = _integrate_path(kappa)
        z = spec.constant_grade * s
        return Road(s, x, y, psi, kappa, z, np.full(n, spec.constant_grade), False)
    # hills
    z, dz = _hills(rng, s, spec.grade_max, spec.hill_wavelengths)
    z = z - z[0] + spec.constant_grade * s
    dz = dz + spec.constant_grade
    kappa = np.zeros(n)
    if kind == "random" and spec.curves:
        # speed expected at each s: max of the reference speed in a window around s
        if v_ref_dist is not None:
            d, v = v_ref_dist
            vv = np.nan_to_num(v, nan=0.0)
            bins = np.minimum((d / 5.0).astype(int), n)
            nb = int(math.ceil(length / 5.0)) + 2
            vmax_bin = np.zeros(nb)
            np.maximum.at(vmax_bin, np.minimum(bins, nb - 1), vv)
            w = 24  # 120 m window
            padded = np.concatenate([vmax_bin, np.full(w, vmax_bin[: max(1, bins.max() + 1)].max())])
            roll = np.array([padded[max(0, i - 8): i + w].max() for i in range(nb)])
            v_at_s = np.interp(s, np.arange(nb) * 5.0, roll)
        else:
            v_at_s = np.full(n, 25.0)
        k_allow = np.minimum(spec.lat_acc / np.maximum(v_at_s, 6.0) ** 2, 1.0 / spec.min_radius)
        c = np.zeros(n)
        for _ in range(3):
            lam = 250.0 + 650.0 * rng.random()
            c += (0.5 + rng.random()) * np.sin(2 * math.pi * s / lam + 2 * math.pi * rng.random())
        c /= max(np.max(np.abs(c)), 1e-9)
        c = np.sign(c) * np.clip((np.abs(c) - 0.3) / 0.7, 0.0, 1.0)
        kappa = _moving_average(c * k_allow, int(30.0 / DS))
        kappa[s < 30.0] = 0.0           # start on a straight
        kappa = _moving_average(kappa, int(10.0 / DS))
    elif kind not in ("random", "straight"):
        raise ValueError(f"unknown RoadSpec.kind {kind!r}")
    x, y, psi = _integrate_path(kappa)
    return Road(s, x, y, psi, kappa, z, dz, False)


def _loop004(spec: RoadSpec, rng: np.random.Generator) -> Road:
    """Closed loop: r(u) = R0 (1 + a2 cos 2u + a3 sin(3u+0.5) + a5 cos(5u+1)), scaled to length."""
    u = np.linspace(0.0, 2 * math.pi, 20001)
    r = 1.0 + 0.22 * np.cos(2 * u) + 0.12 * np.sin(3 * u + 0.5) + 0.045 * np.cos(5 * u + 1.0)
    px, py = r * np.cos(u), r * np.sin(u)
    seg = np.hypot(np.diff(px), np.diff(py))
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    scale = spec.length / cum[-1]
    n = int(round(spec.length / DS))
    s = np.arange(n) * DS
    uu = np.interp(s / scale, cum, u)
    rr = 1.0 + 0.22 * np.cos(2 * uu) + 0.12 * np.sin(3 * uu + 0.5) + 0.045 * np.cos(5 * uu + 1.0)
    x = scale * rr * np.cos(uu)
    y = scale * rr * np.sin(uu)
    # heading / curvature on the periodic grid
    dx = (np.roll(x, -1) - np.roll(x, 1)) / (2 * DS)
    dy = (np.roll(y, -1) - np.roll(y, 1)) / (2 * DS)
    psi = np.unwrap(np.arctan2(dy, dx))
    dpsi = np.angle(np.exp(1j * (np.roll(psi, -1) - np.roll(psi, 1))))
    kappa = _moving_average(dpsi / (2 * DS), 9, wrap=True)
    # start (point O) on the straightest part
    ks = _moving_average(np.abs(kappa), int(120.0 / DS), wrap=True)
    i0 = int(np.argmin(ks))
    x, y, kappa = np.roll(x, -i0), np.roll(y, -i0), np.roll(kappa, -i0)
    x, y = x - x[0], y - y[0]
    dx = (np.roll(x, -1) - np.roll(x, 1)) / (2 * DS)
    dy = (np.roll(y, -1) - np.roll(y, 1)) / (2 * DS)
    psi = np.unwrap(np.arctan2(dy, dx))
    # hills, periodic over the loop
    z, dz = _hills(rng, s, spec.grade_max, (spec.length / 2, spec.length / 3, spec.length / 5),
                   periodic_len=spec.length)
    z = z - z[0]
    # curvature-limited speed along the loop with accel/decel limits (forward/backward passes)
    v = np.clip(np.sqrt(spec.loop_lat_acc / np.maximum(np.abs(_moving_average(kappa, int(40 / DS), True)), 1e-6)),
                spec.loop_speed_min, spec.loop_speed_max)
    v[: int(60 / DS)] = spec.loop_speed_max
    for _ in range(2):
        for i in range(1, n):             # accel limit 1.2 m/s²
            v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * 1.2 * DS))
        for i in range(n - 2, -1, -1):    # decel limit 1.8 m/s²
            v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * 1.8 * DS))
        v[-1] = min(v[-1], math.sqrt(v[0] ** 2 + 2 * 1.8 * DS))
    v = _moving_average(v, int(20 / DS), wrap=True)
    return Road(s, x, y, psi, kappa, z, dz, True, v_of_s=v)


def _dlc3888_curvature(spec: RoadSpec, s: np.ndarray) -> np.ndarray:
    """Curvature of the ISO 3888-2 centre line: quintic lateral transitions over sections 2
    and 4 between the lane centres of sections 1/5 and 3 (lateral shift
    ``(1.1 w + 0.25)/2 + 1 + (w + 1)/2`` for vehicle width ``w``, to the left)."""
    w = spec.dlc_vehicle_width
    shift = 0.5 * (1.1 * w + 0.25) + 1.0 + 0.5 * (w + 1.0)
    pos = s - spec.dlc_lead_in
    if spec.dlc_repeat_m > 0.0:
        pos = np.where(pos >= 0.0, np.mod(pos, spec.dlc_repeat_m), pos)
    y2 = np.zeros_like(s)   # d2y/dx2 of the lateral offset
    y1 = np.zeros_like(s)
    for start, length, sign in ((12.0, 13.5, 1.0), (36.5, 12.5, -1.0)):
        u = (pos - start) / length
        inside = (u >= 0.0) & (u <= 1.0)
        uu = np.clip(u, 0.0, 1.0)
        y1 += np.where(inside, sign * shift * 30.0 * uu ** 2 * (1.0 - uu) ** 2 / length, 0.0)
        y2 += np.where(inside, sign * shift * 60.0 * uu * (1.0 - uu) * (1.0 - 2.0 * uu) / length ** 2, 0.0)
    return y2 / (1.0 + y1 * y1) ** 1.5
