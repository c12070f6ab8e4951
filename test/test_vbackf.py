"""Tests of the variational-Bayes adaptive CKF (paper 004 Sec. 4) and its vehicle-state use."""

import math
from pathlib import Path

import numpy as np
import pytest

from vehicle_estimation.estimators.state.ckf import CubatureKalmanFilter, VehicleStateCKF, VehicleStateConfig
from vehicle_estimation.estimators.state.vbackf import VariationalBayesCKF, VBConfig, VehicleStateVBACKF
from vehicle_estimation.estimators.state.vehicle_model import (
    VehicleInputs,
    free_rolling_wheel_speeds,
    measurement,
    measurement_affine,
    transition,
)
from vehicle_estimation.contract.vehicle import load_vehicle_params

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SEDAN = load_vehicle_params(PARAMS_DIR / "sedan_d_class.yaml")

# ---- a linear-Gaussian test system: 2-D constant velocity, positions measured ------------
DT = 0.1
F = np.array([[1.0, 0.0, DT, 0.0], [0.0, 1.0, 0.0, DT], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
_G = 0.5 * np.array([[DT ** 3 / 3, DT ** 2 / 2], [DT ** 2 / 2, DT]])   # white-acceleration, q = 0.5
Q = np.zeros((4, 4))
Q[np.ix_([0, 2], [0, 2])] = _G
Q[np.ix_([1, 3], [1, 3])] = _G
R_TRUE = np.array([[1.0, 0.2], [0.2, 0.5]])
X0 = np.zeros(4)
P0 = 10.0 * np.eye(4)


def f_lin(X, dt):
    return X @ F.T


def h_lin(X):
    return X @ H.T


def _simulate(seed, steps, noise_factor=lambda k: 1.0):
    """Truth and measurements of the linear system; R_k = noise_factor(k) * R_TRUE."""
    rng = np.random.default_rng(seed)
    Lq, Lr = np.linalg.cholesky(Q), np.linalg.cholesky(R_TRUE)
    x = np.array([0.0, 0.0, 1.0, 0.5])
    xs, zs = [], []
    for k in range(steps):
        x = F @ x + Lq @ rng.normal(size=4)
        xs.append(x)
        zs.append(H @ x + math.sqrt(noise_factor(k)) * (Lr @ rng.normal(size=2)))
    return np.array(xs), np.array(zs)


def test_agrees_with_ckf_when_prior_is_concentrated_at_true_r():
    xs, zs = _simulate(seed=1, steps=300)
    ckf = CubatureKalmanFilter(f_lin, h_lin, Q, R_TRUE, X0, P0)
    vb = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0,
                             vb=VBConfig(rho=1.0, prior_weight=1e9, iterations=5))
    for z in zs:
        for filt in (ckf, vb):
            filt.predict(DT)
            filt.update(z)
        assert np.allclose(vb.x, ckf.x, rtol=0.0, atol=1e-6)
        assert np.allclose(vb.P, ckf.P, rtol=0.0, atol=1e-6)
    assert np.allclose(vb.R_mean, R_TRUE, rtol=1e-6)
    assert vb.vb_fallbacks == 0 and vb.last_iterations == 5
    # the filters are doing something: error well below the measurement noise
    assert np.sqrt(np.mean((vb.x[:2] - xs[-1, :2]) ** 2)) < 1.5


def test_prediction_keeps_mean_and_forgets_dof():
    vb = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0,
                             vb=VBConfig(rho=0.9, prior_weight=10.0, nominal_dt=DT))
    assert vb.dof == pytest.approx(2 + 1 + 10.0)
    vb.predict(DT)                       # Eq. 11-style: nu - d - 1 -> rho (nu - d - 1)
    assert vb.dof == pytest.approx(3 + 9.0)
    assert np.allclose(vb.R_mean, R_TRUE)
    vb.predict(2 * DT)                   # rho per nominal_dt: rho ** 2 over 2 DT
    assert vb.dof == pytest.approx(3 + 9.0 * 0.81)
    assert np.allclose(vb.R_vb, vb.scale / vb.dof)


