"""Tests for vehicle_estimation.estimators.common.geodesy (WGS84 <-> ENU)."""
import math

import numpy as np
import pytest

from vehicle_estimation.estimators.common.geodesy import (WGS84_A, WGS84_B, LocalTangentPlane, ecef_to_geodetic,
                                             geodetic_to_ecef)


def test_ecef_known_points():
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [WGS84_A, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(90.0, 0.0, 0.0), [0.0, 0.0, WGS84_B], atol=1e-6)
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 90.0, 100.0), [0.0, WGS84_A + 100.0, 0.0], atol=1e-6)
    # 45 N, 45 E, h = 0: x = y = N/2, z = N (1 - e2) sin(45), N = prime-vertical radius
    lat = math.radians(45.0)
    e2 = 6.69437999014e-3
    n = WGS84_A / math.sqrt(1 - e2 * math.sin(lat) ** 2)
    np.testing.assert_allclose(geodetic_to_ecef(45.0, 45.0, 0.0),
                               [n * 0.5, n * 0.5, n * (1 - e2) * math.sin(lat)], rtol=1e-12)


def test_ecef_round_trip_vectorised():
    rng = np.random.default_rng(1)
    lat = rng.uniform(-89.9, 89.9, 1000)
    lon = rng.uniform(-180, 180, 1000)
    alt = rng.uniform(-500, 9000, 1000)
    la, lo, al = ecef_to_geodetic(geodetic_to_ecef(lat, lon, alt))
    np.testing.assert_allclose(la, lat, atol=1e-9)
    np.testing.assert_allclose(((lo - lon + 180) % 360) - 180, 0.0, atol=1e-9)
    np.testing.assert_allclose(al, alt, atol=1e-4)


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
