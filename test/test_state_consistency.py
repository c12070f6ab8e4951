"""Published vehicle-state variances against truth that our simulator did not make.

The state filters take the tyres' cornering stiffness as exact and the road as level across; the
covariance a core publishes adds the vy error that a stiffness off by ``tyre_stiffness_std`` and a
road bank of ``road_bank_std_deg`` cause (``ModelErrorSettings``). On a drive of the CommonRoad
multi-body car (Pacejka tyres, not the filters' Dugoff model; a level road) the shipped tuning
must put 90 % or more of the vy errors within the published 2 sigma, and the check must be able
to fail: with that variance halved, or without the stiffness term, it does.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vehicle_estimation.contract.vehicle import VehicleParams, load_vehicle_params
from vehicle_estimation.estimators.registry import StateSettings, build_state_filter
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs, free_rolling_wheel_speeds
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.paths import params_file

WARMUP_S = 5.0


def test_model_error_widens_the_published_vy_variance_only():
    vehicle = VehicleParams()
    plain = build_state_filter("vbackf", vehicle)
    widened = build_state_filter("vbackf", vehicle, dataclasses.replace(StateSettings.defaults(), tyre_stiffness_std=0.3,
                                                                          road_bank_std_deg=2.0))
    x = np.array([20.0, 0.4, 0.2, 0.0, 4.0])
    for k in range(200):
        inputs = VehicleInputs(steer_angle=0.03, wheel_speeds=free_rolling_wheel_speeds(x, 0.03, vehicle))
        for core in (plain, widened):
            core.step(0.01 * (k + 1), inputs, np.array([0.0, 4.0, 0.2]))
    np.testing.assert_array_equal(plain.x, widened.x)
    vy, r = widened.x[1], widened.x[2]
    added = widened.P - plain.P
    expected = np.zeros((5, 5))
    stiffness = (0.3 * (vy - vehicle.lr * r)) ** 2
    # a 2 deg bank: the rear axle holds l_f/L of m g sin(2 deg) more than ay says
    rear_force = vehicle.mass * vehicle.gravity * np.sin(np.radians(2.0)) * vehicle.lf / vehicle.wheelbase
    bank = (widened.x[0] * rear_force / (2.0 * vehicle.cornering_stiffness_rear)) ** 2
    expected[1, 1] = stiffness + bank
    np.testing.assert_allclose(added, expected, rtol=1e-12, atol=1e-15)
    assert stiffness > 1e-4 and bank > 1e-4           # the rear axle slips, and fast: both matter here
    assert widened.sideslip_variance > plain.sideslip_variance
    np.testing.assert_array_equal(plain.filter.P, widened.filter.P)   # the filter's own is untouched


@pytest.fixture(scope="module")
def slalom(tmp_path_factory):
    pytest.importorskip("vehiclemodels")
    from vehicle_estimation.validation import commonroad as cr
    from vehicle_estimation.validation.lateral import read_drive
    result = cr.sensor_result(cr.simulate("slalom"), seed=11)   # 30 s: 20 s of 0.5 Hz slalom
    return read_drive(cr.write_drive(result, tmp_path_factory.mktemp("cr") / "slalom"))


def _vy_errors_and_variance(drive, settings):
    from vehicle_estimation.validation import lateral
    vehicle = load_vehicle_params(params_file("commonroad_bmw320i"))
    build = lateral.make_core
    try:
        lateral.make_core = lambda name, v, overrides=None: build_state_filter(name, v, settings=settings)
        # without the roll acceleration (vehicle.roll_lever) the errors are twice as large: a
        # variance half as large as the published one is then caught, which the test shows
        est = lateral.run_core("vbackf", drive, vehicle, use_wheels=True, roll_lever=0.0)
    finally:
        lateral.make_core = build
    truth = drive["truth"]
    t, vy, vy_true = metrics.align(est["t"], est["vy"], truth["t"], truth["vy"])
    sel = t >= WARMUP_S
    return np.abs(vy - vy_true)[sel], np.interp(t, est["t"], est["vy_variance"])[sel]


def test_published_vy_variance_is_honest_on_a_foreign_car(slalom):
    from vehicle_estimation.validation.lateral import shipped_state_settings
    shipped = shipped_state_settings()
    assert shipped.tyre_stiffness_std > 0.0 and shipped.road_bank_std_deg > 0.0
    error, variance = _vy_errors_and_variance(slalom, shipped)
    assert float(np.mean(error <= 2.0 * np.sqrt(variance))) >= 0.90
    # this simulator's road is level: without the bank's share the stiffness term alone holds,
    level = dataclasses.replace(shipped, road_bank_std_deg=0.0)
    error, variance = _vy_errors_and_variance(slalom, level)
    within = float(np.mean(error <= 2.0 * np.sqrt(variance)))
    assert within >= 0.90, within
    # and the check can fail: a variance half as large, or one without the model error, is caught
    assert float(np.mean(error <= 2.0 * np.sqrt(0.5 * variance))) < 0.90
    error, variance = _vy_errors_and_variance(slalom, dataclasses.replace(level, tyre_stiffness_std=0.0))
    assert float(np.mean(error <= 2.0 * np.sqrt(variance))) < 0.90


def test_the_imus_stated_noise_keeps_the_learnt_yaw_rate_noise_honest(tmp_path):
    """Where the model is nearly exact (our simulator's car: its own model), the VB-ACKF cannot
    tell the gyro's noise from its process noise: the learnt yaw-rate noise drifts down over
    the demo drive, and with it the published variance (its sigma from 3.6e-3 to 0.7e-3 rad/s;
    86 % of the errors within 2 sigma, 70 % in the last minute). The state node keeps the learnt
    R at or above the IMU's stated noise of each step's mean (96 %; as an addition on top of
    the learnt R it was 100 % at NEES 0.06: over-cautious). The gyro's noise keeps paper 004's
    0.55 s memory (params/estimation.yaml): with the accelerometer's 20 s its learnt noise
    holds the model's yaw error and the variance is cautious instead (NEES 0.10). Through the
    nodes, the demo drive with the IMU covariance in the bag and with it zeroed (unknown,
    REP-145)."""
    from rosharness import replay_side_by_side

    from vehicle_estimation.evaluation.report import read_bag
    from vehicle_estimation.io.bagtools import rewrite_bag
    from vehicle_estimation.sim import scenario_by_name, simulate, write_bag
    from vehicle_estimation.contract import topics as T

    bag = write_bag(simulate(scenario_by_name("default")), tmp_path / "drive")

    def unknown_covariance(msg, index):
        msg.linear_acceleration_covariance[:] = 0.0
        msg.angular_velocity_covariance[:] = 0.0

    sources = {"stated": bag, "unknown": rewrite_bag(bag, tmp_path / "no_covariance", edit={T.IMU: unknown_covariance})}
    records = replay_side_by_side({name: [str(source)] for name, source in sources.items()}, tmp_path)
    within, nees = {}, {}
    for name, record in records.items():
        data = read_bag(record, [T.VEHICLE_STATE, T.GT_VEHICLE_STATE])
        est, truth = data[T.VEHICLE_STATE], data[T.GT_VEHICLE_STATE]
        sel = est["t"] >= est["t"][0] + WARMUP_S
        error = est["yaw_rate"][sel] - np.interp(est["t"][sel], truth["t"], truth["yaw_rate"])
        within[name] = float(np.mean(np.abs(error) <= 2.0 * np.sqrt(est["var_yaw_rate"][sel])))
        nees[name] = float(np.mean(error ** 2 / est["var_yaw_rate"][sel]))
    assert within["stated"] >= 0.95, (within, nees)
    assert within["unknown"] < 0.90, (within, nees)
    assert nees["stated"] > 0.3, (within, nees)     # a floor, not a second noise on top (0.06)
