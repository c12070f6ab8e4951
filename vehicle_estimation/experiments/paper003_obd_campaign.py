"""Paper 003's experimental campaign on the simulator: calibration + the 18 drives + wind drives.

``python -m vehicle_estimation.experiments.paper003_obd_campaign [--out DIR] [--quick]`` reproduces Secs. 7.3-7.5
of Jensen et al. 2022 with the Audi A4 of Table 1 (``params/audi_a4.yaml``):

1. Training phase (Sec. 6, 7.3): one ~60 min calibration drive at the known mass (1580 kg) on a
   mixed route driven briskly so that it covers all seven gears and a wide range of engine load
   and speed (the paper's separate parameter-estimation drive), calibrated by
   :func:`vehicle_estimation.training.calibrate.calibrate_signals` (the code path of
   ``calibrate BAG``): gear ratios by Eq. 50 (w = 0.02), torque map Eq. 49 on the OBD-II load
   (quantised to 1/255 like PID 04) and engine speed, C_d A_0, C_r, I_e, I_w by the Eq.-48 grid
   over Table 5. Compared with Table 1 (gears, target 2 %) and Table 6 (R^2 >= 0.97).
2. Operational phase (Sec. 7.4): the drives of Table B.1 on an ~85 km mixed route (city,
   country roads, highway; Appendix A), each a fresh random route and traffic: reference drives
   1-4, 13, 14; +125 kg (5, 6) and +240 kg (7, 8); tyre pressure +0.5 bar (9, 10: C_r x 0.8)
   and -0.5 bar (11, 12: C_r x 1.4; Sec. 7.6: 25-50 %, more for a pressure drop); one window
   open (15, 16: C_d x 1.05) and two (17, 18: C_d x 1.10; Sec. 7.6: ~5 % per Buscariolo et al.)
   -- all in still air -- and four wind drives W1-W4 (reference vehicle, steady 5 m/s wind from
   0, 90, 180 and 270 deg). The mass core (method ``rls``: paper 003 Eqs. 4-11 with the
   calibrated parameters; engine load and speed only, gear predicted by Eq. 11, no torque
   signal) runs offline on the simulator's sensor arrays exactly as the mass node feeds it: means
   over 0.25 s update windows (``UpdateWindow``), the acceleration as the least-squares slope of
   the undriven wheels' speed, brake torque as the window maximum. Road grade: the simulator's
   true slope plus Gauss-Markov noise of 0.3 deg RMS (5 s correlation time), like the slope
   observer's error. Heading for the wind compensation: the true ENU yaw plus 0.5 deg white noise
   (the fusion odometry's). Every drive starts from the paper's m(0) = 1000 kg, p(0) = 1000.
   Each drive runs twice: wind compensation off (the paper) and on (estimators/mass/wind.py).
3. Fig. 13: drives 4-8 put sequentially (load 0, +125, +125, +240, +240 kg) for lambda = 0.998,
   0.9995 and 0.9999: the lag after each load change (time and distance until the estimate has
   covered 90 % of the step) and the fluctuation.

Metrics per drive: share of update windows within +-5 % of the true mass after convergence
(the paper's criterion; "after convergence" = after the first ``--converge-km`` km, default 10),
mean and max |error| after it, and the km at which the estimate first enters the band.

Writes ``campaign.json``, ``calibration.png`` (Fig. 6/8a analogues), ``drives.png`` (Figs.
11-15 analogues + the wind drives) and ``lambda.png`` (Fig. 13) under ``--out``, and prints the
tables. ``--quick``: a short calibration drive and three short drives (smoke test).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from vehicle_estimation.estimators.mass import calibration as cal
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.estimators.mass.mass_rls import LongitudinalMassEstimator, MassRLSConfig
from vehicle_estimation.estimators.mass.update_window import window_edges, window_ids, window_max, window_mean, window_slope
from vehicle_estimation.contract.vehicle import VehicleParams

PERIOD = 0.25                      # update window [s]: 4 Hz CAN, the mass node's update_rate_hz
SLOPE_NOISE_DEG = 0.3              # RMS of the slope-input error [deg]
SLOPE_NOISE_TAU = 5.0              # its correlation time [s]
HEADING_NOISE_DEG = 0.5
LAMBDAS = (0.998, 0.9995, 0.9999)
ROUTE_MIX = (("urban",) + ("country",) * 7 + ("highway",) * 6 + ("urban",) * 15 + ("highway",) * 8
             + ("country",) * 3 + ("urban",))          # Appendix A: city, country, highway, city, highway, ...
RING_LENGTH_M = 42500.0
CALIBRATION_SLOPE_SEED = 4242
CALIBRATION_MIX = ("urban", "country", "highway", "urban", "country", "urban", "highway")


@dataclasses.dataclass(frozen=True)
class Drive:
    """One drive of the campaign."""

    name: str
    kind: str
    extra_mass: float = 0.0          # [kg]
    rolling_factor: float = 1.0      # C_r multiplier (tyre pressure)
    drag_factor: float = 1.0         # C_d multiplier (windows)
    wind_speed: float = 0.0          # [m/s]
    wind_from_deg: float = 0.0       # meteorological: where the wind comes from, clockwise from north
    seed: int = 0

    def wind_enu(self) -> tuple[float, float, float]:
        a = math.radians(self.wind_from_deg)
        return (-self.wind_speed * math.sin(a), -self.wind_speed * math.cos(a), 0.0)

    def vehicle(self, base: VehicleParams) -> VehicleParams:
        return dataclasses.replace(base, mass=base.mass + self.extra_mass,
                                   rolling_resistance=base.rolling_resistance * self.rolling_factor,
                                   drag_coefficient=base.drag_coefficient * self.drag_factor)


def paper_drives() -> list[Drive]:
    """Table B.1 (drives 1-18, still air) and the wind drives W1-W4."""
    # drive: (type, extra mass [kg], C_r factor, C_d factor)
    table: dict[int, tuple[str, float, float, float]] = {
        1: ("reference", 0.0, 1.0, 1.0), 2: ("reference", 0.0, 1.0, 1.0), 3: ("reference", 0.0, 1.0, 1.0),
        4: ("reference", 0.0, 1.0, 1.0), 5: ("+125 kg", 125.0, 1.0, 1.0), 6: ("+125 kg", 125.0, 1.0, 1.0),
        7: ("+240 kg", 240.0, 1.0, 1.0), 8: ("+240 kg", 240.0, 1.0, 1.0), 9: ("+0.5 bar", 0.0, 0.8, 1.0),
        10: ("+0.5 bar", 0.0, 0.8, 1.0), 11: ("-0.5 bar", 0.0, 1.4, 1.0), 12: ("-0.5 bar", 0.0, 1.4, 1.0),
        13: ("reference", 0.0, 1.0, 1.0), 14: ("reference", 0.0, 1.0, 1.0),
        15: ("1 window open", 0.0, 1.0, 1.05), 16: ("1 window open", 0.0, 1.0, 1.05),
        17: ("2 windows open", 0.0, 1.0, 1.10), 18: ("2 windows open", 0.0, 1.0, 1.10)}
    drives = []
    for i, (kind, extra, rf, df) in table.items():
        drives.append(Drive(f"{i:02d}", kind, extra, rf, df, seed=100 + i))
    for j, direction in enumerate((0.0, 90.0, 180.0, 270.0), start=1):
        drives.append(Drive(f"W{j}", f"wind 5 m/s from {direction:03.0f} deg", wind_speed=5.0,
                            wind_from_deg=direction, seed=200 + j))
    return drives


def quick_drives() -> list[Drive]:
    return [Drive("01", "reference", seed=101), Drive("07", "+240 kg", 240.0, seed=107),
            Drive("W4", "wind 5 m/s from 270 deg", wind_speed=5.0, wind_from_deg=270.0, seed=204)]


# ---------------------------------------------------------------------------- simulation
def _scenario(name: str, vehicle: VehicleParams, duration: float, mix: tuple[str, ...], seed: int,
              wind: tuple[float, float, float] = (0.0, 0.0, 0.0), max_accel: float = 1.8,
              max_decel: float = 2.0, ring: bool = True):
    """A drive on the ~85 km route: ``ring`` a closed ~42.5 km ring road (``loop004`` scaled up,
    driven about twice, every heading occurs like on the paper's out-and-back route of
    Appendix A, hills up to 5 %), else a random curvy, hilly road (up to 6 %) whose heading
    stays within about +-90 deg of its start."""
    from vehicle_estimation.sim.profiles import SpeedProfile
    from vehicle_estimation.sim.road import RoadSpec
    from vehicle_estimation.sim.scenario import Scenario
    road = (RoadSpec(kind="loop004", length=RING_LENGTH_M, grade_max=0.05) if ring
            else RoadSpec(kind="random", grade_max=0.06))
    return Scenario(name=name, vehicle=vehicle, duration_s=duration,
                    speed_profile=SpeedProfile(kind="route", route_mix=mix, max_accel=max_accel, max_decel=max_decel),
                    road=road, wind_enu=wind, seed=seed)


def calibration_scenario(base: VehicleParams, duration: float = 3600.0):
    """The training drive: the known (unloaded) mass, a brisk driver (up to 3.5 m/s^2) on a mixed
    route, so that every gear and a wide range of load and engine speed occur (paper Sec. 7.1)."""
    return _scenario("calibration", base, duration, CALIBRATION_MIX, seed=3, max_accel=3.5, max_decel=2.5,
                     ring=False)


def calibrate_simulated(base: VehicleParams, duration: float = 3600.0, kinematic_grade: bool = False):
    """Simulate the training drive and calibrate it: (CalibrationResult, calibrated vehicle,
    Eq.-49 coefficients). The grade is the operational drives' slope signal (the same observer
    is used in both phases) unless ``kinematic_grade``."""
    from vehicle_estimation.sim.simulate import simulate
    from vehicle_estimation.training.calibrate import calibrate_signals
    sim = simulate(calibration_scenario(base, duration))
    calib = calibrate_signals(drive_signals(sim, None if kinematic_grade else CALIBRATION_SLOPE_SEED), base.mass, base)
    return calib, calib.vehicle(base, base.mass), calib.torque_regression()


def observer_like_slope(t: np.ndarray, slope: np.ndarray, seed: int) -> np.ndarray:
    """The true road slope plus first-order Gauss-Markov noise of ``SLOPE_NOISE_DEG`` RMS and
    ``SLOPE_NOISE_TAU`` correlation time: the error of a slope observer, not its squat/dive
    (a kinematic or pitch-derived grade also sees the body pitch, ~0.002 rad per m/s^2 here)."""
    from scipy.signal import lfilter
    rng = np.random.default_rng(seed)
    dt = float(np.median(np.diff(t)))
    phi = math.exp(-dt / SLOPE_NOISE_TAU)
    sigma = math.radians(SLOPE_NOISE_DEG)
    white = rng.standard_normal(t.size) * sigma * math.sqrt(1.0 - phi * phi)
    noise, _ = lfilter([1.0], [1.0, -phi], white, zi=[phi * rng.standard_normal() * sigma])
    return np.asarray(slope, dtype=float) + noise


def drive_signals(result: Any, slope_seed: int | None = None):
    """The calibrate tool's :class:`DriveSignals` from a :class:`SimResult`'s sensors: the CAN
    speed, the wheel speeds and brake torques, engine speed and the OBD-II load (quantised to
    1/255, PID 04's resolution), the IMU's x specific force, and the GNSS height. The height is
    the simulator's ENU up (its world is a flat tangent plane, so its ellipsoidal altitude rises
    by d^2 / 2R away from the origin, which a real road does not). With ``slope_seed`` the grade
    signal is :func:`observer_like_slope` (the one the operational drives use) instead of the
    calibrate tool's kinematic grade from the IMU."""
    from vehicle_estimation.training.calibrate import DriveSignals
    S = result.sensors
    js, pt = S["joint_states"], S["powertrain"]
    sig = DriveSignals(
        speed_t=S["speed"]["t"], speed=S["speed"]["v"], powertrain_t=pt["t"], engine_speed=pt["engine_speed"],
        engine_load=np.round(np.asarray(pt["load"]) * 255.0) / 255.0,
        wheel_t=js["t"], wheel_speed=js["velocity"][:, :4], brake_torque=js["effort"][:, :4].sum(axis=1),
        imu_t=S["imu"]["t"], accel_x=S["imu"]["accel"][:, 0],
        gnss_t=S["gnss"]["t"], gnss_alt=S["gnss"]["enu_meas"][:, 2])
    if slope_seed is not None:
        sig.slope_t = result.truth["t"]
        sig.slope = observer_like_slope(result.truth["t"], result.truth["slope"], slope_seed)
    return sig


