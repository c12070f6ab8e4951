"""Tests of the paper-004 vehicle model (vehicle_estimation.estimators.state.vehicle_model, Eqs. 1-9)."""

import math
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.estimators.state.vehicle_model import (
    VehicleInputs,
    free_rolling_wheel_speeds,
    measurement,
    sideslip,
    state_derivative,
    transition,
    tyre_forces,
    _dugoff,
)
from vehicle_estimation.contract.vehicle import load_vehicle_params

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SEDAN = load_vehicle_params(PARAMS_DIR / "sedan_d_class.yaml")
DT = 0.01


def _simulate(params, v0, delta, seconds, front_slip=0.0, slope=0.0):
    x = np.array([v0, 0.0, 0.0, 0.0, 0.0])
    slip = np.array([front_slip, front_slip, 0.0, 0.0])
    for _ in range(int(round(seconds / DT))):
        u = VehicleInputs(delta, free_rolling_wheel_speeds(x, delta, params, slip), slope)
        x = transition(x, u, params, DT)
    return x


def test_straight_line_steady_state():
    x = _simulate(SEDAN, 20.0, 0.0, 5.0, front_slip=0.003)
    assert abs(x[1]) < 1e-9 and abs(x[2]) < 1e-9 and abs(x[4]) < 1e-9
    # driving slip accelerates: ax = sum(Fx)/m - drag/m > 0 with Fx ~ 2 C_s sigma
    assert x[3] > 0.0 and x[0] > 20.0


def test_straight_line_on_slope_gravity():
    # free-rolling wheels on a 3 % uphill: ax (kinematic) ~ -g sin(theta) - drag/m
    theta = math.atan(0.03)
    x0 = np.array([20.0, 0, 0, 0, 0])
    u = VehicleInputs(0.0, free_rolling_wheel_speeds(x0, 0.0, SEDAN), theta)
    drag = 0.5 * SEDAN.drag_area * SEDAN.air_density * x0[0] ** 2 / SEDAN.mass
    assert state_derivative(x0, u, SEDAN)[0] == pytest.approx(-SEDAN.gravity * math.sin(theta) - drag)
    x = x0.copy()
    x[3] = state_derivative(x0, u, SEDAN)[0]
    # the accelerometer sees the specific force, i.e. ~ -drag/m only
    z = measurement(x, u, SEDAN)
    assert z[0] == pytest.approx(-drag, abs=2e-3)


@pytest.mark.parametrize("vx", [10.0, 20.0, 30.0])
def test_steady_cornering_matches_linear_bicycle(vx):
    """r = vx delta / (L + K vx^2), K = m/L (l_R/C_F - l_F/C_R), C_F/R = 2 C_alpha per axle."""
    p = SEDAN
    delta = 0.01
    L = p.wheelbase
    K = p.mass / L * (p.lr / (2 * p.cornering_stiffness_front) - p.lf / (2 * p.cornering_stiffness_rear))
    # small driving slip on the front wheels to roughly hold the speed against drag
    x = _simulate(p, vx, delta, 8.0, front_slip=0.0015)
    expected = x[0] * delta / (L + K * x[0] ** 2)
    assert x[2] == pytest.approx(expected, rel=0.01)
    assert x[4] == pytest.approx(x[0] * x[2], rel=0.02)      # ay = vx r in steady state


def test_dugoff_saturates_at_mu_fz():
    fz = np.full(4, 4000.0)
    mu_fz = SEDAN.road_friction * fz
    for s in (0.0, 0.01, 0.05, 0.2, 1.0, 5.0, 50.0):
        for a in (0.0, 0.02, 0.1, 0.5, 1.2):
            fx, fy = _dugoff(np.full(4, s), np.full(4, a), fz, SEDAN)
            res = np.hypot(fx, fy)
            assert np.all(res <= mu_fz * (1 + 1e-12))
    # pure driving slip: lambda -> mu Fz / (2 C_s), |F| -> (1 - mu Fz / (4 C_s)) mu Fz (~0.99 mu Fz)
    fx, fy = _dugoff(np.full(4, 1e6), np.zeros(4), fz, SEDAN)
    limit = (1 - mu_fz / (4 * SEDAN.longitudinal_stiffness)) * mu_fz
    assert np.allclose(fx, limit, rtol=1e-5)
    fx, fy = _dugoff(np.zeros(4), np.full(4, 1.565), fz, SEDAN)
    assert np.allclose(np.hypot(fx, fy), mu_fz, rtol=1e-3)
    # locked wheel (1 + sigma = 0): finite, braking force mu Fz
    fx, fy = _dugoff(np.full(4, -1.0), np.zeros(4), fz, SEDAN)
    assert np.all(np.isfinite(fx)) and np.allclose(fx, -mu_fz, rtol=1e-6)
    # linear region: F = C sigma / (1 + sigma)
    fx, _ = _dugoff(np.full(4, 0.001), np.zeros(4), fz, SEDAN)
    assert np.allclose(fx, SEDAN.longitudinal_stiffness * 0.001 / 1.001)


