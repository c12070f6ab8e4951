"""What a bag holds, per contract input topic: one pass over the file, content sampled.

Header stamps are read for every message (for rosbag2's CDR straight from the bytes: int32
sec and uint32 nanosec right after the 4-byte encapsulation header, then the frame_id); the
content checks deserialize at most :data:`MAX_SAMPLES` messages per topic (every k-th, and the
first IMU and speed messages for the alignment check), so an hour of 200 Hz IMU costs a pass
over the file and no more. :func:`read_bag` collects,
:func:`topic_summary` turns one topic's statistics into plain data for ``inspect``.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from vehicle_estimation.contract import topics

#: Content checks deserialize at most this many messages of a topic (every k-th).
MAX_SAMPLES = 2000
#: IMU / speed messages read from the start of the bag for the alignment check.
START_IMU_SAMPLES = 400
START_SPEED_SAMPLES = 200

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


class InspectError(Exception):
    """A bag, params file or remap that cannot be used (the message says which)."""


def _cdr_header(raw: memoryview | bytes) -> tuple[float, str]:
    """(stamp [s], frame_id) of a CDR-serialized message that starts with a std_msgs/Header."""
    order = "<" if raw[1] & 1 else ">"          # encapsulation: 0x0001 CDR_LE, 0x0000 CDR_BE
    sec, nsec, length = struct.unpack_from(order + "iII", raw, 4)
    frame = bytes(raw[16:16 + max(length - 1, 0)]).decode("utf-8", "replace") if length else ""
    return sec + nsec * 1e-9, frame


class TopicStats:
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
        # vehicle/joint_states: stamps of the sampled messages with both rear wheel speeds (what
        # the state filters read vx from), and every how many messages one is sampled
        self.rear_wheel_stamps: list[float] = []
        self.sample_every = 1
        self.malformed = 0
        # NavSatFix
        self.no_fix = 0
        # start-of-bag samples for the alignment check
        self.start_values: list[Any] = []
        # imu/data and vehicle/speed: (stamp, values...) of every sample_every-th message over
        # the whole bag, for the check of the IMU's yaw against the car's accelerations
        self.samples: list[tuple[float, ...]] = []

    @property
    def type_ok(self) -> bool:
        return self.types == {topics.INPUT_TYPES[self.contract]}


def _joint_sample(stats: TopicStats, msg: Any) -> None:
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
    if stats.contract == topics.JOINT_STATES:
        rear = [names.index(w) for w in topics.WHEEL_JOINTS[2:] if w in names]
        if len(rear) == 2 and np.isfinite(arrays["velocity"][rear]).all():
            stats.rear_wheel_stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def _sample_content(stats: TopicStats, msg: Any) -> None:
    stats.sampled += 1
    if stats.contract in (topics.JOINT_STATES, topics.POWERTRAIN):
        _joint_sample(stats, msg)
    elif stats.contract == topics.GNSS:
        ok = msg.status.status >= 0 and math.isfinite(msg.latitude) and math.isfinite(msg.longitude)
        stats.no_fix += int(not ok)


def _motion_sample(stats: TopicStats, msg: Any, stamp: float, index: int) -> None:
    """imu/data's specific force and rate, vehicle/speed's speed: at the start (the alignment
    check) and every ``sample_every``-th message (the yaw check)."""
    if stats.contract == topics.IMU:
        a, w = msg.linear_acceleration, msg.angular_velocity
        values: tuple[float, ...] = (a.x, a.y, a.z, w.x, w.y, w.z)
    else:
        values = (msg.twist.twist.linear.x,)
    if index < (START_IMU_SAMPLES if stats.contract == topics.IMU else START_SPEED_SAMPLES):
        stats.start_values.append(values if stats.contract == topics.IMU else values[0])
    if index % stats.sample_every == 0:
        stats.samples.append((stamp, *values))


def read_bag(bag: Path, remaps: dict[str, str]) -> dict[str, Any]:
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
        contract = {t: TopicStats(t) for t in topics.INPUT_TOPICS}
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
        for stats in contract.values():
            stats.sample_every = every[stats.contract]
        for conn, log_ns, raw in reader.messages(connections=used) if used else ():
            stats = by_conn[conn.id]
            index = stats.count
            stats.count += 1
            t_log = log_ns * 1e-9
            stats.first_log = min(stats.first_log, t_log)
            stats.last_log = max(stats.last_log, t_log)
            content = contract_ok[conn.id] and (
                index % every[stats.contract] == 0
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
                    _motion_sample(stats, msg, stamp, index)
                elif index % every[stats.contract] == 0:
                    _sample_content(stats, msg)
        storage = "rosbag2" if is2 else "ROS 1 bag"
        if is2:
            ids = {getattr(c.ext, "serialization_format", "cdr") for c in reader.connections}
            storage += f" ({', '.join(sorted(ids))})"
        start, end = reader.start_time * 1e-9, reader.end_time * 1e-9
    finally:
        reader.close()
    return {"storage": storage, "start": start, "end": end, "contract": contract, "others": others}


def topic_summary(stats: TopicStats) -> dict[str, Any]:
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
