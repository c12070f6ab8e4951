"""Drives of the CommonRoad multi-body vehicle model, as bags in our topic contract.

The truth comes from an implementation that is *not* ours: ``vehicle_dynamics_mb`` of
``commonroad-vehicle-models`` 3.0.2 (PyPI, module ``vehiclemodels``; Althoff & Würsching,
"CommonRoad: Vehicle Models", 2020) with ``parameters_vehicle2`` (BMW 320i): 29 states
(sprung mass with roll/pitch/heave, front and rear unsprung masses, four wheel-spin states,
compliant pin joints), PAC2002-style Magic-Formula tyres with combined slip, rear-wheel drive
(``T_se = 0``), no aerodynamic drag and no rolling resistance.

State layout (0-based, from the package source): 0/1 x/y position (global; here ENU east/north),
2 front road-wheel angle δ, 3 vx (body, at the reference point), 4 yaw ψ, 5 yaw rate r,
6/7 roll angle/rate, 8/9 pitch angle/rate, 10 vy, 11/12 z/vz of the sprung mass (z down),
13-17 front unsprung (roll, roll rate, vy, z, vz), 18-22 rear unsprung, 23-26 wheel angular
speeds "LF, RF, LR, RR" [rad/s] (mirrored labels, see ``WHEEL_STATE``), 27/28 compliant-joint lateral deflections. Inputs:
``u = [steering angle velocity dδ/dt, longitudinal acceleration]``; the model limits both
(``|dδ/dt| <= 0.4 rad/s``; the acceleration is turned into engine/brake torque ``m R_w u``).

Integration: fixed-step classical RK4 at 1 kHz (``SIM_RATE_HZ``); the fastest mode is the wheel
spin (time constant ``I_w v / (K_x R_w^2)`` ≈ 4 ms at 22 m/s), well inside RK4's stability
region at 1 ms. The drive is preceded by ``SETTLE_S`` of straight driving that is not
recorded, so the suspension starts settled; the recording starts with ``WARMUP_S`` of straight
cruise. A closed-loop speed keeper (PI on the acceleration input) holds ``CRUISE_SPEED``; the
driver tracks a road-wheel-angle profile with a feed-forward + P law on the steering rate.

Sensors (all stamps start at 0 s):

* ``imu/data`` 200 Hz, at the CG, axes of the sprung body (``imu_link`` = ``base_link``):
  specific force = non-gravitational acceleration of the sprung mass (``dvx/dt - r vy``,
  ``dvy/dt + r vx``, ``g - dvz_down/dt``, from the model's own state derivatives) rotated
  into the rolled/pitched body, so ``+g`` on z at rest and ``g sin(roll)`` in ay in a turn, as
  a body-fixed IMU feels it; gyro = the body's angular rate from the Euler rates (ZYX: in a
  turn the rolled body's y axis turns at ``r sin(roll) cos(pitch)``). White noise
  0.05 m/s² / 0.003 rad/s, a constant bias per axis of ±0.05 m/s² / ±0.002 rad/s (signs from
  the seed), optional band-limited vibration (10-60 Hz, ``vibration_std`` m/s² on each of
  ax, ay, az).
* ``vehicle/speed`` 100 Hz: the true vx quantised to 1 km/h (covariance[0] = the
  quantisation variance (1/3.6)²/12).
* ``vehicle/joint_states`` 100 Hz: ``wheel_fl/fr/rl/rr`` velocity = the model's wheel angular
  speeds [rad/s]; ``steering_wheel`` position = δ × ``STEERING_RATIO`` (16.0, a guess for the
  E90 320i's standard steering; the model knows only δ). Efforts NaN (not modelled).
* ``gnss/fix`` 10 Hz: ENU position around ``ORIGIN`` to WGS84 by
  :class:`vehicle_estimation.estimators.common.geodesy.LocalTangentPlane`, 0.5 m white noise (east, north),
  1.0 m up.
* Ground truth 100 Hz: ``ground_truth/vehicle_state`` (vx, vy, r in base_link at the model's
  reference point), ``ground_truth/sideslip`` = atan(vy/vx), ``ground_truth/odometry``,
  ``ground_truth/mass`` (library mass), ``ground_truth/road_slope`` = 0. No powertrain topic
  (the model has no engine or gearbox).

CLI: ``python -m vehicle_estimation.validation.commonroad --out DIR [--vibration-std X]``.
"""

