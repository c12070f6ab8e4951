"""Offline comparison of our state cores with a textbook linear single-track KF on one bag.

:func:`compare_state_filters` reads a bag of :mod:`.commonroad` (or any bag with the topic
contract and ground truth), and runs, without ROS:

* the baseline :func:`vehicle_estimation.validation.baselines.baseline_linear_kf` (its ``cf``/``cr``
  are per *axle*: 2 x the per-tyre ``VehicleParams`` values, as ``validation.stanford`` passes them),
  fed with the IMU ay and yaw rate (averaged to 100 Hz, as the state node does), the road-wheel
  angle (steering wheel / ``steering_ratio``) and the CAN speed (zero-order hold);
* ``VehicleStateCKF``, ``VehicleStateVBACKF`` and ``VehicleStateAOUKF`` fed as
  ``ros/state_node.py`` feeds them (mirrored here, that file is not imported: it needs rclpy):
  the node's shipped tuning (the ``vehicle_state`` section of ``params/estimation.yaml``:
  ``p0_diag``, ``q_diag``, ``r_diag``, ``initial_vx``, ``init_vx_from_wheel_speeds``,
  ``wheel_slip_forces``, the axle force noise and the ``vbackf.*``/``aoukf.*`` it sets; no GA-BPNN
  weights for this car), IMU without the fusion's bias (the node runs alone here), but with the node's
  ``roll_compensation``: ``g sin(roll) cos(pitch)`` taken out of the measured ay, with the
  ground-truth attitude standing in for the fusion's (``--roll truth``, default; ``--roll none``
  feeds the raw ay, which on the CommonRoad car reads 15 % above the true ay in a corner:
  4.3 deg of roll at 4.7 m/s^2), slope unknown (slope 0 plus the
  ``missing_slope_std_deg`` = 2 deg vx process noise; while neither wheel speeds nor a fresh
  ``vehicle/speed`` measure vx, the ``dead_reckoning_accel_std`` noise too) and the nominal mass; the last joint state
  and speed *before* the IMU sample (in the bag a joint state with the same stamp is written
  after the IMU message); a 1 s wait for wheel speeds before starting from ``initial_vx``; IMU
  [ax, ay, r] averaged over the samples since the last 100 Hz step. Each filter runs twice:
  ``wheels`` (joint-state wheel speeds) and ``can`` (wheel speeds NaN, vx from
  ``vehicle/speed`` through ``update_speed``: the node's ``speed_fallback``).

Metrics from ``start`` (default the end of the warm-up, 5 s): sideslip RMSE [deg], vy MAE and
RMSE [m/s], vx RMSE [m/s], the ratio of the filter's sideslip RMSE to the baseline's, and the
share of vy errors within twice the filter's own sigma (honest: 95 %).
The baseline takes the raw ay (textbook, and as ``validate`` feeds it).
CLI: ``python -m vehicle_estimation.validation.lateral BAG... [--vehicle YAML] [--wheel-radius R]
[--roll truth|none]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml

from vehicle_estimation.contract import topics as T
from vehicle_estimation.estimators.registry import StateSettings, build_state_filter
from vehicle_estimation.estimators.state.core import (
    DEFAULT_CORNERING_ACCEL_STD, DEFAULT_CORNERING_MIN_YAW_RATE, CorneringSpeed, RollAccelerationTerm)
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.validation.baselines import baseline_linear_kf
from vehicle_estimation.contract.vehicle import VehicleParams, load_vehicle_params, merge_ros_parameters
from vehicle_estimation.paths import params_file
from vehicle_estimation.estimators.common.guard import STAMP_TOLERANCE_S
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler

PARAMS_FILE = params_file("commonroad_bmw320i")
FILTER_RATE_HZ = 100.0
STALE_INPUT_S = 0.5               # state node stale_input_s
WHEEL_WAIT_S = 1.0                # state node
GRADE_CORRELATION_S = 5.0         # state node
MISSING_SLOPE_STD_DEG = 2.0       # state node missing_slope_std_deg
SPEED_FALLBACK_STD = 0.3          # state node speed_fallback_std
DEAD_RECKONING_ACCEL_STD = 0.35   # state node dead_reckoning_accel_std
FILTERS = ("ckf", "vbackf", "aoukf")
ROLL_SOURCES = ("truth", "none")
DEFAULT_ROLL = "truth"


# --------------------------------------------------------------------------- bag reading
def read_drive(bag: Path, imu_mounting_rpy=(0.0, 0.0, 0.0)) -> dict[str, dict[str, np.ndarray]]:
    """The inputs and truth of a bag as arrays (header stamps, in bag order; the IMU turned into
    base_link by ``imu_mounting_rpy``, as the nodes turn it)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    want = {T.IMU, T.JOINT_STATES, T.SPEED, T.GT_VEHICLE_STATE, T.GT_SIDESLIP, T.GT_ODOMETRY}
    rows: dict[str, list] = {k: [] for k in want}
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic.lstrip("/") in want]
        for conn, log_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            topic = conn.topic.lstrip("/")
            if topic == T.GT_SIDESLIP:
                rows[topic].append((log_ns * 1e-9, msg.data))
                continue
            t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            if topic == T.IMU:
                a, w = msg.linear_acceleration, msg.angular_velocity
                rows[topic].append((t, a.x, a.y, a.z, w.x, w.y, w.z))
            elif topic == T.JOINT_STATES:
                vel = dict(zip(msg.name, msg.velocity))
                pos = dict(zip(msg.name, msg.position))
                rows[topic].append((t, *[vel.get(n, math.nan) for n in T.WHEEL_JOINTS],
                                    pos.get(T.STEERING_JOINT, math.nan)))
            elif topic == T.GT_ODOMETRY:
                q = msg.pose.pose.orientation
                n = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
                # R[2, 1] = sin(roll) cos(pitch): the share of gravity on the body y axis, as
                # ros.conversions.lateral_gravity_entry reads it off the fusion's estimation/imu
                rows[topic].append((t, 2.0 * (q.y * q.z + q.w * q.x) / n if n > 0.5 else math.nan))
            elif topic == T.SPEED:
                rows[topic].append((t, msg.twist.twist.linear.x, msg.twist.covariance[0]))
            else:
                tw = msg.twist.twist
                rows[topic].append((t, tw.linear.x, tw.linear.y, tw.angular.z))
    widths = {T.IMU: 7, T.JOINT_STATES: 6, T.SPEED: 3, T.GT_VEHICLE_STATE: 4, T.GT_SIDESLIP: 2, T.GT_ODOMETRY: 2}
    # a topic the bag lacks (no CAN speed, no attitude truth) is an empty table
    arr = {k: np.array(v, dtype=float).reshape(-1, widths[k]) for k, v in rows.items()}
    imu, js, sp, gt, gb, go = (arr[T.IMU], arr[T.JOINT_STATES], arr[T.SPEED], arr[T.GT_VEHICLE_STATE],
                               arr[T.GT_SIDESLIP], arr[T.GT_ODOMETRY])
    C = rotmat_from_euler(*(float(a) for a in imu_mounting_rpy))     # imu_link -> base_link
    return {
        "imu": {"t": imu[:, 0], "f": imu[:, 1:4] @ C.T, "w": imu[:, 4:7] @ C.T},
        "joints": {"t": js[:, 0], "wheels": js[:, 1:5], "steering_wheel": js[:, 5]},
        "speed": {"t": sp[:, 0], "v": sp[:, 1], "var": sp[:, 2]},
        "truth": {"t": gt[:, 0], "vx": gt[:, 1], "vy": gt[:, 2], "yaw_rate": gt[:, 3],
                  "sideslip_t": gb[:, 0], "sideslip": gb[:, 1],
                  "attitude_t": go[:, 0], "lateral_gravity": go[:, 1]},
    }


