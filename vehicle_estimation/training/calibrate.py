"""``calibrate BAG --mass KG --out params.yaml``: the training phase of paper 003 (Sec. 6).

From one recorded drive with a known mass it estimates

* the gear ratios, from the distribution of engine/vehicle speed ratios with widening intervals
  and peak finding (Eq. 50, w = 0.02 as Fig. 6; only i_t,j i_d / r is observable, so the ratios
  are written for the base vehicle's final drive and tyre radius; as many as the base vehicle
  has, or those the drive shows above 3 m/s when it shows fewer, unless ``--gears`` says);
* the engine torque map T_load = w0 + w1 L + w2 N_e + w3 N_e^2 (Eq. 49, L the OBD-II calculated
  load as the vehicle reports it, 0-1 on ``vehicle/powertrain``; N_e in rpm) jointly with
  C_d A_0, C_r, I_e and I_w by the grid search of Eq. 48 over the ranges of Table 5,

and writes a ROS 2 params file with the ``vehicle`` section of the base vehicle updated by the
fitted values (under ``/**``) and the mass node's ``mass.torque_regression`` (under ``mass``), so that
``vehicle-estimation replay BAG --vehicle calibrated.yaml`` runs method ``rls`` on engine load and
speed only (no torque signal), as the paper does.

Data preparation (paper Sec. 7.1: 4 Hz CAN samples, only samples with a > 0): every input is
averaged over 0.25 s windows as the mass node does. Vehicle speed: the undriven wheels' mean
speed x r when ``vehicle/joint_states`` has them (finer than the 1 km/h CAN speed), else
``vehicle/speed``; acceleration: the least-squares slope of that speed in each window. Road
grade: ``--slope-topic`` (a Float64 [rad] or a stamped companion, e.g. the fusion's pitch grade
or ``estimation/road_slope`` of a replay) or, by default, the kinematic grade
sin(alpha) = (f_x - dv/dt) / g from ``imu/data`` with its constant offset (accelerometer bias,
mounting pitch) removed so that it integrates to the GNSS height change of the drive
(:func:`vehicle_estimation.estimators.mass.calibration.debias_grade`). Windows are used for the torque fit
when: v >= 3 m/s, a > 0, no brake torque, one gear through the window and the one before it (no
shift), the measured ratio within 10 % of a fitted gear (no clutch slip), and, when the bag has no
brake torques, an engine load above 0 (a closed-throttle window may hide braking, see
:func:`calibrate_signals`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler
from vehicle_estimation.estimators.mass import calibration as cal
from vehicle_estimation.estimators.mass.update_window import (window_edges, window_ids, window_max, window_mean,
                                                               window_slope)
from vehicle_estimation.contract.vehicle import VehicleParams

UPDATE_PERIOD_S = 0.25      # the paper's 4 Hz CAN rate and the mass node's update window
MIN_SPEED = 3.0             # [m/s]
MAX_BRAKE_TORQUE = 1.0      # [N m] total; above it the window is braking
GEAR_TOLERANCE = 0.10       # relative ratio mismatch still counted as "in gear"


@dataclasses.dataclass
class DriveSignals:
    """Raw signals of one drive, each with its own stamps [s] (plain arrays, SI).

    ``wheel_speed`` (N, 4) [rad/s] fl, fr, rl, rr; ``engine_speed`` [rad/s]; ``engine_load`` 0-1;
    ``accel_x`` IMU specific force x [m/s^2]; ``slope`` [rad] if a grade signal is used.
    Optional groups are None.
    """

    speed_t: np.ndarray
    speed: np.ndarray
    powertrain_t: np.ndarray
    engine_speed: np.ndarray
    engine_load: np.ndarray
    wheel_t: np.ndarray | None = None
    wheel_speed: np.ndarray | None = None
    brake_torque: np.ndarray | None = None     # total of the four wheels, at wheel_t
    imu_t: np.ndarray | None = None
    accel_x: np.ndarray | None = None
    gnss_t: np.ndarray | None = None
    gnss_alt: np.ndarray | None = None
    slope_t: np.ndarray | None = None
    slope: np.ndarray | None = None


@dataclasses.dataclass
class CalibrationResult:
    gears: cal.GearRatioEstimate
    transmission_ratios: tuple[float, ...]
    fit: cal.TorqueModelFit
    grade_offset: float                 # removed constant of sin(alpha) (kinematic grade only)
    grade_source: str
    n_windows: int
    speed_order: int

    def torque_regression(self) -> list[float]:
        return [float(w) for w in self.fit.coefficients]

    def vehicle(self, base: VehicleParams, mass: float) -> VehicleParams:
        """``base`` with the fitted values. C_a is split as C_d = C_a / A_0 with the base
        frontal area A_0 (only the product is identifiable)."""
        return dataclasses.replace(
            base, mass=float(mass), gear_ratios=tuple(self.transmission_ratios),
            drag_coefficient=self.fit.drag_area / base.frontal_area,
            rolling_resistance=self.fit.rolling_resistance, engine_inertia=self.fit.engine_inertia,
            wheel_inertia=self.fit.wheel_inertia)


@dataclasses.dataclass
class PreparedWindows:
    """4 Hz window means of one drive (what the mass node feeds its core)."""

    t: np.ndarray             # end of each window [s]
    v: np.ndarray
    a: np.ndarray
    slope: np.ndarray
    engine_speed: np.ndarray
    engine_load: np.ndarray
    brake: np.ndarray         # max total brake torque in the window
    ratio: np.ndarray         # engine_speed / v of the window means
    single_ratio_gear: np.ndarray  # gear assigned to every raw sample of the window, else 0 (filled later)
    grade_offset: float = 0.0
    grade_source: str = ""


def prepare_windows(sig: DriveSignals, base: VehicleParams, period: float = UPDATE_PERIOD_S) -> PreparedWindows:
    """Window means/slopes of a drive on the powertrain clock (see the module docstring)."""
    edges = window_edges(sig.powertrain_t, period)
    n = len(edges)
    if n < 10:
        raise ValueError("the drive is too short for calibration")
    if sig.wheel_t is not None and sig.wheel_speed is not None:
        vt = np.asarray(sig.wheel_t, float)
        vv = np.mean(np.asarray(sig.wheel_speed, float)[:, list(base.undriven_wheels)], axis=1) * base.wheel_radius
    else:
        vt, vv = np.asarray(sig.speed_t, float), np.asarray(sig.speed, float)
    ids_v = window_ids(vt, edges)
    v = window_mean(ids_v, vv, n)
    a = window_slope(ids_v, vt, vv, n)
    ids_p = window_ids(sig.powertrain_t, edges)
    we = window_mean(ids_p, sig.engine_speed, n)
    load = window_mean(ids_p, sig.engine_load, n)
    brake = np.zeros(n)
    if sig.brake_torque is not None and sig.wheel_t is not None:
        brake = window_max(window_ids(sig.wheel_t, edges), sig.brake_torque, n)
    t_win = edges
    g = base.gravity
    offset = 0.0
    if sig.slope is not None and sig.slope_t is not None:
        slope = window_mean(window_ids(sig.slope_t, edges), sig.slope, n)
        source = "topic"
    elif sig.imu_t is not None and sig.accel_x is not None:
        fx = window_mean(window_ids(sig.imu_t, edges), sig.accel_x, n)
        sin_grade = (fx - a) / g
        dh = math.nan
        if sig.gnss_t is not None and sig.gnss_alt is not None:
            alt = np.asarray(sig.gnss_alt, float)
            ta = np.asarray(sig.gnss_t, float)
            ok = np.isfinite(alt)
            if np.count_nonzero(ok) >= 2:
                ta, alt = ta[ok], alt[ok]
                # mean of the first and last 10 s: GNSS height noise is metres per fix
                dh = float(np.mean(alt[ta >= ta[-1] - 10.0]) - np.mean(alt[ta <= ta[0] + 10.0]))
        step = np.diff(edges, prepend=edges[0] - period)
        sin_grade, offset = cal.debias_grade(sin_grade, np.nan_to_num(v) * step, dh if math.isfinite(dh) else 0.0)
        slope = np.arcsin(np.clip(sin_grade, -0.5, 0.5))
        source = "kinematic (imu - dv/dt, GNSS height debias)" if math.isfinite(dh) else "kinematic (imu - dv/dt, closed-route debias)"
    else:
        raise ValueError("no road grade: the bag has neither imu/data nor the --slope-topic")
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(v > 0.5, we / v, np.nan)
    return PreparedWindows(t=t_win, v=v, a=a, slope=slope, engine_speed=we, engine_load=load, brake=brake,
                           ratio=ratio, single_ratio_gear=np.zeros(n, dtype=np.int64), grade_offset=offset,
                           grade_source=source)


def calibrate_signals(sig: DriveSignals, mass: float, base: VehicleParams, *, n_gears: int | None = None,
                      width: float = 0.02, speed_order: int = 2,
                      grid: dict[str, tuple[float, float, float]] | None = None) -> CalibrationResult:
    """Gear ratios (Eq. 50) and the joint torque/parameter fit (Eqs. 48-49) of one drive."""
    if not (math.isfinite(mass) and mass > 0.0):
        raise ValueError(f"mass must be a positive number of kg, got {mass!r}")
    win = prepare_windows(sig, base)
    # -- gear ratios from every powertrain sample (speed interpolated to its stamp)
    if sig.wheel_t is not None and sig.wheel_speed is not None:
        vt = np.asarray(sig.wheel_t, float)
        vv = np.mean(np.asarray(sig.wheel_speed, float)[:, list(base.undriven_wheels)], axis=1) * base.wheel_radius
    else:
        vt, vv = np.asarray(sig.speed_t, float), np.asarray(sig.speed, float)
    v_pt = np.interp(sig.powertrain_t, vt, vv)
    ratios = cal.speed_ratios(sig.engine_speed, v_pt, idle_speed=base.engine_idle_speed, min_vehicle_speed=MIN_SPEED)
    if n_gears is None:
        # Default: the base vehicle's number of gears, or the gears the drive shows when it
        # engages fewer above MIN_SPEED. A gear used only while crawling (the WLTP shift rules
        # of vehicle_estimation.validation.wltp_drive leave 1st gear below 3 m/s) cannot be
        # fitted and is left out of the calibrated file, whose ratios then start at the first
        # gear seen (the mass node matches gears by ratio only); --gears insists on a number.
        seen = len(cal.estimate_gear_ratios(ratios, width=width).gearings)
        n_gears = min(len(base.gear_ratios), seen) if seen else len(base.gear_ratios)
    gears = cal.estimate_gear_ratios(ratios, n_gears=n_gears, width=width)
    # -- a window is in one gear when every raw sample of it is (and the window before it too)
    with np.errstate(invalid="ignore", divide="ignore"):
        raw_ratio = np.where(v_pt > 0.5, np.asarray(sig.engine_speed, float) / v_pt, np.nan)
    raw_gear = cal.assign_gears(raw_ratio, gears.gearings, GEAR_TOLERANCE).astype(float)
    n = win.t.size
    ids = window_ids(sig.powertrain_t, win.t)
    gmax = window_max(ids, raw_gear, n, empty=0.0)
    gmin = -window_max(ids, -raw_gear, n, empty=0.0)
    gear = np.where((gmax == gmin) & (gmin > 0), gmax, 0).astype(np.int64)
    prev = np.concatenate([[0], gear[:-1]])
    steady = (gear > 0) & (gear == prev)
    G = np.where(gear > 0, np.asarray(gears.gearings + (math.nan,))[np.maximum(gear, 1) - 1], np.nan)
    use = (steady & (win.v >= MIN_SPEED) & (win.a > 0.0) & (win.brake <= MAX_BRAKE_TORQUE)
           & np.isfinite(win.engine_load) & np.isfinite(win.slope) & np.isfinite(win.a))
    if sig.brake_torque is None:
        # No brake signal (an OBD-II-only car without vehicle/joint_states): a window at zero
        # load (closed throttle, overrun fuel cut) that still speeds up is on a downhill, where
        # the driver may also be braking, and nothing in the bag shows it. Its Eq.-(3) torque is
        # then the brakes', not the engine's; fitted as engine torque at L = 0 it bends Eq. 49
        # and C_r (the JRC WLTP tool's drives, vehicle_estimation.validation.wltp_drive, whose
        # negative wheel power is all brakes: 19 % of the windows, R^2 0.94 instead of 0.998,
        # and +2.4 % instead of +1.2 % mean last-half error of the mass replayed on a 20 %
        # heavier drive). With a brake signal such windows are engine braking and stay in.
        use &= win.engine_load > 0.0
    if np.count_nonzero(use) < 50:
        raise ValueError(f"only {np.count_nonzero(use)} driving windows usable for the torque fit (need 50)")
    fit = cal.fit_torque_model(mass, win.v[use], win.a[use], win.slope[use], G[use], win.engine_load[use],
                               win.engine_speed[use], wheel_radius=base.wheel_radius,
                               air_density=base.air_density, gravity=base.gravity,
                               speed_order=speed_order, grid=grid)
    return CalibrationResult(gears=gears, transmission_ratios=gears.transmission_ratios(base.final_drive, base.wheel_radius),
                             fit=fit, grade_offset=win.grade_offset, grade_source=win.grade_source,
                             n_windows=int(np.count_nonzero(use)), speed_order=speed_order)


# ---------------------------------------------------------------------------- bag reading
def _stamp(msg: Any, log_ns: int) -> float:
    header = getattr(msg, "header", None)
    if header is not None:
        ns = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
        if ns > 0:
            return ns * 1e-9
    return log_ns * 1e-9


def _joint(msg: Any, name: str, field: str) -> float:
    names = list(msg.name)
    if name not in names:
        return math.nan
    values = getattr(msg, field)
    i = names.index(name)
    return float(values[i]) if i < len(values) else math.nan


def _match_topic(available: list[str], relative: str) -> str | None:
    """The bag topic for a relative name: as written, with a leading '/', or a unique
    '/ns/.../name' (a namespaced recording)."""
    rel = relative.lstrip("/")
    for name in (rel, "/" + rel):
        if name in available:
            return name
    suffix = [name for name in sorted(available) if name.endswith("/" + rel)]
    return suffix[0] if len(suffix) == 1 else None


def read_drive(bag: str | Path, slope_topic: str | None = None, imu_mounting_rpy=(0.0, 0.0, 0.0)) -> DriveSignals:
    """Signals of the topic contract from a rosbag2 (MCAP or sqlite3) via ``rosbags``; the IMU's
    forward specific force in base_link, turned by ``imu_mounting_rpy`` (``vehicle.*``)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    wanted = {"speed": topics.SPEED, "powertrain": topics.POWERTRAIN, "joints": topics.JOINT_STATES,
              "imu": topics.IMU, "gnss": topics.GNSS}
    # base_link x in imu_link's axes: the row of imu_link -> base_link that gives f_x
    forward = rotmat_from_euler(*(float(a) for a in imu_mounting_rpy))[0]
    if slope_topic:
        wanted["slope"] = slope_topic
    rows: dict[str, list[tuple]] = {k: [] for k in wanted}
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        names = sorted({c.topic for c in reader.connections})
        topic_key = {}
        for key, rel in wanted.items():
            name = _match_topic(names, rel)
            if name is not None:
                topic_key[name] = key
        if "slope" in wanted and "slope" not in topic_key.values():
            raise ValueError(f"slope topic {slope_topic!r} is not in the bag")
        conns = [c for c in reader.connections if c.topic in topic_key]
        if not conns:
            raise ValueError("the bag has none of the topics of the contract")
        for conn, log_ns, raw in reader.messages(connections=conns):
            key = topic_key[conn.topic]
            msg: Any = reader.deserialize(raw, conn.msgtype)
            t = _stamp(msg, log_ns)
            if key == "speed":
                rows[key].append((t, float(msg.twist.twist.linear.x)))
            elif key == "powertrain":
                rows[key].append((t, _joint(msg, topics.ENGINE_JOINT, "velocity"),
                                  _joint(msg, topics.ENGINE_LOAD_JOINT, "position")))
            elif key == "joints":
                w = [_joint(msg, j, "velocity") for j in topics.WHEEL_JOINTS]
                b = [_joint(msg, j, "effort") for j in topics.WHEEL_JOINTS]
                rows[key].append((t, *w, float(np.nansum(b)) if np.any(np.isfinite(b)) else math.nan))
            elif key == "imu":
                a = msg.linear_acceleration
                rows[key].append((t, float(forward @ (a.x, a.y, a.z))))
            elif key == "gnss":
                ok = int(msg.status.status) >= 0
                rows[key].append((t, float(msg.altitude) if ok else math.nan))
            elif key == "slope":
                if conn.msgtype == "std_msgs/msg/Float64":
                    rows[key].append((t, float(msg.data)))
                elif conn.msgtype == "geometry_msgs/msg/Vector3Stamped":
                    rows[key].append((t, float(msg.vector.x)))
                else:
                    raise ValueError(f"slope topic {conn.topic} has type {conn.msgtype}; "
                                     "need std_msgs/Float64 or geometry_msgs/Vector3Stamped")

    def arr(key: str) -> np.ndarray | None:
        if not rows.get(key):
            return None
        a = np.array(sorted(rows[key], key=lambda r: r[0]), dtype=float)
        return a

    sp, pt = arr("speed"), arr("powertrain")
    if pt is None:
        raise ValueError(f"the bag has no {topics.POWERTRAIN} (engine speed and load are needed)")
    if sp is None:
        raise ValueError(f"the bag has no {topics.SPEED}")
    if not np.any(np.isfinite(pt[:, 2])):
        raise ValueError(f"{topics.POWERTRAIN} carries no '{topics.ENGINE_LOAD_JOINT}' joint (OBD-II load)")
    sig = DriveSignals(speed_t=sp[:, 0], speed=sp[:, 1], powertrain_t=pt[:, 0], engine_speed=pt[:, 1],
                       engine_load=pt[:, 2])
    js = arr("joints")
    if js is not None and np.all(np.isfinite(js[:, 1:5]), axis=1).mean() > 0.9:
        sig.wheel_t, sig.wheel_speed, sig.brake_torque = js[:, 0], js[:, 1:5], js[:, 5]
    imu, gn, sl = arr("imu"), arr("gnss"), arr("slope")
    if imu is not None:
        sig.imu_t, sig.accel_x = imu[:, 0], imu[:, 1]
    if gn is not None:
        sig.gnss_t, sig.gnss_alt = gn[:, 0], gn[:, 1]
    if sl is not None:
        sig.slope_t, sig.slope = sl[:, 0], sl[:, 1]
    return sig