def test_vertical_loads_sum_and_transfer():
    x = np.array([20.0, 0.0, 0.0, 2.0, 3.0])
    u = VehicleInputs(0.0, free_rolling_wheel_speeds(x, 0.0, SEDAN), 0.0)
    tf = tyre_forces(x, u, SEDAN)
    assert tf.fz.sum() == pytest.approx(SEDAN.mass * SEDAN.gravity)
    assert tf.fz[0] < tf.fz[1] and tf.fz[2] < tf.fz[3]          # ay > 0 (left turn): right wheels loaded
    assert tf.fz[:2].sum() < SEDAN.mass * SEDAN.gravity * SEDAN.lr / SEDAN.wheelbase  # ax > 0: rear loaded


def test_vectorised_transition_matches_per_point():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(10, 5)) * [2.0, 0.5, 0.1, 1.0, 1.0] + [20.0, 0, 0, 0, 0]
    x0 = np.array([20.0, 0.1, 0.05, 0.3, 1.0])
    for u in (VehicleInputs(0.03, free_rolling_wheel_speeds(x0, 0.03, SEDAN, 0.01), 0.03, 1400.0),
              VehicleInputs(0.03, [np.nan] * 4, 0.03),
              VehicleInputs(0.03, [np.nan] * 4, 0.0, drive_torque=800.0, brake_torques=[0, 0, 100, 100])):
        for dt in (0.005, 0.01, 0.025):
            batch = transition(X, u, SEDAN, dt)
            single = np.array([transition(x, u, SEDAN, dt) for x in X])
            assert np.allclose(batch, single, rtol=0, atol=1e-12)
            assert np.allclose(state_derivative(X, u, SEDAN),
                               np.array([state_derivative(x, u, SEDAN) for x in X]), atol=1e-9)
        assert np.allclose(measurement(X, u, SEDAN), np.array([measurement(x, u, SEDAN) for x in X]))


def test_fallback_without_wheel_speeds_uses_state_ax():
    x = np.array([20.0, 0.0, 0.0, 1.5, 0.0])
    u = VehicleInputs(0.0, [np.nan] * 4, 0.0)
    xn = transition(x, u, SEDAN, 0.1)
    assert xn[3] == pytest.approx(1.5)                          # random walk
    assert xn[0] == pytest.approx(20.0 + 0.1 * 1.5)
    d = state_derivative(x, u, SEDAN)
    assert d[0] == pytest.approx(1.5) and d[3] == 0.0


def test_standstill_is_finite():
    x = np.zeros(5)
    u = VehicleInputs(0.2, np.zeros(4), 0.05)
    xn = transition(x, u, SEDAN, DT)
    assert np.all(np.isfinite(xn))
    assert sideslip(x) == 0.0


def test_sideslip_eq14():
    assert sideslip(np.array([20.0, 0.5, 0, 0, 0])) == pytest.approx(math.atan(0.5 / 20.0))


def test_tyre_load_exponent_scales_stiffness_with_load():
    """``tyre_load_exponent`` n: C (F_z / F_z0)^n; n = 0 is paper Eq. 9 (constant stiffness)."""
    import dataclasses
    prop = dataclasses.replace(SEDAN, tyre_load_exponent=1.0)
    fz0 = np.array([SEDAN.lr, SEDAN.lr, SEDAN.lf, SEDAN.lf]) / (2 * SEDAN.wheelbase) * SEDAN.mass * SEDAN.gravity
    slip, alpha = np.full(4, 0.002), np.full(4, 0.01)
    # at the static loads both are the paper's tyre
    assert np.allclose(_dugoff(slip, alpha, fz0, prop), _dugoff(slip, alpha, fz0, SEDAN))
    # a corner: 40 % of the load moved from the inner to the outer wheels
    fz = fz0 * np.array([0.6, 1.4, 0.6, 1.4])
    fx0, fy0 = _dugoff(slip, alpha, fz, SEDAN)
    fx1, fy1 = _dugoff(slip, alpha, fz, prop)
    c = np.array([SEDAN.cornering_stiffness_front] * 2 + [SEDAN.cornering_stiffness_rear] * 2)
    # proportional stiffness, linear region: force in proportion to the load, axle sum unchanged
    assert np.allclose(fy1, c * np.tan(alpha) * fz / fz0 / 1.002, rtol=1e-9)
    assert np.allclose(fx1, SEDAN.longitudinal_stiffness * slip * fz / fz0 / 1.002, rtol=1e-9)
    assert fy1[:2].sum() == pytest.approx(fy0[:2].sum(), rel=1e-9)
    # constant stiffness saturates an unloaded wheel where the load-sensitive tyre does not
    alpha = np.full(4, 0.04)
    fy0 = _dugoff(np.zeros(4), alpha, fz, SEDAN)[1]
    fy1 = _dugoff(np.zeros(4), alpha, fz, prop)[1]
    assert fy1[0] + fy1[1] > fy0[0] + fy0[1]
    with pytest.raises(ValueError, match="tyre_load_exponent"):
        dataclasses.replace(SEDAN, tyre_load_exponent=-0.5).validate()


