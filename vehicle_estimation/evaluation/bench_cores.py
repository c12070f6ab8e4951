"""The ``cores`` section of ``vehicle-estimation bench``: the per-step cost of every estimator
core on the arrays of one simulated drive, each fed what its node feeds it, and the compiled
kernels against the same maths in numpy, side by side (see :mod:`.bench`)."""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Any, Callable, Iterable

import numpy as np

@dataclasses.dataclass
class StepTiming:
    name: str
    steps: int
    median_us: float
    p99_us: float
    note: str = ""


def time_steps(name: str, calls: Iterable[Callable[[], Any]], note: str = "", warmup: int = 20) -> StepTiming:
    """Run every call once, timing each; the first ``warmup`` are not counted."""
    durations = []
    clock = time.perf_counter_ns
    for i, call in enumerate(calls):
        t0 = clock()
        call()
        dt = clock() - t0
        if i >= warmup:
            durations.append(dt)
    if not durations:
        raise ValueError(f"{name}: no timed steps")
    d = np.asarray(durations, dtype=float) * 1e-3
    return StepTiming(name, len(d), float(np.median(d)), float(np.percentile(d, 99)), note)


class DriveArrays:
    """The sensor arrays of a simulated drive, resampled where a core wants another rate."""

    def __init__(self, seconds: float, seed: int = 1) -> None:
        from vehicle_estimation.sim import default_scenario, simulate
        self.result = simulate(default_scenario(duration_s=seconds, seed=seed))
        s, tr = self.result.sensors, self.result.truth
        self.vehicle = self.result.scenario.vehicle
        self.imu_t, self.accel, self.gyro = s["imu"]["t"], s["imu"]["accel"], s["imu"]["gyro"]
        self.speed_t, self.speed_v = s["speed"]["t"], s["speed"]["v"]
        self.gnss = s["gnss"]
        self.js = s["joint_states"]
        self.pt = s["powertrain"]
        self.truth = tr

    def at_truth(self, key: str, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self.truth["t"], self.truth[key])

    def state_inputs(self, i_every: int = 2) -> list[tuple[float, Any, np.ndarray]]:
        """(t, VehicleInputs, z = [ax, ay, r]) at 100 Hz, as the state node builds them."""
        from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
        out = []
        js_t = self.js["t"]
        vp = self.vehicle
        for i in range(0, len(self.imu_t), i_every):
            t = float(self.imu_t[i])
            j = min(int(np.searchsorted(js_t, t)), len(js_t) - 1)
            wheels = self.js["velocity"][j, :4]
            steer = float(self.js["position"][j, 4]) / vp.steering_ratio
            inputs = VehicleInputs(steer_angle=steer, wheel_speeds=np.array(wheels, dtype=float),
                                   slope=float(self.at_truth("slope", np.array([t]))[0]), mass=vp.mass)
            z = np.array([self.accel[i, 0], self.accel[i, 1], self.gyro[i, 2]])
            out.append((t, inputs, z))
        return out


def bench_fusion(d: DriveArrays) -> list[StepTiming]:
    """The fusion's steps by the compiled kernels and by numpy (their oracle), side by side."""
    from vehicle_estimation.estimators.common import compiled
    out = []
    for on in ((True, False) if compiled.enabled() else (False,)):
        out += _bench_fusion(d, on)
    return out


