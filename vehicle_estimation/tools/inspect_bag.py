"""``vehicle-estimation inspect BAG``: what a bag holds and what the nodes will make of it.

For a user who just brought their own bag (MCAP or sqlite3 rosbag2, or a ROS 1 ``.bag``)::

    vehicle-estimation inspect BAG [--vehicle V] [--params P ...] [--remap FROM:=TO ...] [--json]

1. Per contract input topic (:data:`vehicle_estimation.topics.INPUT_TOPICS`): present or
   missing, message type (warned when it is not the contract's), count, mean rate, first and
   last header stamp and log time, out-of-order and duplicated header stamps, frame_id(s);
   for the JointState topics which joints report which entries (NaN = not reported), for
   ``gnss/fix`` the share without a fix. Every other topic is listed as ignored (ground truth
   as used by ``report``).
2. Per node, the method and the fallbacks that will run with the layered parameters.
3. Which outputs will stay empty (or that every output will be published).

Header stamps are read for every message (for rosbag2's CDR straight from the bytes: int32
sec and uint32 nanosec right after the 4-byte encapsulation header, then the frame_id); the
content checks deserialize at most :data:`MAX_SAMPLES` messages per topic (every k-th), so an
hour of 200 Hz IMU costs a pass over the file and no more. ``replay`` prints the same summary
(:func:`summarize`, :func:`format_summary`) before it starts.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vehicle_estimation import topics
from vehicle_estimation.nodes import PIPELINE
from vehicle_estimation.tools.report import json_safe
from vehicle_estimation.vehicle import merge_ros_parameters

#: Content checks deserialize at most this many messages of a topic (every k-th).
MAX_SAMPLES = 2000
#: IMU / speed messages read from the start of the bag for the alignment check.
START_IMU_SAMPLES = 400
START_SPEED_SAMPLES = 200

NODES = tuple(spec.name for spec in PIPELINE)

#: The contract's joints and the entries of each that the nodes read (see the README's Inputs).
CONTRACT_JOINTS = {
    topics.JOINT_STATES: {
        **{w: {"velocity": "wheel speed", "effort": "brake torque"} for w in topics.WHEEL_JOINTS},
        topics.STEERING_JOINT: {"position": "steering-wheel angle"},
    },
    topics.POWERTRAIN: {
        topics.ENGINE_JOINT: {"velocity": "engine speed", "effort": "engine torque"},
        topics.ENGINE_LOAD_JOINT: {"position": "engine load"},
        topics.GEAR_JOINT: {"position": "gear"},
        topics.DRIVE_JOINT: {"effort": "drive force"},
    },
}

#: Node parameter defaults, as the nodes declare them (a test checks them against the source):
#: ``nodes/slope_node.py`` (``method``), ``nodes/state_node.py`` (``filter``,
#: ``speed_fallback``), ``nodes/mass_node.py`` (``method``, ``accel_source``,
#: ``speed_source``, ``require_slope``). The ``fusion.*``, ``mass.*`` and ``vehicle.*``
#: defaults come from their config dataclasses (:func:`_dataclass_defaults`).
NODE_DEFAULTS: dict[str, dict[str, Any]] = {
    "fusion": {},
    "road_slope": {"method": "auto"},
    "vehicle_state": {"filter": "vbackf", "speed_fallback": True},
    "mass": {"method": "ffrls", "accel_source": "auto", "speed_source": "fusion", "require_slope": True},
}

FUSION_OUTPUTS = (topics.ODOMETRY, topics.IMU_COMPENSATED, topics.IMU_BIAS, topics.FUSION_GRADE)
SLOPE_OUTPUTS = (topics.ROAD_SLOPE, topics.ROAD_SLOPE_STAMPED)
STATE_OUTPUTS = (topics.VEHICLE_STATE, topics.SIDESLIP, topics.SIDESLIP_STAMPED)
MASS_OUTPUTS = (topics.MASS, topics.MASS_STAMPED)
ALL_OUTPUTS = FUSION_OUTPUTS + SLOPE_OUTPUTS + STATE_OUTPUTS + MASS_OUTPUTS


class InspectError(Exception):
    """A bag, params file or remap that cannot be used (the message says which)."""


# ------------------------------------------------------------------------------ parameters
def _dataclass_defaults() -> dict[str, dict[str, Any]]:
    """``fusion.*``, ``mass.*`` and ``vehicle.*`` defaults from the cores' config dataclasses."""
    import dataclasses

    from vehicle_estimation.core.esekf import FusionConfig
    from vehicle_estimation.core.mass_rls import MassRLSConfig
    from vehicle_estimation.vehicle import VehicleParams

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