# ---------------------------------------------------------------------------- output
def _rounded(x: float, digits: int = 6) -> float:
    return float(f"{x:.{digits}g}")


def params_document(result: CalibrationResult, base: VehicleParams, mass: float) -> dict[str, Any]:
    """The params document: under ``/**`` the ``vehicle`` section of ``base`` with the fitted
    values, under the mass node ``mass.torque_regression`` (Eq. 49 coefficients, N_e in rpm)."""
    vehicle = result.vehicle(base, mass).as_mapping()
    for key, value in list(vehicle.items()):
        if isinstance(value, float):
            vehicle[key] = _rounded(value)
    vehicle["gear_ratios"] = [_rounded(g, 5) for g in vehicle["gear_ratios"]]
    mass_section = {"torque_regression": [_rounded(w, 8) for w in result.torque_regression()],
                    "torque_regression_speed_unit": "rpm"}
    if math.isfinite(result.fit.relative_std):
        mass_section["torque_regression_relative_std"] = _rounded(result.fit.relative_std, 6)
    if result.fit.covariance and all(math.isfinite(c) for c in result.fit.covariance):
        mass_section["torque_model_covariance"] = [_rounded(c, 8) for c in result.fit.covariance]
    return {"/**": {"ros__parameters": {"vehicle": vehicle}}, "mass": {"ros__parameters": {"mass": mass_section}}}