def test_r_estimate_follows_a_noise_jump_and_beats_nominal_ckf():
    jump = (200, 600)
    factor = 10.0
    xs, zs = _simulate(seed=0, steps=800, noise_factor=lambda k: factor if jump[0] <= k < jump[1] else 1.0)
    ckf = CubatureKalmanFilter(f_lin, h_lin, Q, R_TRUE, X0, P0)         # nominal R throughout
    vb = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0)           # default VBConfig
    err_ckf, err_vb, r_ratio = [], [], []
    for x, z in zip(xs, zs):
        for filt in (ckf, vb):
            filt.predict(DT)
            filt.update(z)
        err_ckf.append(ckf.x[:2] - x[:2])
        err_vb.append(vb.x[:2] - x[:2])
        r_ratio.append(np.diag(vb.R_mean) / np.diag(R_TRUE))
    r_ratio = np.array(r_ratio)
    before = r_ratio[100:200].mean(axis=0)
    during = r_ratio[350:600].mean(axis=0)       # after ~3 memory lengths (1/(1-rho) = 55 steps)
    after = r_ratio[750:].mean(axis=0)
    assert np.all((before > 0.7) & (before < 1.4)), before
    assert np.all((during > 0.7 * factor) & (during < 1.3 * factor)), during
    assert np.all(after < 0.25 * factor), after            # comes back down
    assert np.all(np.linalg.eigvalsh(vb.R_mean) > 0)
    rmse_ckf = np.sqrt(np.mean(np.square(err_ckf[50:])))
    rmse_vb = np.sqrt(np.mean(np.square(err_vb[50:])))
    assert rmse_vb < 0.95 * rmse_ckf, (rmse_vb, rmse_ckf)
    assert vb.vb_fallbacks == 0 and vb.rejected_measurements == 0


def test_bad_measurements_never_produce_nan():
    vb = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0)
    _, zs = _simulate(seed=2, steps=20)
    for z in zs[:10]:
        vb.predict(DT)
        vb.update(z)
    x, P, dof, scale = vb.x, vb.P, vb.dof, vb.scale

    # NaN measurement: skipped and counted, nothing changes
    innovation = vb.update(np.array([np.nan, 1.0]))
    assert np.all(np.isnan(innovation))
    assert vb.rejected_measurements == 1
    assert np.array_equal(vb.x, x) and np.array_equal(vb.P, P)
    assert vb.dof == dof and np.array_equal(vb.scale, scale)

    # a measurement so large that B overflows: the VB iteration fails, plain CKF is used
    vb.predict(DT)
    vb.update(np.array([1e200, 0.0]))
    assert vb.vb_fallbacks == 1
    assert np.all(np.isfinite(vb.x)) and np.all(np.isfinite(vb.P))
    assert np.all(np.isfinite(vb.R_mean))

    # corrupted (non-PD) noise statistics: fallback, statistics back to the prior
    vb = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0)
    vb._scale = -np.eye(2)
    vb.predict(DT)
    vb.update(zs[10])
    assert vb.vb_fallbacks == 1
    assert np.allclose(vb.R_mean, R_TRUE) and np.all(np.isfinite(vb.x))

    # non-PD state covariance: cubature points from the clipped square root, still finite
    vb._P = -np.eye(4)
    vb.predict(DT)
    vb.update(zs[11])
    assert np.all(np.isfinite(vb.x)) and np.all(np.isfinite(vb.P))
    for z in zs[12:]:
        vb.predict(DT)
        vb.update(z)
    assert np.all(np.isfinite(vb.x)) and np.all(np.isfinite(vb.R_mean))


def test_each_channel_forgets_at_its_own_rate():
    """``rho_per_channel`` (diagonal noise only): the same rho on every channel is the default
    filter, to the digit; with channel 0 at a 2000-step memory and channel 1 at the default 55,
    200 steps after 400 of a tenfold noise channel 1 has forgotten it and channel 0 not."""
    xs, zs = _simulate(seed=0, steps=800, noise_factor=lambda k: 10.0 if 200 <= k < 600 else 1.0)
    rho = VBConfig().rho
    diagonal = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0, vb=VBConfig(noise_structure="diagonal"))
    same = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0,
                               vb=VBConfig(noise_structure="diagonal", rho_per_channel=(rho, rho)))
    mixed = VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0,
                                vb=VBConfig(noise_structure="diagonal", rho_per_channel=(0.9995, rho)))
    for z in zs:
        for filt in (diagonal, same, mixed):
            filt.predict(DT)
            filt.update(z)
        assert np.array_equal(same.x, diagonal.x) and np.array_equal(same.R_mean, diagonal.R_mean)
    ratio = np.diag(mixed.R_mean) / np.diag(R_TRUE)
    assert ratio[1] < 2.5 and ratio[0] > 4.0, ratio
    assert mixed.dofs[0] > mixed.dofs[1]


