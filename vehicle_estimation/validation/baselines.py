"""Textbook baselines for the estimators, run offline on a bag's arrays.

Every figure of ``validate`` is a ratio to one of these, computed in the same run on the same
data, so that a number says how much better (or worse) than the obvious method an estimator is:

* :func:`kinematic_grade`: the road grade from the accelerometer and the speed alone,
  ``theta = asin((f_x - dv/dt) / g)`` (the IMU's specific force less the vehicle's own
  acceleration is the gravity along the road), low-passed by a causal second-order
  Butterworth filter so that it is an *online* method like ours. No bias estimate, no model.
* :func:`batch_ls_mass`: the least-squares mass over the whole drive from Newton's law along
  the road, ``F_drive - F_aero = (m + I_w / R^2) a + m g (sin theta + C_r cos theta)``, on
  the driving samples (drive force and speed above thresholds). Given the true grade it is the
  best an estimator on these signals can do with the vehicle file's resistances; given our
  published slope, it says how much of our mass error the slope causes. Samples whose residual
  is an outlier (braking while a drive force is still reported) are trimmed and the fit redone.

* :func:`baseline_linear_kf`: the lateral baseline, the linear single-track KF of the Stanford
  data's source repository (``vehicle-estimation stanford``), given the vehicle file's
  cornering stiffnesses and a speed; its R from the high-passed signals (:func:`highpass_std`).

The fusion's and the state's motion outputs are held against the raw sensors they start from:

* :func:`kinematic_roll`: the roll from the accelerometer, ``phi = asin((f_y - v r) / g)`` (the
  lateral specific force less the centripetal acceleration is the gravity across the car),
  low-passed as the grade; the pitch's baseline is the kinematic grade's tilt itself.
* :func:`gnss_course`: the heading from the GNSS fixes alone, the direction of the displacement
  over the last second (a course over ground without Doppler).
* the CAN speed for the speed and vx, the gyro's own yaw rate for the yaw rate (no baseline
  function: the sensor is the baseline).

:func:`read_sensor_inputs` reads those raw sensors from a bag, the IMU turned into base_link by
the mounting the nodes are given.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import signal

from vehicle_estimation.contract import topics as T
from vehicle_estimation.contract.vehicle import GRAVITY, VehicleParams
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler

#: Corner of the kinematic grade's low-pass [Hz]: the accelerometer's vibration and the
#: differentiated speed's quantisation are far above it, a road's grade changes below it.
KINEMATIC_GRADE_CUTOFF_HZ = 0.3
#: Driving samples for the batch mass: enough force and speed that the drive force dominates
#: the resistances the vehicle file can only approximate.
MIN_DRIVE_FORCE_N = 300.0
MIN_SPEED_MS = 3.0
#: Robust refit of the batch mass: residuals beyond this many MADs are dropped, twice.
TRIM_MADS = 4.0
TRIM_ITERATIONS = 2
#: The speed's derivative is taken after this low-pass, like any estimator would [Hz].
SPEED_DERIVATIVE_CUTOFF_HZ = 1.0


def _uniform(t: np.ndarray, y: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    grid = np.arange(t[0], t[-1], 1.0 / rate_hz)
    return grid, np.interp(grid, t, y)


def _lowpass(y: np.ndarray, rate_hz: float, cutoff_hz: float, *, causal: bool) -> np.ndarray:
    sos = signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")
    if causal:
        return signal.sosfilt(sos, y, zi=signal.sosfilt_zi(sos) * y[0])[0]
    return signal.sosfiltfilt(sos, y)


def speed_derivative(t: np.ndarray, v: np.ndarray, rate_hz: float = 50.0, *, causal: bool = True
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(grid, low-passed speed, its derivative) on a uniform ``rate_hz`` grid."""
    grid, vu = _uniform(t, v, rate_hz)
    vs = _lowpass(vu, rate_hz, SPEED_DERIVATIVE_CUTOFF_HZ, causal=causal)
    return grid, vs, np.gradient(vs, 1.0 / rate_hz)


def kinematic_grade(imu_t: np.ndarray, fx: np.ndarray, speed_t: np.ndarray, speed: np.ndarray, *,
                    gravity: float = GRAVITY, rate_hz: float = 50.0,
                    cutoff_hz: float = KINEMATIC_GRADE_CUTOFF_HZ) -> tuple[np.ndarray, np.ndarray]:
    """(t, grade [rad]) from the longitudinal specific force and the speed, causal."""
    grid, _, dv = speed_derivative(speed_t, speed, rate_hz)
    # The same low-pass on f_x as on v, so that the two are compared at the same delay.
    f = _lowpass(np.interp(grid, imu_t, fx), rate_hz, SPEED_DERIVATIVE_CUTOFF_HZ, causal=True)
    raw = np.arcsin(np.clip((f - dv) / gravity, -1.0, 1.0))
    return grid, _lowpass(raw, rate_hz, cutoff_hz, causal=True)


