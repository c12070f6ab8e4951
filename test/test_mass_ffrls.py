"""Tests of the paper-004 FFRLS mass estimator (vehicle_estimation.estimators.mass.mass_ffrls)."""

import dataclasses
import inspect
import math
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.estimators.mass.mass_ffrls import (
    PAPER_SAMPLE_PERIOD_S,
    REJECT_REASONS,
    FFRLSMassConfig,
    FFRLSMassEstimator,
    equivalent_forgetting_factor,
)
from vehicle_estimation.estimators.mass.mass_rls import LongitudinalMassEstimator
from vehicle_estimation.contract.vehicle import load_vehicle_params

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SEDAN = load_vehicle_params(PARAMS_DIR / "sedan_d_class.yaml")   # paper 004 Table 1


def eq28_drive_force(mass, vx, ax, slope, brake_torque, params=SEDAN, rotating_inertia=0.0):
    """Drive force at the wheels that satisfies Eq. (28) exactly (sin/cos, not linearised)."""
    g = params.gravity
    return (mass * g * math.sin(slope) + mass * g * params.rolling_resistance * math.cos(slope)
            + (mass + rotating_inertia) * ax
            + 0.5 * params.drag_coefficient * params.frontal_area * params.air_density * vx * vx
            + brake_torque / params.wheel_radius)


def synthetic_drive(rng, n, dt=0.1):
    """Speed, acceleration, slope and brake torque of a drive with accelerating, cruising and
    braking phases on rolling hills. Braking uses the brakes whenever the deceleration is more
    than the resistances give."""
    t = np.arange(n) * dt
    ax = 1.2 * np.sin(2 * np.pi * t / 23.0) + 0.4 * np.sin(2 * np.pi * t / 7.0)
    vx = 15.0 + np.cumsum(ax) * dt
    vx = np.clip(vx, 3.0, 35.0)
    slope = 0.04 * np.sin(2 * np.pi * t / 61.0)
    brake = np.where(ax < -0.3, 1500.0 * (-ax - 0.3), 0.0)           # total T_b [N m]
    return t, vx, ax, slope, brake


def test_recovers_known_mass_with_noise_including_braking():
    rng = np.random.default_rng(0)
    true_mass = 1529.98
    t, vx, ax, slope, brake = synthetic_drive(rng, 6000)
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(forgetting_factor=0.998, initial_mass=1300.0))
    rls003 = LongitudinalMassEstimator(SEDAN)
    braking_updates = 0
    for k in range(t.size):
        force = eq28_drive_force(true_mass, vx[k], ax[k], slope[k], brake[k])
        # noisy force, acceleration and brake torque measurements
        drive = force + rng.normal(0.0, 60.0)
        ax_meas = ax[k] + rng.normal(0.0, 0.03)
        brake_meas = brake[k] + (rng.normal(0.0, 20.0) if brake[k] > 0 else 0.0)
        used = est.step(t[k], vx[k], ax_meas, slope[k], drive_force=drive, brake_torque=brake_meas)
        braking_updates += used and brake[k] > 0.0
        rls003.step(t[k], vx[k], ax_meas, slope[k], drive_force=drive, brake_torque=brake_meas)
    assert abs(est.mass - true_mass) / true_mass < 0.01
    assert math.isfinite(est.variance) and 0.0 < est.variance < 50.0 ** 2
    assert est.converged
    # FFRLS learns from braking (T_b is in y of Eq. 29); paper 003's RLS rejects those samples.
    assert braking_updates > 500
    assert rls003.rejected["braking"] + rls003.rejected["accel"] > braking_updates


def test_braking_only_phase_updates_the_mass():
    true_mass = 1800.0
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(initial_mass=1300.0))
    for k in range(400):
        ax = -1.5 - 0.5 * math.sin(0.1 * k)                       # braking, Omega_m < 0
        brake = 2000.0 + 300.0 * math.sin(0.1 * k)
        vx = 25.0 - 0.02 * k
        drive = eq28_drive_force(true_mass, vx, ax, 0.0, brake)  # engine drag: drive near zero
        assert est.step(0.1 * k, vx, ax, 0.0, drive_force=drive, brake_torque=brake)
    assert est.mass == pytest.approx(true_mass, rel=1e-3)
    assert est.last_phi < 0.0 and est.last_y < 0.0