def test_vbconfig_validate_names_the_field():
    for kwargs, field in (({"rho": 0.0}, "rho"), ({"rho": 1.5}, "rho"), ({"rho": float("nan")}, "rho"),
                          ({"iterations": 0}, "iterations"), ({"iterations": 2.5}, "iterations"),
                          ({"prior_weight": -1.0}, "prior_weight"), ({"nominal_dt": 0.0}, "nominal_dt"),
                          ({"r_estimate": "median"}, "r_estimate"), ({"tolerance": -1.0}, "tolerance")):
        with pytest.raises(ValueError, match=field):
            VBConfig(**kwargs).validate()
    VBConfig().validate()
    with pytest.raises(ValueError, match="rho"):
        VehicleStateVBACKF(SEDAN, vb=VBConfig(rho=2.0))
    with pytest.raises(ValueError, match="R"):
        VariationalBayesCKF(f_lin, h_lin, Q, -np.eye(2), X0, P0)
    with pytest.raises(ValueError, match="rho_per_channel"):
        VBConfig(rho_per_channel=(0.99, 1.5), noise_structure="diagonal").validate()
    with pytest.raises(ValueError, match="rho_per_channel"):
        VBConfig(rho_per_channel=(0.99, 0.98)).validate()           # a full R has one nu
    VBConfig(rho_per_channel=(0.99, 0.99)).validate()
    with pytest.raises(ValueError, match="rho_per_channel"):
        VariationalBayesCKF(f_lin, h_lin, Q, R_TRUE, X0, P0,
                            vb=VBConfig(rho_per_channel=(0.99,) * 3, noise_structure="diagonal"))


# ---- the vehicle-state estimator -------------------------------------------------------
R_PAPER = np.diag([4e-2, 4e-2, 6e-5])


def _drive(seconds, dt=0.01, seed=0, v0=20.0, noise_factor=lambda t: 1.0):
    """Truth from the model itself; z = h(x) + N(0, noise_factor(t) R_paper)."""
    rng = np.random.default_rng(seed)
    x = np.array([v0, 0.0, 0.0, 0.0, 0.0])
    for k in range(int(round(seconds / dt))):
        t = k * dt
        delta = 0.03 * math.sin(2 * math.pi * 0.3 * t)
        slip = np.array([1, 1, 0, 0]) * (0.002 + 0.004 * math.sin(2 * math.pi * 0.1 * t))
        u = VehicleInputs(delta, free_rolling_wheel_speeds(x, delta, SEDAN, slip), 0.01)
        if k > 0:
            x = transition(x, u, SEDAN, dt)
        z = measurement(x, u, SEDAN) + math.sqrt(noise_factor(t)) * rng.multivariate_normal(np.zeros(3), R_PAPER)
        yield t, u, z, x


def test_vehicle_state_vbackf_tracks_and_reuses_the_ckf_machinery():
    f = VehicleStateVBACKF(SEDAN)
    assert isinstance(f, VehicleStateCKF) and isinstance(f.filter, VariationalBayesCKF)
    assert f.vb_config.nominal_dt == pytest.approx(0.01)            # paper tau
    assert np.allclose(f.measurement_noise, VehicleStateConfig().R)  # prior mean = Sec. 7.1 R
    errs = []
    for t, u, z, x in _drive(seconds=6.0):
        if abs(t - 3.0) < 1e-9:
            z = np.array([np.nan, 0.0, 0.0])
            assert not f.step(t, u, z)
            continue
        assert f.step(t, u, z)
        if t > 2.0:
            errs.append(f.x[:3] - x[:3])
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    assert rms[0] < 0.05 and rms[1] < 0.08 and rms[2] < 0.01, rms
    assert f.rejected["nonfinite_measurement"] == 1
    assert f.vb_fallbacks == 0
    R = f.measurement_noise
    assert np.all(np.isfinite(R)) and np.all(np.linalg.eigvalsh(R) > 0)
    assert 0.0 < f.sideslip_variance < 1e-3


def test_vehicle_gap_keeps_noise_numerical_failure_resets_it():
    # Q well below the Sec. 7.1 value: with Q = 0.1 I per 10 ms the predicted measurement
    # covariance (~6 (m/s^2)^2) dwarfs R and R is not identifiable from the innovations.
    f = VehicleStateVBACKF(SEDAN, VehicleStateConfig(Q=1e-4 * np.eye(5)))
    u = VehicleInputs(0.0, free_rolling_wheel_speeds(np.array([22.0, 0, 0, 0, 0]), 0.0, SEDAN), 0.0)
    rng = np.random.default_rng(3)
    t = 0.0
    for _ in range(300):                                 # IMU noise 5x the nominal std
        t += 0.01
        f.step(t, u, 5.0 * np.sqrt(np.diag(R_PAPER)) * rng.normal(size=3))
    learnt = f.measurement_noise
    assert np.all(np.diag(learnt) > 10.0 * np.diag(R_PAPER))      # true: 25x
    assert f.step(t + 2.0, u, np.zeros(3))               # gap > max_gap_s: re-initialised
    assert f.reinitialisations == 1 and "gap" in f.last_event
    assert np.allclose(f.measurement_noise, learnt, rtol=0.05)   # one update further
    f.filter._x[:] = np.nan                              # numerical failure of the state
    assert not f.step(t + 2.01, u, np.zeros(3))
    assert f.last_event.endswith("numerical failure")
    assert np.allclose(f.measurement_noise, VehicleStateConfig().R)
    assert np.all(np.isfinite(f.x))


