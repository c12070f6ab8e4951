"""Tests of the paper-003 training phase: vehicle_estimation.estimators.mass.calibration and training/calibrate."""

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.estimators.mass import calibration as cal
from vehicle_estimation.estimators.mass.mass_rls import EngineTorqueRegression, MassRLSConfig
from vehicle_estimation.contract.vehicle import load_vehicle_params, read_ros_params_file

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
AUDI = load_vehicle_params(PARAMS_DIR / "audi_a4.yaml")
AUDI_G = np.array([AUDI.effective_gearing(j) for j in range(1, 8)])


def synthetic_ratios(rng, counts=(300, 800, 2000, 4000, 8000, 12000, 6000), spread=0.004, outliers=3000):
    parts = [g * (1.0 + spread * rng.standard_normal(n)) for g, n in zip(AUDI_G, counts)]
    # shifts, launch slip, coasting: ratios anywhere in the range
    parts.append(np.exp(rng.uniform(np.log(4.0), np.log(60.0), outliers)))
    return np.concatenate(parts)


def test_gear_ratios_recovered_from_synthetic_ratios():
    rng = np.random.default_rng(1)
    est = cal.estimate_gear_ratios(synthetic_ratios(rng), n_gears=7, width=0.02)
    assert len(est.gearings) == 7
    rel = np.asarray(est.gearings) / AUDI_G - 1.0
    assert np.max(np.abs(rel)) < 0.005, rel            # paper's target is 2 % (Table 4)
    ratios = est.transmission_ratios(AUDI.final_drive, AUDI.wheel_radius)
    assert ratios == pytest.approx(AUDI.gear_ratios, rel=0.005)


def test_gear_ratios_without_gear_count_finds_the_peaks():
    rng = np.random.default_rng(2)
    est = cal.estimate_gear_ratios(synthetic_ratios(rng, outliers=500), width=0.02, min_prominence=0.01)
    assert len(est.gearings) == 7
    assert np.asarray(est.gearings) == pytest.approx(AUDI_G, rel=0.005)


def test_too_few_gear_peaks_is_an_error():
    rng = np.random.default_rng(3)
    ratios = AUDI_G[4] * (1.0 + 0.003 * rng.standard_normal(2000))
    with pytest.raises(ValueError, match="gear peaks"):
        cal.estimate_gear_ratios(ratios, n_gears=7)


def test_histogram_is_eq50_with_widening_intervals():
    rng = np.random.default_rng(4)
    r = rng.uniform(5.0, 50.0, 500)
    grid, counts = cal.gear_ratio_histogram(r, 5.0, 50.0, width=0.02, resolution=0.01)
    brute = np.array([np.count_nonzero((r >= 0.98 * g) & (r <= 1.02 * g)) for g in grid])
    assert np.array_equal(counts, brute)
    assert np.allclose(np.diff(np.log(grid)), math.log(1.01))


def test_speed_ratios_skip_idle_and_standstill():
    w = np.array([AUDI.engine_idle_speed, 200.0, 300.0, 300.0])
    v = np.array([10.0, 10.0, 0.5, 20.0])
    assert cal.speed_ratios(w, v, idle_speed=AUDI.engine_idle_speed) == pytest.approx([20.0, 15.0])


def _synthetic_drive(rng, n=3000, truth=(0.60, 0.010, 0.24, 5.0), w=(-45.0, 280.0, 0.02, -3.0e-6), noise=1.0):
    mass = 1580.0
    gear = rng.integers(1, 8, n)
    G = AUDI_G[gear - 1]
    v = rng.uniform(3.0, 40.0, n)
    a = rng.uniform(0.0, 2.0, n) / np.sqrt(gear)
    slope = rng.uniform(-0.06, 0.06, n)
    b0, B = cal.dynamics_torque_basis(mass, v, a, slope, G, wheel_radius=AUDI.wheel_radius,
                                      air_density=AUDI.air_density, gravity=AUDI.gravity)
    torque = b0 + B @ np.asarray(truth)
    rpm = rng.uniform(1000.0, 5500.0, n)
    load = (torque - w[0] - w[2] * rpm - w[3] * rpm ** 2) / w[1] + noise / w[1] * rng.standard_normal(n)
    return mass, v, a, slope, G, load, rpm * math.pi / 30.0