def test_fallback_drive_force_leaves_less_lateral_force_on_the_driven_wheels():
    """Without slip or torques the fallback puts ``drive_force`` on the driven wheels, and the
    lateral force has the friction it leaves (the friction ellipse): nothing changes in the
    tyre's linear range, and near the limit a driven wheel has less lateral force."""
    driven = [i for i in range(4) if i not in SEDAN.undriven_wheels]
    undriven = list(SEDAN.undriven_wheels)
    x = np.array([25.0, -0.5, 0.27, 1.5, 7.0])                  # near the limit: ay 7 m/s^2, mu 0.9
    free = tyre_forces(x, VehicleInputs(0.04, [np.nan] * 4), SEDAN)
    driving = tyre_forces(x, VehicleInputs(0.04, [np.nan] * 4, drive_force=3000.0), SEDAN)
    assert np.all(free.fx == 0.0)
    assert driving.fx[driven] == pytest.approx([1500.0, 1500.0]) and np.all(driving.fx[undriven] == 0.0)
    assert np.array_equal(driving.fy[undriven], free.fy[undriven])
    kept = np.abs(driving.fy[driven]) / np.abs(free.fy[driven])
    assert np.all(kept < 1.0) and kept.min() < 0.8            # the unloaded inner wheel most
    mu_fz = SEDAN.road_friction * driving.fz
    assert np.all(np.hypot(driving.fx, driving.fy) <= mu_fz * (1.0 + 1e-12))
    # with torques the drive force is not used; braking torques share the friction too
    braking = tyre_forces(x, VehicleInputs(0.04, [np.nan] * 4, brake_torques=[400.0] * 4,
                                           drive_force=3000.0), SEDAN)
    assert np.allclose(braking.fx, -400.0 / SEDAN.wheel_radius)
    assert np.all(np.abs(braking.fy) < np.abs(free.fy))
    # the tyre's linear range: the same lateral forces
    gentle = np.array([25.0, -0.02, 0.05, 2.0, 1.0])
    a = tyre_forces(gentle, VehicleInputs(0.01, [np.nan] * 4), SEDAN)
    b = tyre_forces(gentle, VehicleInputs(0.01, [np.nan] * 4, drive_force=3000.0), SEDAN)
    assert np.allclose(a.fy, b.fy, rtol=1e-12)


def test_state_cores_take_the_drive_force_from_their_acceleration_estimate():
    """The CKF/VB-ACKF hand the model the drive force of their own ax, only in the fallback."""
    from vehicle_estimation.estimators.state.ckf import VehicleStateCKF, VehicleStateConfig
    core = VehicleStateCKF(SEDAN, VehicleStateConfig(wheel_slip_forces=False))
    u = VehicleInputs(0.0, [np.nan] * 4, 0.02)
    core.step(0.0, u, np.array([1.0, 0.0, 0.0]))
    core._filter._x[:] = [20.0, 0.0, 0.0, 1.0, 0.0]
    drag = 0.5 * SEDAN.drag_coefficient * SEDAN.frontal_area * SEDAN.air_density * 400.0
    force = core._with_drive_force(u).drive_force
    assert force == pytest.approx(SEDAN.mass * (1.0 + SEDAN.gravity * math.sin(0.02)) + drag)
    core._filter._x[3] = -3.0                                    # braking: no drive force
    assert core._with_drive_force(u).drive_force is None
    torques = VehicleInputs(0.0, [np.nan] * 4, 0.02, drive_torque=100.0)
    core._filter._x[3] = 1.0
    assert core._with_drive_force(torques).drive_force is None