def test_update_is_eq30():
    lam, p0, m0 = 0.998, 10.0, 1300.0
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(forgetting_factor=lam, initial_gain=p0,
                                                    initial_mass=m0))
    vx, ax, slope, brake, drive = 20.0, 0.8, 0.02, 150.0, 2500.0
    assert est.step(0.0, vx, ax, slope, drive_force=drive, brake_torque=brake)
    g = SEDAN.gravity
    omega = g * slope + g * SEDAN.rolling_resistance + ax                                  # Eq. (29)
    y = (drive - brake / SEDAN.wheel_radius
         - SEDAN.drag_coefficient * SEDAN.frontal_area * SEDAN.air_density * vx ** 2 / 2)  # Eq. (29)
    gain = p0 * omega / (lam + omega * p0 * omega)                                         # Eq. (30)
    assert est.raw_mass == pytest.approx(m0 + gain * (y - omega * m0))
    assert est.gain == pytest.approx((p0 - gain * omega * p0) / lam)
    assert est.last_phi == pytest.approx(omega) and est.last_y == pytest.approx(y)


def test_tracks_mass_step_with_lag_of_forgetting_factor():
    """After a load change the old data's weight decays as lambda^k: the error left after k
    accepted samples is about lambda^k of the step (e^-1 after 1/(1-lambda) = 500 samples)."""
    rng = np.random.default_rng(3)
    lam = 0.998
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(forgetting_factor=lam, initial_mass=1300.0))
    m_before, m_after = 1500.0, 1800.0
    k = 0

    def feed(mass, count):
        nonlocal k
        for _ in range(count):
            ax = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.5)
            vx = 20.0
            assert est.step(0.01 * k, vx, ax, 0.0, drive_force=eq28_drive_force(mass, vx, ax, 0.0, 0.0))
            k += 1

    feed(m_before, 5000)
    assert est.mass == pytest.approx(m_before, rel=1e-6)
    memory = round(1.0 / (1.0 - lam))                               # 500 samples
    feed(m_after, memory)
    remaining = (m_after - est.mass) / (m_after - m_before)
    assert remaining == pytest.approx(lam ** memory, abs=0.08)      # ~ e^-1 = 0.37
    feed(m_after, 4 * memory)
    remaining = (m_after - est.mass) / (m_after - m_before)
    assert 0.0 <= remaining < 2.0 * lam ** (5 * memory)             # ~ e^-5 = 0.7 %


def test_threshold_judgment_eq31():
    cfg = FFRLSMassConfig(excitation_threshold=0.3)
    est = FFRLSMassEstimator(SEDAN, cfg)
    g = SEDAN.gravity
    mass0, gain0 = est.raw_mass, est.gain
    # Level cruise: epsilon = g zeta = 0.127 m/s^2 < 0.3, rejected.
    assert not est.step(0.0, 25.0, 0.0, 0.0, drive_force=600.0)
    # Hard acceleration exactly cancelled by a down-hill grade: epsilon = |Omega_m| ~ 0, rejected
    # although dv/dt is large. Eq. (31) thresholds the regressor, not the acceleration.
    ax = 1.0
    slope = -(ax + g * SEDAN.rolling_resistance) / g
    assert not est.step(0.1, 25.0, ax, slope, drive_force=500.0)
    assert est.last_epsilon == pytest.approx(0.0, abs=1e-12)
    assert est.rejected["threshold"] == 2
    # A rejected sample leaves the estimate and P as they were ("remains the same").
    assert est.raw_mass == mass0 and est.gain == gain0 and est.samples_used == 0
    # Braking: Omega_m = -0.6 m/s^2, epsilon = 0.6 >= 0.3, used.
    ax = -0.6 - g * SEDAN.rolling_resistance
    assert est.step(0.2, 25.0, ax, 0.0, drive_force=0.0,
                    brake_torque=eq28_drive_force(1530.0, 25.0, ax, 0.0, 0.0) * -SEDAN.wheel_radius)
    assert est.last_epsilon == pytest.approx(0.6)
    assert est.samples_used == 1
    # Just below / at the threshold.
    for omega, expected in ((0.2999, False), (0.3001, True), (-0.3001, True)):
        ax = omega - g * SEDAN.rolling_resistance
        assert est.step(0.3, 20.0, ax, 0.0, drive_force=2000.0) is expected
    # Threshold zero: every valid sample is used.
    est0 = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(excitation_threshold=0.0))
    assert est0.step(0.0, 25.0, 0.0, 0.0, drive_force=600.0)