from __future__ import annotations

import argparse
import types
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vehicle_estimation.contract import topics as T
from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
from vehicle_estimation.sim import bag as simbag
from vehicle_estimation.sim.noise import band_limited_noise
from vehicle_estimation.validation import road_drive as rd

G_MODEL = 9.81                   # the model's gravity constant [m/s^2]
SIM_RATE_HZ = 1000
SETTLE_S = 2.0                   # unrecorded straight driving before t = 0 [s]
WARMUP_S = 5.0                   # recorded straight cruise at the start [s]
CRUISE_SPEED = 22.0              # [m/s] (79.2 km/h: not a whole km/h, so the CAN quantisation shows)
STEERING_RATIO = 16.0            # steering wheel / road wheel; a guess (not in the library)
ORIGIN = (48.2626, 11.6679, 480.0)  # Garching (TUM), lat/lon [deg], alt [m]
IMU_RATE_HZ, CAN_RATE_HZ, GNSS_RATE_HZ, TRUTH_RATE_HZ = 200, 100, 10, 100
ACCEL_NOISE, GYRO_NOISE = 0.05, 0.003            # white-noise std [m/s^2], [rad/s]
ACCEL_BIAS, GYRO_BIAS = 0.05, 0.002              # constant bias magnitude [m/s^2], [rad/s]
GNSS_NOISE_H, GNSS_NOISE_V = 0.5, 1.0            # [m]
VEHICLE_NAME = "commonroad_bmw320i"
#: Lateral conventions of the MB model, read off its equations: its "left" wheels sit at
#: y = -T/2 (they are the faster ones for r > 0, and a forward force on them yaws the car
#: counter-clockwise), so its L/R labels are mirrored against REP-103 (y left): our
#: ``wheel_fl`` is its RF state, and so on. Its roll angle is positive when its "left" (our
#: right) suspension extends, i.e. ISO/REP-103 roll = -x[6]; its pitch is positive when the
#: front suspension extends (nose up), i.e. ISO/REP-103 pitch (nose down positive) = -x[8].
ROLL_SIGN, PITCH_SIGN = -1.0, -1.0
#: Model wheel-state index for our wheel_fl, wheel_fr, wheel_rl, wheel_rr.
WHEEL_STATE = (24, 23, 26, 25)


# --------------------------------------------------------------------------- parameters
def model_parameters():
    """``parameters_vehicle2()`` (BMW 320i): the library's dataclass (plain attributes)."""
    from vehiclemodels.parameters_vehicle2 import parameters_vehicle2

    return parameters_vehicle2()


def static_tyre_loads(p) -> tuple[float, float]:
    """Static vertical load per front / rear tyre [N], as ``init_mb`` settles it."""
    front = (p.m_s * G_MODEL * p.b / (p.a + p.b) + p.m_uf * G_MODEL) / 2.0
    rear = (p.m_s * G_MODEL * p.a / (p.a + p.b) + p.m_ur * G_MODEL) / 2.0
    return front, rear


