"""Tests for vehicle_estimation.estimators.common.geodesy (WGS84 <-> ENU over pymap3d), against
values computed here from the WGS84 definition, independently of the library."""
import math

import numpy as np
import pytest

from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane

WGS84_A = 6378137.0                      # semi-major axis [m] (the WGS84 definition)
WGS84_E2 = 6.69437999014e-3              # first eccentricity squared


def test_enu_matches_the_ellipsoid_radii_of_curvature():
    """Small offsets scale with the prime-vertical and meridian radii at the origin's latitude."""
    for lat0 in (0.0, 35.0, 57.0488, 80.0):
        ltp = LocalTangentPlane(lat0, 9.9, 0.0)
        s = math.sin(math.radians(lat0))
        n_radius = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
        m_radius = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s) ** 1.5
        d = 1e-5   # deg: ~1 m, where arc and chord agree to micrometres
        east = ltp.to_enu(lat0, 9.9 + d, 0.0)[0]
        north = ltp.to_enu(lat0 + d, 9.9, 0.0)[1]
        assert east == pytest.approx(n_radius * math.cos(math.radians(lat0)) * math.radians(d), rel=1e-5)
        assert north == pytest.approx(m_radius * math.radians(d), rel=1e-5)


def test_enu_known_offsets():
    ltp = LocalTangentPlane(0.0, 0.0, 0.0)
    # 1 mdeg east at the equator: a * dlon (arc) ~= chord to < 1 mm
    e = ltp.to_enu(0.0, 1e-3, 0.0)
    assert e.shape == (3,)
    np.testing.assert_allclose(e[0], WGS84_A * math.radians(1e-3), atol=1e-3)
    assert abs(e[1]) < 1e-6
    # 1e-3 deg north at the equator: meridian radius M = a (1 - e2) -> 110.574 m
    n = ltp.to_enu(1e-3, 0.0, 0.0)
    np.testing.assert_allclose(n[1], 110.574, atol=2e-3)
    assert abs(n[0]) < 1e-6
    # Straight up
    np.testing.assert_allclose(LocalTangentPlane(55.7, 12.5, 30.0).to_enu(55.7, 12.5, 130.0),
                               [0.0, 0.0, 100.0], atol=1e-6)
    # Origin maps to zero
    ltp2 = LocalTangentPlane(57.0, 9.9, 20.0)
    np.testing.assert_allclose(ltp2.to_enu(57.0, 9.9, 20.0), 0.0, atol=1e-9)


def test_enu_round_trip_and_vectorised():
    ltp = LocalTangentPlane(57.0488, 9.9217, 15.0)   # Aalborg
    rng = np.random.default_rng(2)
    enu = rng.uniform(-20000, 20000, (200, 3))
    enu[:, 2] = rng.uniform(-100, 500, 200)
    lat, lon, alt = ltp.to_geodetic(enu)
    back = ltp.to_enu(lat, lon, alt)
    assert back.shape == (200, 3)
    np.testing.assert_allclose(back, enu, atol=1e-5)
    la, lo, al = ltp.to_geodetic(np.array([100.0, -50.0, 3.0]))
    assert isinstance(la, float)
    np.testing.assert_allclose(ltp.to_enu(la, lo, al), [100.0, -50.0, 3.0], atol=1e-6)
    # East of the origin increases longitude, north increases latitude
    assert lo > 9.9217 and la < 57.0488


def test_bad_origin():
    with pytest.raises(ValueError):
        LocalTangentPlane(float("nan"), 0.0, 0.0)
    with pytest.raises(ValueError):
        LocalTangentPlane(91.0, 0.0, 0.0)
