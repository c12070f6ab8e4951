"""`vehicle-estimation inspect BAG`: topics of a bag and what each node will make of it."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.contract import topics
from vehicle_estimation.paths import params_file
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag
from vehicle_estimation.io import inspect_bag
from vehicle_estimation.launcher import node_plan
from vehicle_estimation.io.inspect_bag import InspectError, format_summary, summarize

ROOT = Path(__file__).resolve().parent.parent
TS = get_typestore(Stores.ROS2_JAZZY)


def _copy(src: Path, dst: Path, transform) -> Path:
    """Copy a bag; ``transform(index_in_topic, topic, msgtype, raw)`` -> (topic, raw) or None (drop)."""
    counts: dict[str, int] = {}
    with AnyReader([src], default_typestore=TS) as reader, \
            Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for conn, t, raw in reader.messages():
            i = counts.get(conn.topic, 0)
            counts[conn.topic] = i + 1
            out = transform(i, conn.topic, conn.msgtype, bytes(raw))
            if out is None:
                continue
            topic, data = out
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, conn.msgtype, typestore=TS)
            writer.write(conns[topic], t, data)
    return dst


def _drop_joints(raw: bytes, drop: set[str]) -> bytes:
    msg = TS.deserialize_cdr(raw, "sensor_msgs/msg/JointState")
    keep = [i for i, name in enumerate(msg.name) if name not in drop]
    msg = dataclasses.replace(
        msg, name=[msg.name[i] for i in keep], position=msg.position[keep],
        velocity=msg.velocity[keep], effort=msg.effort[keep])
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("inspect")
    full = write_bag(simulate(dataclasses.replace(scenario_by_name("short"), duration_s=20.0)), root / "full")
    out = {"full": Path(full)}
    out["no_gnss"] = _copy(full, root / "no_gnss",
                           lambda i, topic, typ, raw: None if topic == topics.GNSS else (topic, raw))
    wheels = set(topics.WHEEL_JOINTS)
    out["no_wheels"] = _copy(full, root / "no_wheels", lambda i, topic, typ, raw: (
        topic, _drop_joints(raw, wheels) if topic == topics.JOINT_STATES else raw))
    force = {topics.DRIVE_JOINT, topics.ENGINE_JOINT}
    out["no_force"] = _copy(full, root / "no_force", lambda i, topic, typ, raw: (
        topic, _drop_joints(raw, force) if topic == topics.POWERTRAIN else raw))
    out["renamed"] = _copy(full, root / "renamed", lambda i, topic, typ, raw: (
        "/sensors/imu" if topic == topics.IMU else topic, raw))

    imu_stamps: list[bytes] = []
    with AnyReader([full], default_typestore=TS) as reader:
        conn = [c for c in reader.connections if c.topic == topics.IMU]
        for k, (_, _, raw) in enumerate(reader.messages(connections=conn)):
            if k > 201:
                break
            imu_stamps.append(bytes(raw[4:12]))

    def swap(i, topic, typ, raw):
        if topic == topics.IMU and i in (100, 101):      # two swapped stamps: one out of order
            raw = raw[:4] + imu_stamps[201 - i] + raw[12:]
        if topic == topics.IMU and i == 201:             # a duplicated stamp (== the one before)
            raw = raw[:4] + imu_stamps[200] + raw[12:]
        return topic, raw
    out["swapped"] = _copy(full, root / "swapped", swap)
    return out


def _files(*extra: Path) -> list[Path]:
    return [params_file("sedan_d_class"), params_file("estimation"), *extra]


@pytest.fixture(scope="module")
def full_summary(bags):
    return summarize(bags["full"], _files(), {})


def _node_text(summary, node: str) -> str:
    return "\n".join(summary["nodes"][node]["lines"])


def test_every_topic_present_with_its_rate(full_summary):
    inputs = full_summary["inputs"]
    for topic in topics.INPUT_TOPICS:
        assert inputs[topic]["present"] and inputs[topic]["type_ok"], topic
        assert inputs[topic]["out_of_order"] == 0 and inputs[topic]["duplicates"] == 0
    assert inputs[topics.IMU]["rate_hz"] == pytest.approx(200.0, rel=0.02)
    assert inputs[topics.GNSS]["rate_hz"] == pytest.approx(10.0, rel=0.02)
    assert inputs[topics.SPEED]["rate_hz"] == pytest.approx(100.0, rel=0.02)
    assert inputs[topics.IMU]["count"] == pytest.approx(4001, abs=2)
    assert inputs[topics.IMU]["frame_ids"] == {topics.IMU_FRAME: inputs[topics.IMU]["count"]}
    assert inputs[topics.GNSS]["no_fix_share"] == 0.0
    joints = inputs[topics.JOINT_STATES]["joints"]
    assert joints["wheel_rl"]["velocity"] == 1.0 and joints[topics.STEERING_JOINT]["position"] == 1.0
    assert inputs[topics.POWERTRAIN]["joints"][topics.DRIVE_JOINT]["effort"] == 1.0
    roles = {o["topic"]: o["role"] for o in full_summary["other_topics"]}
    assert roles[topics.GT_MASS] == "ground truth, used by report"
    assert full_summary["empty_outputs"] == []
    text = format_summary(full_summary)
    assert "GNSS-aided; odom = ENU at the first fix" in text
    assert "aligns at standstill" in text
    assert text.splitlines()[-1] == "every output will be published"
    json.dumps(full_summary, allow_nan=False)


def _turned_imu(raw: bytes, C) -> bytes:
    """An imu/data message as an IMU turned by C (imu_link -> base_link) would read it."""
    msg = TS.deserialize_cdr(raw, "sensor_msgs/msg/Imu")
    for field in ("linear_acceleration", "angular_velocity"):
        v = getattr(msg, field)
        v.x, v.y, v.z = (float(x) for x in C.T @ [v.x, v.y, v.z])
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/Imu"))


def test_an_imu_on_its_side_is_named_unless_the_vehicle_file_says_so(bags, tmp_path):
    from vehicle_estimation.estimators.common.rotations import quat_from_euler, quat_to_rotmat

    C = quat_to_rotmat(quat_from_euler(math.pi / 2, 0.0, 0.0))
    bag = _copy(bags["full"], tmp_path / "on_its_side", lambda i, topic, typ, raw: (
        topic, _turned_imu(raw, C) if topic == topics.IMU else raw))
    text = _node_text(summarize(bag, _files(), {}), "fusion")
    assert re.search(r"imu/data reads gravity (8[5-9]|9[0-5]) deg from base_link z", text), text
    assert "mostly on its own y axis" in text
    layer = tmp_path / "on_its_side.yaml"
    layer.write_text("/**:\n  ros__parameters:\n    vehicle.imu_mounting_rpy: [1.5707963267948966, 0.0, 0.0]\n")
    text = _node_text(summarize(bag, _files(layer), {}), "fusion")
    assert "reads gravity" not in text
    assert "IMU mounting: imu_link at roll, pitch, yaw 90.0, 0.0, 0.0 deg in base_link" in text
    assert "reads gravity" not in _node_text(summarize(bags["full"], _files(), {}), "fusion")


@pytest.fixture(scope="module")
def minute_drive(tmp_path_factory) -> Path:
    """The 60-s drive: enough accelerating and turning above walking pace for the yaw check."""
    return Path(write_bag(simulate(scenario_by_name("short")), tmp_path_factory.mktemp("yaw") / "short"))


@pytest.mark.parametrize("yaw_deg", [90.0, 180.0, -25.0])
def test_an_imu_turned_about_z_is_named_from_the_cars_accelerations(minute_drive, tmp_path, yaw_deg):
    """Gravity cannot show a yaw (an IMU facing backwards reads it as a level one does); the car's
    accelerations from vehicle/speed, (dv/dt, v r), can: inspect names the IMU's yaw unless the
    vehicle file gives it."""
    from vehicle_estimation.estimators.common.rotations import rotmat_from_euler

    C = rotmat_from_euler(0.0, 0.0, math.radians(yaw_deg))
    bag = _copy(minute_drive, tmp_path / "turned", lambda i, topic, typ, raw: (
        topic, _turned_imu(raw, C) if topic == topics.IMU else raw))
    text = _node_text(summarize(bag, _files(), {}), "fusion")
    found = re.search(r"horizontal axes are (\d+) deg about base_link z .* IMU yaw of about (-?\d+) deg", text)
    assert found, text
    assert abs(int(found.group(1)) - abs(yaw_deg)) <= 5
    assert abs((int(found.group(2)) - yaw_deg + 180) % 360 - 180) <= 5
    assert "reads gravity" not in text
    layer = tmp_path / "turned.yaml"
    layer.write_text(f"/**:\n  ros__parameters:\n    vehicle.imu_mounting_rpy: [0.0, 0.0, {math.radians(yaw_deg)!r}]\n")
    assert "horizontal axes" not in _node_text(summarize(bag, _files(layer), {}), "fusion")
    assert "horizontal axes" not in _node_text(summarize(minute_drive, _files(), {}), "fusion")


def test_the_yaw_check_says_nothing_where_the_drive_cannot_show_it():
    """Too little acceleration above 3 m/s, or an IMU force the car's acceleration does not
    explain (vibration): None, not a guess."""
    t = np.arange(0.0, 60.0, 0.01)
    v = 10.0 + 0.5 * np.sin(0.3 * t)                       # 0.15 m/s^2 of acceleration: too little
    speed = np.column_stack([t, v])
    imu = np.column_stack([t, np.gradient(v, t), np.zeros_like(t), np.full_like(t, 9.81),
                           np.zeros((t.size, 3))])
    def offset(imu, speed):
        return node_plan.imu_yaw_check(imu, speed, (0.0, 0.0, 0.0)).offset

    assert offset(imu, speed) is None
    v = 10.0 + 5.0 * np.sin(0.3 * t)                       # 1.5 m/s^2: enough
    speed, imu[:, 1] = np.column_stack([t, v]), np.gradient(v, t)
    assert offset(imu, speed) == pytest.approx(0.0, abs=0.01)
    shaken = imu.copy()
    shaken[:, 1:3] += np.random.default_rng(0).normal(0.0, 4.0, (t.size, 2))
    assert offset(shaken, speed) is None
    assert offset(imu[:10], speed) is None


def test_out_of_order_and_duplicated_stamps(bags):
    imu = summarize(bags["swapped"], _files(), {})["inputs"][topics.IMU]
    assert imu["out_of_order"] == 1
    assert imu["duplicates"] == 1
    assert "1 out of order, 1 duplicated stamps" in "\n".join(inspect_bag._format_topic(imu))


def test_no_gnss_dead_reckons(bags):
    summary = summarize(bags["no_gnss"], _files(), {})
    assert not summary["inputs"][topics.GNSS]["present"]
    text = _node_text(summary, "fusion")
    assert "no GNSS: dead reckoning, odom = start pose with a free heading; position covariance grows" in text
    assert "accelerometer bias held at its prior" in text
    assert "IMU mounting learnt only from 1 m/s up" in text
    assert "gnss/fix: MISSING" in format_summary(summary)


def test_state_falls_back_to_vehicle_speed_without_wheel_speeds(bags, tmp_path):
    on = tmp_path / "fallback_on.yaml"
    on.write_text("vehicle_state:\n  ros__parameters:\n    speed_fallback: true\n")
    off = tmp_path / "fallback_off.yaml"
    off.write_text("/**:\n  ros__parameters:\n    speed_fallback: true\n"
                   "vehicle_state:\n  ros__parameters:\n    speed_fallback: false\n")
    summary = summarize(bags["no_wheels"], _files(on), {})
    joints = summary["inputs"][topics.JOINT_STATES]["joints"]
    assert set(joints) == {topics.STEERING_JOINT}
    text = _node_text(summary, "vehicle_state")
    assert "no wheel speeds: vx from vehicle/speed" in text
    assert "steering from steering_wheel" in text
    # the node's section overrides /**, a later file overrides an earlier one
    assert "vx dead-reckoned from ax (drifts)" in _node_text(summarize(bags["no_wheels"], _files(off), {}),
                                                              "vehicle_state")
    assert "vx from vehicle/speed" in _node_text(summarize(bags["no_wheels"], _files(off, on), {}),
                                                 "vehicle_state")
    assert "vx from the wheel speeds" in _node_text(summarize(bags["full"], _files(off), {}), "vehicle_state")
    # paper 002's AO-UKF takes vx as a measurement: with no speed at all another filter runs
    aoukf = tmp_path / "aoukf.yaml"
    aoukf.write_text("vehicle_state:\n  ros__parameters:\n    filter: aoukf\n")
    fallback = "aoukf needs a speed: filter vbackf runs instead (automatic fallback, no_speed_filter)"
    assert fallback in _node_text(summarize(bags["no_wheels"], _files(off, aoukf), {}), "vehicle_state")
    assert fallback not in _node_text(summarize(bags["no_wheels"], _files(on, aoukf), {}), "vehicle_state")


def test_a_speed_missing_mid_drive_is_named_for_a_filter_that_needs_one(bags, tmp_path):
    """The AO-UKF measures vx: where a bag's only speed, vehicle/speed, stops for 6 s, the plan
    names the stretch the no-speed filter runs (from a second after the last sample to a second
    after the next one); where the rear wheels' speeds are NaN for 6 s, likewise."""
    first: list[float] = []

    def dropout(i, topic, typ, raw):
        if topic != topics.SPEED:
            return topic, raw
        sec, nanosec = struct.unpack("<iI", raw[4:12])
        first.extend([] if first else [sec + nanosec * 1e-9])
        return None if 6.0 <= sec + nanosec * 1e-9 - first[0] < 12.0 else (topic, raw)

    bag = _copy(bags["no_wheels"], tmp_path / "speed_dropout", dropout)
    aoukf = tmp_path / "aoukf.yaml"
    aoukf.write_text("vehicle_state:\n  ros__parameters:\n    filter: aoukf\n")
    text = _node_text(summarize(bag, _files(aoukf), {}), "vehicle_state")
    found = re.search(r"aoukf needs a speed: filter vbackf runs where none came for 1 s, "
                      r"([\d.]+)-([\d.]+) s after the first IMU sample", text)
    assert found, text
    start, end = map(float, found.groups())
    assert start == pytest.approx(7.0, abs=0.1) and end == pytest.approx(13.0, abs=0.1)
    for clean in (bags["no_wheels"], bags["full"]):
        assert "runs where none came" not in _node_text(summarize(clean, _files(aoukf), {}), "vehicle_state")

    first_joints: list[float] = []

    def wheels_dropout(i, topic, typ, raw):
        if topic == topics.SPEED:
            return None
        if topic != topics.JOINT_STATES:
            return topic, raw
        msg = TS.deserialize_cdr(raw, typ)
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        first_joints.extend([] if first_joints else [t])
        if 6.0 <= t - first_joints[0] < 12.0:
            velocity = msg.velocity.copy()
            velocity[[msg.name.index(w) for w in topics.WHEEL_JOINTS]] = float("nan")
            msg = dataclasses.replace(msg, velocity=velocity)
        return topic, bytes(TS.serialize_cdr(msg, typ))

    bag = _copy(bags["full"], tmp_path / "wheels_dropout", wheels_dropout)
    text = _node_text(summarize(bag, _files(aoukf), {}), "vehicle_state")
    found = re.search(r"runs where none came for 1 s, ([\d.]+)-([\d.]+) s after", text)
    assert found, text
    start, end = map(float, found.groups())
    assert start == pytest.approx(7.0, abs=0.3) and end == pytest.approx(13.0, abs=0.3)