def vehicle_params_mapping(p=None, *, wheel_radius: float | None = None) -> dict:
    """Our ``vehicle.*`` section for the library car (see :func:`params_yaml` for sources)."""
    p = model_parameters() if p is None else p
    fz_f, fz_r = static_tyre_loads(p)
    # PAC2002 as the library codes it: K_y = p_ky1 F_z (no load degression), so C_alpha =
    # |p_ky1| F_z0 per tyre; K_x = p_kx1 F_z.
    return {
        "name": VEHICLE_NAME, "mass": p.m, "curb_mass": p.m, "lf": p.a, "lr": p.b,
        "track_front": p.T_f, "track_rear": p.T_r, "cg_height": p.h_cg,
        # the IMU sits at the sprung mass's CG (h_s), the body rolls about the roll axis (h_ra*)
        "roll_lever": p.h_s - 0.5 * (p.h_raf + p.h_rar), "yaw_inertia": p.I_z,
        "wheel_radius": p.R_w if wheel_radius is None else wheel_radius,
        "wheel_inertia": 4.0 * p.I_y_w,
        "frontal_area": 2.1, "drag_coefficient": 0.05, "air_density": 1.2, "rolling_resistance": 0.0,
        "driveline_efficiency": 0.9, "final_drive": 3.23,
        "gear_ratios": [4.32, 2.46, 1.66, 1.23, 1.0, 0.85],
        "steering_ratio": STEERING_RATIO, "driven_axle": "rear",
        "engine_idle_speed": 73.3, "engine_max_speed": 680.7, "engine_max_torque": 200.0,
        "engine_max_power": 110000.0, "engine_drag_torque": 20.0, "max_brake_torque": 2500.0,
        "brake_front_share": p.T_sb,
        "cornering_stiffness_front": abs(p.tire.p_ky1) * fz_f,
        "cornering_stiffness_rear": abs(p.tire.p_ky1) * fz_r,
        "longitudinal_stiffness": p.tire.p_kx1 * (fz_f + fz_r) / 2.0,
        "tyre_load_exponent": 1.0,
        "road_friction": 1.0,
        "magic_b": abs(p.tire.p_ky1) / (p.tire.p_cy1 * p.tire.p_dy1), "magic_c": p.tire.p_cy1,
        "magic_d": p.tire.p_dy1, "magic_e": p.tire.p_ey1,
        "pitch_gain": 0.002, "pitch_time_constant": 0.15, "gravity": G_MODEL,
    }


def params_yaml(p=None) -> str:
    """The text of ``params/commonroad_bmw320i.yaml``."""
    v = vehicle_params_mapping(p)
    p = model_parameters() if p is None else p
    fz_f, fz_r = static_tyre_loads(p)
    lib = "library (parameters_vehicle2)"
    notes = {
        "name": "", "mass": f"{lib} m (total)", "curb_mass": "= mass",
        "lf": f"{lib} a (the model's CG-to-front-axle lever arm)", "lr": f"{lib} b",
        "track_front": f"{lib} T_f", "track_rear": f"{lib} T_r", "cg_height": f"{lib} h_cg",
        "roll_lever": f"derived: {lib} h_s (the sprung CG, where the IMU is) - roll axis h_raf = h_rar",
        "yaw_inertia": f"{lib} I_z", "wheel_radius": f"{lib} R_w (see effective_rolling_radius)",
        "wheel_inertia": f"{lib} 4 x I_y_w", "frontal_area": "guess (real 320i ~2.1 m^2)",
        "drag_coefficient": "the model has NO aero drag; 0.05 is the lowest the nodes accept (30 N at 22 m/s)",
        "air_density": "guess", "rolling_resistance": "the model has none",
        "driveline_efficiency": "guess (no powertrain in the model)", "final_drive": "guess",
        "gear_ratios": "guess (6-speed manual)",
        "steering_ratio": "guess; the bag's steering_wheel = delta x this",
        "driven_axle": f"{lib} T_se = 0: all engine torque on the rear axle",
        "engine_idle_speed": "guess", "engine_max_speed": "guess", "engine_max_torque": "guess",
        "engine_max_power": "guess", "engine_drag_torque": "guess", "max_brake_torque": "guess",
        "brake_front_share": f"{lib} T_sb",
        "cornering_stiffness_front": f"derived: |p_ky1| x Fz0_front = {abs(p.tire.p_ky1):.2f} x {fz_f:.0f} N",
        "cornering_stiffness_rear": f"derived: |p_ky1| x Fz0_rear = {abs(p.tire.p_ky1):.2f} x {fz_r:.0f} N",
        "longitudinal_stiffness": f"derived: p_kx1 x mean Fz0 = {p.tire.p_kx1:.2f} x {(fz_f + fz_r) / 2:.0f} N",
        "tyre_load_exponent": "library: K_y = p_ky1 Fz, K_x = p_kx1 Fz, both proportional to the load",
        "road_friction": "derived: ~p_dx1 (1.17) / p_dy1 (1.05), rounded",
        "magic_b": "derived: |p_ky1| / (p_cy1 p_dy1)", "magic_c": f"{lib} p_cy1",
        "magic_d": f"{lib} p_dy1", "magic_e": f"{lib} p_ey1",
        "pitch_gain": "guess (our default)", "pitch_time_constant": "guess (our default)",
        "gravity": "the model's g",
    }
    header = [
        "# BMW 320i of commonroad-vehicle-models 3.0.2 (vehiclemodels.parameters_vehicle2), the car",
        "# of the multi-body validation drives (vehicle_estimation.validation.commonroad).",
        "# Written by vehicle_estimation.validation.commonroad.params_yaml(); each value says whether",
        "# it comes from the library, is derived from it, or is a guess.",
        "# Cornering stiffness: the library's lateral PAC2002 uses K_y = p_ky1 F_z (it simplifies",
        "# K_y0 to p_ky1 F_z), so for small slip F_y = -|p_ky1| F_z alpha per tyre: C_alpha =",
        "# |p_ky1| F_z0 at the static load F_z0 = (m_s g b/(a+b) + m_uf g)/2 (front),",
        "# (m_s g a/(a+b) + m_ur g)/2 (rear), g = 9.81 as the model. Per tyre, as VehicleParams.",
        "# Both stiffnesses grow with the tyre's load (tyre_load_exponent 1): with constant ones",
        "# the Dugoff tyre saturates the unloaded inner wheels of this light, high car early in a",
        "# corner (issue 13: sideslip 40-70 % too large in the step steer's steady state).",
    ]
    return rd.format_vehicle_yaml(header, v, notes)