def summary(result: CalibrationResult, base: VehicleParams | None = None) -> str:
    """Human-readable table of the fitted values (and the base vehicle's, when given)."""
    f = result.fit
    lines = [f"grade source: {result.grade_source} (offset removed {result.grade_offset:+.4f})",
             f"gear ratios (Eq. 50, w = {result.gears.width}), G = i_t i_d / r [1/m] and i_t:"]
    ref = base.gear_ratios if base is not None else ()
    if len(ref) > len(result.gears.gearings):
        lines.append(f"  NOTE: the drive shows {len(result.gears.gearings)} of the base vehicle's {len(ref)} gears "
                     f"above {MIN_SPEED:g} m/s; the calibrated file has those (--gears insists on a number)")
        ref = ()   # which base gear each one is, is not known
    for j, (G, it) in enumerate(zip(result.gears.gearings, result.transmission_ratios), start=1):
        extra = ""
        if j <= len(ref):
            extra = f"   base i_t {ref[j - 1]:.3f}  error {100.0 * (it / ref[j - 1] - 1.0):+.2f} %"
        lines.append(f"  gear {j}: G = {G:8.3f}  ({G * 30 / math.pi:6.1f} rpm/(m/s))  i_t = {it:.4f}{extra}")
    lines.append(f"torque fit (Eqs. 48-49, {f.n_samples} windows of 0.25 s): R^2 = {f.r2:.4f}, RMSE = {f.rmse:.2f} N m, "
                 f"map known to {100.0 * f.relative_std:.2f} % (relative std at the mean operating point)")
    names = ("w0 [N m]", "w1 [N m per load]") + tuple(f"w{k + 2} [N m/rpm^{k + 1}]" for k in range(result.speed_order))
    n = len(f.coefficients) + len(cal.GRID_PARAMETERS)
    sigma = (np.sqrt(np.maximum(np.diag(np.asarray(f.covariance, dtype=float).reshape(n, n)), 0.0))
             if len(f.covariance) == n * n else np.full(n, math.nan))

    def spread(k: int) -> str:
        return f" +- {sigma[k]:.2g}" if math.isfinite(sigma[k]) else ""

    for k, (name, w) in enumerate(zip(names, f.coefficients)):
        lines.append(f"  {name:<22}{w: .6g}{spread(k)}")
    for k, (name, unit) in enumerate((("drag_area", "m^2"), ("rolling_resistance", "-"),
                                      ("engine_inertia", "kg m^2"), ("wheel_inertia", "kg m^2")),
                                     start=len(f.coefficients)):
        val = getattr(f, name)
        extra = ""
        if base is not None:
            b = base.drag_area if name == "drag_area" else getattr(base, name)
            extra = f"   (base {b:.4g})"
        lines.append(f"  {name:<22}{val: .4g}{spread(k)} {unit}{extra}")
    if f.on_grid_edge:
        lines.append(f"  WARNING: at the edge of the Table 5 grid: {', '.join(f.on_grid_edge)}")
    return "\n".join(lines)