@dataclasses.dataclass
class DriveWindows:
    """The 4 Hz inputs of the mass core for one drive (plus truth for scoring)."""

    t: np.ndarray
    v: np.ndarray
    a: np.ndarray
    slope: np.ndarray
    engine_speed: np.ndarray
    engine_load: np.ndarray
    brake: np.ndarray
    heading: np.ndarray
    distance: np.ndarray        # [m] travelled at the end of each window
    true_mass: float

    @staticmethod
    def concatenate(parts: Sequence["DriveWindows"]) -> tuple["DriveWindows", np.ndarray, np.ndarray]:
        """Drives back to back (time and distance continue); returns the windows, the true mass
        of every window, and the index of the first window of each part."""
        fields = ("t", "v", "a", "slope", "engine_speed", "engine_load", "brake", "heading", "distance")
        out: dict[str, list] = {f: [] for f in fields}
        masses, starts = [], []
        t_off = d_off = 0.0
        n = 0
        for p in parts:
            starts.append(n)
            for f in fields:
                x = getattr(p, f)
                out[f].append(x + (t_off if f == "t" else d_off if f == "distance" else 0.0))
            masses.append(np.full(p.t.size, p.true_mass))
            t_off += float(p.t[-1]) + PERIOD
            d_off += float(p.distance[-1])
            n += p.t.size
        merged = DriveWindows(**{f: np.concatenate(v) for f, v in out.items()}, true_mass=float("nan"))
        return merged, np.concatenate(masses), np.asarray(starts)