# --------------------------------------------------------------------------- manoeuvres
def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _sine_pulse(t, t0, period, amp):
    """One full sine period of amplitude ``amp`` starting at ``t0`` (0 outside)."""
    s = (t - t0) / period
    return np.where((s >= 0.0) & (s <= 1.0), amp * np.sin(2.0 * np.pi * s), 0.0)


def _dlc(t):
    # ISO 3888-1-like: lane change out (one sine period of steering), hold, lane change back;
    # twice. Amplitude gives |ay| ~ 4-5 m/s^2 at 22 m/s.
    amp, period = 0.028, 2.5
    d = 0.0 * t
    for start in (WARMUP_S, WARMUP_S + 12.0):
        d = d + _sine_pulse(t, start, period, amp) - _sine_pulse(t, start + period + 1.5, period, amp)
    return d


def _slalom(t):
    amp, freq, duration = 0.025, 0.5, 20.0
    env = _smoothstep((t - WARMUP_S) / 2.0) * (1.0 - _smoothstep((t - WARMUP_S - duration + 2.0) / 2.0))
    return env * amp * np.sin(2.0 * np.pi * freq * (t - WARMUP_S))


def _step_steer(t):
    amp, ramp = 0.025, 0.25   # ramp within the model's 0.4 rad/s steering-rate limit
    up = _smoothstep((t - WARMUP_S) / ramp) - _smoothstep((t - WARMUP_S - 7.0) / ramp)
    down = _smoothstep((t - WARMUP_S - 11.0) / ramp) - _smoothstep((t - WARMUP_S - 18.0) / ramp)
    return amp * (up - down)


@dataclass(frozen=True)
class Manoeuvre:
    name: str
    duration: float
    steer: Callable[[np.ndarray], np.ndarray]   # road-wheel angle profile δ(t) [rad]