def test_grid_search_recovers_known_drag_and_rolling_resistance():
    rng = np.random.default_rng(5)
    mass, v, a, slope, G, load, we = _synthetic_drive(rng)
    fit = cal.fit_torque_model(mass, v, a, slope, G, load, we, wheel_radius=AUDI.wheel_radius,
                               air_density=AUDI.air_density, gravity=AUDI.gravity)
    assert fit.drag_area == pytest.approx(0.60)
    assert fit.rolling_resistance == pytest.approx(0.010)
    assert fit.engine_inertia == pytest.approx(0.24)
    assert fit.wheel_inertia == pytest.approx(5.0)
    assert fit.coefficients == pytest.approx((-45.0, 280.0, 0.02, -3.0e-6), rel=0.05, abs=0.5)
    assert fit.r2 > 0.99
    assert fit.on_grid_edge == ()
    # The fitted map is what the mass core evaluates (Eq. 49, N_e in rpm).
    reg = EngineTorqueRegression(fit.coefficients, "rpm")
    w0, w1, w2, w3 = fit.coefficients
    assert reg.torque(0.5, 3000 * math.pi / 30) == pytest.approx(w0 + 0.5 * w1 + 3000 * w2 + 3000 ** 2 * w3)


def test_closed_form_grid_equals_explicit_regression_per_grid_point():
    rng = np.random.default_rng(6)
    mass, v, a, slope, G, load, we = _synthetic_drive(rng, n=400, noise=15.0)
    grid = {"drag_area": (0.4, 0.8, 0.1), "rolling_resistance": (0.006, 0.014, 0.004),
            "engine_inertia": (0.1, 0.3, 0.1), "wheel_inertia": (3.0, 7.0, 2.0)}
    fit = cal.fit_torque_model(mass, v, a, slope, G, load, we, wheel_radius=AUDI.wheel_radius,
                               air_density=AUDI.air_density, gravity=AUDI.gravity, grid=grid)
    b0, B = cal.dynamics_torque_basis(mass, v, a, slope, G, wheel_radius=AUDI.wheel_radius,
                                      air_density=AUDI.air_density, gravity=AUDI.gravity)
    X = cal.torque_features(load, we, 2)
    best, best_ss = None, math.inf
    for ca in np.arange(0.4, 0.8001, 0.1):
        for cr in np.arange(0.006, 0.0141, 0.004):
            for ie in np.arange(0.1, 0.3001, 0.1):
                for iw in np.arange(3.0, 7.001, 2.0):
                    target = b0 + B @ np.array([ca, cr, ie, iw])
                    w, *_ = np.linalg.lstsq(X / X.max(axis=0), target, rcond=None)
                    ss = float(np.sum((target - (X / X.max(axis=0)) @ w) ** 2))
                    if ss < best_ss:
                        best, best_ss = (ca, cr, ie, iw), ss
    assert (fit.drag_area, fit.rolling_resistance, fit.engine_inertia, fit.wheel_inertia) == pytest.approx(best)
    assert fit.rmse == pytest.approx(math.sqrt(best_ss / v.size), rel=1e-6)


def test_grid_search_needs_enough_samples():
    X = np.ones((5, 4))
    with pytest.raises(ValueError, match="valid samples"):
        cal.grid_search(X, np.ones(5), np.ones((5, 4)))


def test_debias_grade_recovers_a_constant_offset():
    rng = np.random.default_rng(8)
    ds = rng.uniform(0.0, 8.0, 5000)
    true_sin = 0.03 * np.sin(np.cumsum(ds) / 700.0)
    height = float(np.sum(true_sin * ds))
    corrected, offset = cal.debias_grade(true_sin + 0.009, ds, height)
    assert offset == pytest.approx(0.009, abs=1e-9)
    assert corrected == pytest.approx(true_sin, abs=1e-9)