def test_other_gates_and_drive_sources():
    est = FFRLSMassEstimator(SEDAN)
    assert not est.step(0.0, 1.0, 1.0, 0.0, drive_force=2000.0)           # creeping
    assert not est.step(0.0, 20.0, 1.0, 0.2, drive_force=2000.0)          # 11 deg grade
    assert not est.step(0.0, 20.0, 1.0, 0.0)                              # no drive term
    assert not est.step(0.0, 20.0, 1.0, 0.0, engine_torque=150.0)         # no gear, no engine speed
    assert {k: v for k, v in est.rejected.items() if v} == {
        "speed": 1, "slope": 1, "no_force": 1, "gear": 1}
    # The three drive sources give the same y for the same physical drive force.
    gear = 3
    engine_torque = 150.0
    force = engine_torque * SEDAN.effective_gearing(gear) * SEDAN.driveline_efficiency  # Eq. (28)
    a = FFRLSMassEstimator(SEDAN)
    b = FFRLSMassEstimator(SEDAN)
    c = FFRLSMassEstimator(SEDAN)
    d = FFRLSMassEstimator(SEDAN)
    engine_speed = SEDAN.effective_gearing(gear) * 15.0                   # no slip at 15 m/s
    assert a.step(0.0, 15.0, 1.0, 0.0, drive_force=force)
    assert b.step(0.0, 15.0, 1.0, 0.0, drive_torque=force * SEDAN.wheel_radius)
    assert c.step(0.0, 15.0, 1.0, 0.0, engine_torque=engine_torque, gear=gear)
    assert d.step(0.0, 15.0, 1.0, 0.0, engine_torque=engine_torque, engine_speed=engine_speed)
    assert d.last_gear == gear
    for other in (b, c, d):
        assert other.last_y == pytest.approx(a.last_y)
        assert other.raw_mass == pytest.approx(a.raw_mass)


def test_rotating_inertia_correction_removes_lumped_inertia():
    rng = np.random.default_rng(5)
    true_mass = 1530.0
    inertia = SEDAN.wheel_inertia / SEDAN.wheel_radius ** 2              # ~38 kg equivalent
    plain = FFRLSMassEstimator(SEDAN)
    corrected = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(rotating_inertia_correction=True))
    for k in range(3000):
        ax = rng.uniform(-1.5, 1.5)
        drive = eq28_drive_force(true_mass, 20.0, ax, 0.0, 0.0, rotating_inertia=inertia)
        plain.step(0.1 * k, 20.0, ax, 0.0, drive_force=drive)
        corrected.step(0.1 * k, 20.0, ax, 0.0, drive_force=drive)
    assert corrected.mass == pytest.approx(true_mass, rel=2e-3)
    # Paper-literal Eq. (28) estimates the mass plus the wheels' equivalent mass.
    assert plain.mass - true_mass == pytest.approx(inertia, rel=0.1)