MANOEUVRES = {
    "dlc": Manoeuvre("dlc", 30.0, _dlc),
    "slalom": Manoeuvre("slalom", 30.0, _slalom),
    "step_steer": Manoeuvre("step_steer", 27.0, _step_steer),
}


# --------------------------------------------------------------------------- simulation
@dataclass
class Trajectory:
    t: np.ndarray          # (n,) [s], 0 at the start of the recording
    x: np.ndarray          # (n, 29) states
    dx: np.ndarray         # (n, 29) state derivatives at the recorded states
    u: np.ndarray          # (n, 2) inputs
    params: object = field(repr=False)


def simulate(manoeuvre: Manoeuvre | str, *, duration: float | None = None,
             speed: float = CRUISE_SPEED, rate_hz: int = SIM_RATE_HZ) -> Trajectory:
    """Integrate the MB model (RK4, ``rate_hz``) through ``manoeuvre``; returns every step."""
    from vehiclemodels.init_mb import init_mb
    from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb

    man = MANOEUVRES[manoeuvre] if isinstance(manoeuvre, str) else manoeuvre
    duration = man.duration if duration is None else float(duration)
    p = model_parameters()
    dt = 1.0 / rate_hz
    n_settle = round(SETTLE_S * rate_hz)
    n = round(duration * rate_hz) + 1
    t_all = (np.arange(n_settle + n) - n_settle) * dt
    d_ref = man.steer(t_all)
    d_ref[t_all < 0.0] = 0.0
    dd_ref = np.gradient(d_ref, dt)

    def f(x, u):
        return np.asarray(vehicle_dynamics_mb(x.tolist(), u, p), dtype=float)

    x = np.asarray(init_mb([0.0, 0.0, 0.0, speed, 0.0, 0.0, 0.0], p), dtype=float)
    integ = 0.0
    xs, dxs, us = np.empty((n, 29)), np.empty((n, 29)), np.empty((n, 2))
    for k in range(n_settle + n):
        err = speed - x[3]
        integ += err * dt
        u = [float(dd_ref[k] + 20.0 * (d_ref[k] - x[2])), float(np.clip(1.5 * err + 0.3 * integ, -3.0, 3.0))]
        k1 = f(x, u)
        if k >= n_settle:
            i = k - n_settle
            xs[i], dxs[i], us[i] = x, k1, u
            if i == n - 1:
                break
        k2 = f(x + 0.5 * dt * k1, u)
        k3 = f(x + 0.5 * dt * k2, u)
        k4 = f(x + dt * k3, u)
        x = x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        x[23:27] = np.maximum(x[23:27], 0.0)   # the model forbids negative wheel spin
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"MB model diverged at t = {t_all[k]:.3f} s")
    return Trajectory(t_all[n_settle:n_settle + n].copy(), xs, dxs, us, p)


# --------------------------------------------------------------------------- sensors
def truth_signals(tr: Trajectory) -> dict[str, np.ndarray]:
    """Truth in base_link/ENU at every integration step."""
    x, dx = tr.x, tr.dx
    vx, vy, r = x[:, 3], x[:, 10], x[:, 5]
    roll, pitch = ROLL_SIGN * x[:, 6], PITCH_SIGN * x[:, 8]
    # non-gravitational acceleration of the sprung mass in the yaw-aligned (level) frame
    a_lvl = np.column_stack([dx[:, 3] - r * vy, dx[:, 10] + r * vx, G_MODEL - dx[:, 12]])
    # into the rolled / pitched body: f_b = Rx(roll)^T Ry(pitch)^T f_level
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    fx1 = cp * a_lvl[:, 0] - sp * a_lvl[:, 2]
    fz1 = sp * a_lvl[:, 0] + cp * a_lvl[:, 2]
    fy = cr * a_lvl[:, 1] + sr * fz1
    fz = -sr * a_lvl[:, 1] + cr * fz1
    # the body's angular rate from the Euler rates (ZYX): a rolled body turning at psi' also
    # pitches about its own y axis at psi' sin(roll) cos(pitch), which a gyro reads
    roll_rate, pitch_rate = ROLL_SIGN * x[:, 7], PITCH_SIGN * x[:, 9]
    wx = roll_rate - r * sp
    wy = pitch_rate * cr + r * sr * cp
    wz = -pitch_rate * sr + r * cr * cp
    return {
        "t": tr.t, "vx": vx, "vy": vy, "yaw_rate": r, "yaw": x[:, 4], "roll": roll, "pitch": pitch,
        "wx": wx, "wy": wy, "wz": wz,
        "x": x[:, 0], "y": x[:, 1], "z": -x[:, 11],
        "sideslip": np.arctan2(vy, vx), "delta": x[:, 2], "wheels": x[:, list(WHEEL_STATE)],
        "accel": np.column_stack([fx1, fy, fz]),
        "ax_level": a_lvl[:, 0], "ay_level": a_lvl[:, 1],
    }


