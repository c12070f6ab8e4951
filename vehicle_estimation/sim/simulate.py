"""``simulate(scenario)``: closed-loop vehicle simulation, ground truth and sensor outputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.signal import lfilter

from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler
from vehicle_estimation.sim.dynamics import simulate_dynamics
from vehicle_estimation.sim.profiles import reference_distance, reference_speed
from vehicle_estimation.sim.road import Road, build_road
from vehicle_estimation.sim.scenario import Scenario, SensorConfig

TRUTH_RATE = 100.0


@dataclasses.dataclass
class SimResult:
    """Output of :func:`simulate`.

    ``truth``: dict of arrays at 100 Hz (see :func:`simulate` for the keys).
    ``sensors``: dict topic-key -> dict of arrays (``t`` in s since start, plus values).
    ``fast``: internal physics-rate arrays (diagnostics).
    """

    scenario: Scenario
    truth: dict
    sensors: dict
    road: Road
    fast: dict

    @property
    def duration(self) -> float:
        return float(self.truth["t"][-1])


def _lowpass(x: np.ndarray, dt: float, tau: float) -> np.ndarray:
    a = dt / (tau + dt)
    y, _ = lfilter([a], [1.0, a - 1.0], x, zi=[x[0] * (1 - a)])
    return y


def simulate(scenario: Scenario) -> SimResult:
    """Simulate ``scenario`` (deterministic for ``scenario.seed``).

    ``result.truth`` keys (100 Hz, SI, body = base_link FLU, world = ENU odom at the start):
    t, vx, vy, yaw_rate (body z rate), sideslip (atan2(vy, vx)), slope (road slope angle,
    + uphill), mass, x, y, z, yaw, pitch (REP-103: + nose down; = -slope + suspension pitch),
    roll, ax, ay, az (body-frame kinematic acceleration, ax = dvx/dt - r vy, ay = dvy/dt + r vx),
    wx, wy, wz (body angular rate), fx, fy, fz (specific force at base_link, what an aligned,
    perfect IMU reads), vx_dot, drive_force (engine tractive force at the wheels, T_e G eta),
    gear, clutch (1 closed), engine_speed [rad/s], engine_torque [N m, net at the flywheel],
    engine_load (0-1), throttle, brake_torque (N, 4) per wheel fl, fr, rl, rr [N m],
    wheel_speed (N, 4) [rad/s], wheel_load (N, 4) [N], steer (road-wheel angle [rad]),
    steering_wheel_angle [rad], v_ref [m/s], s (path position [m]), lat, lon, alt (WGS84).
    """
    scn = scenario
    vp = scn.vehicle
    vp.validate()
    seeds = np.random.SeedSequence(scn.seed).spawn(8)
    rng_profile = np.random.default_rng(seeds[0])
    rng_road = np.random.default_rng(seeds[1])

    dtc = 1.0 / TRUTH_RATE
    v_ref = reference_speed(scn.speed_profile, scn.duration_s, scn.standstill_s, scn.initial_speed,
                            rng_profile, dtc)
    d_ref = reference_distance(v_ref, dtc)
    road = build_road(scn.road, rng_road, float(d_ref[-1]) + scn.initial_speed * scn.duration_s * 0.2,
                      (d_ref, v_ref))
    if scn.speed_profile.kind == "distance" and road.v_of_s is None:
        raise ValueError("SpeedProfile(kind='distance') needs a road with a speed profile (RoadSpec kind 'loop004')")
    out = simulate_dynamics(vp, road, v_ref, scn.duration_s, scn.initial_speed, scn.wind_enu,
                            physics_rate=scn.physics_rate, control_rate=TRUTH_RATE)
    fast, slow, dt, sub = out["fast"], out["slow"], out["dt"], out["sub"]
    cfg = scn.sensors
    g = vp.gravity

    # ---- state on the physics grid t_i = i*dt (i = 0..n): prepend the initial state
    def with_init(a, a0):
        return np.concatenate([[a0], a])

    def step_vals(a):  # value over step i, placed at its start time
        return np.concatenate([a, a[-1:]])

    psi0 = float(road.psi[0])
    tt = np.arange(fast["vx"].size + 1) * dt
    vx = with_init(fast["vx"], scn.initial_speed)
    vy = with_init(fast["vy"], 0.0)
    r = with_init(fast["r"], 0.0)
    X = with_init(fast["X"], 0.0)
    Y = with_init(fast["Y"], 0.0)
    Z = with_init(fast["Z"], 0.0)
    psi = with_init(fast["psi"], psi0)
    # road slope on the physics grid from the (smooth) path position; the dynamics hold it
    # per control tick, which would make the pitch rate staircase-shaped
    s_slow = slow["s"]
    if road.closed:
        s_slow = np.unwrap(s_slow, period=road.length + float(road.s[1] - road.s[0]))
    s_fast = np.interp(tt, slow["t"], s_slow)
    if road.closed:
        s_fast = np.mod(s_fast, road.length + float(road.s[1] - road.s[0]))
    theta = np.arctan(np.interp(s_fast, road.s, road.grade))
    ax = step_vals(fast["ax"])
    ay = step_vals(fast["ay"])
    vxd = step_vals(fast["vxd"])
    # body attitude: road slope + suspension
    pitch = -theta + _lowpass(-vp.pitch_gain * ax, dt, vp.pitch_time_constant)
    roll = _lowpass(cfg.suspension_roll_gain * ay, dt, 0.15)
    pdot = np.gradient(pitch, dt)
    rdot = np.gradient(roll, dt)
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    psid = r  # planar yaw rate drives the heading
    wx = rdot - psid * sp
    wy = pdot * cr + psid * cp * sr
    wz = -pdot * sr + psid * cp * cr
    az = wx * vy - wy * vx
    fx = ax - g * sp
    fy = ay + g * cp * sr
    fz = az + g * cp * cr

    # ---- truth at 100 Hz
    n_ctrl = slow["t"].size
    ik = np.arange(n_ctrl) * sub
    t = slow["t"]
    sideslip = np.where(vx[ik] > 0.1, np.arctan2(vy[ik], np.maximum(vx[ik], 1e-9)), 0.0)
    lat, lon, alt = LocalTangentPlane(scn.origin_lat, scn.origin_lon, scn.origin_alt).to_geodetic(
        np.stack([X[ik], Y[ik], Z[ik]], axis=-1))
    truth = {
        "t": t,
        "vx": vx[ik], "vy": vy[ik], "yaw_rate": wz[ik], "sideslip": sideslip,
        "slope": theta[ik], "mass": np.full(n_ctrl, vp.mass),
        "x": X[ik], "y": Y[ik], "z": Z[ik], "yaw": psi[ik], "pitch": pitch[ik], "roll": roll[ik],
        "ax": ax[ik], "ay": ay[ik], "az": az[ik], "wx": wx[ik], "wy": wy[ik], "wz": wz[ik],
        "fx": fx[ik], "fy": fy[ik], "fz": fz[ik], "vx_dot": vxd[ik],
        "drive_force": slow["F_drive"], "gear": slow["gear"].astype(int), "clutch": slow["clutch"],
        "engine_speed": slow["w_e"], "engine_torque": slow["Te"], "engine_load": slow["load"],
        "throttle": slow["throttle"],
        "brake_torque": np.stack([slow["Tb1"], slow["Tb2"], slow["Tb3"], slow["Tb4"]], axis=1),
        "wheel_speed": np.stack([slow["w1"], slow["w2"], slow["w3"], slow["w4"]], axis=1),
        "wheel_load": np.stack([slow["Fz1"], slow["Fz2"], slow["Fz3"], slow["Fz4"]], axis=1),
        "steer": slow["delta"], "steering_wheel_angle": slow["delta"] * vp.steering_ratio,
        "v_ref": slow["v_ref"], "s": slow["s"], "lateral_error": slow["lat_err"],
        "lat": lat, "lon": lon, "alt": alt,
    }
    kin = {"t": tt, "f": np.stack([fx, fy, fz], 1), "w": np.stack([wx, wy, wz], 1),
           "X": X, "Y": Y, "Z": Z}
    sensors = make_sensors(scn, cfg, truth, kin, seeds[2:])
    fast_out = {"t": tt, "vx": vx, "vy": vy, "r": r, "ax": ax, "ay": ay, "pitch": pitch, "roll": roll,
                "fx": fx, "fy": fy, "fz": fz, "wx": wx, "wy": wy, "wz": wz}
    return SimResult(scenario=scn, truth=truth, sensors=sensors, road=road, fast=fast_out)


def _sample_times(rate: float, duration: float) -> np.ndarray:
    n = int(math.floor(duration * rate + 1e-9)) + 1
    # integer nanoseconds to keep stamps exact
    return np.round(np.arange(n) * (1e9 / rate)).astype(np.int64) / 1e9


def _zoh_index(t: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(np.floor(t * TRUTH_RATE + 1e-6).astype(int), n - 1)


def make_sensors(scn: Scenario, cfg: SensorConfig, truth: dict, kin: dict, seeds) -> dict:
    vp = scn.vehicle
    duration = float(truth["t"][-1])
    n_truth = truth["t"].size
    rng_imu, rng_gnss, rng_can, rng_out = (np.random.default_rng(s) for s in seeds[:4])
    sensors: dict = {}

    # ---------------- IMU
    ti = _sample_times(cfg.imu_rate, duration)
    n = ti.size
    f = np.stack([np.interp(ti, kin["t"], kin["f"][:, i]) for i in range(3)], 1)
    w = np.stack([np.interp(ti, kin["t"], kin["w"][:, i]) for i in range(3)], 1)
    mis = np.radians(np.asarray(cfg.imu_misalignment_deg, float))
    C = rotmat_from_euler(*mis)  # imu_link orientation in base_link
    f = f @ C          # = (C^T f^T)^T
    w = w @ C
    dti = 1.0 / cfg.imu_rate
    ba0 = np.asarray(cfg.accel_bias if cfg.accel_bias is not None else rng_imu.normal(0, cfg.accel_bias_std, 3))
    bg0 = np.asarray(cfg.gyro_bias if cfg.gyro_bias is not None else rng_imu.normal(0, cfg.gyro_bias_std, 3))
    ba = ba0 + np.cumsum(rng_imu.normal(0, cfg.accel_bias_rw * math.sqrt(dti), (n, 3)), 0)
    bg = bg0 + np.cumsum(rng_imu.normal(0, cfg.gyro_bias_rw * math.sqrt(dti), (n, 3)), 0)
    na = rng_imu.normal(0, cfg.accel_noise, (n, 3))
    ng = rng_imu.normal(0, cfg.gyro_noise, (n, 3))
    std_mult = np.ones(n)
    if cfg.eq34_noise:
        mult = np.asarray(cfg.eq34_multipliers, float)
        seg = (np.floor(ti / cfg.eq34_segment_s).astype(int)) % mult.size
        std_mult = np.sqrt(mult[seg])
        na[:, 0] *= std_mult
        na[:, 1] *= std_mult
        ng[:, 2] *= std_mult
    accel = f + ba + na
    gyro = w + bg + ng
    outlier_mask = np.zeros(n, dtype=np.uint8)  # bit 0: ay, bit 1: yaw rate
    if cfg.outliers:
        for col, arr, mag, bit in ((1, accel, cfg.outlier_magnitude_ay, 1), (2, gyro, cfg.outlier_magnitude_r, 2)):
            hit = rng_out.random(n) < cfg.outlier_isolated_rate
            n_b = rng_out.poisson(cfg.outlier_burst_rate * duration)
            starts = rng_out.integers(0, n, n_b)
            lens = rng_out.integers(cfg.outlier_burst_len[0], cfg.outlier_burst_len[1] + 1, n_b)
            for s0, ln in zip(starts, lens):
                hit[s0:s0 + ln] = True
            idx = np.nonzero(hit)[0]
            arr[idx, col] += mag * rng_out.uniform(0.7, 1.5, idx.size) * rng_out.choice([-1.0, 1.0], idx.size)
            outlier_mask[idx] |= bit
    sensors["imu"] = {
        "t": ti, "accel": accel, "gyro": gyro,
        "accel_cov": np.full(3, cfg.accel_noise ** 2), "gyro_cov": np.full(3, cfg.gyro_noise ** 2),
        "accel_bias": ba, "gyro_bias": bg, "noise_std_multiplier": std_mult, "outlier_mask": outlier_mask,
        "misalignment_rpy": mis,
    }

    # ---------------- GNSS
    tg = _sample_times(cfg.gnss_rate, duration)
    ng_ = tg.size
    pos = np.stack([np.interp(tg, kin["t"], kin[k]) for k in ("X", "Y", "Z")], 1)
    sig = np.asarray(cfg.gnss_noise, float)
    white = rng_gnss.normal(0, 1, (ng_, 3))
    if cfg.gnss_noise_tau > 0:
        phi = math.exp(-1.0 / (cfg.gnss_rate * cfg.gnss_noise_tau))
        err = lfilter([math.sqrt(1 - phi * phi)], [1.0, -phi], white, axis=0)
        err[0] = white[0]
    else:
        err = white
    pos_m = pos + err * sig
    lat, lon, alt = LocalTangentPlane(scn.origin_lat, scn.origin_lon, scn.origin_alt).to_geodetic(pos_m[:, :3])
    status = np.zeros(ng_, dtype=np.int8)
    keep = np.ones(ng_, dtype=bool)
    for (a, b) in cfg.gnss_outages:
        inside = (tg >= a) & (tg < b)
        if cfg.gnss_outage_mode == "drop":
            keep &= ~inside
        else:
            status[inside] = -1
    lat = np.where(status < 0, np.nan, lat)
    lon = np.where(status < 0, np.nan, lon)
    alt = np.where(status < 0, np.nan, alt)
    sensors["gnss"] = {"t": tg[keep], "lat": lat[keep], "lon": lon[keep], "alt": alt[keep],
                       "status": status[keep], "cov": sig ** 2, "enu_true": pos[keep], "enu_meas": pos_m[keep],
                       "origin": (scn.origin_lat, scn.origin_lon, scn.origin_alt)}

    # ---------------- CAN / OBD-II (zero-order hold of the 100 Hz signals)
    q = cfg.speed_quantum_kmh
    ts = _sample_times(cfg.speed_rate, duration)
    iz = _zoh_index(ts, n_truth)
    v = truth["vx"][iz] + (rng_can.normal(0, cfg.speed_noise, ts.size) if cfg.speed_noise > 0 else 0.0)
    v_q = np.round(np.maximum(v, 0.0) * 3.6 / q) * q / 3.6
    sensors["speed"] = {"t": ts, "v": v_q, "var": (q / 3.6) ** 2 / 12.0 + cfg.speed_noise ** 2}

    tj = _sample_times(cfg.joint_states_rate, duration)
    iz = _zoh_index(tj, n_truth)
    ws = truth["wheel_speed"]
    wheel_angle = np.concatenate([np.zeros((1, 4)), np.cumsum(0.5 * (ws[1:] + ws[:-1]) / TRUTH_RATE, 0)])
    vel = ws[iz] + rng_can.normal(0, cfg.wheel_speed_noise, (tj.size, 4))
    vel = np.where(ws[iz] == 0.0, 0.0, vel)   # wheel-speed sensors read exactly zero at rest
    eff = truth["brake_torque"][iz] + (rng_can.normal(0, cfg.brake_torque_noise, (tj.size, 4))
                                       if cfg.brake_torque_noise > 0 else 0.0)
    eff = np.maximum(eff, 0.0)
    swa = truth["steering_wheel_angle"][iz] + rng_can.normal(0, cfg.steering_noise, tj.size)
    nanc = np.full((tj.size, 1), np.nan)
    sensors["joint_states"] = {
        "t": tj,
        "position": np.hstack([wheel_angle[iz], swa[:, None]]),
        "velocity": np.hstack([vel, nanc]),
        "effort": np.hstack([eff, nanc]),
    }

    tp = _sample_times(cfg.powertrain_rate, duration)
    iz = _zoh_index(tp, n_truth)
    we = truth["engine_speed"][iz] + (rng_can.normal(0, cfg.engine_speed_noise, tp.size) if cfg.engine_speed_noise > 0 else 0.0)
    tq_noise = rng_can.normal(0, cfg.engine_torque_noise, tp.size) if cfg.engine_torque_noise > 0 else np.zeros(tp.size)
    te = truth["engine_torque"][iz]
    gear = truth["gear"][iz]
    G = np.asarray([vp.effective_gearing(int(gg)) for gg in range(1, len(vp.gear_ratios) + 1)])[gear - 1]
    # The contract's `drive` is the force the driveline delivers to the driven wheels: the
    # propulsion force eta T_e G of paper 003 Eq. 1 less what accelerates the engine-side
    # inertia (I_e G^2 a, only while the clutch is closed).
    clutch = truth["clutch"][iz] > 0.5
    drive = truth["drive_force"][iz] - np.where(clutch, vp.engine_inertia * G ** 2 * truth["vx_dot"][iz], 0.0)
    drive = np.where(truth["drive_force"][iz] != 0.0, drive, 0.0)
    transmitting = drive != 0.0
    te_m = te + np.where(transmitting | (te != 0.0), tq_noise, 0.0)
    drive_m = drive + np.where(transmitting, tq_noise * G * vp.driveline_efficiency, 0.0)
    powertrain = {"engine_speed": we, "engine_torque": te_m, "engine_load": truth["engine_load"][iz],
                  "gear": gear.astype(float), "drive_force": drive_m}
    unknown = set(cfg.powertrain_reports) - set(powertrain)
    if unknown:
        raise ValueError(f"SensorConfig.powertrain_reports: unknown signals {sorted(unknown)}")
    reported = {name: (v if name in cfg.powertrain_reports else np.full(tp.size, np.nan))
                for name, v in powertrain.items()}
    sensors["powertrain"] = {"t": tp, "load": reported.pop("engine_load"), **reported}
    return sensors