def test_the_papers_lumped_inertia_is_in_the_variance():
    """Without the correction (the paper's Eq. 28) the estimate is off by the wheels' equivalent
    mass on every drive, an error the residuals cannot show: the published sigma must cover it,
    and must not grow by it where the inertia is taken out. (Without the lasting force term the
    paper's sigma here is a few kg for an error of ~38 kg.)"""
    rng = np.random.default_rng(7)
    true_mass = 1530.0
    inertia = SEDAN.wheel_inertia / SEDAN.wheel_radius ** 2
    plain = FFRLSMassEstimator(SEDAN)
    corrected = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(rotating_inertia_correction=True))
    t, vx, ax, slope, brake = synthetic_drive(rng, 4000)
    for k in range(t.size):
        drive = eq28_drive_force(true_mass, vx[k], ax[k], slope[k], brake[k], rotating_inertia=inertia)
        drive += rng.normal(0.0, 60.0)
        plain.step(t[k], vx[k], ax[k], slope[k], drive_force=drive, brake_torque=brake[k])
        corrected.step(t[k], vx[k], ax[k], slope[k], drive_force=drive, brake_torque=brake[k])
    error = plain.mass - true_mass
    assert error > 0.3 * inertia                       # the paper's estimate carries the wheels
    assert abs(error) < 2.0 * math.sqrt(plain.variance), (error, math.sqrt(plain.variance))
    assert math.sqrt(plain.residual_share) < 0.5 * abs(error)     # the residuals alone are bold
    assert abs(corrected.mass - true_mass) < 2.0 * math.sqrt(corrected.variance)
    assert corrected.variance < 0.25 * plain.variance
    assert corrected.bias_variance == pytest.approx(0.0, abs=1e-6)


def test_no_nan_from_nan_or_inf_inputs():
    est = FFRLSMassEstimator(SEDAN)
    assert est.step(0.0, 20.0, 1.0, 0.0, drive_force=2500.0)
    bad = (math.nan, math.inf, -math.inf)
    for value in bad:
        assert not est.step(value, 20.0, 1.0, 0.0, drive_force=2500.0)
        assert not est.step(1.0, value, 1.0, 0.0, drive_force=2500.0)
        assert not est.step(1.0, 20.0, value, 0.0, drive_force=2500.0)
        assert not est.step(1.0, 20.0, 1.0, value, drive_force=2500.0)
        assert not est.step(1.0, 20.0, 1.0, 0.0, drive_force=2500.0, brake_torque=value)
        assert not est.step(1.0, 20.0, 1.0, 0.0, drive_force=value)              # no other source
        assert not est.step(1.0, 20.0, 1.0, 0.0, engine_torque=value, gear=3)
    assert not est.step(1.0, 20.0, 1.0, 0.0, drive_force=None)
    assert not est.step(1.0, 20.0, 1.0, 0.0, drive_force="x")
    # Finite but absurd inputs must not overflow the state either.
    for vx, ax, drive in ((1e200, 1.0, 2500.0), (20.0, 1e200, 2500.0), (20.0, 1.0, 1e308),
                          (20.0, 1e154, -1e308)):
        est.step(2.0, vx, ax, 0.0, drive_force=drive)
        assert math.isfinite(est.mass) and math.isfinite(est.variance) and math.isfinite(est.gain)
    assert est.rejected["nan"] >= 5 * len(bad)
    assert math.isfinite(est.mass) and math.isfinite(est.variance)
    # still learns afterwards
    assert est.step(3.0, 20.0, 1.0, 0.0, drive_force=2500.0)


