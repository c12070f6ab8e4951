"""What each node will do with a bag: its method, the fallbacks that will run and the outputs
that will stay empty or at their prior, from the bag's topic summary and the layered params.

``inspect`` and ``replay`` print it (:mod:`vehicle_estimation.io.inspect_bag`); the
defaults it assumes are the nodes' declarations (:data:`NODE_DEFAULTS`, checked by a test).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vehicle_estimation.contract import topics
from vehicle_estimation.contract.vehicle import UNDRIVEN_WHEELS, merge_ros_parameters
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler
from vehicle_estimation.estimators.fusion.mounting_check import MountingYawCheck
from vehicle_estimation.estimators.registry import DEFAULT_NO_SPEED_FILTER, NO_SPEED_HOLD_S, STATE_FILTERS
from vehicle_estimation.estimators.state.core import DEFAULT_CORNERING_ACCEL_STD
from vehicle_estimation.io.bag_survey import InspectError, TopicStats
from vehicle_estimation.ros import PIPELINE

NODES = tuple(spec.name for spec in PIPELINE)

#: Node parameter defaults, as the nodes declare them (a test checks them against the source):
#: ``ros/fusion_node.py`` (``wheel_speed_fallback``), ``ros/slope_node.py`` (``method``),
#: ``ros/state_node.py`` (``filter``,
#: ``speed_fallback``), ``ros/mass_node.py`` (``method``, ``accel_source``,
#: ``speed_source``, ``require_slope``). The ``fusion.*``, ``mass.*`` and ``vehicle.*``
#: defaults come from their config dataclasses (:func:`_dataclass_defaults`).
NODE_DEFAULTS: dict[str, dict[str, Any]] = {
    "fusion": {"wheel_speed_fallback": True},
    "road_slope": {"method": "auto"},
    "vehicle_state": {"filter": "vbackf", "speed_fallback": True},
    "mass": {"method": "ffrls", "accel_source": "auto", "speed_source": "fusion", "require_slope": True},
}

FUSION_OUTPUTS = (topics.ODOMETRY, topics.IMU_COMPENSATED, topics.IMU_BIAS, topics.FUSION_GRADE,
                  topics.SPEED_SCALE)
SLOPE_OUTPUTS = (topics.ROAD_SLOPE, topics.ROAD_SLOPE_STAMPED)
STATE_OUTPUTS = (topics.VEHICLE_STATE, topics.SIDESLIP, topics.SIDESLIP_STAMPED)
MASS_OUTPUTS = (topics.MASS, topics.MASS_STAMPED)
ALL_OUTPUTS = FUSION_OUTPUTS + SLOPE_OUTPUTS + STATE_OUTPUTS + MASS_OUTPUTS


# ------------------------------------------------------------------------------ parameters
def _dataclass_defaults() -> dict[str, dict[str, Any]]:
    """``fusion.*``, ``mass.*`` and ``vehicle.*`` defaults from the cores' config dataclasses."""
    import dataclasses

    from vehicle_estimation.contract.vehicle import VehicleParams
    from vehicle_estimation.estimators.fusion.config import FusionConfig
    from vehicle_estimation.estimators.mass.mass_rls import MassRLSConfig

    def prefixed(prefix: str, obj: Any) -> dict[str, Any]:
        return {f"{prefix}.{f.name}": getattr(obj, f.name) for f in dataclasses.fields(obj)}

    vehicle = prefixed("vehicle", VehicleParams())
    return {
        "fusion": {**vehicle, **prefixed("fusion", FusionConfig())},
        "road_slope": dict(vehicle),
        "vehicle_state": dict(vehicle),
        "mass": {**vehicle, **prefixed("mass", MassRLSConfig())},
    }