def _bench_fusion(d: DriveArrays, compiled_maths: bool) -> list[StepTiming]:
    from vehicle_estimation.estimators.fusion.config import FusionConfig
    from vehicle_estimation.estimators.fusion.esekf import FusionEKF
    # As params/estimation.yaml runs it: the mounting states on, with the tight vertical constraint.
    ekf = FusionEKF(dataclasses.replace(FusionConfig(), estimate_mounting=True, nh_sigma_z=0.1))
    ekf.compiled = compiled_maths
    how = _how(compiled_maths)
    events = [(float(t), 0, i) for i, t in enumerate(d.imu_t)]
    events += [(float(t), 1, i) for i, t in enumerate(d.speed_t)]
    events += [(float(t), 2, i) for i, t in enumerate(d.gnss["t"])]
    events.sort()
    per_kind: dict[int, list[int]] = {0: [], 1: [], 2: []}
    clock = time.perf_counter_ns
    for t, kind, i in events:
        t0 = clock()
        if kind == 0:
            ekf.process_imu(t, d.accel[i], d.gyro[i])
        elif kind == 1:
            ekf.update_speed(t, float(d.speed_v[i]))
        elif math.isfinite(d.gnss["enu_meas"][i, 0]):
            ekf.update_gnss(t, d.gnss["enu_meas"][i], np.diag(d.gnss["cov"]))
        per_kind[kind].append(clock() - t0)
    out = []
    for kind, label in ((0, "fusion ES-EKF: IMU step (18 states, incl. vehicle constraints)"),
                        (1, "fusion ES-EKF: CAN speed update"), (2, "fusion ES-EKF: GNSS update")):
        x = np.asarray(per_kind[kind][20:], dtype=float) * 1e-3
        out.append(StepTiming(f"{label}, {how}", len(x), float(np.median(x)), float(np.percentile(x, 99))))
    return out


def _how(compiled_maths: bool) -> str:
    return "compiled" if compiled_maths else "numpy"


def bench_slope(d: DriveArrays) -> list[StepTiming]:
    from vehicle_estimation.estimators.slope.cubic_prediction import CubicPredictionSlopeObserver
    from vehicle_estimation.estimators.slope.observers import ClassicalSlopeObserver
    from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeSlope
    t = d.imu_t
    vx = d.at_truth("vx", t)
    grade = d.at_truth("slope", t)
    out = []
    for name, obs in (("slope: classical (paper 004 Eqs. 32-33)", ClassicalSlopeObserver()),
                      ("slope: cubic_prediction (paper 004 Eqs. 15-27)", CubicPredictionSlopeObserver())):
        out.append(time_steps(name, (lambda i=i, o=obs: o.step(float(t[i]), float(d.accel[i, 0]), float(vx[i]))
                                     for i in range(len(t)))))
    pitch = PitchGradeSlope()
    out.append(time_steps("slope: fusion_pitch (paper 003 Sec. 7.2, LWMA)",
                          (lambda i=i: pitch.step(float(t[i]), float(grade[i]), 1e-5) for i in range(len(t)))))
    return out


def bench_state(d: DriveArrays) -> list[StepTiming]:
    from vehicle_estimation.estimators.state.ckf import VehicleStateCKF
    from vehicle_estimation.estimators.state.vbackf import VBConfig, VehicleStateVBACKF
    from vehicle_estimation.estimators.common import compiled
    samples = d.state_inputs()
    out = []
    # Compiled kernels and numpy (their oracle) side by side, the CKF and the shipped VB-ACKF.
    for on in ((True, False) if compiled.enabled() else (False,)):
        ckf = VehicleStateCKF(d.vehicle)
        ckf.use_compiled(on)
        out.append(time_steps(f"vehicle state: CKF (paper 004, 5 states, 4-wheel Dugoff), {_how(on)}",
                              (lambda s=s, f=ckf: f.step(*s) for s in samples)))
        vb = VehicleStateVBACKF(d.vehicle, vb=VBConfig(iterations=10, tolerance=0.0))
        vb.use_compiled(on)
        out.append(time_steps(f"vehicle state: VB-ACKF, N = 10 (shipped), {_how(on)}",
                              (lambda s=s, f=vb: f.step(*s) for s in samples)))
    for n in range(1, 6):
        vb = VehicleStateVBACKF(d.vehicle, vb=VBConfig(iterations=n, tolerance=0.0))
        out.append(time_steps(f"vehicle state: VB-ACKF, N = {n} iterations",
                              (lambda s=s, f=vb: f.step(*s) for s in samples)))
    # The shipped N = 10 in numpy, side by side: closed-form IMU moments against the cubature
    # rule (the oracle the closed form is tested against).
    for closed in (True, False):
        vb = VehicleStateVBACKF(d.vehicle, vb=VBConfig(iterations=10, tolerance=0.0))
        vb.use_compiled(False)
        if not closed:
            vb.filter.h_affine = None
        out.append(time_steps(f"vehicle state: VB-ACKF, N = 10 (shipped), moments {'closed-form' if closed else 'by cubature'}",
                              (lambda s=s, f=vb: f.step(*s) for s in samples),
                              note="" if closed else "the oracle"))
    return out