def write_params(path: str | Path, document: Mapping[str, Any], header: str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = "".join(f"# {line}\n" for line in header.splitlines())
    text += yaml.safe_dump(dict(document), sort_keys=False, default_flow_style=None)
    path.write_text(text, encoding="utf-8")
    return path


# ---------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("bag", help="rosbag2 directory or file (MCAP or sqlite3) of one drive with known mass")
    p.add_argument("--mass", type=float, required=True, help="true vehicle mass during the drive [kg]")
    p.add_argument("--out", required=True, help="params YAML to write")
    p.add_argument("--vehicle", default="audi_a4",
                   help="base vehicle params (name under params/ or a YAML path): tyre radius, final drive, "
                        "frontal area, engine idle speed, number of gears (default audi_a4)")
    p.add_argument("--gears", type=int, default=None,
                   help="number of forward gears (default: the base vehicle's, or fewer when the drive "
                        "engages fewer above 3 m/s)")
    p.add_argument("--width", type=float, default=0.02, help="Eq. 50 interval width w (default 0.02, Fig. 6)")
    p.add_argument("--speed-order", type=int, default=2,
                   help="highest power of the engine speed in Eq. 49 (default 2, as Table 6)")
    p.add_argument("--slope-topic", default=None,
                   help="road grade topic [rad] (Float64 or stamped companion); default: kinematic grade "
                        "from imu/data, debiased with the GNSS height change")


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.sim.scenario import params_path
    from vehicle_estimation.contract.vehicle import load_vehicle_params

    bag = Path(args.bag)
    if not bag.exists():
        print(f"calibrate: no such bag: {bag}", file=sys.stderr)
        return 2
    try:
        base_path = params_path(args.vehicle)
        base = load_vehicle_params(base_path)
        sig = read_drive(bag, args.slope_topic, base.imu_mounting_rpy)
        result = calibrate_signals(sig, float(args.mass), base, n_gears=args.gears, width=args.width,
                                   speed_order=args.speed_order)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"calibrate: {exc}", file=sys.stderr)
        return 1
    doc = params_document(result, base, float(args.mass))
    header = (f"Calibrated by `calibrate {bag} --mass {args.mass:g}` (paper 003 Sec. 6, Eqs. 48-50).\n"
              f"Base vehicle: {base_path}. Torque fit R^2 = {result.fit.r2:.4f}.")
    out = write_params(args.out, doc, header)
    print(summary(result, base))
    print(f"params written to {out}")
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    sys.exit(run_as_script(sys.modules[__name__]))