# ------------------------------------------------------------------------------ reading

def parse_remaps(items: list[str] | None) -> dict[str, str]:
    """``["FROM:=TO", ...]`` -> ``{FROM: TO}`` as written (see :func:`topics.bag_to_contract`)."""
    out = {}
    for item in items or []:
        try:
            src, dst = topics.parse_remap(item)
        except ValueError as exc:
            raise InspectError(f"--remap: {exc}") from exc
        out[src] = dst
    return out


def _cdr_header(raw: memoryview | bytes) -> tuple[float, str]:
    """(stamp [s], frame_id) of a CDR-serialized message that starts with a std_msgs/Header."""
    order = "<" if raw[1] & 1 else ">"          # encapsulation: 0x0001 CDR_LE, 0x0000 CDR_BE
    sec, nsec, length = struct.unpack_from(order + "iII", raw, 4)
    frame = bytes(raw[16:16 + max(length - 1, 0)]).decode("utf-8", "replace") if length else ""
    return sec + nsec * 1e-9, frame


class _TopicStats:
    def __init__(self, contract: str) -> None:
        self.contract = contract
        self.bag_topics: set[str] = set()
        self.types: set[str] = set()
        self.count = 0
        self.stamps: list[float] = []
        self.first_log = math.inf
        self.last_log = -math.inf
        self.frames: dict[str, int] = {}
        self.unreadable = 0
        self.sampled = 0
        # JointState: joint -> field -> [messages with the joint, finite values]
        self.joints: dict[str, dict[str, list[int]]] = {}
        self.malformed = 0
        # NavSatFix
        self.no_fix = 0
        # start-of-bag samples for the alignment check
        self.start_values: list[Any] = []

    @property
    def type_ok(self) -> bool:
        return self.types == {topics.INPUT_TYPES[self.contract]}


def _joint_sample(stats: _TopicStats, msg: Any) -> None:
    names = list(msg.name)
    n = len(names)
    arrays = {}
    for field in ("position", "velocity", "effort"):
        values = np.asarray(getattr(msg, field), dtype=float)
        if values.size not in (0, n):
            stats.malformed += 1
            return
        arrays[field] = values if values.size else np.full(n, np.nan)
    for i, name in enumerate(names):
        entry = stats.joints.setdefault(name, {f: [0, 0] for f in arrays})
        for field, values in arrays.items():
            entry[field][0] += 1
            entry[field][1] += int(math.isfinite(values[i]))


def _sample_content(stats: _TopicStats, msg: Any) -> None:
    stats.sampled += 1
    if stats.contract in (topics.JOINT_STATES, topics.POWERTRAIN):
        _joint_sample(stats, msg)
    elif stats.contract == topics.GNSS:
        ok = msg.status.status >= 0 and math.isfinite(msg.latitude) and math.isfinite(msg.longitude)
        stats.no_fix += int(not ok)


def _start_value(stats: _TopicStats, msg: Any) -> None:
    if stats.contract == topics.IMU:
        a, w = msg.linear_acceleration, msg.angular_velocity
        stats.start_values.append((a.x, a.y, a.z, w.x, w.y, w.z))
    elif stats.contract == topics.SPEED:
        stats.start_values.append(msg.twist.twist.linear.x)