def _every(t: np.ndarray, rate: float) -> np.ndarray:
    dt = t[1] - t[0]
    step = round(1.0 / (rate * dt))
    return np.arange(0, t.size, step)


def sensor_result(tr: Trajectory, *, vibration_std: float = 0.0, seed: int = 0, mass: float | None = None,
                  imu_rpy_deg=(0.0, 0.0, 0.0)):
    """A :class:`~vehicle_estimation.sim.simulate.SimResult`-like object (``sensors``, ``truth``)
    that :func:`vehicle_estimation.sim.bag.build_streams` accepts. ``imu_rpy_deg``: roll, pitch,
    yaw of the IMU's imu_link in base_link [deg] (the vibration shakes the body, so it turns
    with the rest of the signal; the noise and bias are the sensor's own)."""
    rng = np.random.default_rng(seed)
    tru = truth_signals(tr)
    t = tr.t
    fs = 1.0 / (t[1] - t[0])
    n = t.size

    # IMU
    i = _every(t, IMU_RATE_HZ)
    accel = tru["accel"].copy()
    if vibration_std > 0.0:
        accel += band_limited_noise(rng, n, fs, vibration_std)
    imu = rd.imu_samples(rng, {**tru, "accel": accel}, i, accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE,
                         accel_bias=ACCEL_BIAS, gyro_bias=GYRO_BIAS, mounting_rpy_deg=imu_rpy_deg)
    imu["accel_cov"] = np.full(3, ACCEL_NOISE ** 2 + vibration_std ** 2)     # the vibration is noise too

    # CAN speed and joint states
    j = _every(t, CAN_RATE_HZ)
    v_can = np.round(tru["vx"][j] * 3.6) / 3.6
    speed = {"t": t[j], "v": v_can, "var": np.full(j.size, (1.0 / 3.6) ** 2 / 12.0)}
    position = np.full((j.size, 5), np.nan)
    position[:, 4] = tru["delta"][j] * STEERING_RATIO
    velocity = np.full((j.size, 5), np.nan)
    velocity[:, :4] = tru["wheels"][j]
    joints = {"t": t[j], "position": position, "velocity": velocity, "effort": np.full((j.size, 5), np.nan)}

    # GNSS
    k = _every(t, GNSS_RATE_HZ)
    ltp = LocalTangentPlane(*ORIGIN)
    enu = np.column_stack([tru["x"][k], tru["y"][k], tru["z"][k]])
    enu = enu + rng.standard_normal((k.size, 3)) * np.array([GNSS_NOISE_H, GNSS_NOISE_H, GNSS_NOISE_V])
    lat, lon, alt = ltp.to_geodetic(enu)
    gnss = {"t": t[k], "lat": np.asarray(lat), "lon": np.asarray(lon), "alt": np.asarray(alt),
            "status": np.zeros(k.size, dtype=np.int64),
            "cov": np.array([GNSS_NOISE_H ** 2, GNSS_NOISE_H ** 2, GNSS_NOISE_V ** 2]), "origin": ORIGIN}

    # powertrain: none (dropped from the bag); build_streams wants the entry
    one = np.array([0.0])
    powertrain = {"t": one, "engine_speed": one, "engine_torque": one, "load": one, "gear": one,
                  "drive_force": one}

    m = _every(t, TRUTH_RATE_HZ)
    truth = {key: np.asarray(tru[key])[m] for key in
             ("t", "vx", "vy", "yaw_rate", "sideslip", "roll", "pitch", "yaw", "x", "y", "z", "wx", "wy", "wz")}
    truth["mass"] = np.full(m.size, tr.params.m if mass is None else mass)
    truth["slope"] = np.zeros(m.size)
    return types.SimpleNamespace(
        sensors={"imu": imu, "gnss": gnss, "speed": speed, "joint_states": joints, "powertrain": powertrain},
        truth=truth)