# --------------------------------------------------------------------------- cores
def shipped_state_parameters() -> dict:
    """The state node's ``ros__parameters`` in the shipped ``params/estimation.yaml``."""
    with open(params_file("estimation"), encoding="utf-8") as stream:
        shipped = yaml.safe_load(stream)
    return merge_ros_parameters(shipped, node="vehicle_state")


def shipped_state_settings() -> StateSettings:
    """The state node's tuning in the shipped ``params/estimation.yaml``."""
    return StateSettings.from_parameters(shipped_state_parameters())


def make_core(name: str, vehicle: VehicleParams, overrides: dict | None = None):
    """A core with the state node's shipped tuning (see the module docstring), with the node
    parameters ``overrides`` (as a params layer would set them) on top."""
    parameters = {**shipped_state_parameters(), **(overrides or {})}
    return build_state_filter(name, vehicle, settings=StateSettings.from_parameters(parameters),
                              parameters=parameters)


def lateral_gravity(drive: dict, t: np.ndarray, source: str) -> np.ndarray:
    """The gravity on the body y axis [m/s^2 per g] at the IMU stamps ``t``, for the roll
    compensation (``roll`` of :func:`run_core`): ``truth`` = the ground-truth attitude (an ideal
    fusion), ``none`` = 0 (raw IMU)."""
    if source == "none":
        return np.zeros_like(t)
    if source != "truth":
        raise ValueError(f"unknown roll source {source!r}")
    tru = drive["truth"]
    if tru["attitude_t"].size == 0:
        raise ValueError("roll='truth' needs ground_truth/odometry in the bag")
    # the last attitude before the sample, as the node's history lookup
    i = np.clip(np.searchsorted(tru["attitude_t"], t + STAMP_TOLERANCE_S) - 1, 0, tru["attitude_t"].size - 1)
    return tru["lateral_gravity"][i]