def kinematic_roll(imu_t: np.ndarray, fy: np.ndarray, yaw_rate: np.ndarray, speed_t: np.ndarray,
                   speed: np.ndarray, *, gravity: float = GRAVITY, rate_hz: float = 50.0,
                   cutoff_hz: float = KINEMATIC_GRADE_CUTOFF_HZ) -> tuple[np.ndarray, np.ndarray]:
    """(t, roll [rad], REP-103: right side down positive) from the lateral specific force, the
    yaw rate and the speed, causal: a body rolled by phi feels g sin(phi) along its y axis on top
    of the centripetal v r (vy' neglected, as a textbook tilt sensor does)."""
    grid, v, _ = speed_derivative(speed_t, speed, rate_hz)
    f = _lowpass(np.interp(grid, imu_t, fy), rate_hz, SPEED_DERIVATIVE_CUTOFF_HZ, causal=True)
    r = _lowpass(np.interp(grid, imu_t, yaw_rate), rate_hz, SPEED_DERIVATIVE_CUTOFF_HZ, causal=True)
    raw = np.arcsin(np.clip((f - v * r) / gravity, -1.0, 1.0))
    return grid, _lowpass(raw, rate_hz, cutoff_hz, causal=True)


def gnss_course(t: np.ndarray, east: np.ndarray, north: np.ndarray, *, baseline_s: float = 1.0,
                min_distance_m: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(t, course [rad], ENU yaw: from east, counter-clockwise) of each fix's displacement from
    the last fix at least ``baseline_s`` before it, where that displacement exceeds
    ``min_distance_m`` (below it the fixes' noise decides the direction)."""
    t, east, north = (np.asarray(x, dtype=float) for x in (t, east, north))
    j = np.searchsorted(t, t - baseline_s, side="right") - 1
    ok = j >= 0
    j = np.clip(j, 0, None)
    de, dn = east - east[j], north - north[j]
    ok &= np.hypot(de, dn) >= min_distance_m
    return t[ok], np.arctan2(dn[ok], de[ok])


def batch_ls_mass(force_t: np.ndarray, drive_force: np.ndarray, speed_t: np.ndarray, speed: np.ndarray,
                  grade_t: np.ndarray, grade: np.ndarray, vehicle: VehicleParams, *,
                  rate_hz: float = 20.0) -> dict[str, float]:
    """Least-squares mass over a whole drive; ``{"mass", "samples"}`` (NaN without samples).

    Offline, so the speed's derivative is zero-phase. The wheels' inertia is a known
    equivalent mass ``I_w / R^2``; the engine's (gear dependent) is left out, as in the
    textbook form: it is part of what the baseline gets wrong.
    """
    grid, v, a = speed_derivative(speed_t, speed, rate_hz, causal=False)
    ok_force = np.isfinite(drive_force)
    if ok_force.sum() < 2:
        return {"mass": math.nan, "samples": 0}
    force = np.interp(grid, force_t[ok_force], drive_force[ok_force])
    theta = np.interp(grid, grade_t, grade)
    p = vehicle
    rotating = p.wheel_inertia / p.wheel_radius ** 2
    y = force - 0.5 * p.air_density * p.drag_area * v * np.abs(v) - rotating * a
    phi = a + p.gravity * (np.sin(theta) + p.rolling_resistance * np.cos(theta))
    use = (force > MIN_DRIVE_FORCE_N) & (v > MIN_SPEED_MS) & np.isfinite(y) & np.isfinite(phi)
    if use.sum() < 10:
        return {"mass": math.nan, "samples": int(use.sum())}
    mass = float(np.sum(phi[use] * y[use]) / np.sum(phi[use] ** 2))
    # The contract has no brake signal: a moment of braking while the drive force is still
    # reported (pedal overlap, a lagging CAN value) is thousands of newtons of force the model
    # lacks. Trim what lies beyond TRIM_MADS robust deviations and refit.
    for _ in range(TRIM_ITERATIONS):
        residual = y - mass * phi
        scale = 1.4826 * np.median(np.abs(residual[use] - np.median(residual[use])))
        keep = use & (np.abs(residual) <= TRIM_MADS * max(scale, 1e-6))
        if keep.sum() < 10:
            break
        mass = float(np.sum(phi[keep] * y[keep]) / np.sum(phi[keep] ** 2))
        use = keep
    return {"mass": mass, "samples": int(use.sum())}


def highpass_std(x: np.ndarray) -> float:
    """Std of the high-passed signal, as BetaStanfordLinear.m estimates sensor noise.

    The source designs ``fdesign.highpass('Fst,Fp,Ast,Ap', 0.15, 0.25, 60, 1)`` (equiripple,
    normalised to Nyquist: stop below 7.5 Hz, pass above 12.5 Hz at 100 Hz) and applies it
    causally with ``filter``; here a Kaiser-window FIR with the same band edges and 60 dB.
    """
    numtaps, beta = signal.kaiserord(60.0, 0.10)
    taps = signal.firwin(numtaps | 1, 0.20, window=("kaiser", beta), pass_zero=False)
    return float(np.std(signal.lfilter(taps, 1.0, np.asarray(x, dtype=float))))


def baseline_linear_kf(t, ay, yaw_rate, delta, vx, *, m, lf, lr, iz, cf, cr) -> tuple[np.ndarray, np.ndarray]:
    """Linear single-track KF of MBDS/sideslip-angle-vehicle-estimation (estimators/matlab_kf).

    State [beta, r]; Euler-discretised bicycle model with the road-wheel angle as input and
    the (reference) speed vx as a known parameter; measurement [ay, r]. As the source: Q is
    the steering noise variance (std of the high-passed steering angle, times 1000 as in
    the source) through B, R = diag(noise of ay, r) from the high-passed signals,
    x0 = 0, P0 = 1e4 I; A uses vx(i-1), C uses vx(i). Returns (beta, r) per sample.
    """
    s_ay, s_r, s_d = highpass_std(ay), highpass_std(yaw_rate), highpass_std(delta) * 1000.0
    R = np.diag([s_ay ** 2, s_r ** 2])
    x, P = np.zeros(2), np.diag([1e4, 1e4])
    out = np.zeros((len(t), 2))
    for i in range(1, len(t)):
        dt, u0, u1 = t[i] - t[i - 1], vx[i - 1], vx[i]
        A = np.array([[1 - dt * (cf + cr) / (m * u0), -dt * (1 + (lf * cf - lr * cr) / (m * u0 ** 2))],
                      [-dt * (lf * cf - lr * cr) / iz, 1 - dt * (lf ** 2 * cf + lr ** 2 * cr) / (iz * u0)]])
        B = dt * np.array([cf / (m * u0), lf * cf / iz])
        C = np.array([[-(cf + cr) / m, -(lf * cf - lr * cr) / (m * u1)], [0.0, 1.0]])
        D = np.array([cf / m, 0.0])
        x, P = A @ x + B * delta[i - 1], A @ P @ A.T + np.outer(B, B) * s_d ** 2       # predict
        K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)                                    # correct
        x, P = x + K @ (np.array([ay[i], yaw_rate[i]]) - C @ x - D * delta[i]), (np.eye(2) - K @ C) @ P
        out[i] = x
    return out[:, 0], out[:, 1]


def read_sensor_inputs(bag: Path, imu_mounting_rpy=(0.0, 0.0, 0.0)) -> dict[str, np.ndarray]:
    """The raw sensors the baselines start from: IMU (f_x, f_y, yaw rate in base_link, turned by
    the mounting the nodes are given, ``vehicle.imu_mounting_rpy``), CAN speed, drive force,
    and the GNSS fixes with a valid status in ENU about the first one (as the fusion's odom
    frame), each topic empty where the bag lacks it."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane

    imu, speed, force, fixes = [], [], [], []
    want = {T.IMU, T.SPEED, T.POWERTRAIN, T.GNSS}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic.lstrip("/") in want]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            topic = conn.topic.lstrip("/")
            if topic == T.IMU:
                a, w = msg.linear_acceleration, msg.angular_velocity
                imu.append((t, a.x, a.y, a.z, w.x, w.y, w.z))
            elif topic == T.SPEED:
                speed.append((t, msg.twist.twist.linear.x))
            elif topic == T.GNSS:
                if msg.status.status >= 0 and math.isfinite(msg.latitude) and math.isfinite(msg.longitude):
                    fixes.append((t, msg.latitude, msg.longitude, msg.altitude))
            else:
                effort = dict(zip(msg.name, msg.effort))
                force.append((t, effort.get(T.DRIVE_JOINT, math.nan)))
    imu_a = np.array(imu, dtype=float).reshape(-1, 7)
    C = rotmat_from_euler(*(float(a) for a in imu_mounting_rpy))     # imu_link -> base_link
    f, w = imu_a[:, 1:4] @ C.T, imu_a[:, 4:7] @ C.T
    speed_a, force_a = (np.array(x, dtype=float).reshape(-1, 2) for x in (speed, force))
    enu = np.zeros((0, 3))
    if fixes:
        origin = LocalTangentPlane(*fixes[0][1:])
        enu = np.array([origin.to_enu(*f[1:]) for f in fixes], dtype=float).reshape(-1, 3)
    return {"imu_t": imu_a[:, 0], "fx": f[:, 0], "fy": f[:, 1], "wz": w[:, 2],
            "speed_t": speed_a[:, 0], "speed": speed_a[:, 1], "force_t": force_a[:, 0], "force": force_a[:, 1],
            "gnss_t": np.array([f[0] for f in fixes], dtype=float), "east": enu[:, 0], "north": enu[:, 1]}