def write_drive(result, path: Path) -> Path:
    """Write a :func:`sensor_result` as an MCAP bag at ``path`` (stamps from 0 s)."""
    simbag.check_new_bag_path(path)
    # No powertrain: the library's model has none (its stream would be all NaN).
    streams = [s for s in simbag.build_streams(result, t0_ns=0) if s[0] != T.POWERTRAIN]
    return simbag.write_streams(streams, path)


def effective_rolling_radius(tr: Trajectory, *, wheels: Sequence[int] = (0, 1), min_t: float = 1.0,
                             max_abs_r: float = 0.01) -> float:
    """``vx / omega`` of the given wheels on the straight parts of a drive (|r| < max_abs_r)."""
    tru = truth_signals(tr)
    sel = (tr.t >= min_t) & (np.abs(tru["yaw_rate"]) < max_abs_r)
    omega = tru["wheels"][sel][:, list(wheels)].mean(axis=1)
    return float(np.sum(tru["vx"][sel] * omega) / np.sum(omega * omega))


def generate(out_dir: Path, *, vibration_std: float = 0.0, seed: int = 0,
             manoeuvres: Sequence[str] | None = None, duration: float | None = None,
             imu_rpy_deg=(0.0, 0.0, 0.0)) -> list[Path]:
    """One bag per manoeuvre in ``out_dir`` (``commonroad_<name>``) plus the vehicle file
    ``commonroad_bmw320i.yaml``, which carries the IMU's mounting ``imu_rpy_deg`` (roll, pitch,
    yaw in base_link [deg]); returns the bag paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{VEHICLE_NAME}.yaml").write_text(rd.with_imu_mounting(params_yaml(), imu_rpy_deg), encoding="utf-8")
    paths = []
    for index, name in enumerate(manoeuvres or MANOEUVRES):
        tr = simulate(name, duration=duration)
        result = sensor_result(tr, vibration_std=vibration_std, seed=seed * 1000 + index, imu_rpy_deg=imu_rpy_deg)
        paths.append(write_drive(result, out_dir / f"commonroad_{name}"))
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vehicle_estimation.validation.commonroad",
                                 description="Bags of the CommonRoad multi-body model (BMW 320i) in our topic contract")
    ap.add_argument("--out", type=Path, required=True, help="output folder (one bag per manoeuvre)")
    ap.add_argument("--vibration-std", type=float, default=0.0, help="10-60 Hz vibration on ax/ay/az [m/s^2]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--manoeuvre", action="append", choices=list(MANOEUVRES), help="default: all")
    ap.add_argument("--duration", type=float, default=None, help="override the manoeuvre length [s]")
    ap.add_argument("--write-params", type=Path, default=None, help="also write the vehicle params file here")
    rd.add_imu_mounting_option(ap)
    args = ap.parse_args(argv)
    if args.write_params is not None:
        args.write_params.parent.mkdir(parents=True, exist_ok=True)   # often the --out folder, made below
        args.write_params.write_text(rd.with_imu_mounting(params_yaml(), args.imu_rpy_deg), encoding="utf-8")
    for path in generate(args.out, vibration_std=args.vibration_std, seed=args.seed,
                         manoeuvres=args.manoeuvre, duration=args.duration, imu_rpy_deg=tuple(args.imu_rpy_deg)):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