def drive_windows(result: Any, base: VehicleParams, seed: int) -> DriveWindows:
    """What the mass node would feed the core, window by window (see the module docstring)."""
    S, T = result.sensors, result.truth
    js, pt = S["joint_states"], S["powertrain"]
    edges = window_edges(pt["t"], PERIOD)
    n = len(edges)
    undriven = list(base.undriven_wheels)
    v_wheel = np.mean(js["velocity"][:, undriven], axis=1) * base.wheel_radius
    ids_j = window_ids(js["t"], edges)
    ids_p = window_ids(pt["t"], edges)
    ids_t = window_ids(T["t"], edges)
    rng = np.random.default_rng(seed)
    yaw = T["yaw"]
    heading = np.arctan2(window_mean(ids_t, np.sin(yaw), n), window_mean(ids_t, np.cos(yaw), n))
    heading = heading + rng.standard_normal(n) * math.radians(HEADING_NOISE_DEG)
    v = window_mean(ids_j, v_wheel, n)
    return DriveWindows(
        t=edges, v=v, a=window_slope(ids_j, js["t"], v_wheel, n),
        slope=window_mean(ids_t, observer_like_slope(T["t"], T["slope"], seed), n),
        engine_speed=window_mean(ids_p, pt["engine_speed"], n),
        engine_load=window_mean(ids_p, np.round(np.asarray(pt["load"]) * 255.0) / 255.0, n),
        brake=window_max(ids_j, js["effort"][:, :4].sum(axis=1), n),
        heading=heading, distance=np.cumsum(np.nan_to_num(v) * np.diff(edges, prepend=edges[0] - PERIOD)),
        true_mass=float(result.scenario.vehicle.mass))