def cornering_speed_from(node: dict) -> CorneringSpeed | None:
    """The state node's cornering speed (``cornering_speed_*``), None where it is off."""
    std = float(node.get("cornering_speed_accel_std", DEFAULT_CORNERING_ACCEL_STD))
    if std <= 0.0:
        return None
    return CorneringSpeed(accel_std=std, min_yaw_rate=float(
        node.get("cornering_speed_min_yaw_rate", DEFAULT_CORNERING_MIN_YAW_RATE)))


def run_core(name: str, drive: dict, vehicle: VehicleParams, *, use_wheels: bool,
             roll: str = DEFAULT_ROLL, roll_lever: float | None = None,
             overrides: dict | None = None) -> dict[str, np.ndarray]:
    """Step one core through a drive as the state node would; (t, vx, vy, r, beta) per step.

    ``overrides``: state-node parameters over the shipped ones (:func:`make_core`).

    ``roll``: the state node's ``roll_compensation`` (on by default there, with the fusion's
    attitude): ``truth`` takes ``g sin(roll) cos(pitch)`` of the ground-truth attitude out of
    the measured ay (the fusion at its best), ``none`` feeds the raw ay."""
    core = make_core(name, vehicle, overrides)
    imu, js, sp = drive["imu"], drive["joints"], drive["speed"]
    g_y = vehicle.gravity * lateral_gravity(drive, imu["t"], roll)
    node = {**shipped_state_parameters(), **(overrides or {})}
    missing_slope_std = math.radians(float(node.get("missing_slope_std_deg", MISSING_SLOPE_STD_DEG)))
    missing_slope_noise = 2.0 * (vehicle.gravity * math.sin(missing_slope_std)) ** 2 * GRADE_CORRELATION_S
    dead_reckoning_noise = 2.0 * float(node.get("dead_reckoning_accel_std", DEAD_RECKONING_ACCEL_STD)) ** 2 \
        * GRADE_CORRELATION_S
    cornering = cornering_speed_from(node)
    vx_measured = False
    ji = si = 0
    n_js, n_sp = js["t"].size, sp["t"].size
    chassis = None
    speed = None
    first_imu_t = None
    z_sum, z_count, last_step = np.zeros(3), 0, -math.inf
    lever = vehicle.roll_lever if roll_lever is None else roll_lever
    roll_acc = RollAccelerationTerm(lever)
    out = []
    for k in range(imu["t"].size):
        t = float(imu["t"][k])
        while ji < n_js and js["t"][ji] < t - STAMP_TOLERANCE_S:
            chassis = ji
            ji += 1
        while si < n_sp and sp["t"][si] < t - STAMP_TOLERANCE_S:
            var = float(sp["var"][si])
            speed = (float(sp["t"][si]), float(sp["v"][si]),
                     var if math.isfinite(var) and var > 0.0 else SPEED_FALLBACK_STD ** 2)
            si += 1
        f, w = imu["f"][k], imu["w"][k]
        fresh = chassis is not None and t - js["t"][chassis] <= STALE_INPUT_S
        if fresh:
            steer = float(js["steering_wheel"][chassis]) / vehicle.steering_ratio
            wheels = js["wheels"][chassis].copy() if use_wheels else np.full(4, np.nan)
        else:
            steer, wheels = 0.0, np.full(4, np.nan)
        if not math.isfinite(steer):
            steer = 0.0
        inputs = VehicleInputs(steer_angle=steer, wheel_speeds=wheels, slope=0.0, mass=vehicle.mass)
        if not core.initialised and not np.all(np.isfinite(wheels)):
            if first_imu_t is None:
                first_imu_t = t
            if t - first_imu_t < WHEEL_WAIT_S:
                continue
        z_sum += (f[0], f[1] - g_y[k], w[2])
        roll_acc.add(w[0])
        z_count += 1
        if core.initialised and t - last_step < 1.0 / FILTER_RATE_HZ - STAMP_TOLERANCE_S:
            continue
        z = z_sum / z_count
        z[1] += roll_acc.step(t)
        z_sum[:] = 0.0
        z_count = 0
        last_step = t
        # as the node: while nothing measures vx, the dead reckoning's drift is process noise
        core.extra_vx_noise_density = missing_slope_noise + (
            0.0 if vx_measured or not core.initialised else dead_reckoning_noise)
        core.step(t, inputs, z)
        rear_wheels_measured = bool(np.all(np.isfinite(wheels[2:])))
        speed_fresh = speed is not None and t - speed[0] <= STALE_INPUT_S
        if not rear_wheels_measured and speed_fresh and core.update_speed(speed[1], speed[2]):
            speed = None
        vx_measured = rear_wheels_measured or speed_fresh
        found = None if cornering is None else cornering.step(t, float(z[1]), float(z[2]), vx_measured)
        if found is not None:
            core.update_speed(*found)
        x = np.asarray(core.x, dtype=float)
        out.append((t, x[0], x[1], x[2], float(core.sideslip), float(core.P[1, 1])))
    a = np.array(out)
    return {"t": a[:, 0], "vx": a[:, 1], "vy": a[:, 2], "yaw_rate": a[:, 3], "sideslip": a[:, 4],
            "vy_variance": a[:, 5]}