def test_mass_without_propulsion_force(bags):
    summary = summarize(bags["no_force"], _files(), {})
    assert "no propulsion force: the mass stays at its prior" in _node_text(summary, "mass")
    assert topics.MASS in summary["prior_outputs"]
    assert summary["empty_outputs"] == []          # the prior is still published


def test_mass_without_brake_torque_says_what_each_method_does(bags):
    assert "no brake torque: braking is not seen" in _node_text(summarize(bags["no_wheels"], _files(), {}), "mass")
    text = _node_text(summarize(bags["no_wheels"], _files(params_file("heavy_truck_ta_aekf")), {}), "mass")
    assert "no brake torque: ta_aekf uses only samples with a positive drive force" in text
    assert "acceleration predicted from the force" in text
    assert "brake torque from the wheels' effort" in _node_text(
        summarize(bags["full"], _files(params_file("heavy_truck_ta_aekf")), {}), "mass")


def test_remap(bags):
    plain = summarize(bags["renamed"], _files(), {})
    assert not plain["inputs"][topics.IMU]["present"]
    other = {o["topic"]: o for o in plain["other_topics"]}
    assert other["/sensors/imu"]["role"] == "ignored"
    assert other["/sensors/imu"]["remap_hint"] == "imu/data:=/sensors/imu"
    assert set(plain["empty_outputs"]) >= {topics.ODOMETRY, topics.VEHICLE_STATE, topics.ROAD_SLOPE}
    assert format_summary(plain).splitlines()[-1].startswith("will stay empty: ")
    remapped = summarize(bags["renamed"], _files(), {"/imu/data": "/sensors/imu"})   # ROS order
    assert remapped == summarize(bags["renamed"], _files(), {"/sensors/imu": "imu/data"})   # or reversed
    imu = remapped["inputs"][topics.IMU]
    assert imu["present"] and imu["bag_topics"] == ["/sensors/imu"]
    assert imu["rate_hz"] == pytest.approx(200.0, rel=0.02)
    assert remapped["empty_outputs"] == []
    with pytest.raises(InspectError):
        summarize(bags["renamed"], _files(), {"/sensors/imu": "imu/raw"})


