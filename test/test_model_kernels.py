"""The compiled kernels against their numpy definitions (the test oracles).

Each kernel is held to the numpy code it stands for: one step from the same state to 1e-12
(relative to the scale of each quantity), and whole drives to 1e-9 (rounding may grow through
a filter's feedback, never more). The failure paths (a covariance that is not positive
definite, non-finite moments, a gated update) must end the same way as the numpy path's.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from vehicle_estimation.contract.vehicle import VehicleParams, load_vehicle_params  # noqa: E402
from vehicle_estimation.estimators.common import compiled, small_linalg  # noqa: E402
from vehicle_estimation.estimators.fusion import ins_kernels  # noqa: E402
from vehicle_estimation.estimators.fusion.config import FusionConfig  # noqa: E402
from vehicle_estimation.estimators.fusion.error_state import N_ERR  # noqa: E402
from vehicle_estimation.estimators.fusion.esekf import FusionEKF  # noqa: E402
from vehicle_estimation.estimators.state.ckf import VehicleStateCKF, VehicleStateConfig  # noqa: E402
from vehicle_estimation.estimators.state.vbackf import VBConfig, VehicleStateVBACKF  # noqa: E402
from vehicle_estimation.estimators.state.vehicle_model import (  # noqa: E402
    VehicleInputs,
    free_rolling_wheel_speeds,
)

SEDAN = load_vehicle_params(Path(__file__).resolve().parents[1] / "params" / "sedan_d_class.yaml")


def _relative(a: np.ndarray, b: np.ndarray, floor: float = 1e-9) -> float:
    """Largest |a - b| relative to the scale of ``b`` (its largest entry)."""
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), floor))


# ---- small linear algebra ---------------------------------------------------------------
def test_cholesky_and_solve_match_numpy_and_refuse_what_numpy_refuses():
    rng = np.random.default_rng(0)
    for n in (1, 3, 5, 17):
        A = rng.normal(size=(n, n))
        S = A @ A.T + 0.1 * np.eye(n)
        L = np.empty((n, n))
        assert small_linalg.cholesky_lower(S, L)
        assert _relative(L, np.linalg.cholesky(S)) < 1e-12
        B = rng.normal(size=(4, n))
        X = np.empty((4, n))
        small_linalg.cholesky_solve_rows(L, B, X)
        assert _relative(X, np.linalg.solve(S, B.T).T) < 1e-10
    L = np.empty((2, 2))
    assert not small_linalg.cholesky_lower(np.array([[1.0, 2.0], [2.0, 1.0]]), L)   # indefinite
    assert not small_linalg.cholesky_lower(np.array([[np.nan, 0.0], [0.0, 1.0]]), L)
    x, P = np.zeros(2), np.eye(2)
    assert small_linalg.valid_moments(x, P, np.empty((2, 2)))
    P[0, 1] = np.inf
    assert not small_linalg.valid_moments(x, P, np.empty((2, 2)))
    assert not small_linalg.all_finite(np.array([0.0, np.nan]), np.eye(2))


def test_scalar_correct_is_the_numpy_kalman_update():
    """The compiled update with one linear measurement (wheel or CAN speed) against the numpy
    correction it stands for (``SigmaPointKalmanFilter.correct`` with a 1 x 1 ``P_zz``)."""
    from vehicle_estimation.estimators.common.sigma_points import CubaturePoints, SigmaPointKalmanFilter

    rng = np.random.default_rng(3)
    for n in (2, 5, 17):
        A = rng.normal(size=(n, n))
        P0, x0, H = A @ A.T + 0.1 * np.eye(n), rng.normal(size=n), rng.normal(size=n)
        value, variance = 1.7, 0.04
        ref = SigmaPointKalmanFilter(lambda x, dt: x, lambda x: x[:1], np.eye(n), np.eye(1), x0, P0, CubaturePoints(n))
        PHt = P0 @ H
        K_ref = ref.correct(np.array([value - H @ x0]), np.array([[H @ PHt + variance]]), PHt[:, None])
        x, P, K = np.empty(n), np.empty((n, n)), np.empty(n)
        innovation, s = small_linalg.scalar_correct(x0, P0, H, value, variance, x, P, K)
        assert _relative(x, ref.x) < 1e-12 and _relative(P, ref.P) < 1e-12 and _relative(K, K_ref[:, 0]) < 1e-12
        assert np.array_equal(P, P.T)
        assert innovation == pytest.approx(value - H @ x0, rel=1e-12) and s == pytest.approx(H @ PHt + variance, rel=1e-12)


# ---- the vehicle-state filters ----------------------------------------------------------
def _inputs(t: float, x_true: np.ndarray, params: VehicleParams, wheels: bool, torque: bool) -> VehicleInputs:
    steer = 0.06 * math.sin(0.7 * t)
    ws = free_rolling_wheel_speeds(x_true, steer, params, slip=np.array([0.01, 0.01, 0.0, 0.0]))
    return VehicleInputs(steer_angle=steer, wheel_speeds=ws if wheels else np.full(4, np.nan), slope=0.03,
                         mass=1.1 * params.mass, drive_torque=400.0 if torque else None,
                         brake_torques=np.array([0.0, 0.0, 50.0, 50.0]) if torque else None)


def _state_drive(core_class, params, config, compiled_on, steps=400, wheels=True, torque=False, known_ay=None):
    core = core_class(params, config)
    core.use_compiled(compiled_on)
    rng = np.random.default_rng(7)
    out = []
    for k in range(steps):
        t = 5.0 + 0.005 * k
        x_true = np.array([18.0 + math.sin(0.2 * t), 0.3 * math.sin(0.7 * t), 0.1 * math.sin(0.7 * t),
                           0.5 * math.cos(0.2 * t), 2.0 * math.sin(0.7 * t)])
        u = _inputs(t, x_true, params, wheels, torque)
        z = np.array([x_true[3] + params.gravity * math.sin(0.03), x_true[4], x_true[2]])
        z = z + rng.normal(0.0, [0.3, 0.3, 0.01])
        if k == 150:
            z[1] = np.nan                      # a rejected sample on both paths
        if known_ay is not None:
            core.set_known_noise(ay=known_ay(k))
        core.step(t, u, z)
        out.append(np.concatenate([core.x, core.P.ravel()]))
    return core, np.array(out)


@pytest.mark.parametrize("core_class", [VehicleStateCKF, VehicleStateVBACKF])
@pytest.mark.parametrize("case", ["wheel slip", "no wheel speeds", "torques, no wheel speeds",
                                  "load-sensitive tyres", "wheel speeds as speed"])
def test_state_filters_compiled_give_the_numpy_estimates(core_class, case):
    params, config = SEDAN, VehicleStateConfig()
    if case == "load-sensitive tyres":
        params = dataclasses.replace(SEDAN, tyre_load_exponent=0.8)
    if case == "wheel speeds as speed":
        config = dataclasses.replace(config, wheel_slip_forces=False)
    kw = {"wheels": case not in ("no wheel speeds", "torques, no wheel speeds"), "torque": case.startswith("torques")}
    numpy_core, a = _state_drive(core_class, params, config, False, **kw)
    compiled_core, b = _state_drive(core_class, params, config, True, **kw)
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-9)
    assert float(np.max(np.abs(a - b) / scale)) < 1e-9
    assert compiled_core.rejected == numpy_core.rejected
    assert compiled_core.updates == numpy_core.updates and compiled_core.reinitialisations == numpy_core.reinitialisations


@pytest.mark.parametrize("core_class", [VehicleStateCKF, VehicleStateVBACKF])
def test_one_state_step_agrees_to_1e12(core_class):
    cores = [core_class(SEDAN), core_class(SEDAN)]
    cores[0].use_compiled(False)
    cores[1].use_compiled(True)
    x_true = np.array([25.0, 0.4, 0.15, 0.8, 3.0])
    for core in cores:   # the same start, then one predict and update from it
        core.step(10.0, _inputs(10.0, x_true, SEDAN, True, False), np.array([1.0, 3.0, 0.15]))
        core.filter._P = np.diag([0.5, 0.2, 0.01, 1.0, 1.0]) + 0.01
        core.step(10.01, _inputs(10.01, x_true, SEDAN, True, False), np.array([1.1, 2.9, 0.16]))
    assert _relative(cores[1].x, cores[0].x) < 1e-12
    assert _relative(cores[1].P, cores[0].P) < 1e-12


def test_vb_failure_paths_end_as_the_numpy_path():
    """A noise prior that is not positive definite falls back to the plain correction, the
    same way on both paths; a measurement whose moments are not finite is rejected."""
    results = []
    for on in (False, True):
        core = VehicleStateVBACKF(SEDAN)
        core.use_compiled(on)
        x_true = np.array([20.0, 0.0, 0.0, 0.0, 0.0])
        core.step(1.0, _inputs(1.0, x_true, SEDAN, True, False), np.zeros(3))
        core.filter._scale = -np.eye(3)           # V_pred not positive definite
        core.step(1.01, _inputs(1.01, x_true, SEDAN, True, False), np.array([0.1, 0.0, 0.0]))
        results.append((core.filter.vb_fallbacks, core.filter.rejected_measurements, core.x, core.P))
    assert results[0][:2] == results[1][:2] == (1, 0)
    assert _relative(results[1][2], results[0][2]) < 1e-12 and _relative(results[1][3], results[0][3]) < 1e-12


# ---- the fusion ES-EKF --------------------------------------------------------------------
def _fusion_run(compiled_on: bool, drive, gnss: bool = True, **cfg) -> tuple[FusionEKF, np.ndarray]:
    ekf = FusionEKF(dataclasses.replace(FusionConfig(), estimate_mounting=True, estimate_speed_scale=True,
                                        nh_sigma_z=0.1, **cfg))
    ekf.compiled = compiled_on
    events = [(float(t), 0, i) for i, t in enumerate(drive.imu_t)]
    events += [(float(t), 1, i) for i, t in enumerate(drive.speed_t)]
    events += [(float(t), 2, i) for i, t in enumerate(drive.gnss["t"]) if gnss]
    rows = []
    for t, kind, i in sorted(events):
        if kind == 0:
            ekf.process_imu(t, drive.accel[i], drive.gyro[i])
            rows.append(np.concatenate([ekf._p, ekf._v, ekf._q, ekf._ba, ekf._bg, ekf._Rm.ravel(),
                                        ekf._speed_scale_error, ekf._P.ravel()]))
        elif kind == 1:
            ekf.update_speed(t, float(drive.speed_v[i]))
        elif math.isfinite(drive.gnss["enu_meas"][i, 0]):
            ekf.update_gnss(t, drive.gnss["enu_meas"][i], np.diag(drive.gnss["cov"]))
    return ekf, np.array(rows)


@pytest.mark.parametrize("gnss", [True, False], ids=["GNSS", "no GNSS, invariant reset"])
def test_fusion_compiled_gives_the_numpy_estimates(gnss):
    from vehicle_estimation.evaluation.bench_cores import DriveArrays
    drive = DriveArrays(40.0, seed=3)
    # Without GNSS the compiled step reads the corner gate (the low-passed yaw rate) before the
    # sample's propagation, the numpy path after it: one sample apart where a corner starts.
    cfg = {} if gnss else {"invariant_reset_without_gnss": True, "mounting_max_yaw_rate_without_gnss": 10.0}
    cfg["stationary_rate_update"] = True      # standing, an update that is not held (the Schmidt hold)
    numpy_ekf, a = _fusion_run(False, drive, gnss, **cfg)
    compiled_ekf, b = _fusion_run(True, drive, gnss, **cfg)
    assert compiled_ekf.status == numpy_ekf.status == ("running" if gnss else "waiting_for_heading")
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-9)
    assert float(np.max(np.abs(a - b) / scale)) < 1e-9
    assert compiled_ekf.rejected == numpy_ekf.rejected and compiled_ekf.events == numpy_ekf.events


def _running_ekf(seed: int, **cfg) -> FusionEKF:
    """A filter in a random running state (every kernel input non-trivial; no GNSS fix)."""
    rng = np.random.default_rng(seed)
    ekf = FusionEKF(dataclasses.replace(FusionConfig(), estimate_mounting=True, estimate_speed_scale=True,
                                        nh_sigma_z=0.1, **cfg))
    ekf.status = "running"
    ekf._t = 100.0
    ekf._p, ekf._v = rng.normal(size=3) * 50.0, rng.normal(size=3) * 10.0
    q = rng.normal(size=4)
    ekf._q = q / np.linalg.norm(q)
    from vehicle_estimation.estimators.common.rotations import quat_to_rotmat
    ekf._R = quat_to_rotmat(ekf._q)
    m = rng.normal(size=4)      # a turned IMU: the mounting's base_link axes are not its own
    ekf._Rm = quat_to_rotmat(m / np.linalg.norm(m))
    ekf._ba, ekf._bg = rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.002
    ekf._speed_scale_error[:] = rng.normal() * 0.02
    A = rng.normal(size=(N_ERR, N_ERR)) * 0.1
    ekf._P = A @ A.T + 1e-3 * np.eye(N_ERR)
    ekf._f_prev, ekf._w_prev = rng.normal(size=3) + [0.0, 0.0, 9.8], rng.normal(size=3) * 0.2
    return ekf


@pytest.mark.parametrize("invariant", [False, True], ids=["ES-EKF", "invariant reset"])
def test_each_fusion_kernel_agrees_to_1e12(invariant):
    pairs = [_running_ekf(1, invariant_reset_without_gnss=invariant) for _ in range(2)]
    pairs[0].compiled, pairs[1].compiled = False, True
    for ekf in pairs:
        ekf._propagate(0.005)
    fields = ("_p", "_v", "_q", "_R", "_P", "_a_lp", "_w_lp")
    for name in fields:
        assert _relative(getattr(pairs[1], name), getattr(pairs[0], name)) < 1e-12, name
    for rows in ([0], [1, 2], [0, 1, 2]):
        (pa, Ha), (pb, Hb) = (ekf._body_speed_rows(rows) for ekf in pairs)
        assert _relative(pb, pa) < 1e-12 and _relative(Hb, Ha) < 1e-12
    for ekf in pairs:
        pred, H = ekf._body_speed_rows([0, 1, 2])
        ekf._update(np.array([0.3, -0.2, 0.1]) - pred, H, np.diag([0.04, 0.01, 0.01]), None)
        ekf.update_speed(ekf.time, 12.0, 0.01)      # the speed's scale error in the gain
        ekf._nh_update(ekf.time)
    for name in (*fields, "_ba", "_bg", "_Rm", "_speed_scale_error"):
        assert _relative(getattr(pairs[1], name), getattr(pairs[0], name)) < 1e-12, name


def test_fusion_gate_and_failure_codes_match_numpy():
    for compiled_on in (False, True):
        ekf = _running_ekf(2)
        ekf.compiled = compiled_on
        H = np.zeros((1, N_ERR))
        H[0, 3] = 1.0
        assert ekf._update(np.array([1e3]), H, np.array([[0.01]]), 9.0) == 0          # gated
        assert ekf._update(np.array([0.1]), H, np.array([[0.01]]), 9.0) == 1
        assert ekf._update(np.array([0.1]), H, np.array([[-1e9]]), None) == -1        # S not PD
        assert ekf.rejected["update_numerical"] == 1


def test_switched_off_by_the_environment():
    code = ("from vehicle_estimation.estimators.common import compiled;"
            "from vehicle_estimation.estimators.fusion.esekf import FusionEKF;"
            "print(compiled.enabled(), FusionEKF().compiled)")
    env = dict(os.environ, VEHICLE_ESTIMATION_COMPILED="0")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
    assert compiled.enabled()
    assert ins_kernels.UPDATE_APPLIED == 1


# ---- the slope observers' 2-state maths, written out in scalars -----------------------------
@pytest.mark.parametrize("gain_mode", ["luenberger", "kalman"])
def test_slope_observer_scalar_steps_equal_the_matrix_form(gain_mode):
    from vehicle_estimation.estimators.slope.observers import ClassicalSlopeConfig, ClassicalSlopeObserver
    obs = ClassicalSlopeObserver(dataclasses.replace(ClassicalSlopeConfig(), gain_mode=gain_mode))
    cfg, g = obs.config, obs.config.gravity
    rng = np.random.default_rng(4)
    for _ in range(20):
        x, A = rng.normal(size=2), rng.normal(size=(2, 2))
        P, dt, u, vx, r = A @ A.T + 0.1 * np.eye(2), 0.005 + 0.01 * rng.random(), rng.normal(size=2), 20.0, 0.04
        obs._x, obs._P = x.copy(), P.copy()
        obs._predict(dt, u)
        w = obs.PHI @ u
        F = np.array([[1.0, -g * dt], [0.0, 1.0]])
        qv, qt = (cfg.accel_noise_std * dt) ** 2, cfg.slope_rate_std ** 2 * dt
        Qd = np.array([[qv + g * g * qt * dt * dt / 3.0, -0.5 * g * qt * dt], [-0.5 * g * qt * dt, qt]])
        x = F @ x + np.array([dt * w[0] - 0.5 * g * dt * dt * w[1], dt * w[1]])
        P = F @ P @ F.T + Qd
        assert _relative(obs._x, x) < 1e-12 and _relative(obs._P, P) < 1e-12
        obs._correct(dt, vx, r)
        if gain_mode == "kalman":
            K = P[:, 0] / (P[0, 0] + r)
        else:
            K = np.asarray(cfg.luenberger_gain, dtype=float) * dt
            if obs._cubic_dir is not None:
                d, innov = obs._cubic_dir, vx - x[0]
                room = max(cfg.cubic_max_step_gain - K[0], 0.0)
                K = K + dt * d * (min(innov * innov, room / (dt * d[0])) if d[0] > 0.0 else innov * innov)
        x = x + K * (vx - x[0])
        IKC = np.eye(2) - np.outer(K, [1.0, 0.0])
        P = IKC @ P @ IKC.T + r * np.outer(K, K)
        assert _relative(obs._x, x) < 1e-12 and _relative(obs._P, 0.5 * (P + P.T)) < 1e-12


def test_vb_diagonal_noise_compiled_gives_the_numpy_estimates():
    """``vbackf.noise_structure: diagonal``: the kernels use only the diagonal of the learnt R,
    as numpy does; R's off-diagonal terms are zero and its diagonal is the full R's."""
    vb = VBConfig(noise_structure="diagonal")

    def make(params, config):
        return VehicleStateVBACKF(params, config, vb)

    numpy_core, a = _state_drive(make, SEDAN, VehicleStateConfig(), False)
    compiled_core, b = _state_drive(make, SEDAN, VehicleStateConfig(), True)
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-9)
    assert float(np.max(np.abs(a - b) / scale)) < 1e-9
    R = compiled_core.filter.R_estimate
    assert np.count_nonzero(R - np.diag(np.diag(R))) == 0
    full = compiled_core.filter._scale / (compiled_core.filter._dof - 4.0)
    np.testing.assert_allclose(np.diag(R), np.diag(full), rtol=1e-12)
    _, c = _state_drive(VehicleStateVBACKF, SEDAN, VehicleStateConfig(), True)
    assert float(np.max(np.abs(c - b) / scale)) > 1e-6      # it is another filter
    # each channel with its own memory (params/estimation.yaml): the same in both paths too
    per_channel = VBConfig(noise_structure="diagonal", rho_per_channel=(0.9995, 0.9995, 0.981684))
    numpy_core, a = _state_drive(lambda p, c: VehicleStateVBACKF(p, c, per_channel), SEDAN, VehicleStateConfig(), False)
    compiled_core, b = _state_drive(lambda p, c: VehicleStateVBACKF(p, c, per_channel), SEDAN, VehicleStateConfig(), True)
    assert float(np.max(np.abs(a - b) / scale)) < 1e-9
    np.testing.assert_allclose(compiled_core.filter.dofs, numpy_core.filter.dofs, rtol=1e-12)
    assert compiled_core.filter.dofs[0] > compiled_core.filter.dofs[2]


@pytest.mark.parametrize("core_class", [VehicleStateCKF, VehicleStateVBACKF])
def test_known_lateral_noise_compiled_gives_the_numpy_estimates_and_weighs_ay_less(core_class):
    """The node's roll-compensation variance on ay: the kernels add it to P_zz as numpy does
    (0 before step 100, then a varying one), and a large one leaves ay nearly unused."""
    def known(k):
        return 0.0 if k < 100 else 2.0 + math.sin(0.05 * k)

    numpy_core, a = _state_drive(core_class, SEDAN, VehicleStateConfig(), False, known_ay=known)
    compiled_core, b = _state_drive(core_class, SEDAN, VehicleStateConfig(), True, known_ay=known)
    scale = np.maximum(np.max(np.abs(a), axis=0), 1e-9)
    assert float(np.max(np.abs(a - b) / scale)) < 1e-9
    _, plain = _state_drive(core_class, SEDAN, VehicleStateConfig(), True)
    assert float(np.max(np.abs(plain[:100] - b[:100]) / scale)) == 0.0     # nothing known: unchanged
    gains = []
    for variance in (0.0, 1e4):
        core = core_class(SEDAN)
        core.set_known_noise(ay=variance)
        x_true = np.array([25.0, 0.4, 0.15, 0.8, 3.0])
        core.step(10.0, _inputs(10.0, x_true, SEDAN, True, False), np.array([1.0, 3.0, 0.15]))
        core.step(10.01, _inputs(10.01, x_true, SEDAN, True, False), np.array([1.1, 2.9, 0.16]))
        gains.append(np.abs(core.filter.last_gain[:, 1]).max())
    assert gains[1] < 0.01 * gains[0]
    core.set_known_noise(ay=0.0)
    assert core.filter.known_noise is None