def _read_bag(bag: Path, remaps: dict[str, str]) -> dict[str, Any]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bag = Path(bag)
    if not bag.exists():
        raise InspectError(f"no bag at {bag}")
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except Exception as exc:  # rosbags raises its own error types per format
        raise InspectError(f"cannot open {bag} as a bag: {exc}") from exc
    try:
        is2 = bool(getattr(reader, "is2", True))
        contract = {t: _TopicStats(t) for t in topics.INPUT_TOPICS}
        used, others = [], {}
        for conn in reader.connections:
            name = remaps.get(topics.relative(conn.topic), topics.relative(conn.topic))
            if name in contract:
                stats = contract[name]
                stats.bag_topics.add(conn.topic)
                stats.types.add(conn.msgtype)
                used.append(conn)
            else:
                entry = others.setdefault(conn.topic, {"topic": conn.topic, "types": set(), "count": 0})
                entry["types"].add(conn.msgtype)
                entry["count"] += int(conn.msgcount or 0)
        totals = {t: sum(int(c.msgcount or 0) for c in used if remaps.get(topics.relative(c.topic), topics.relative(c.topic)) == t)
                  for t in contract}
        every = {t: max(1, math.ceil(totals[t] / MAX_SAMPLES)) for t in contract}
        by_conn = {c.id: contract[remaps.get(topics.relative(c.topic), topics.relative(c.topic))] for c in used}
        cdr = {c.id: is2 and getattr(c.ext, "serialization_format", "cdr") == "cdr" for c in used}
        contract_ok = {c.id: c.msgtype == topics.INPUT_TYPES[by_conn[c.id].contract] for c in used}
        for conn, log_ns, raw in reader.messages(connections=used) if used else ():
            stats = by_conn[conn.id]
            index = stats.count
            stats.count += 1
            t_log = log_ns * 1e-9
            stats.first_log = min(stats.first_log, t_log)
            stats.last_log = max(stats.last_log, t_log)
            content = contract_ok[conn.id] and (
                (stats.contract in (topics.JOINT_STATES, topics.POWERTRAIN, topics.GNSS)
                 and index % every[stats.contract] == 0)
                or (stats.contract == topics.IMU and index < START_IMU_SAMPLES)
                or (stats.contract == topics.SPEED and index < START_SPEED_SAMPLES))
            msg = None
            try:
                if cdr[conn.id] and not content:
                    stamp, frame = _cdr_header(raw)
                else:
                    msg = reader.deserialize(raw, conn.msgtype)
                    header = msg.header
                    stamp, frame = header.stamp.sec + header.stamp.nanosec * 1e-9, header.frame_id
            except Exception:  # noqa: BLE001 -- not a stamped message, truncated, a foreign type
                stats.unreadable += 1
                continue
            stats.stamps.append(stamp)
            stats.frames[frame] = stats.frames.get(frame, 0) + 1
            if msg is not None and content:
                if stats.contract in (topics.IMU, topics.SPEED):
                    _start_value(stats, msg)
                else:
                    _sample_content(stats, msg)
        storage = "rosbag2" if is2 else "ROS 1 bag"
        if is2:
            ids = {getattr(c.ext, "serialization_format", "cdr") for c in reader.connections}
            storage += f" ({', '.join(sorted(ids))})"
        start, end = reader.start_time * 1e-9, reader.end_time * 1e-9
    finally:
        reader.close()
    return {"storage": storage, "start": start, "end": end, "contract": contract, "others": others}