def _flatten(values: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if not isinstance(values, dict):
        return out
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


def layered_params(params_files: list[Path]) -> dict[str, dict[str, Any]]:
    """Effective parameters per node: defaults, then per file ``/**`` and the node's section."""
    defaults = _dataclass_defaults()
    merged = {node: {**defaults[node], **NODE_DEFAULTS[node]} for node in NODES}
    for path in params_files:
        try:
            document = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise InspectError(f"cannot read params file {path}: {exc}") from exc
        if not isinstance(document, dict):
            raise InspectError(f"params file {path} is not a mapping of node sections")
        for node in NODES:
            merged[node].update(_flatten(merge_ros_parameters(document, node)))
    return merged


# ------------------------------------------------------------------------------ node plan
def _reported(inputs: dict[str, Any], topic: str, joint: str, field: str) -> bool:
    info = inputs[topic]
    return bool(info.get("joints", {}).get(joint, {}).get(field, 0.0) > 0.0)


def _usable(inputs: dict[str, Any], topic: str) -> bool:
    info = inputs[topic]
    return bool(info["present"] and info.get("type_ok") and info.get("first_stamp") is not None)


def _alignment(stats: TopicStats | None, speed: TopicStats | None, fusion: dict[str, Any],
               have_speed: bool) -> tuple[str, bool]:
    """(line, aligns) for the fusion filter, from the first samples of the IMU and speed."""
    threshold = float(fusion.get("fusion.stationary_speed_threshold", 0.05))
    in_motion = bool(fusion.get("fusion.in_motion_alignment", True))
    window = float(fusion.get("fusion.in_motion_window_s", 5.0))
    if have_speed and speed is not None and speed.start_values:
        start = np.abs(np.asarray(speed.start_values[:100], dtype=float))
        if np.all(start <= threshold):
            return "aligns at standstill (vehicle/speed ~ 0 at the start)", True
        if in_motion:
            return f"moving from the start: aligns in motion after {window:g} s (needs vehicle/speed)", True
        return ("moving from the start and fusion.in_motion_alignment is off: "
                "aligns at the first standstill"), True
    n = int(fusion.get("fusion.init_stationary_samples", 200))
    values = np.asarray(stats.start_values[:n], dtype=float) if stats else np.empty((0, 6))
    if values.shape[0] >= min(n, 2):
        std = values.std(axis=0)
        quiet = (np.all(std[:3] <= float(fusion.get("fusion.init_max_accel_std", 0.3)))
                 and np.all(std[3:] <= float(fusion.get("fusion.init_max_gyro_std", 0.02))))
        if quiet:
            return "aligns at standstill (IMU quiet at the start; no vehicle/speed)", True
    return ("moving from the start and no vehicle/speed: cannot align: every fusion output stays "
            "empty (unless the car later stands still with a quiet IMU)"), False


#: Beyond this angle between base_link z and the start's mean specific force turned by the
#: nominal mounting, the mounting is not the IMU's: no road or mounting error is that large.
GRAVITY_MISMATCH_DEG = 20.0


def _mounting_lines(stats: TopicStats | None, fusion: dict[str, Any]) -> list[str]:
    """What ``vehicle.imu_mounting_rpy`` says, and whether the IMU's start agrees: the mean
    specific force of the first samples, turned into base_link by it, should point up."""
    rpy = [float(a) for a in fusion.get("vehicle.imu_mounting_rpy", (0.0, 0.0, 0.0))]
    lines = []
    if any(rpy):
        degrees = ", ".join(f"{math.degrees(a):.1f}" for a in rpy)
        lines.append(f"IMU mounting: imu_link at roll, pitch, yaw {degrees} deg in base_link "
                     "(vehicle.imu_mounting_rpy); every node turns imu/data by it")
    values = np.asarray(stats.start_values, dtype=float) if stats else np.empty((0, 6))
    if values.shape[0] < 2 or not np.isfinite(values[:, :3]).all():
        return lines
    f = rotmat_from_euler(*rpy) @ values[:, :3].mean(axis=0)
    norm = float(np.linalg.norm(f))
    if not 5.0 <= norm <= 15.0:
        return lines
    off = math.degrees(math.acos(max(-1.0, min(1.0, f[2] / norm))))
    if off > GRAVITY_MISMATCH_DEG:
        axis = "xyz"[int(np.argmax(np.abs(values[:, :3].mean(axis=0))))]
        lines.append(f"imu/data reads gravity {off:.0f} deg from base_link z after vehicle.imu_mounting_rpy "
                     f"(mostly on its own {axis} axis): give the IMU's mounting in the vehicle file, "
                     "or every node reads the IMU in the wrong axes")
    return lines


def imu_yaw_check(imu_samples, speed_samples, mounting_rpy) -> MountingYawCheck:
    """The yaw check (:class:`~vehicle_estimation.estimators.fusion.mounting_check.MountingYawCheck`)
    on a bag's samples: ``imu_samples`` (stamp, f_x, f_y, f_z, w_x, w_y, w_z) in imu_link and
    ``speed_samples`` (stamp, v), each every k-th message of the bag."""
    check = MountingYawCheck(mounting_rpy)
    imu = np.asarray(imu_samples, dtype=float)
    speed = np.asarray(speed_samples, dtype=float)
    if imu.ndim != 2 or imu.shape[1] != 7 or speed.ndim != 2 or speed.shape[0] < 2:
        return check
    t_s, v = speed[np.argsort(speed[:, 0], kind="stable")].T
    new = np.concatenate([[True], np.diff(t_s) > 0.0])
    check.add_samples(imu[:, 0], *check.to_base(imu[:, 1:4], imu[:, 4:7]), t_s[new], v[new])
    return check


def _mounting_yaw_lines(imu: TopicStats | None, speed: TopicStats | None, fusion: dict[str, Any]) -> list[str]:
    """A line when vehicle/speed's accelerations show the IMU turned about base_link z from the
    nominal mounting (gravity cannot show a yaw: an IMU facing backwards reads it as a level one)."""
    if imu is None or speed is None:
        return []
    rpy = [float(a) for a in fusion.get("vehicle.imu_mounting_rpy", (0.0, 0.0, 0.0))]
    check = imu_yaw_check(imu.samples, speed.samples, rpy)
    offset = check.offset
    if offset is None or not check.mismatched:
        return []
    return [f"imu/data's horizontal axes are {abs(math.degrees(offset)):.0f} deg about base_link z from "
            f"where vehicle.imu_mounting_rpy puts them (vehicle/speed's accelerations and turns "
            f"show an IMU yaw of about {check.implied_yaw_deg():.0f} deg): give the IMU's mounting in the "
            "vehicle file, or every node reads the car's forward acceleration on the wrong axis"]


def _speedless_stretches(imu: TopicStats | None, stamps: np.ndarray,
                         spacing_s: float) -> list[tuple[float, float]]:
    """Where the state node runs ``no_speed_filter``: (from, to) in seconds after the IMU's
    first stamp, from NO_SPEED_HOLD_S after a speed sample (``stamps``, which may skip up to
    ``spacing_s`` of samples; after the first IMU sample where none came yet) with none after
    it, to NO_SPEED_HOLD_S after the next sample."""
    if imu is None or not imu.stamps:
        return []
    t0, t1 = min(imu.stamps), max(imu.stamps)
    s = np.unique(stamps)
    s = s[(s >= t0) & (s <= t1)]
    gone = np.concatenate([[t0], s + spacing_s]) + NO_SPEED_HOLD_S   # the fallback from here
    following = np.concatenate([s, [math.inf]])                   # to the next sample's hold
    return [(float(a - t0), float(min(b + NO_SPEED_HOLD_S, t1) - t0))
            for a, b in zip(gone, following) if b > a and a < t1]


def _stretches_text(stretches: list[tuple[float, float]]) -> str:
    shown = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in stretches[:3])
    return shown + (f" and {len(stretches) - 3} more" if len(stretches) > 3 else "")