def run_core(w: DriveWindows, vehicle: VehicleParams, regression: Sequence[float], *, forgetting: float = 0.9995,
             wind: bool = False, rolling_resistance: bool = False, fit: Any = None,
             trace: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, LongitudinalMassEstimator]:
    """Published mass after every window (the core's output as the node would publish it). The
    core is told the slope's error (``SLOPE_NOISE_DEG`` over ``SLOPE_NOISE_TAU``) as the node tells
    it the fusion's, and the calibration's own error (``fit``'s relative std and covariance, as
    calibrate writes them); ``trace`` (a dict) gets the published 'variance' and 'converged' per window."""
    relative_std = fit.relative_std if fit is not None and math.isfinite(fit.relative_std) else 0.0
    cfg = MassRLSConfig(forgetting_factor=forgetting, torque_regression=list(regression), wind_compensation=wind,
                        rolling_resistance_estimation=rolling_resistance, torque_regression_relative_std=relative_std,
                        torque_model_covariance=list(fit.covariance) if fit is not None else [])
    core = LongitudinalMassEstimator(vehicle, cfg)
    out = np.empty(w.t.size)
    variance, converged = np.empty(w.t.size), np.zeros(w.t.size, dtype=bool)
    slope_error_variance, nan = (vehicle.gravity * math.radians(SLOPE_NOISE_DEG)) ** 2, math.nan
    for k in range(w.t.size):
        core.step(float(w.t[k]), float(w.v[k]), float(w.a[k]), float(w.slope[k]),
                  engine_speed=float(w.engine_speed[k]), engine_load=float(w.engine_load[k]), gear=nan,
                  brake_torque=float(w.brake[k]), heading=float(w.heading[k]),
                  regressor_bias_variance=slope_error_variance, regressor_bias_correlation_s=SLOPE_NOISE_TAU)
        out[k] = core.mass
        if trace is not None:
            variance[k], converged[k] = core.variance, core.converged
    if trace is not None:
        trace.update(variance=variance, converged=converged)
    return out, core


# ---------------------------------------------------------------------------- metrics
def drive_metrics(mass: np.ndarray, true_mass: np.ndarray | float, distance: np.ndarray, converge_m: float) -> dict:
    truth = np.broadcast_to(np.asarray(true_mass, dtype=float), mass.shape)
    rel = (mass - truth) / truth
    after = distance >= converge_m
    inside = np.abs(rel) <= 0.05
    first = np.nonzero(inside)[0]
    if not np.any(after):
        return {"within_5pct": math.nan, "mean_error_pct": math.nan, "max_abs_error_pct": math.nan,
                "first_within_km": math.nan}
    return {
        "within_5pct": float(np.mean(inside[after])),
        "mean_error_pct": float(100.0 * np.mean(rel[after])),
        "max_abs_error_pct": float(100.0 * np.max(np.abs(rel[after]))),
        "final_error_pct": float(100.0 * rel[-1]),
        "first_within_km": float(distance[first[0]] / 1000.0) if first.size else math.nan,
    }