def test_calibrate_cli_on_a_simulated_bag(tmp_path):
    from vehicle_estimation.sim.bag import write_bag
    from vehicle_estimation.sim.profiles import SpeedProfile
    from vehicle_estimation.sim.road import RoadSpec
    from vehicle_estimation.sim.scenario import Scenario, SensorConfig
    from vehicle_estimation.sim.simulate import simulate
    from vehicle_estimation.training import calibrate

    pts = ((0, 0), (14, 30), (20, 30), (30, 12), (42, 38), (70, 38), (80, 25), (95, 25), (102, 8),
           (110, 8), (118, 20), (130, 14), (140, 0), (144, 0))
    scn = Scenario(name="cal", vehicle=AUDI, duration_s=150.0, seed=9,
                   speed_profile=SpeedProfile(kind="points", points=pts),
                   road=RoadSpec(kind="random", grade_max=0.04),
                   sensors=dataclasses.replace(SensorConfig(), imu_rate=50.0, speed_rate=20.0,
                                               joint_states_rate=50.0, powertrain_rate=50.0, gnss_rate=1.0))
    result = simulate(scn)
    gears = sorted(set(result.truth["gear"][result.truth["vx"] > 3.0].tolist()))
    bag = write_bag(result, tmp_path / "drive")
    out = tmp_path / "calibrated.yaml"
    parser = argparse.ArgumentParser()
    calibrate.add_arguments(parser)
    args = parser.parse_args([str(bag), "--mass", str(AUDI.mass), "--out", str(out), "--gears", str(len(gears)),
                              "--vehicle", str(PARAMS_DIR / "audi_a4.yaml")])
    assert calibrate.main(args) == 0
    vehicle = load_vehicle_params(out)
    merged = read_ros_params_file(out)
    config = MassRLSConfig.from_mapping(merged["mass"])
    assert len(config.torque_regression) == 4
    assert config.torque_regression_speed_unit == "rpm"
    assert 0.0 < config.torque_regression_relative_std < 0.1     # how well the map is known
    covariance = config.model_covariance()                        # the map and C_a, C_r, I_e, I_w
    assert covariance is not None and covariance.shape == (8, 8)
    assert np.all(np.linalg.eigvalsh(covariance) > -1e-9 * np.max(np.diag(covariance)))
    for j, gear in enumerate(gears):
        # only i_t i_d / r is observable; the file keeps the base i_d and r
        assert vehicle.effective_gearing(j + 1) == pytest.approx(AUDI.effective_gearing(gear), rel=0.02)
    assert vehicle.mass == AUDI.mass


def test_calibrate_cli_reports_a_missing_bag(tmp_path, capsys):
    from vehicle_estimation.training import calibrate
    parser = argparse.ArgumentParser()
    calibrate.add_arguments(parser)
    args = parser.parse_args([str(tmp_path / "nope"), "--mass", "1500", "--out", str(tmp_path / "x.yaml")])
    assert calibrate.main(args) == 2
    assert "no such bag" in capsys.readouterr().err


def test_the_map_s_relative_std_is_the_spread_of_refitted_maps():
    """map_relative_std against Monte Carlo: refit a linear map on fresh AR(1) residuals (rho
    0.9, as a torque map's between consecutive windows) and take the spread of the fitted
    torque at the mean row; the formula's mean over the refits is that spread within 15 %. Taken
    as white (rho = 0) it would be 4 times too small."""
    from vehicle_estimation.estimators.mass.calibration import map_relative_std
    rng = np.random.default_rng(3)
    n = 600
    X = np.column_stack([np.ones(n), rng.uniform(0.2, 1.0, n), rng.uniform(1.0, 4.0, n)])
    w_true = np.array([5.0, 120.0, 10.0])
    fits, stds = [], []
    for _ in range(300):
        e = np.empty(n)
        e[0] = rng.normal()
        for k in range(1, n):
            e[k] = 0.9 * e[k - 1] + math.sqrt(1 - 0.81) * rng.normal()
        y = X @ w_true + 8.0 * e
        w, *_ = np.linalg.lstsq(X, y, rcond=None)
        fits.append(X.mean(axis=0) @ w)
        stds.append(map_relative_std(X, w, y - X @ w))
    spread = float(np.std(fits) / (X.mean(axis=0) @ w_true))
    assert float(np.mean(stds)) == pytest.approx(spread, rel=0.15)