def plan_nodes(inputs: dict[str, Any], params: dict[str, dict[str, Any]],
          imu: TopicStats | None, speed_stats: TopicStats | None,
          joint_stats: TopicStats | None = None) -> dict[str, Any]:
    JS, PT = topics.JOINT_STATES, topics.POWERTRAIN
    have_imu = _usable(inputs, topics.IMU)
    have_speed = _usable(inputs, topics.SPEED)
    gnss = inputs[topics.GNSS]
    have_gnss = _usable(inputs, topics.GNSS) and (gnss.get("no_fix_share") is None or gnss["no_fix_share"] < 1.0)
    have_js, have_pt = _usable(inputs, JS), _usable(inputs, PT)
    wheel = {w: have_js and _reported(inputs, JS, w, "velocity") for w in topics.WHEEL_JOINTS}
    rear_wheels = wheel["wheel_rl"] and wheel["wheel_rr"]
    all_wheels = all(wheel.values())
    nodes: dict[str, Any] = {}
    empty: list[str] = []
    prior: list[str] = []

    # fusion
    lines = []
    if not have_imu:
        lines.append("no imu/data: the fusion filter does not run; every fusion output stays empty")
        fusion_ok = False
    else:
        if have_gnss:
            lines.append("GNSS-aided; odom = ENU at the first fix")
        else:
            lines.append("no GNSS: dead reckoning, odom = start pose with a free heading; "
                         "position covariance grows; accelerometer bias held at its prior, "
                         "which the grade's variance carries")
        fusion = params["fusion"]
        if not have_gnss and _truthy(fusion.get("fusion.estimate_mounting", False)):
            lines.append("IMU mounting learnt only from "
                         f"{float(fusion.get('fusion.mounting_min_speed_without_gnss', 1.0)):g} m/s up, "
                         "its pitch not in corners")
        undriven = UNDRIVEN_WHEELS.get(str(fusion.get("vehicle.driven_axle", "front")), (0, 1, 2, 3))
        wheel_speed = (not have_speed and _truthy(fusion.get("wheel_speed_fallback", True))
                       and all(wheel[topics.WHEEL_JOINTS[i]] for i in undriven))
        if wheel_speed:
            window = float(fusion.get("fusion.in_motion_window_s", 5.0))
            lines.append("aligns at standstill, or in motion after "
                         f"{window:g} s, on the wheel speeds")
            lines.append("no vehicle/speed: the undriven wheels' speed aids the filter "
                         "(automatic fallback, wheel_speed_fallback)")
            fusion_ok = True
        else:
            line, fusion_ok = _alignment(imu, speed_stats, fusion, have_speed)
            lines.append(line)
            lines.append("CAN speed aids the filter (vehicle/speed)" if have_speed
                         else "no vehicle/speed: only the vehicle constraints bound the velocity")
        lines += _mounting_lines(imu, fusion)
        if have_speed:
            lines += _mounting_yaw_lines(imu, speed_stats, fusion)
    if not fusion_ok:
        empty += FUSION_OUTPUTS
    elif not _truthy(fusion.get("fusion.estimate_speed_scale", False)):
        empty.append(topics.SPEED_SCALE)        # published only where the scale is estimated
    nodes["fusion"] = {"needs": "imu/data", "runs": fusion_ok, "lines": lines}

    # vehicle_state
    vs = params["vehicle_state"]
    lines = []
    state_vx = "none"
    if not have_imu:
        lines.append("no imu/data: the vehicle-state filter does not run")
        empty += STATE_OUTPUTS
    else:
        lines.append(f"filter {vs['filter']}")
        configured = STATE_FILTERS.get(str(vs["filter"]))
        fallback = str(vs.get("no_speed_filter", DEFAULT_NO_SPEED_FILTER))
        if rear_wheels or all_wheels:
            lines.append("vx from the wheel speeds")
            state_vx = "wheels"
        elif have_speed and _truthy(vs.get("speed_fallback", True)):
            lines.append("no wheel speeds: vx from vehicle/speed (automatic fallback, speed_fallback)")
            state_vx = "speed"
        else:
            hint = (" (vehicle/speed is there: set vehicle_state speed_fallback: true to use it)"
                    if have_speed else "")
            corners = (", measured in every corner as mean(ay) / mean(r)"
                       if float(vs.get("cornering_speed_accel_std", DEFAULT_CORNERING_ACCEL_STD)) > 0.0 else "")
            lines.append(f"no wheel speeds: vx dead-reckoned from ax (drifts){corners}{hint}")
            state_vx = "dead_reckoned"
            if configured is not None and configured.needs_speed and fallback:
                lines.append(f"{vs['filter']} needs a speed: filter {fallback} runs instead "
                             "(automatic fallback, no_speed_filter)")
        if state_vx != "dead_reckoned" and configured is not None and configured.needs_speed and fallback:
            # the wheel speeds are read from sampled messages: a gap as long as their spacing is none
            stamps, spacing = [np.empty(0)], 0.0
            if state_vx == "wheels" and joint_stats is not None and len(joint_stats.stamps) > 1:
                stamps.append(np.asarray(joint_stats.rear_wheel_stamps, dtype=float))
                spacing = float(np.median(np.diff(np.sort(joint_stats.stamps)))) * joint_stats.sample_every
            if have_speed and speed_stats is not None and _truthy(vs.get("speed_fallback", True)):
                stamps.append(np.asarray(speed_stats.stamps, dtype=float))
            stretches = _speedless_stretches(imu, np.concatenate(stamps), spacing)
            if stretches:
                lines.append(f"{vs['filter']} needs a speed: filter {fallback} runs where none came for "
                             f"{NO_SPEED_HOLD_S:g} s, {_stretches_text(stretches)} after the first IMU "
                             "sample (automatic fallback, no_speed_filter)")
        if have_js and _reported(inputs, JS, topics.STEERING_JOINT, "position"):
            lines.append("steering from steering_wheel")
        else:
            lines.append("δ = 0 (no steering)")
    nodes["vehicle_state"] = {"needs": "imu/data", "runs": have_imu, "vx": state_vx, "lines": lines}

    # road_slope
    rs = params["road_slope"]
    method = str(rs.get("method"))
    lines = [f"method {method}"]
    slope_ok = False
    if not have_imu:
        lines.append("no imu/data: the slope node never publishes")
        empty += SLOPE_OUTPUTS
    else:
        if state_vx in ("wheels", "speed"):
            speed_line = "speed from the vehicle state's vx and vy"
        elif fusion_ok:
            speed_line = "speed from the fusion odometry"
        elif have_speed:
            speed_line = "speed from vehicle/speed (vy = 0)"
        else:
            speed_line = "speed only from the vehicle state's dead-reckoned vx (drifts)"
        if method == "fusion_pitch":
            if fusion_ok:
                lines.append("fusion pitch grade (estimation/fusion/road_grade)")
                slope_ok = True
            else:
                lines.append("stays at its prior (no fusion grade)")
                prior += SLOPE_OUTPUTS
        elif method == "auto":
            if fusion_ok:
                lines.append("fusion pitch grade while it is available and converged, else the "
                             f"IMU + speed observer (cubic_prediction; {speed_line})")
            else:
                lines.append(f"no fusion grade: the IMU + speed observer (cubic_prediction; {speed_line})")
            slope_ok = True
        else:
            lines.append(f"imu/data and a speed: {speed_line}")
            slope_ok = True
    nodes["road_slope"] = {"needs": "imu/data", "method": method, "converges": slope_ok, "lines": lines}

    # mass
    ms = params["mass"]
    method = str(ms.get("method"))
    lines = [f"method {method}"]
    if not have_pt:
        lines.append("no vehicle/powertrain (its trigger): the mass node never publishes")
        empty += MASS_OUTPUTS
        nodes["mass"] = {"needs": "vehicle/powertrain", "method": method, "force": None, "lines": lines}
    else:
        drive = _reported(inputs, PT, topics.DRIVE_JOINT, "effort")
        torque = _reported(inputs, PT, topics.ENGINE_JOINT, "effort")
        engine_speed = _reported(inputs, PT, topics.ENGINE_JOINT, "velocity")
        gear = _reported(inputs, PT, topics.GEAR_JOINT, "position")
        load = _reported(inputs, PT, topics.ENGINE_LOAD_JOINT, "position")
        regression = ms.get("mass.torque_regression") or []
        n_gears = len(ms.get("vehicle.gear_ratios") or [])
        force = None
        if drive:
            force = "drive"
            lines.append("propulsion force from the drive effort")
        elif torque and gear:
            force = "engine_torque"
            lines.append("propulsion force from the engine torque (effort) with the reported gear")
        elif torque and engine_speed and n_gears:
            force = "engine_torque"
            lines.append(f"propulsion force from the engine torque (effort), gear predicted from the "
                         f"engine speed and vehicle.gear_ratios ({n_gears} gears)")
        elif method == "rls" and load and engine_speed and regression:
            force = "torque_regression"
            lines.append("propulsion force from engine_load + engine speed through mass.torque_regression")
            if ms.get("mass.torque_model_covariance"):
                lines.append("the calibration's own error (mass.torque_model_covariance) is in the mass variance")
            elif float(ms.get("mass.torque_regression_relative_std") or 0.0) > 0.0:
                lines.append("the map's own error is in the mass variance, not its fitted vehicle values' "
                             "(no mass.torque_model_covariance: run calibrate again to write it)")
            else:
                lines.append("the map is taken as exact in the mass variance (no calibration error "
                             "given: run calibrate again to write it)")
        else:
            hint = ""
            if load and engine_speed and not regression:
                hint = (" (engine_load and engine speed are reported: `vehicle-estimation calibrate` "
                        "fits mass.torque_regression for method rls)")
            elif load and engine_speed and method != "rls":
                hint = " (the torque regression of engine_load + engine speed is used by method rls only)"
            lines.append(f"no propulsion force: the mass stays at its prior{hint}")
        undriven = {"front": ("wheel_rl", "wheel_rr"), "rear": ("wheel_fl", "wheel_fr")}.get(
            str(ms.get("vehicle.driven_axle", "front")), topics.WHEEL_JOINTS)
        undriven_ok = all(wheel[w] for w in undriven)
        source = str(ms.get("speed_source"))
        if source == "fusion" and fusion_ok:
            speed = "speed from the fusion odometry"
        elif source == "vehicle_state" and state_vx in ("wheels", "speed", "dead_reckoned"):
            speed = "speed from the vehicle state's vx" + (" (dead-reckoned: drifts)" if state_vx == "dead_reckoned" else "")
        elif source == "wheel_speed" and undriven_ok:
            speed = "speed from the undriven wheels"
        elif have_speed:
            speed = f"speed from vehicle/speed (no {source.replace('_', ' ')} speed)"
        else:
            speed = None
        accel_src = str(ms.get("accel_source"))
        if method == "ta_aekf":       # it predicts a_x from the force (Eq. 14) and fits it to the speed
            accel = "acceleration predicted from the force, checked against the speed"
        elif accel_src in ("auto", "wheel_speed") and undriven_ok:
            accel = "acceleration from the undriven wheels"
        elif accel_src == "wheel_speed":
            accel = None
        elif accel_src == "vehicle_state" and have_imu:
            accel = "acceleration from the vehicle state's vx" + (
                " (dead-reckoned: drifts)" if state_vx == "dead_reckoned" else "")
        elif accel_src in ("auto", "imu") and fusion_ok:
            accel = "acceleration from the IMU with the fusion bias"
        else:
            accel = None
        if speed is None or accel is None:
            missing = " and ".join(w for w, v in (("speed", speed), (f"acceleration ({accel_src})", accel)) if v is None)
            lines.append(f"no {missing}: the mass stays at its prior")
        else:
            lines.append(f"{speed}; {accel}")
        needs_slope = _truthy(ms.get("require_slope", True))
        if needs_slope and not slope_ok:
            lines.append("no converged road slope (require_slope): the mass stays at its prior")
        if have_js and any(_reported(inputs, JS, w, "effort") for w in topics.WHEEL_JOINTS):
            lines.append("brake torque from the wheels' effort")
        else:
            lines.append("no brake torque: ta_aekf uses only samples with a positive drive force"
                         if method == "ta_aekf" else
                         "no brake torque: braking is not seen (rls may take braking samples)")
        if force is None or speed is None or accel is None or (needs_slope and not slope_ok):
            prior += MASS_OUTPUTS
        nodes["mass"] = {"needs": "vehicle/powertrain", "method": method, "force": force, "lines": lines}
    return {"nodes": nodes, "empty_outputs": [t for t in ALL_OUTPUTS if t in empty],
            "prior_outputs": [t for t in ALL_OUTPUTS if t in prior and t not in empty]}


def _truthy(value: Any) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes", "on")
    return bool(value)