def run_baseline(drive: dict, vehicle: VehicleParams) -> dict[str, np.ndarray]:
    """The linear single-track KF on 100 Hz means of the IMU (pairs of 200 Hz samples)."""
    imu, js, sp = drive["imu"], drive["joints"], drive["speed"]
    per = max(1, round(1.0 / (FILTER_RATE_HZ * np.median(np.diff(imu["t"])))))
    n = imu["t"].size // per * per
    t = imu["t"][:n].reshape(-1, per)[:, -1]
    ay = imu["f"][:n, 1].reshape(-1, per).mean(axis=1)
    r = imu["w"][:n, 2].reshape(-1, per).mean(axis=1)
    ij = np.clip(np.searchsorted(js["t"], t - STAMP_TOLERANCE_S) - 1, 0, js["t"].size - 1)
    delta = js["steering_wheel"][ij] / vehicle.steering_ratio
    isp = np.clip(np.searchsorted(sp["t"], t - STAMP_TOLERANCE_S) - 1, 0, sp["t"].size - 1)
    vx = np.maximum(sp["v"][isp], 1.0)
    beta, rr = baseline_linear_kf(t, ay, r, delta, vx, m=vehicle.mass, lf=vehicle.lf, lr=vehicle.lr,
                                  iz=vehicle.yaw_inertia, cf=2.0 * vehicle.cornering_stiffness_front,
                                  cr=2.0 * vehicle.cornering_stiffness_rear)
    return {"t": t, "vx": vx, "vy": vx * np.tan(beta), "yaw_rate": rr, "sideslip": beta}


def _scores(est: dict, truth: dict, start: float) -> dict[str, float]:
    def err(key, tt, yt):
        ta, ea, ra = metrics.align(est["t"], est[key], tt, yt)
        sel = ta >= start
        return ea[sel], ra[sel]

    b_e, b_r = err("sideslip", truth["sideslip_t"], truth["sideslip"])
    t_vy, vy_e, vy_r = metrics.align(est["t"], est["vy"], truth["t"], truth["vy"])
    sel = t_vy >= start
    vy_e, vy_r = vy_e[sel], vy_r[sel]
    vx_e, vx_r = err("vx", truth["t"], truth["vx"])
    scores = {"sideslip_rmse_deg": math.degrees(metrics.rmse(b_e, b_r)),
              "vy_mae": metrics.mae(vy_e, vy_r), "vy_rmse": metrics.rmse(vy_e, vy_r),
              "vx_rmse": metrics.rmse(vx_e, vx_r)}
    if "vy_variance" in est:     # is the published vy variance honest? (95 % within 2 sigma)
        sigma = np.sqrt(np.interp(t_vy[sel], est["t"], est["vy_variance"]))
        scores["vy_within_2sigma"] = float(np.mean(np.abs(vy_e - vy_r) <= 2.0 * sigma))
    return scores