def _topic_summary(stats: _TopicStats) -> dict[str, Any]:
    present = stats.count > 0 or bool(stats.bag_topics)
    out: dict[str, Any] = {"topic": stats.contract, "present": present,
                           "expected_type": topics.INPUT_TYPES[stats.contract]}
    if not present:
        return out
    s = np.asarray(stats.stamps, dtype=float)
    out.update({
        "bag_topics": sorted(stats.bag_topics),
        "types": sorted(stats.types),
        "type_ok": stats.type_ok,
        "count": stats.count,
        "unreadable": stats.unreadable,
        "first_log": _num(stats.first_log), "last_log": _num(stats.last_log),
        "frame_ids": dict(sorted(stats.frames.items())),
    })
    if s.size:
        span = float(s.max() - s.min())
        out.update({
            "first_stamp": float(s.min()), "last_stamp": float(s.max()),
            "rate_hz": (s.size - 1) / span if s.size > 1 and span > 0 else None,
            "out_of_order": int(np.sum(s[1:] < np.maximum.accumulate(s)[:-1])) if s.size > 1 else 0,
            "duplicates": int(s.size - np.unique(s).size),
            "stamp_minus_log_s": float(s[0] - stats.first_log),
        })
    if stats.contract in CONTRACT_JOINTS and stats.type_ok:
        joints = {}
        for name, fields in sorted(stats.joints.items()):
            joints[name] = {f: (finite / seen if seen else 0.0) for f, (seen, finite) in fields.items()}
        out["sampled"] = stats.sampled
        out["malformed"] = stats.malformed
        out["joints"] = joints
    if stats.contract == topics.GNSS and stats.type_ok:
        out["sampled"] = stats.sampled
        out["no_fix_share"] = stats.no_fix / stats.sampled if stats.sampled else None
    return out


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


# ------------------------------------------------------------------------------ node plan
def _reported(inputs: dict[str, Any], topic: str, joint: str, field: str) -> bool:
    info = inputs[topic]
    return bool(info.get("joints", {}).get(joint, {}).get(field, 0.0) > 0.0)


def _usable(inputs: dict[str, Any], topic: str) -> bool:
    info = inputs[topic]
    return bool(info["present"] and info.get("type_ok") and info.get("first_stamp") is not None)


def _alignment(stats: _TopicStats | None, speed: _TopicStats | None, fusion: dict[str, Any],
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


def _plan(inputs: dict[str, Any], params: dict[str, dict[str, Any]],
          imu: _TopicStats | None, speed_stats: _TopicStats | None) -> dict[str, Any]:
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
                         "position covariance grows")
        line, fusion_ok = _alignment(imu, speed_stats, params["fusion"], have_speed)
        lines.append(line)
        lines.append("CAN speed aids the filter (vehicle/speed)" if have_speed
                     else "no vehicle/speed: only the vehicle constraints bound the velocity")
    if not fusion_ok:
        empty += FUSION_OUTPUTS
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
        if rear_wheels or all_wheels:
            lines.append("vx from the wheel speeds")
            state_vx = "wheels"
        elif have_speed and _truthy(vs.get("speed_fallback", True)):
            lines.append("no wheel speeds: vx from vehicle/speed (automatic fallback, speed_fallback)")
            state_vx = "speed"
        else:
            hint = (" (vehicle/speed is there: set vehicle_state speed_fallback: true to use it)"
                    if have_speed else "")
            lines.append(f"no wheel speeds: vx dead-reckoned from ax (drifts){hint}")
            state_vx = "dead_reckoned"
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
        if accel_src in ("auto", "wheel_speed") and undriven_ok:
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
            lines.append("no brake torque: braking is not seen (rls may take braking samples)")
        if force is None or speed is None or accel is None or (needs_slope and not slope_ok):
            prior += MASS_OUTPUTS
        nodes["mass"] = {"needs": "vehicle/powertrain", "method": method, "force": force, "lines": lines}
    return {"nodes": nodes, "empty_outputs": [t for t in ALL_OUTPUTS if t in empty],
            "prior_outputs": [t for t in ALL_OUTPUTS if t in prior and t not in empty]}


def _truthy(value: Any) -> bool:
    if isinstance(value, str):
        return value.strip().lower() in ("true", "1", "yes", "on")
    return bool(value)