def bench_aoukf(d: DriveArrays) -> list[StepTiming]:
    """The vehicle-state AO-UKF of paper 002 (plain UKF, anti-outlier, + GA-BPNN), and our
    generic UKF against filterpy's on the same 3-DOF model, data and tuning (predict + update
    of [ay, r]). filterpy calls the model once per sigma point; ours once per step on all 7."""
    from vehicle_estimation.estimators.state.aoukf import AOUKFConfig, VehicleStateAOUKF
    from vehicle_estimation.estimators.state.aoukf_filters import UnscentedKalmanFilter
    from vehicle_estimation.estimators.state.three_dof_model import ThreeDofModel
    from vehicle_estimation.estimators.state.gabpnn import (
        default_weights_path,
        load_correction,
    )
    samples = d.state_inputs()
    out = []
    weights = default_weights_path(d.vehicle.name)
    for label, config, correction in (
            ("AO-UKF: plain UKF (paper 002, 3 states)", AOUKFConfig(filter="ukf"), None),
            ("AO-UKF: anti-outlier UKF (Sec. 3.3)", AOUKFConfig(), None),
            ("AO-UKF: anti-outlier UKF + GA-BPNN (Eq. 5)", AOUKFConfig(),
             load_correction(weights) if weights.exists() else None)):
        f = VehicleStateAOUKF(d.vehicle, config, correction)
        out.append(time_steps(label, (lambda s=s, f=f: f.step(*s) for s in samples)))

    config = AOUKFConfig()
    model = ThreeDofModel.from_params(d.vehicle, config)
    Q = np.diag(config.q_diag)
    R = np.diag([config.r_ay, config.r_yaw_rate])
    x0 = np.array([float(d.at_truth("vx", np.array([samples[0][0]]))[0]), 0.0, 0.0])
    P0 = np.diag(config.p0_diag)
    steps = [(t1 - t0, float(z1[0]), float(inputs.steer_angle), z1[1:3])
             for (t0, _, _), (t1, inputs, z1) in zip(samples[:-1], samples[1:])]
    ours = UnscentedKalmanFilter(lambda X, dt, ax, delta: model.transition(X, dt, ax, delta),
                                 lambda X, delta: model.measurement(X, delta), Q,
                                 np.diag([config.r_ay, config.r_yaw_rate, config.r_wheel_speed]), x0, P0,
                                 alpha=config.ukf_alpha, beta=config.ukf_beta, kappa=config.ukf_kappa)
    select = np.array([0, 1])

    def our_step(dt, ax, delta, z):
        ours.predict(dt, ax, delta)
        ours.update(z, delta, select=select)
    out.append(time_steps("UKF, ours (vectorised sigma points): predict + update",
                          (lambda s=s: our_step(*s) for s in steps)))
    try:
        from filterpy.kalman import MerweScaledSigmaPoints
        from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF
    except ImportError as exc:
        out.append(StepTiming("filterpy UKF", 0, math.nan, math.nan, f"unavailable: {exc} (pip install filterpy)"))
        return out
    points = MerweScaledSigmaPoints(3, alpha=config.ukf_alpha, beta=config.ukf_beta, kappa=config.ukf_kappa)
    theirs = FilterpyUKF(dim_x=3, dim_z=2, dt=0.01, points=points,
                         fx=lambda x, dt, ax, delta: model.transition(x, dt, ax, delta),
                         hx=lambda x, delta: model.measurement(x, delta)[:2])
    theirs.x, theirs.P, theirs.Q, theirs.R = x0.copy(), P0.copy(), Q.copy(), R.copy()

    def their_step(dt, ax, delta, z):
        theirs.predict(dt=dt, ax=ax, delta=delta)
        theirs.update(z, delta=delta)
    out.append(time_steps("filterpy UKF, same model and data: predict + update",
                          (lambda s=s: their_step(*s) for s in steps)))
    return out