def compare_state_filters(bag: Path, *, vehicle: VehicleParams | str | Path | None = None,
                          wheel_radius: float | None = None, start: float = 5.0,
                          filters: Sequence[str] = FILTERS, roll: str = DEFAULT_ROLL) -> dict:
    """Scores of the baseline and of each filter (with and without wheel speeds) on ``bag``.

    ``vehicle``: params (default ``params/commonroad_bmw320i.yaml``); ``wheel_radius``
    overrides its ``wheel_radius`` (e.g. the measured effective rolling radius); ``roll``: the
    roll compensation of our filters (:func:`run_core`; the baseline, as textbook, takes the
    raw ay).
    Returns ``{"bag", "baseline": scores, "<filter>/wheels": scores, "<filter>/can": scores}``;
    each filter's scores carry ``ratio`` = its sideslip RMSE / the baseline's.
    """
    if vehicle is None or isinstance(vehicle, (str, Path)):
        vehicle = load_vehicle_params(PARAMS_FILE if vehicle is None else vehicle)
    if wheel_radius is not None:
        vehicle = dataclasses.replace(vehicle, wheel_radius=float(wheel_radius))
    drive = read_drive(Path(bag), vehicle.imu_mounting_rpy)
    truth = drive["truth"]
    out: dict = {"bag": str(bag), "wheel_radius": vehicle.wheel_radius, "roll": roll}
    base = _scores(run_baseline(drive, vehicle), truth, start)
    out["baseline"] = base
    for name in filters:
        for mode in ("wheels", "can"):
            s = _scores(run_core(name, drive, vehicle, use_wheels=mode == "wheels", roll=roll), truth, start)
            s["ratio"] = s["sideslip_rmse_deg"] / base["sideslip_rmse_deg"] if base["sideslip_rmse_deg"] > 0 else math.nan
            out[f"{name}/{mode}"] = s
    return out


def format_table(result: dict) -> str:
    lines = [f"{Path(result['bag']).name} (wheel_radius {result['wheel_radius']:.5f} m, "
             f"roll compensation {result.get('roll', DEFAULT_ROLL)})",
             f"{'estimator':<16}{'beta RMSE deg':>14}{'vy MAE':>9}{'vy RMSE':>9}{'vx RMSE':>9}{'ratio':>8}"
             f"{'vy in 2 sigma':>15}"]
    for key, s in result.items():
        if not isinstance(s, dict):
            continue
        ratio = f"{s['ratio']:8.2f}" if "ratio" in s else f"{'1.00':>8}"
        within = f"{100.0 * s['vy_within_2sigma']:14.0f}%" if "vy_within_2sigma" in s else f"{'n/a':>15}"
        lines.append(f"{key:<16}{s['sideslip_rmse_deg']:14.3f}{s['vy_mae']:9.4f}{s['vy_rmse']:9.4f}"
                     f"{s['vx_rmse']:9.4f}{ratio}{within}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vehicle_estimation.validation.lateral",
                                 description="State cores vs the linear single-track KF on validation bags")
    ap.add_argument("bags", nargs="+", type=Path)
    ap.add_argument("--vehicle", type=Path, default=None, help=f"vehicle params (default {PARAMS_FILE.name})")
    ap.add_argument("--wheel-radius", type=float, default=None, help="override vehicle.wheel_radius [m]")
    ap.add_argument("--filter", action="append", choices=FILTERS, help="default: all")
    ap.add_argument("--start", type=float, default=5.0, help="score from this time [s]")
    ap.add_argument("--roll", choices=ROLL_SOURCES, default=DEFAULT_ROLL,
                    help="roll compensation of our filters' ay: ground-truth attitude (ideal fusion) or none")
    args = ap.parse_args(argv)
    for bag in args.bags:
        result = compare_state_filters(bag, vehicle=args.vehicle, wheel_radius=args.wheel_radius,
                                       start=args.start, filters=args.filter or FILTERS, roll=args.roll)
        print(format_table(result))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