# ------------------------------------------------------------------------------ public API
def summarize(bag: Path, params_files: list[Path], remaps: dict[str, str]) -> dict:
    """Everything ``inspect`` prints, as plain JSON-able data (see :func:`format_summary`)."""
    try:
        remaps = topics.bag_to_contract((remaps or {}).items(), topics.INPUT_TOPICS)
    except ValueError as exc:
        raise InspectError(f"--remap: {exc}") from None
    params = layered_params([Path(p) for p in params_files])
    data = _read_bag(Path(bag), remaps)
    contract = data["contract"]
    inputs = {t: _topic_summary(contract[t]) for t in topics.INPUT_TOPICS}
    others = []
    missing = [t for t in topics.INPUT_TOPICS if not inputs[t]["present"]]
    for topic, entry in sorted(data["others"].items()):
        gt = topics.relative(topic) in topics.GROUND_TRUTH_TOPICS or topics.relative(topic).startswith("ground_truth/")
        hint = None
        if not gt:
            # a missing input under a namespace (/car1/imu/data), or the only topic of its type
            hint = next((t for t in missing if topics.relative(topic).endswith("/" + t)), None)
            by_type = [t for t in missing if {topics.INPUT_TYPES[t]} == entry["types"]]
            same = [o for o, e in data["others"].items() if e["types"] == entry["types"]]
            if hint is None and len(by_type) == 1 and len(same) == 1:
                hint = by_type[0]
        others.append({"topic": topic, "types": sorted(entry["types"]), "count": entry["count"],
                       "role": "ground truth, used by report" if gt else "ignored",
                       "remap_hint": f"{hint}:={topic}" if hint else None})
    plan = _plan(inputs, params, contract[topics.IMU], contract[topics.SPEED])
    shown = ("method", "filter", "speed_fallback", "accel_source", "speed_source", "require_slope",
             "mass.torque_regression", "vehicle.name", "vehicle.driven_axle", "vehicle.gear_ratios")
    return {
        "bag": str(bag),
        "storage": data["storage"],
        "log_time": {"start": data["start"], "end": data["end"], "duration_s": data["end"] - data["start"]},
        "params_files": [str(p) for p in params_files],
        "remaps": remaps,
        "inputs": inputs,
        "other_topics": others,
        "params": {node: {k: json_safe(v) for k, v in params[node].items() if k in shown} for node in NODES},
        **plan,
    }


def _pct(x: float) -> str:
    return f"{100.0 * x:.0f} %"


def _format_topic(info: dict[str, Any]) -> list[str]:
    name = info["topic"]
    if not info["present"]:
        return [f"  {name}: MISSING (expected {info['expected_type']})"]
    shown = ", ".join(t for t in info["bag_topics"] if topics.relative(t) != name)
    head = f"  {name}" + (f" (from {shown})" if shown else "") + f": {info['count']} messages, "
    head += ", ".join(info["types"])
    lines = [head]
    if not info["type_ok"]:
        lines.append(f"    WARNING: the contract's type is {info['expected_type']}; the nodes will not read it")
    if info.get("first_stamp") is None:
        lines.append("    no readable header stamps")
    else:
        rate = f"{info['rate_hz']:.1f} Hz" if info.get("rate_hz") else "rate unknown"
        lines.append(f"    {rate} mean; header stamps {info['first_stamp']:.3f} .. {info['last_stamp']:.3f} s, "
                     f"log time {info['first_log']:.3f} .. {info['last_log']:.3f} s")
        if abs(info["stamp_minus_log_s"]) > 1.0:
            lines.append(f"    note: header stamps are {info['stamp_minus_log_s']:+.3f} s off the log time")
        order = f"{info['out_of_order']} out of order, {info['duplicates']} duplicated stamps"
        frames = ", ".join(f"'{f}' ({n})" if len(info["frame_ids"]) > 1 else f"'{f}'"
                           for f, n in info["frame_ids"].items())
        lines.append(f"    {order}; frame_id {frames}")
    if info.get("unreadable"):
        lines.append(f"    {info['unreadable']} messages without a readable header")
    if "joints" in info:
        wanted = CONTRACT_JOINTS[name]
        lines.append(f"    joints (in {info['sampled']} sampled messages): "
                     + (", ".join(info["joints"]) if info["joints"] else "none"))
        for joint, fields in wanted.items():
            seen = info["joints"].get(joint)
            if seen is None:
                lines.append(f"      {joint}: not in the messages ({', '.join(fields.values())} not reported)")
                continue
            parts = []
            for field, meaning in fields.items():
                share = seen.get(field, 0.0)
                state = "finite" if share >= 0.999 else (f"finite in {_pct(share)}" if share > 0 else "NaN (not reported)")
                parts.append(f"{field} ({meaning}) {state}")
            lines.append(f"      {joint}: " + ", ".join(parts))
        extra = sorted(set(info["joints"]) - set(wanted))
        if extra:
            lines.append(f"      not in the contract, ignored: {', '.join(extra)}")
        if info.get("malformed"):
            lines.append(f"      {info['malformed']} sampled messages with arrays that do not match the names")
    if info.get("no_fix_share") is not None:
        lines.append(f"    no fix (status < 0) in {_pct(info['no_fix_share'])} of {info['sampled']} sampled messages")
    return lines


