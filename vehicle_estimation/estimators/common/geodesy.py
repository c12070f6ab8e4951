"""WGS84 geodetic <-> local tangent plane (ENU) conversion.

Follows paper 003 (Jensen et al. 2022, MSSP 171, 108925), Sec. 5.1: geodetic
coordinates are converted to Earth-centred Earth-fixed (ECEF) coordinates,
Eqs. (14)-(15), and then rotated into a local tangent plane about an origin,
Eq. (16).  The paper uses north-east-down; this module returns REP-103/105
east-north-up (ENU), i.e. the rows of Eq. (16) reordered as (E, N, -D).

Pure numpy, no ROS import.
"""
from __future__ import annotations

import numpy as np

# WGS84 ellipsoid
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)            # first eccentricity squared
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)         # second eccentricity squared


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """Geodetic (deg, deg, m above ellipsoid) -> ECEF [m], paper Eqs. (14)-(15).

    Vectorised: returns an array of shape ``broadcast_shape + (3,)``.
    """
    lat = np.radians(np.asarray(lat_deg, dtype=float))
    lon = np.radians(np.asarray(lon_deg, dtype=float))
    h = np.asarray(alt_m, dtype=float)
    s_lat, c_lat = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s_lat * s_lat)   # prime-vertical radius
    x = (n + h) * c_lat * np.cos(lon)
    y = (n + h) * c_lat * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * s_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(ecef) -> tuple:
    """ECEF [m] -> geodetic (lat_deg, lon_deg, alt_m).

    Bowring's parametric-latitude iteration (3 iterations: sub-millimetre for
    terrestrial heights).  Vectorised over leading dimensions.
    """
    e = np.asarray(ecef, dtype=float)
    x, y, z = e[..., 0], e[..., 1], e[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    beta = np.arctan2(z, (1.0 - WGS84_F) * p)            # initial parametric latitude
    for _ in range(3):
        sb, cb = np.sin(beta), np.cos(beta)
        lat = np.arctan2(z + WGS84_EP2 * WGS84_B * sb ** 3, p - WGS84_E2 * WGS84_A * cb ** 3)
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
    s_lat, c_lat = np.sin(lat), np.cos(lat)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * s_lat * s_lat)
    # Height, numerically stable at all latitudes.
    alt = p * c_lat + z * s_lat - WGS84_A * WGS84_A / n
    return np.degrees(lat), np.degrees(lon), alt


def ecef_to_enu_matrix(lat_deg: float, lon_deg: float) -> np.ndarray:
    """Rotation ECEF -> ENU at (lat, lon); rows are the E, N, U unit vectors.

    This is Eq. (16) of paper 003 with rows reordered from NED to ENU.
    """
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array([
        [-so, co, 0.0],
        [-sl * co, -sl * so, cl],
        [cl * co, cl * so, sl],
    ])


class LocalTangentPlane:
    """WGS84 <-> ENU (east, north, up) about a fixed origin (REP-105 ``map``/``odom`` style).

    ``to_enu`` is vectorised: scalar inputs give shape (3,), array inputs of shape
    S give shape S + (3,).  ``to_geodetic`` accepts (3,) or (..., 3) and returns a
    tuple of floats (or arrays) ``(lat_deg, lon_deg, alt_m)``.
    """

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float):
        vals = (float(lat_deg), float(lon_deg), float(alt_m))
        if not all(np.isfinite(vals)):
            raise ValueError(f"non-finite origin {vals}")
        if not -90.0 <= vals[0] <= 90.0:
            raise ValueError(f"latitude out of range: {vals[0]}")
        self.lat_deg, self.lon_deg, self.alt_m = vals
        self._origin_ecef = geodetic_to_ecef(*vals)
        self._r_enu_ecef = ecef_to_enu_matrix(vals[0], vals[1])

    @property
    def origin(self) -> tuple:
        return (self.lat_deg, self.lon_deg, self.alt_m)

    def to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        d = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - self._origin_ecef
        return d @ self._r_enu_ecef.T

    def to_geodetic(self, enu):
        enu = np.asarray(enu, dtype=float)
        if enu.shape[-1] != 3:
            raise ValueError(f"enu must have a trailing dimension of 3, got {enu.shape}")
        ecef = enu @ self._r_enu_ecef + self._origin_ecef
        lat, lon, alt = ecef_to_geodetic(ecef)
        if np.ndim(lat) == 0:
            return float(lat), float(lon), float(alt)
        return lat, lon, alt