@pytest.mark.parametrize("core_class", [VehicleStateCKF, VehicleStateVBACKF])
def test_closed_form_moments_give_the_cubature_estimates(core_class):
    """The IMU measurement is affine in the state, so the filters take its moments in closed
    form; the cubature rule (``h_affine`` off) is the oracle: the same estimates to 1e-9."""
    rng = np.random.default_rng(5)
    X = rng.normal(size=(7, 5)) * [20.0, 1.0, 0.3, 3.0, 3.0]
    u = VehicleInputs(0.02, np.full(4, 60.0), 0.04)
    H, c = measurement_affine(u, SEDAN)
    assert np.allclose(X @ H.T + c, measurement(X, u, SEDAN), rtol=0.0, atol=1e-12)

    cores = [core_class(SEDAN), core_class(SEDAN)]
    cores[1].filter.h_affine = None
    assert cores[0].filter.h_affine is not None
    worst = 0.0
    for t, u, z, _ in _drive(seconds=4.0, seed=2):
        for core in cores:
            core.step(t, u, z)
        a, b = cores[0].x, cores[1].x
        # covariances relative to their scale sqrt(P_ii P_jj): a near-zero off-diagonal
        # entry is not a relative error of its own
        scale = np.sqrt(np.outer(np.diag(cores[1].P), np.diag(cores[1].P)))
        worst = max(worst, float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-3))),
                    float(np.max(np.abs(cores[0].P - cores[1].P) / scale)))
    assert worst < 1e-9, worst


def test_real_drive_without_speed_keeps_vy_within_1_m_s(tmp_path):
    """The real Stanford drive as logged (IMU and steering, no speed of any kind), clean and
    with 4 m/s^2 of 10-60 Hz vibration, fed as `vehicle-estimation stanford` feeds the node (R
    from the data, the reference's first vx, a slope from the slope node). vx is then
    dead-reckoned; the shipped settings keep every vy error below 1 m/s. Two things hold vx:
    the speed each corner shows (mean(ay) / mean(r), ``cornering_speed_accel_std``) and the
    accelerometer's learnt noise keeping 20 s of residuals (paper 004's 0.55 s learns each
    burst of model error as noise and discounts ay by as much). Without the corners the clean
    drive's vy errors reach 1.35 m/s; without both, the vibrating one's 1.5 m/s."""
    from vehicle_estimation.paths import params_file, shared_data_dir
    from vehicle_estimation.sim.noise import band_limited_noise
    from vehicle_estimation.validation import baselines, lateral, stanford
    if not (shared_data_dir(stanford.MAPPING) / "t.txt").is_file():
        pytest.skip("Stanford data not available")
    pytest.importorskip("rosbags")
    bag = tmp_path / "stanford"
    stanford.import_bag(bag, "none")
    clean = lateral.read_drive(bag)
    vehicle = load_vehicle_params(params_file(stanford.VEHICLE))
    no_corners = {"cornering_speed_accel_std": 0.0}

    def largest_vy_error(vibration: float, **overrides) -> float:
        drive = {**clean, "imu": dict(clean["imu"])}
        imu, truth = drive["imu"], drive["truth"]
        fs = 1.0 / float(np.median(np.diff(imu["t"])))
        if vibration:
            imu["f"] = imu["f"] + band_limited_noise(np.random.default_rng(0), imu["t"].size, fs, vibration)
        r_diag = [baselines.highpass_std(imu["f"][:, 0]) ** 2, baselines.highpass_std(imu["f"][:, 1]) ** 2,
                  baselines.highpass_std(imu["w"][:, 2]) ** 2]
        node = {"r_diag": r_diag, "initial_vx": float(truth["vx"][0]), "missing_slope_std_deg": 0.0}
        est = lateral.run_core("vbackf", drive, vehicle, use_wheels=True, roll="none", overrides={**node, **overrides})
        after = est["t"] >= est["t"][0] + 5.0
        return float(np.max(np.abs(est["vy"] - np.interp(est["t"], truth["t"], truth["vy"]))[after]))

    assert largest_vy_error(0.0) < 1.0
    assert largest_vy_error(0.0, **no_corners) > 1.2
    assert largest_vy_error(4.0) < 1.0
    assert largest_vy_error(4.0, **no_corners) < 1.0
    assert largest_vy_error(4.0, **no_corners, **{"vbackf.rho_per_channel": [VBConfig().rho] * 3}) > 1.3