def _mass_samples(d: DriveArrays, rate_hz: float) -> list[dict[str, float]]:
    """Window means at ``rate_hz``, as the mass node passes them to its core."""
    t = d.pt["t"]
    period = 1.0 / rate_hz
    edges = np.arange(t[0], t[-1], period)
    idx = np.searchsorted(t, edges)
    vx = d.at_truth("vx", t)
    ax = np.gradient(vx, t)
    slope = d.at_truth("slope", t)
    brake = np.interp(t, d.truth["t"], np.sum(d.truth["brake_torque"], axis=1))
    out = []
    for a, b in zip(idx[:-1], idx[1:]):
        if b <= a:
            continue
        sl = slice(a, b)
        out.append(dict(t=float(t[b - 1]), vx=float(vx[sl].mean()), ax=float(ax[sl].mean()),
                        slope=float(slope[sl].mean()), drive_force=float(d.pt["drive_force"][sl].mean()),
                        engine_torque=float(d.pt["engine_torque"][sl].mean()),
                        engine_speed=float(d.pt["engine_speed"][sl].mean()),
                        engine_load=float(d.pt["load"][sl].mean()), gear=float(d.pt["gear"][b - 1]),
                        brake_torque=float(brake[sl].mean())))
    return out


def bench_mass(d: DriveArrays) -> list[StepTiming]:
    from vehicle_estimation.estimators.mass.mass_ffrls import FFRLSMassEstimator
    from vehicle_estimation.estimators.mass.mass_rls import LongitudinalMassEstimator
    out = []
    samples = _mass_samples(d, 4.0)
    for name, core in (("mass: RLS (paper 003, 4 Hz windows)", LongitudinalMassEstimator(d.vehicle)),
                       ("mass: FFRLS (paper 004, 4 Hz windows)", FFRLSMassEstimator(d.vehicle))):
        out.append(time_steps(name, (lambda s=s, c=core: c.step(s["t"], s["vx"], s["ax"], s["slope"],
                                                                 **_mass_kwargs(s)) for s in samples),
                              warmup=5))
    try:
        from vehicle_estimation.estimators.mass.ta_aekf import TaAekfMassEstimator
    except ImportError as exc:   # pragma: no cover
        out.append(StepTiming("mass: TA-AEKF", 0, math.nan, math.nan, f"unavailable: {exc}"))
        return out
    import torch
    torch.set_num_threads(1)       # as the mass node runs it
    core = TaAekfMassEstimator(d.vehicle)
    samples = _mass_samples(d, 100.0)
    out.append(time_steps("mass: TA-AEKF (paper 000, 100 Hz, incl. transformer inference)",
                          (lambda s=s: core.step(s["t"], s["vx"], s["ax"], s["slope"], **_mass_kwargs(s))
                           for s in samples), note="see the p99: the steps with an inference"))
    return out


def _mass_kwargs(s: dict[str, float]) -> dict[str, float]:
    return {k: s[k] for k in ("drive_force", "engine_torque", "engine_speed", "engine_load", "gear",
                              "brake_torque")}


def run_cores(seconds: float) -> list[StepTiming]:
    d = DriveArrays(seconds)
    rows: list[StepTiming] = []
    for section in (bench_fusion, bench_slope, bench_state, bench_aoukf, bench_mass):
        print(f"  cores: {section.__name__[6:]} ...", file=sys.stderr, flush=True)
        rows += section(d)
    return rows