def test_reset_state_dict_and_api_parity():
    est = FFRLSMassEstimator(SEDAN)
    assert est.mass == 1300.0 and est.samples_used == 0 and not est.converged
    assert set(est.rejected) == set(REJECT_REASONS)
    assert est.variance == pytest.approx(10.0 * 500.0 ** 2)
    for k in range(50):
        est.step(0.1 * k, 20.0, 1.0, 0.0, drive_force=3000.0 + k)
    state = est.state_dict()
    other = FFRLSMassEstimator(SEDAN)
    other.load_state_dict(state)
    assert other.raw_mass == est.raw_mass and other.gain == est.gain
    assert other.variance == pytest.approx(est.variance)
    est.reset()
    assert est.mass == 1300.0 and est.samples_used == 0 and sum(est.rejected.values()) == 0
    est.reset(mass=2000.0, gain=1.0)
    assert est.mass == 2000.0 and est.gain == 1.0
    with pytest.raises(ValueError):
        est.reset(mass=math.nan)
    # Every keyword of the paper-003 estimator's step is accepted, so the node can switch.
    ours = inspect.signature(FFRLSMassEstimator.step).parameters
    theirs = inspect.signature(LongitudinalMassEstimator.step).parameters
    assert set(theirs) <= set(ours)
    est.step(0.0, 20.0, 1.0, 0.0, drive_force=3000.0, engine_torque=math.nan, engine_speed=math.nan,
             engine_load=0.5, gear=3.0, brake_torque=0.0)


def test_published_mass_is_clipped():
    est = FFRLSMassEstimator(SEDAN, FFRLSMassConfig(initial_gain=1e6))
    est.step(0.0, 20.0, 1.0, 0.0, drive_force=-1e6)     # absurd negative force: raw mass < 0
    assert est.raw_mass < 0.0
    assert est.mass == est.config.min_mass


def test_equivalent_forgetting_factor():
    assert PAPER_SAMPLE_PERIOD_S == 0.01
    lam4 = equivalent_forgetting_factor(0.998, PAPER_SAMPLE_PERIOD_S, 0.25)
    assert lam4 == pytest.approx(0.998 ** 25)
    # same memory in seconds: period / (1 - lambda) ~ 5 s at both rates
    assert 0.25 / (1.0 - lam4) == pytest.approx(0.01 / (1.0 - 0.998), rel=0.03)
    assert equivalent_forgetting_factor(1.0, 0.01, 0.25) == 1.0
    for args in ((0.0, 0.01, 0.25), (0.998, 0.0, 0.25), (0.998, 0.01, math.nan)):
        with pytest.raises(ValueError):
            equivalent_forgetting_factor(*args)


def test_config_defaults_from_paper():
    cfg = FFRLSMassConfig()
    assert cfg.forgetting_factor == 0.998        # Sec. 7.1
    assert cfg.initial_mass == 1300.0            # Sec. 7.1
    assert cfg.rotating_inertia_correction is False   # Eq. (28) has no rotating-mass term
    cfg.validate()


@pytest.mark.parametrize("field, value", [
    ("forgetting_factor", 0.0), ("forgetting_factor", 1.01), ("forgetting_factor", math.nan),
    ("initial_mass", -1.0), ("initial_gain", 0.0), ("excitation_threshold", -0.1),
    ("excitation_threshold", math.inf), ("min_speed", -1.0), ("max_abs_slope", 2.0),
    ("convergence_window", 1), ("convergence_window", 2.5), ("convergence_max_cv", 0.0),
    ("convergence_max_rel_change", -1.0), ("initial_residual_std", 0.0), ("min_mass", 0.0),
    ("max_mass", 100.0), ("rotating_inertia_correction", "yes"), ("initial_mass", "heavy"),
])
def test_config_validation_names_the_field(field, value):
    cfg = dataclasses.replace(FFRLSMassConfig(), **{field: value})
    with pytest.raises(ValueError, match=field if field != "max_mass" else "max_mass|min_mass"):
        cfg.validate()
    with pytest.raises(ValueError):
        FFRLSMassEstimator(SEDAN, cfg)


def test_config_from_mapping():
    cfg = FFRLSMassConfig.from_mapping({"forgetting_factor": 0.99, "convergence_window": 50.0,
                                        "rotating_inertia_correction": True})
    assert cfg.forgetting_factor == 0.99 and cfg.convergence_window == 50
    assert cfg.rotating_inertia_correction is True
    with pytest.raises(ValueError, match="bogus"):
        FFRLSMassConfig.from_mapping({"bogus": 1.0})
    with pytest.raises(ValueError, match="excitation_threshold"):
        FFRLSMassConfig.from_mapping({"excitation_threshold": -1.0})
