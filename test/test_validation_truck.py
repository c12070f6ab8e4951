"""The 36 t truck of NREL FASTSim 3 on a long-haul road (vehicle_estimation.validation.fastsim_truck):
the low-excitation mass case is what it claims to be."""

from __future__ import annotations

import math

import numpy as np
import pytest

fastsim = pytest.importorskip("fastsim")

from vehicle_estimation.contract.vehicle import VehicleParams, load_vehicle_params
from vehicle_estimation.validation import fastsim_drive as fd
from vehicle_estimation.validation import fastsim_truck as ft

DURATION = 420.0     # s: the start and five minutes of cruise


@pytest.fixture(scope="module")
def drive():
    return ft.simulate(DURATION)


def test_the_truck_is_fastsims_conventional_vehicle_at_36_t(drive):
    assert drive.mass == pytest.approx(36000.0)
    assert drive.vehicle["veh.chassis.num_wheels"] == 18
    assert drive.vehicle["veh.pt_type.Conv.fc.pwr_out_max_watts"] == pytest.approx(380000.0)


def test_cruise_is_low_excitation(drive):
    """After the start the regressor a + g (sin(theta) + C_r) of the longitudinal dynamics varies
    by well under 0.1 m/s^2, the case where least squares with noise in it is biased."""
    h, t = drive.history, drive.t
    slope = np.arctan(h["grade"])
    a = np.gradient(h["speed"], t)
    phi = a + fd.G_MODEL * (np.sin(slope) + ft.TRUCK["chassis.wheel_rr_coef"] * np.cos(slope))
    cruise = t > 150.0
    assert 0.03 < float(np.std(phi[cruise])) < 0.09
    assert float(np.max(np.abs(a[cruise]))) < 0.05
    assert 20.0 < float(np.min(h["speed"][cruise])) and float(np.max(h["speed"][cruise])) < 24.0
    assert np.max(np.abs(np.degrees(slope))) < 1.0


def test_the_vehicle_file_describes_fastsims_truck(tmp_path, drive):
    path = tmp_path / "truck.yaml"
    path.write_text(ft.params_yaml(), encoding="utf-8")
    vehicle = load_vehicle_params(path)
    assert isinstance(vehicle, VehicleParams)
    assert vehicle.name == ft.VEHICLE_NAME and vehicle.mass == pytest.approx(drive.mass)
    assert vehicle.rolling_resistance == pytest.approx(0.0055) and vehicle.gravity == pytest.approx(fd.G_MODEL)
    # FASTSim's drag power at cruise is the vehicle file's 1/2 rho C_d A v^3
    h = drive.history
    v_avg = 0.5 * (h["speed"][1:] + h["speed"][:-1])
    cruise = v_avg > 20.0
    k = float(np.median(h["pwr_drag"][1:][cruise] / v_avg[cruise] ** 3))
    assert 0.5 * vehicle.air_density * vehicle.drag_area == pytest.approx(k, rel=1e-3)
    assert math.isfinite(vehicle.wheel_inertia) and vehicle.wheel_inertia > 0.0