def test_cli_exit_code_and_json(bags):
    cmd = [sys.executable, "-m", "vehicle_estimation", "inspect", str(bags["full"])]
    done = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "every output will be published" in done.stdout
    done = subprocess.run(cmd + ["--json", "--remap", "/x:=imu/data"], check=False, capture_output=True, text=True,
                          timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    data = json.loads(done.stdout)
    assert data["inputs"][topics.IMU]["count"] > 0 and data["remaps"] == {"x": "imu/data"}
    bad = subprocess.run(cmd[:-1] + [str(bags["full"].parent / "nothing")], check=False, capture_output=True,
                         text=True, timeout=120, cwd=ROOT)
    assert bad.returncode == 2 and "no bag" in bad.stderr


@pytest.mark.parametrize(("node", "module", "kind", "param"), [
    ("road_slope", "slope_node", "str", "method"),
    ("vehicle_state", "state_node", "str", "filter"),
    ("vehicle_state", "state_node", "bool", "speed_fallback"),
    ("mass", "mass_node", "str", "method"),
    ("mass", "mass_node", "str", "accel_source"),
    ("mass", "mass_node", "str", "speed_source"),
    ("mass", "mass_node", "bool", "require_slope"),
])
def test_node_defaults_match_the_node_sources(node, module, kind, param):
    source = (ROOT / "vehicle_estimation" / "ros" / f"{module}.py").read_text(encoding="utf-8")
    found = re.findall(rf'declare_{kind}\(\s*"{re.escape(param)}",\s*("[^"]*"|True|False)', source)
    assert len(found) == 1, f"{module}.py declares {param!r} {len(found)} times"
    declared = found[0].strip('"') if kind == "str" else found[0] == "True"
    assert node_plan.NODE_DEFAULTS[node][param] == declared, (
        f"node_plan.NODE_DEFAULTS[{node!r}][{param!r}] drifted from {module}.py")


def test_ros1_bag(bags, tmp_path):
    """A ROS 1 .bag: stamps and content by deserialization, topics with a leading '/'."""
    from rosbags.rosbag1 import Writer as Ros1Writer
    ts1 = get_typestore(Stores.ROS1_NOETIC)
    header_cls, time_cls = ts1.types["std_msgs/msg/Header"], ts1.types["builtin_interfaces/msg/Time"]
    path = tmp_path / "drive.bag"
    keep = (topics.IMU, topics.SPEED, topics.JOINT_STATES)
    with AnyReader([bags["full"]], default_typestore=TS) as reader, Ros1Writer(path) as writer:
        conns = {}
        for conn, t, raw in reader.messages(connections=[c for c in reader.connections if c.topic in keep]):
            if t > reader.start_time + 3_000_000_000:
                break
            msg = TS.deserialize_cdr(raw, conn.msgtype)
            stamp = msg.header.stamp
            header = header_cls(seq=0, stamp=time_cls(sec=stamp.sec, nanosec=stamp.nanosec),
                                frame_id=msg.header.frame_id)
            cls = ts1.types[conn.msgtype]
            msg1 = cls(**{f: header if f == "header" else getattr(msg, f) for f in cls.__dataclass_fields__})
            if conn.topic not in conns:
                conns[conn.topic] = writer.add_connection("/" + conn.topic, conn.msgtype, typestore=ts1)
            writer.write(conns[conn.topic], t, ts1.serialize_ros1(msg1, conn.msgtype))
    summary = summarize(path, _files(), {})
    assert summary["storage"] == "ROS 1 bag"
    imu = summary["inputs"][topics.IMU]
    assert imu["present"] and imu["unreadable"] == 0 and imu["bag_topics"] == ["/imu/data"]
    assert imu["rate_hz"] == pytest.approx(200.0, rel=0.02) and imu["out_of_order"] == 0
    assert summary["inputs"][topics.JOINT_STATES]["joints"]["wheel_rr"]["velocity"] == 1.0
    assert "aligns at standstill" in _node_text(summary, "fusion")
    assert not summary["inputs"][topics.POWERTRAIN]["present"]
    assert summary["empty_outputs"] == [topics.MASS, topics.MASS_STAMPED]