def format_summary(summary: dict) -> str:
    """The summary in plain words, one topic or node aspect per line."""
    lt = summary["log_time"]
    out = [(f"bag {summary['bag']}: {summary['storage']}, log time {lt['start']:.3f} .. {lt['end']:.3f} s "
            f"({lt['duration_s']:.1f} s)")]
    if summary["params_files"]:
        out.append("params: " + " < ".join(Path(p).name for p in summary["params_files"])
                   + " (a later file overrides)")
    if summary["remaps"]:
        out.append("remaps: " + ", ".join(f"{v}:={k}" for k, v in summary["remaps"].items()))
    out.append("")
    out.append("inputs:")
    for topic in topics.INPUT_TOPICS:
        out += _format_topic(summary["inputs"][topic])
    if summary["other_topics"]:
        out.append("other topics:")
        for entry in summary["other_topics"]:
            line = f"  {entry['topic']}: {entry['count']} messages, {', '.join(entry['types'])}: {entry['role']}"
            if entry.get("remap_hint"):
                line += f" (a contract input? --remap {entry['remap_hint']})"
            out.append(line)
    out.append("")
    out.append("nodes:")
    for node in NODES:
        info = summary["nodes"][node]
        out.append(f"  {node} (needs {info['needs']}):")
        out += [f"    - {line}" for line in info["lines"]]
    out.append("")
    if summary["prior_outputs"]:
        out.append("will stay at the prior: " + ", ".join(summary["prior_outputs"]))
    if summary["empty_outputs"]:
        out.append("will stay empty: " + ", ".join(summary["empty_outputs"]))
    else:
        out.append("every output will be published")
    return "\n".join(out)


# ------------------------------------------------------------------------------ command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag2 directory (MCAP or sqlite3) or ROS 1 .bag")
    parser.add_argument("--vehicle", default="sedan_d_class",
                        help="vehicle params file or name in params/ (default: sedan_d_class)")
    parser.add_argument("--params", action="append", default=None,
                        help="node params file or name in params/ (default: estimation); repeat to "
                             "layer files, a later file overriding an earlier one")
    parser.add_argument("--remap", action="append", default=None, metavar="FROM:=TO",
                        help="read a bag topic as a contract topic, CONTRACT:=BAG_TOPIC as for replay (repeatable)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.paths import params_file
    try:
        files = [params_file(args.vehicle)] + [params_file(n) for n in (args.params or ["estimation"])]
        summary = summarize(Path(args.bag), files, parse_remaps(args.remap))
    except (InspectError, FileNotFoundError) as exc:
        print(f"inspect: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(json_safe(summary), indent=2, allow_nan=False))
    else:
        print(format_summary(summary))
    return 0