def _refits(rng, X, B, zeta, count=200, rho=0.9, sigma=6.0):
    """Least-squares refits of b0 = [X, -B] zeta on fresh AR(1) residuals (``rho``): per refit
    the fitted [w, theta] and joint_covariance's sigmas (no grid rounding)."""
    from vehicle_estimation.estimators.mass.calibration import joint_covariance
    Z = np.column_stack([X, -B])
    scale = np.max(np.abs(Z), axis=0)
    fits, sigmas = [], []
    for _ in range(count):
        e = np.empty(len(X))
        e[0] = rng.normal()
        for k in range(1, len(X)):
            e[k] = rho * e[k - 1] + math.sqrt(1 - rho * rho) * rng.normal()
        b0 = Z @ zeta + sigma * e
        fit = np.linalg.lstsq(Z / scale, b0, rcond=None)[0] / scale
        fits.append(fit)
        sigmas.append(np.sqrt(np.diag(joint_covariance(X, B, b0 - Z @ fit, [0.0] * 4))))
    return np.asarray(fits), np.asarray(sigmas)


def test_the_joint_covariance_is_the_spread_of_refitted_vehicle_values():
    """joint_covariance against Monte Carlo: T = X w + B theta (the Eq.-48 fit, unconstrained)
    refitted on fresh AR(1) residuals (rho 0.9); the predicted sigma of each vehicle value is
    the spread of the refits within 20 %. These columns change from sample to sample, so the
    residuals' correlation hardly widens them; the white formula times (1 + rho) / (1 - rho),
    right for a constant column, would be 4 times too wide. A slowly changing column (the
    drag's, the speed held for a while) is widened as a mean is, and its sigma still matches."""
    from vehicle_estimation.estimators.mass.calibration import joint_covariance
    rng = np.random.default_rng(4)
    n = 800
    v = rng.uniform(8.0, 35.0, n)
    X = np.column_stack([np.ones(n), rng.uniform(0.1, 1.0, n), rng.uniform(1000.0, 4000.0, n)])
    B = np.column_stack([0.6 * v * v / 40.0, 1500.0 * 9.81 * (1.0 + 0.05 * rng.normal(size=n)) / 40.0,
                         rng.uniform(0.0, 2.0, n) * 40.0, rng.uniform(0.0, 2.0, n) / (0.1 * 40.0)])
    zeta = np.array([-20.0, 250.0, 0.01, 0.6, 0.010, 0.25, 5.0])
    fits, sigmas = _refits(rng, X, B, zeta)
    assert sigmas.mean(axis=0)[3:] == pytest.approx(fits.std(axis=0)[3:], rel=0.2)
    residual = rng.normal(size=n)
    rounded = joint_covariance(X, B, residual, [0.05, 0.002, 0.02, 1.0])
    plain = joint_covariance(X, B, residual, [0.0] * 4)
    assert rounded[3, 3] - plain[3, 3] == pytest.approx(0.05 ** 2 / 12.0, rel=1e-6)
    assert np.allclose(rounded[:3, :3], plain[:3, :3])
    slow = np.repeat(rng.uniform(8.0, 35.0, n // 40), 40)
    B_slow = B.copy()
    B_slow[:, 0] = 0.6 * slow * slow / 40.0
    fits, sigmas = _refits(rng, X, B_slow, zeta)
    assert sigmas.mean(axis=0)[3] == pytest.approx(fits.std(axis=0)[3], rel=0.2)


def test_calibrate_reads_a_turned_imus_forward_specific_force(tmp_path):
    """The kinematic grade of the calibration starts from f_x in base_link: an IMU facing left
    (its -y forward) read with the vehicle file's mounting gives the level IMU's f_x, less the
    noise and bias the turn moves between axes; read as if level, it gives the lateral one."""
    from vehicle_estimation.training.calibrate import read_drive
    from vehicle_estimation.validation import wltp_drive

    level = wltp_drive.generate(tmp_path / "level", duration=30.0, seed=2)[0]
    turned = wltp_drive.generate(tmp_path / "turned", duration=30.0, seed=2, imu_rpy_deg=(0.0, 0.0, 90.0))[0]
    mounting = load_vehicle_params(tmp_path / "turned" / f"{wltp_drive.VEHICLE_NAME}.yaml").imu_mounting_rpy
    reference = read_drive(level).accel_x
    read = read_drive(turned, None, mounting).accel_x
    assert np.abs(read - reference).max() < 0.5                  # 2 x (0.05 bias + 5 sigma of 0.05 noise)
    assert np.std(reference) > 0.3                                 # a drive that accelerates
    assert np.abs(read_drive(turned).accel_x - reference).max() > 1.0