def step_lag(mass: np.ndarray, t: np.ndarray, distance: np.ndarray, start: int, m_old: float, m_new: float,
             share: float = 0.9) -> dict:
    """Time [min] and distance [km] after window ``start`` until the estimate has covered
    ``share`` of the step from ``m_old`` to ``m_new`` (NaN: never, within the data given)."""
    level = m_old + share * (m_new - m_old)
    seg = mass[start:]
    hit = np.nonzero((seg - level) * np.sign(m_new - m_old) >= 0.0)[0]
    if not hit.size:
        return {"lag_min": math.nan, "lag_km": math.nan}
    k = start + int(hit[0])
    return {"lag_min": float((t[k] - t[start]) / 60.0), "lag_km": float((distance[k] - distance[start]) / 1000.0)}


# ---------------------------------------------------------------------------- the campaign
def run_campaign(out: Path, *, quick: bool = False, converge_km: float = 10.0, jobs: int = 1,
                 ring: bool = True, kinematic_grade: bool = False, log=print) -> dict:
    from vehicle_estimation.sim.scenario import load_vehicle
    from vehicle_estimation.sim.simulate import simulate
    from vehicle_estimation.training.calibrate import calibrate_signals, prepare_windows, summary

    out.mkdir(parents=True, exist_ok=True)
    base = load_vehicle("audi_a4")
    t_start = time.time()
    # ---- 1. training phase
    cal_duration = 900.0 if quick else 3600.0
    cal_sim = simulate(calibration_scenario(base, cal_duration))
    signals = drive_signals(cal_sim, None if kinematic_grade else CALIBRATION_SLOPE_SEED)
    calib = calibrate_signals(signals, base.mass, base)
    fitted = calib.vehicle(base, base.mass)
    regression = calib.torque_regression()
    log(summary(calib, base))
    gear_err = [100.0 * (g / b - 1.0) for g, b in zip(calib.transmission_ratios, base.gear_ratios)]
    cal_info = {
        "drive": {"duration_s": cal_duration, "km": float(cal_sim.truth["s"][-1] / 1000.0),
                  "gear_share": np.bincount(cal_sim.truth["gear"], minlength=len(base.gear_ratios) + 1)[1:].tolist(),
                  "rpm_p99": float(np.percentile(cal_sim.truth["engine_speed"], 99) * 30 / math.pi),
                  "load_p99": float(np.percentile(cal_sim.truth["engine_load"], 99))},
        "gear_ratios": list(calib.transmission_ratios), "gear_ratio_error_pct": gear_err,
        "gearings_rpm_per_mps": [g * 30 / math.pi for g in calib.gears.gearings],
        "table1_gear_ratios": list(base.gear_ratios),
        "fit": dataclasses.asdict(calib.fit), "true_parameters": {
            "drag_area": base.drag_area, "rolling_resistance": base.rolling_resistance,
            "engine_inertia": base.engine_inertia, "wheel_inertia": base.wheel_inertia,
            "driveline_efficiency": base.driveline_efficiency},
        "grade_source": calib.grade_source,
    }
    _plot_calibration(out / "calibration.png", calib, prepare_windows(signals, base), base)
    del cal_sim
    # ---- 2. operational phase
    drives = quick_drives() if quick else paper_drives()
    duration = 1500.0 if quick else 4300.0
    scenarios = [_scenario(f"drive_{d.name}", d.vehicle(base), duration, ROUTE_MIX, d.seed, d.wind_enu(), ring=ring)
                 for d in drives]
    windows = _simulate_windows(scenarios, base, jobs)
    converge_m = (3.0 if quick else converge_km) * 1000.0
    rows, traces = [], {}
    consistency: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for d, w in zip(drives, windows):
        m_off, _ = run_core(w, fitted, regression)
        m_on, core_on = run_core(w, fitted, regression, wind=True)
        shipped: dict[str, np.ndarray] = {}
        m_cr, core_cr = run_core(w, fitted, regression, wind=True, rolling_resistance=True, trace=shipped, fit=calib.fit)
        assert core_on.wind is not None and core_cr.wind is not None
        m_off_stats = drive_metrics(m_off, w.true_mass, w.distance, converge_m)
        m_on_stats = drive_metrics(m_on, w.true_mass, w.distance, converge_m)
        m_cr_stats = drive_metrics(m_cr, w.true_mass, w.distance, converge_m)
        row: dict[str, Any] = {"drive": d.name, "kind": d.kind, "true_mass": w.true_mass, "km": float(w.distance[-1] / 1000.0),
               "wind_off": m_off_stats, "wind_on": m_on_stats, "wind_and_cr": m_cr_stats,
               "wind_true_enu": list(d.wind_enu()[:2]), "wind_est_enu": list(core_on.wind.wind_enu),
               "wind_est_std": list(core_on.wind.wind_std),
               "cr_true": d.rolling_factor * base.rolling_resistance, "cr_fitted": fitted.rolling_resistance,
               "cr_est": core_cr.rolling_resistance, "cr_est_std": core_cr.wind.rolling_resistance_offset_std}
        after = w.distance >= converge_m        # the 'wind and C_r' errors, variances, flags
        consistency.append((m_cr[after] - w.true_mass, shipped["variance"][after], shipped["converged"][after]))
        row["wind_and_cr"]["consistency"] = metrics.consistency(*consistency[-1])
        rows.append(row)
        step = max(1, int(round(20.0 / PERIOD)))
        traces[d.name] = {"km": (w.distance[::step] / 1000.0).tolist(), "off": m_off[::step].tolist(),
                          "on": m_on[::step].tolist(), "true": w.true_mass, "kind": d.kind}
        log(f"drive {d.name:>3} {d.kind:<26} within +-5 %: {m_off_stats['within_5pct']:6.1%} (paper), "
            f"{m_on_stats['within_5pct']:6.1%} (wind compensation), {m_cr_stats['within_5pct']:6.1%} (and C_r)")
    # ---- 3. Fig. 13: drives 4-8 back to back
    seq_names = ["04", "05", "06", "07", "08"] if not quick else ["01", "07"]
    by_name = dict(zip((d.name for d in drives), windows))
    seq, seq_mass, starts = DriveWindows.concatenate([by_name[n] for n in seq_names if n in by_name])
    lam_rows, lam_traces = [], {}
    for lam in LAMBDAS:
        for wind in (False, True):
            m, _ = run_core(seq, fitted, regression, forgetting=lam, wind=wind)
            changes = []
            for s in starts[1:]:
                m_old, m_new = float(seq_mass[s - 1]), float(seq_mass[s])
                if m_new != m_old:
                    lag63 = step_lag(m, seq.t, seq.distance, int(s), m_old, m_new, 0.63)
                    changes.append({"at_km": float(seq.distance[s] / 1000.0), "from": m_old, "to": m_new,
                                    "lag63_min": lag63["lag_min"], "lag63_km": lag63["lag_km"],
                                    **step_lag(m, seq.t, seq.distance, int(s), m_old, m_new, 0.9)})
            conv = seq.distance >= converge_m
            rel = (m - seq_mass) / seq_mass
            lam_rows.append({"lambda": lam, "wind_compensation": wind, "changes": changes,
                             "within_5pct": float(np.mean(np.abs(rel[conv]) <= 0.05)),
                             "std_error_pct": float(100.0 * np.std(rel[conv]))})
            if not wind:
                step = max(1, int(round(20.0 / PERIOD)))
                lam_traces[str(lam)] = m[::step].tolist()
    lam_traces["km"] = (seq.distance[::max(1, int(round(20.0 / PERIOD)))] / 1000.0).tolist()
    lam_traces["true"] = seq_mass[::max(1, int(round(20.0 / PERIOD)))].tolist()
    result = {"quick": quick, "road": "ring" if ring else "random", "kinematic_grade": kinematic_grade, "converge_km": converge_m / 1000.0, "calibration": cal_info,
              "calibrated_vehicle": fitted.as_mapping(), "torque_regression": regression,
              "drives": rows, "lambda_sequence": {"drives": seq_names, "rows": lam_rows},
              "consistency_all_drives": metrics.consistency(*(np.concatenate(x) for x in zip(*consistency))),
              "runtime_s": time.time() - t_start}
    _plot_drives(out / "drives.png", traces)
    _plot_lambda(out / "lambda.png", lam_traces)
    from vehicle_estimation.evaluation.report import json_safe
    (out / "campaign.json").write_text(json.dumps(json_safe(result), indent=1), encoding="utf-8")
    return result


