"""WGS84 geodetic <-> local tangent plane (ENU), the one geodesy of the package, via pymap3d.

Paper 003 (Jensen et al. 2022, MSSP 171, 108925), Sec. 5.1 converts geodetic coordinates to
Earth-centred Earth-fixed (ECEF) coordinates, Eqs. (14)-(15), and rotates them into a local
tangent plane about an origin, Eq. (16). pymap3d does exactly that (its ellipsoid defaults to
WGS84, so the constants are written nowhere in this package); the paper's frame is
north-east-down, ours is REP-103/105 east-north-up (the rows of Eq. (16) as E, N, -D).

The simulator writes its GNSS fixes with :meth:`LocalTangentPlane.to_geodetic` and the fusion
reads them with :meth:`LocalTangentPlane.to_enu`: one implementation, so a round trip is exact
to the conversion's own accuracy. Pure numpy + pymap3d, no ROS import.
"""
from __future__ import annotations

import numpy as np
import pymap3d


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

    @property
    def origin(self) -> tuple:
        return (self.lat_deg, self.lon_deg, self.alt_m)

    def to_enu(self, lat_deg, lon_deg, alt_m) -> np.ndarray:
        e, n, u = pymap3d.geodetic2enu(np.asarray(lat_deg, dtype=float), np.asarray(lon_deg, dtype=float),
                                       np.asarray(alt_m, dtype=float), *self.origin)
        return np.stack(np.broadcast_arrays(e, n, u), axis=-1).astype(float)

    def to_geodetic(self, enu):
        enu = np.asarray(enu, dtype=float)
        if enu.shape[-1] != 3:
            raise ValueError(f"enu must have a trailing dimension of 3, got {enu.shape}")
        lat, lon, alt = pymap3d.enu2geodetic(enu[..., 0], enu[..., 1], enu[..., 2], *self.origin)
        if np.ndim(lat) == 0:
            return float(lat), float(lon), float(alt)
        return np.asarray(lat, float), np.asarray(lon, float), np.asarray(alt, float)
