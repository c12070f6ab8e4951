"""Rewrite a bag into the variants users bring: other start time, rates, topics, joints, format.

The replay must accept any bag a user records, and the tests and the validation-set script
need such bags without a real car: :func:`rewrite_bag` copies a bag (MCAP or sqlite3
rosbag2, or ROS 1, whatever ``rosbags.highlevel.AnyReader`` reads) into a new one, shifted to
start at 0 s, cut, with topics left out or renamed, joints removed from every JointState, a
topic thinned to a lower rate, or written in another storage format (ROS 1 included).

Messages are copied byte for byte when nothing in them changes and the format stays; else
they are deserialised, converted to the target's types (:mod:`msgconvert`: ROS 2 Jazzy for
rosbag2, ROS 1 Noetic for a ``.bag``), edited and serialised again.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores
from rosbags.typesys.base import Nodetype, normalize_fieldname
from rosbags.typesys.store import Typestore

from vehicle_estimation.contract import topics
from vehicle_estimation.io.msgconvert import (
    cached_typestore,
    convert_message,
    jazzy_typestore,
)

Storage = Literal["mcap", "sqlite3", "ros1"]
STORAGES = ("mcap", "sqlite3", "ros1")
HEADER = "std_msgs/msg/Header"
JOINT_STATE = "sensor_msgs/msg/JointState"
JOINT_ARRAYS = ("position", "velocity", "effort")


def noetic_typestore() -> Typestore:
    """The ROS 1 Noetic typestore, whose msgdefs and MD5 sums ROS 1 tools expect in a ``.bag``."""
    return cached_typestore(Stores.ROS1_NOETIC)



def _check_destination(dst: Path, storage: str) -> None:
    if storage not in STORAGES:
        raise ValueError(f"storage {storage!r} is not one of {', '.join(STORAGES)}")
    if dst.exists():
        raise FileExistsError(f"{dst} exists already; rewrite_bag never overwrites a bag")
    # AnyReader (and ros2 bag / rosbag) decide the format by the name: a '.bag' is ROS 1.
    if storage == "ros1" and dst.suffix != ".bag":
        raise ValueError(f"{dst}: a ROS 1 bag must be a file ending in '.bag', or it will not be read as one")
    if storage != "ros1" and dst.suffix == ".bag":
        raise ValueError(f"{dst}: a rosbag2 directory must not end in '.bag' (it would be read as a ROS 1 "
                         f"bag file); name it e.g. {dst.with_suffix('')}")


def _check_topics(what: str, names: Iterable[str], in_bag: set[str]) -> None:
    # A typo in a topic name would otherwise silently leave the bag unchanged.
    missing = sorted("/" + topics.relative(n) for n in names if topics.relative(n) not in in_bag)
    if missing:
        raise ValueError(f"{what}: topic(s) {', '.join(missing)} not in the bag "
                         f"(it has {', '.join('/' + t for t in sorted(in_bag))})")


def _has_header(ts: Typestore, msgtype: str, seen: dict[str, bool]) -> bool:
    """Whether ``msgtype`` contains a std_msgs/Header anywhere (so a time shift touches it)."""
    if msgtype not in seen:
        seen[msgtype] = False     # recursion guard
        found = False
        for _, (kind, rest) in ts.fielddefs[msgtype][1]:
            sub = rest[0] if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (kind, rest)
            if sub[0] == Nodetype.NAME and (sub[1] == HEADER or _has_header(ts, sub[1], seen)):
                found = True
        seen[msgtype] = found
    return seen[msgtype]


def _shift_headers(msg: Any, ts: Typestore, msgtype: str, offset_ns: int, where: str) -> None:
    """Add ``offset_ns`` to every header stamp in ``msg`` (in place, nested ones too)."""
    for name, (kind, rest) in ts.fielddefs[msgtype][1]:
        attr = normalize_fieldname(name)
        if kind == Nodetype.NAME:
            items, subtype = [getattr(msg, attr)], rest
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and rest[0][0] == Nodetype.NAME:
            items, subtype = getattr(msg, attr), rest[0][1]
        else:
            continue
        for item in items:
            if subtype == HEADER:
                stamp = item.stamp
                ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) + offset_ns
                if ns < 0:
                    raise ValueError(
                        f"{where}: header stamp {stamp.sec}.{stamp.nanosec:09d} s would be negative after the "
                        f"shift by {offset_ns * 1e-9:.9f} s (its header is older than the first log time); "
                        "choose a later start_at_s")
                stamp.sec, stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
            else:
                _shift_headers(item, ts, subtype, offset_ns, where)


def _drop_joints(msg: Any, drop: set[str], where: str) -> None:
    """Remove the named joints of a JointState in place, keeping its arrays aligned with ``name``."""
    names = list(msg.name)
    keep = np.array([n not in drop for n in names], dtype=bool)
    if keep.all():
        return
    for attr in JOINT_ARRAYS:
        values = np.asarray(getattr(msg, attr))
        if values.size == 0:          # an empty array means "not reported": stays empty
            continue
        if values.size != len(names):
            raise ValueError(f"{where}: JointState has {len(names)} names but {values.size} {attr} values, "
                             "so the joints to drop cannot be matched to its entries")
        setattr(msg, attr, values[keep])
    msg.name = [n for n, k in zip(names, keep) if k]


def rewrite_bag(src: Path | str, dst: Path | str, *, start_at_s: float | None = None,
                duration_s: float | None = None, drop_topics: Iterable[str] = (),
                drop_joints: Iterable[str] = (), keep_every: Mapping[str, int] | None = None,
                rename: Mapping[str, str] | None = None, storage: Storage = "mcap",
                edit: Mapping[str, Callable[[Any, int], None]] | None = None) -> Path:
    """Copy the bag ``src`` to a new bag ``dst``, changed as asked; returns ``dst``.

    * ``start_at_s``: shift every log time and every header stamp by one offset so that the
      first message written is at this time (0.0: a bag "starting at 0 s", as simulators,
      CSV exports and many loggers write them).
    * ``duration_s``: keep only the messages logged within this long after the first one
      (a cheap cut of a long drive).
    * ``drop_topics``: topics left out (with or without the leading '/').
    * ``drop_joints``: joint names removed from every sensor_msgs/JointState, their
      position/velocity/effort entries with them (a vehicle that does not report a signal).
    * ``keep_every``: ``{topic: n}`` keeps the 1st, (n+1)-th, ... message of the topic (a
      lower rate: IMU 200 -> 100 Hz is 2, GNSS 10 -> 1 Hz is 10).
    * ``rename``: ``{old: new}`` writes a topic under another name (a recorder's own names).
    * ``edit``: ``{topic: fn(msg, index)}`` changes each message of the topic in place
      (deserialised; ``index`` counts the topic's messages in ``src`` from 0): added noise,
      a sensor fault.
    * ``storage``: ``"mcap"`` or ``"sqlite3"`` (a rosbag2 directory, ROS 2 Jazzy types) or
      ``"ros1"`` (a ``.bag`` file, ROS 1 Noetic types: a Header gets ``seq`` 0).

    Topic names in the options must be in the bag (a typo raises ``ValueError``), so that a
    mistaken option never yields an unchanged copy.
    """
    src, dst = Path(src), Path(dst)
    _check_destination(dst, storage)
    if start_at_s is not None and not (np.isfinite(start_at_s) and start_at_s >= 0.0):
        raise ValueError(f"start_at_s must be a finite time >= 0 s (ROS time is never negative), got {start_at_s}")
    if duration_s is not None and not (np.isfinite(duration_s) and duration_s > 0.0):
        raise ValueError(f"duration_s must be a finite time > 0 s, got {duration_s}")
    keep_every = {topics.relative(t): n for t, n in (keep_every or {}).items()}
    for topic, n in keep_every.items():
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"keep_every[{topic!r}] must be a whole number >= 1 (keep every n-th message), got {n!r}")
    rename = {topics.relative(old): topics.relative(new) for old, new in (rename or {}).items()}
    if any(not new for new in rename.values()):
        raise ValueError(f"rename: an empty new topic name in {rename}")
    drop_topic_set = {topics.relative(t) for t in drop_topics}
    edits = {topics.relative(t): fn for t, fn in (edit or {}).items()}
    joints_to_drop = set(drop_joints)
    to_ros1 = storage == "ros1"
    dst_ts = noetic_typestore() if to_ros1 else jazzy_typestore()

    with AnyReader([src], default_typestore=jazzy_typestore()) as reader:
        same_family = reader.is2 != to_ros1
        in_bag = {topics.relative(c.topic) for c in reader.connections}
        _check_topics("drop_topics", drop_topic_set, in_bag)
        _check_topics("keep_every", keep_every, in_bag)
        _check_topics("rename", rename, in_bag)
        _check_topics("edit", edits, in_bag)
        kept = [c for c in reader.connections if topics.relative(c.topic) not in drop_topic_set]
        if not kept:
            raise ValueError(f"{src}: no topic left to write (all of {', '.join(sorted(in_bag))} dropped)")
        out_names: dict[str, str] = {}
        for conn in kept:
            name = topics.relative(conn.topic)
            out = rename.get(name, name)
            for other, other_out in out_names.items():
                if other != name and other_out == out:
                    raise ValueError(f"rename: topics {other} and {name} would both be written as /{out}")
            out_names[name] = out
        first = next(iter(reader.messages(connections=kept)), None)
        if first is None:
            raise ValueError(f"{src}: the topics to write hold no message")
        t_first = first[1]
        t_stop = t_first + round(duration_s * 1e9) if duration_s is not None else None
        offset_ns = round(start_at_s * 1e9) - t_first if start_at_s is not None else 0

        writer: Any = Ros1Writer(dst) if to_ros1 else Ros2Writer(
            dst, version=9, storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
        writer.open()
        try:
            out_conns: dict[tuple[str, str], Any] = {}
            by_id: dict[int, Any] = {}
            raw_types: set[str] = set()     # known to the bag only: copied byte for byte
            for conn in kept:
                topic = "/" + out_names[topics.relative(conn.topic)]
                key = (topic, conn.msgtype)
                if key not in out_conns:
                    conn_ts = dst_ts
                    if conn.msgtype not in dst_ts.fielddefs:
                        if not same_family:
                            raise ValueError(f"topic {conn.topic}: type {conn.msgtype} is not a ROS "
                                             f"{'1 Noetic' if to_ros1 else '2 Jazzy'} type, so it cannot be converted")
                        conn_ts = reader.typestore
                        raw_types.add(conn.msgtype)
                    out_conns[key] = writer.add_connection(topic, conn.msgtype, typestore=conn_ts)
                by_id[conn.id] = out_conns[key]
            header_cache: dict[str, bool] = {}
            seen: Counter[str] = Counter()
            for conn, timestamp, data in reader.messages(connections=kept):
                if t_stop is not None and timestamp >= t_stop:
                    break
                name = topics.relative(conn.topic)
                index = seen[name]
                seen[name] += 1
                if index % keep_every.get(name, 1):
                    continue
                msgtype = conn.msgtype
                if msgtype in raw_types:
                    if name in edits:
                        raise ValueError(f"edit: topic {conn.topic} has type {msgtype}, known to the bag only")
                    if offset_ns != 0 and _has_header(reader.typestore, msgtype, header_cache):
                        raise ValueError(f"topic {conn.topic}: type {msgtype} is known to the bag only, so its "
                                         "header stamps cannot be shifted; drop the topic or leave start_at_s unset")
                    payload = bytes(data)
                else:
                    edit_joints = bool(joints_to_drop) and msgtype == JOINT_STATE
                    shift = offset_ns != 0 and _has_header(dst_ts, msgtype, header_cache)
                    user_edit = edits.get(name)
                    if same_family and not (edit_joints or shift or user_edit):
                        payload = bytes(data)
                    else:
                        where = f"topic {conn.topic}, message {index}"
                        msg = convert_message(reader.deserialize(data, msgtype), dst_ts, msgtype, where)
                        if shift:
                            _shift_headers(msg, dst_ts, msgtype, offset_ns, where)
                        if edit_joints:
                            _drop_joints(msg, joints_to_drop, where)
                        if user_edit is not None:
                            user_edit(msg, index)
                        payload = bytes(dst_ts.serialize_ros1(msg, msgtype) if to_ros1
                                        else dst_ts.serialize_cdr(msg, msgtype))
                writer.write(by_id[conn.id], timestamp + offset_ns, payload)
        except BaseException:
            # A half-written bag must not be mistaken for a good one.
            writer.close()
            _remove(dst)
            raise
        writer.close()
    return dst


def _remove(path: Path) -> None:
    import shutil
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