def _sim_one(args: tuple) -> DriveWindows:
    from vehicle_estimation.sim.simulate import simulate
    scn, base, seed = args
    return drive_windows(simulate(scn), base, seed)


def _simulate_windows(scenarios: list, base: VehicleParams, jobs: int) -> list[DriveWindows]:
    work = [(s, base, s.seed + 7919) for s in scenarios]
    if jobs <= 1:
        return [_sim_one(w) for w in work]
    from multiprocessing import get_context
    with get_context("spawn").Pool(jobs) as pool:
        return pool.map(_sim_one, work)


# ---------------------------------------------------------------------------- tables
def _pct(x: float, digits: int = 1) -> str:
    return "n/a" if not math.isfinite(x) else f"{100.0 * x:.{digits}f} %"


def format_tables(result: dict) -> str:
    c = result["calibration"]
    lines = ["## Calibration (training phase, Sec. 7.3)", "",
             "| gear | Table 1 i_t | estimated i_t | error | G [rpm/(m/s)] |", "| --- | --- | --- | --- | --- |"]
    for j, (ref, est, err, g) in enumerate(zip(c["table1_gear_ratios"], c["gear_ratios"], c["gear_ratio_error_pct"],
                                               c["gearings_rpm_per_mps"]), start=1):
        lines.append(f"| {j} | {ref:.3f} | {est:.4f} | {err:+.2f} % | {g:.1f} |")
    f, tp = c["fit"], c["true_parameters"]
    lines += ["", "| parameter | fitted (Table 5 grid) | simulator truth | paper Table 6 |", "| --- | --- | --- | --- |",
              f"| C_d A_0 [m^2] | {f['drag_area']:.2f} | {tp['drag_area']:.3f} | 0.70 |",
              f"| C_r [-] | {f['rolling_resistance']:.3f} | {tp['rolling_resistance']:.3f} | 0.008 |",
              f"| I_e [kg m^2] | {f['engine_inertia']:.2f} | {tp['engine_inertia']:.2f} | 0.14 |",
              f"| I_w [kg m^2] | {f['wheel_inertia']:.1f} | {tp['wheel_inertia']:.1f} | 7.0 |",
              f"| w0..wn (L 0-1, N_e rpm) | {', '.join(f'{w:.4g}' for w in f['coefficients'])} | | -17.85, 9.64/%, 2.50e-3, -1.44e-6 |",
              f"| R^2 | {f['r2']:.4f} | | 0.972 |", "",
              f"grade for the fit: {c['grade_source']}; {f['n_samples']} windows used", ""]
    lines += [f"## Drives (lambda = 0.9995; after the first {result['converge_km']:g} km)", "",
              "| drive | type | km | within +-5 % (paper) | mean err | max err | within +-5 % (wind comp.) | mean err | max err "
              "| within +-5 % (wind and C_r) | mean err | max err | C_r est. (true) | wind est. (E, N) m/s |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in result["drives"]:
        a, b, c3 = r["wind_off"], r["wind_on"], r["wind_and_cr"]
        we = r["wind_est_enu"]
        lines.append(f"| {r['drive']} | {r['kind']} | {r['km']:.0f} | {_pct(a['within_5pct'])} | {a['mean_error_pct']:+.1f} % | "
                     f"{a['max_abs_error_pct']:.1f} % | {_pct(b['within_5pct'])} | {b['mean_error_pct']:+.1f} % | "
                     f"{b['max_abs_error_pct']:.1f} % | {_pct(c3['within_5pct'])} | {c3['mean_error_pct']:+.1f} % | "
                     f"{c3['max_abs_error_pct']:.1f} % | {r['cr_est']:.4f} +- {r['cr_est_std']:.4f} (fit {r['cr_fitted']:.4f}, sim {r['cr_true']:.4f}) | "
                     f"({we[0]:+.1f}, {we[1]:+.1f}) true ({r['wind_true_enu'][0]:+.1f}, {r['wind_true_enu'][1]:+.1f}) |")
    lines += ["", f"## Is the published variance honest? (the 'wind and C_r' estimates; after the first "
              f"{result['converge_km']:g} km; the core is told the slope's error, {SLOPE_NOISE_DEG:g} deg over "
              f"{SLOPE_NOISE_TAU:g} s)", "",
              "| drive | within 1 sigma | within 2 sigma | NEES | flagged converged | converged within 2 sigma | "
              "converged beyond 3 sigma |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, c4 in ([(r["drive"], r["wind_and_cr"].get("consistency")) for r in result["drives"]]
                     + [("all drives", result.get("consistency_all_drives"))]):
        if c4:
            lines.append(f"| {name} | {_pct(c4['within_1sigma'], 0)} | {_pct(c4['within_2sigma'], 0)} | "
                         f"{c4['nees']:.2f} | {_pct(c4['converged_share'], 0)} | "
                         f"{_pct(c4['converged_within_2sigma'], 0)} | {_pct(c4['converged_beyond_3sigma'])} |")
    seq = result["lambda_sequence"]
    lines += ["", f"## Fig. 13: drives {'-'.join(seq['drives'])} back to back", "",
              "| lambda | wind comp. | load change at km | step | lag to 63 % [min] | [km] | lag to 90 % [min] | [km] | within +-5 % | std of error |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in seq["rows"]:
        for ch in r["changes"] or [{"at_km": math.nan, "from": math.nan, "to": math.nan, "lag_min": math.nan,
                                    "lag_km": math.nan, "lag63_min": math.nan, "lag63_km": math.nan}]:
            lines.append(f"| {r['lambda']} | {'on' if r['wind_compensation'] else 'off'} | {ch['at_km']:.0f} | "
                         f"{ch['from']:.0f} -> {ch['to']:.0f} kg | {ch['lag63_min']:.1f} | {ch['lag63_km']:.1f} | "
                         f"{ch['lag_min']:.1f} | {ch['lag_km']:.1f} | "
                         f"{_pct(r['within_5pct'])} | {r['std_error_pct']:.2f} % |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- plots
def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _plot_calibration(path: Path, calib, win, base: VehicleParams) -> None:
    plt = _plt()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    g = calib.gears
    ax1.plot(g.grid * 30 / math.pi, g.counts, lw=0.8)
    for G in g.gearings:
        ax1.axvline(G * 30 / math.pi, color="r", lw=0.6, ls="--")
    for j in range(1, len(base.gear_ratios) + 1):
        ax1.axvline(base.effective_gearing(j) * 30 / math.pi, color="k", lw=0.5, ls=":")
    ax1.set_xscale("log")
    ax1.set_xlabel("engine / vehicle speed [rpm/(m/s)]")
    ax1.set_ylabel("samples in [(1-w)G, (1+w)G]")
    ax1.set_title("Eq. 50, w = 0.02 (red: found, black: Table 1)")
    fit = calib.fit
    ok = np.isfinite(win.engine_load) & np.isfinite(win.engine_speed)
    rpm = win.engine_speed[ok] * 30 / math.pi
    X = cal.torque_features(win.engine_load[ok], win.engine_speed[ok], calib.speed_order)
    sc = ax2.scatter(win.engine_load[ok] * 100, X @ np.asarray(fit.coefficients), c=rpm, s=1, cmap="viridis")
    fig.colorbar(sc, ax=ax2, label="engine speed [rpm]")
    ax2.set_xlabel("OBD-II calculated load [%]")
    ax2.set_ylabel("T_load of Eq. 49 [N m]")
    ax2.set_title(f"torque map (R^2 = {fit.r2:.3f})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_drives(path: Path, traces: dict) -> None:
    plt = _plt()
    names = list(traces)
    ncol = 4
    nrow = int(math.ceil(len(names) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 2.6 * nrow), squeeze=False, sharey=True)
    for ax, name in zip(axes.ravel(), names):
        tr = traces[name]
        km = np.asarray(tr["km"])
        ax.fill_between(km, 0.95 * tr["true"], 1.05 * tr["true"], color="0.9")
        ax.plot(km, tr["off"], lw=0.8, label="paper (no wind comp.)")
        ax.plot(km, tr["on"], lw=0.8, label="wind compensation")
        ax.axhline(tr["true"], color="k", lw=0.6)
        ax.set_title(f"{name}: {tr['kind']}", fontsize=9)
        ax.set_ylim(1300, 2100)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("distance [km]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_lambda(path: Path, traces: dict) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(11, 4))
    km = np.asarray(traces["km"])
    true = np.asarray(traces["true"])
    ax.fill_between(km, 0.95 * true, 1.05 * true, color="0.9")
    for lam in LAMBDAS:
        ax.plot(km, traces[str(lam)], lw=0.8, label=f"lambda = {lam}")
    ax.plot(km, true, "k", lw=0.8, label="true mass")
    ax.set_ylim(1300, 2100)
    ax.set_xlabel("distance [km]")
    ax.set_ylabel("mass [kg]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/campaign", help="output directory (default out/campaign)")
    p.add_argument("--quick", action="store_true", help="short calibration drive and three short drives (smoke test)")
    p.add_argument("--converge-km", type=float, default=10.0,
                   help="metrics count after this distance of each drive [km] (default 10)")
    p.add_argument("--jobs", type=int, default=1, help="simulate drives in this many processes (default 1)")
    p.add_argument("--kinematic-grade", action="store_true",
                   help="calibrate with the calibrate tool's kinematic grade from the IMU (it sees the body's "
                        "squat, which the operational slope does not) instead of the operational slope signal")
    p.add_argument("--road", choices=("ring", "random"), default="ring",
                   help="route of the drives: a ~42.5 km ring road driven twice (every heading, default) or a "
                        "random curvy road (heading within about +-90 deg of the start: wind is less observable)")


def main(args: argparse.Namespace) -> int:
    out = Path(args.out)
    result = run_campaign(out, quick=bool(args.quick), converge_km=float(args.converge_km), jobs=int(args.jobs),
                          ring=args.road == "ring", kinematic_grade=bool(args.kinematic_grade))
    print(format_tables(result))
    print(f"\nwritten: {out / 'campaign.json'}, calibration.png, drives.png, lambda.png "
          f"({result['runtime_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    sys.exit(run_as_script(sys.modules[__name__]))
