"""The bag a user brings: stamps from 0 s, ROS 1 bags, other topic names, other rates, extra topics.

Every variant is made from one short simulated drive with ``io.bagtools.rewrite_bag`` and
replayed through the real launcher. Cases are combined where that keeps the intent clear (each
replay costs ~10 s): ROS 1 + start at 0 s; remapped names + unrelated extra topics; 100 Hz
IMU + 1 Hz GNSS (written as sqlite3).
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.contract import topics
from vehicle_estimation.cli import build_parser
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag
from vehicle_estimation.io.bagtools import rewrite_bag
from vehicle_estimation.launcher.processes import NodeGroup

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

TS = get_typestore(Stores.ROS2_JAZZY)
ESTIMATES = ("/estimation/odometry", "/estimation/vehicle_state", "/estimation/mass")
#: The contract inputs as a recorder with its own names would write them.
VENDOR_NAMES = {
    "/imu/data": "/sensors/imu",
    "/gnss/fix": "/sensors/gnss",
    "/vehicle/speed": "/can/speed",
    "/vehicle/joint_states": "/can/wheels",
    "/vehicle/powertrain": "/can/powertrain",
}


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    """The first 22 s of the short simulated drive (MCAP, stamps at 1.7e9 s)."""
    root = tmp_path_factory.mktemp("any_bag")
    full = write_bag(simulate(scenario_by_name("short")), root / "full")
    return rewrite_bag(full, root / "drive", duration_s=22.0)


def _messages(bag: Path, topic: str) -> list[tuple[int, object]]:
    with AnyReader([bag], default_typestore=TS) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(t, reader.deserialize(d, c.msgtype)) for c, t, d in reader.messages(connections=conns)]


def _counts(bag: Path) -> dict[str, int]:
    with AnyReader([bag], default_typestore=TS) as reader:
        return {c.topic: c.msgcount for c in reader.connections}


def _fields(msg: object, drop: tuple[str, ...] = ()) -> object:
    """A message as nested dicts and lists (arrays as lists), for a field-by-field comparison."""
    if dataclasses.is_dataclass(msg):
        return {f.name: _fields(getattr(msg, f.name), drop) for f in dataclasses.fields(msg)
                if f.name not in drop and not f.name.startswith("__")
                and not f.name.isupper()}   # constants (ROS 1 and 2 define different ones)
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, list):
        return [_fields(item, drop) for item in msg]
    return msg


def _replay(bag: Path, out: Path, *extra: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record", str(out),
                           "--quiet", *extra], check=False, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "lossless: True" in proc.stdout, proc.stdout
    counts = _counts(out)
    for topic in ESTIMATES:
        assert counts.get(topic, 0) > 0, f"{topic} not recorded: {counts}"
    return proc


def _read_column(stdout: str, topic: str) -> int:
    """Messages read on ``topic`` in the replay's per-topic table."""
    for line in stdout.splitlines():
        parts = line.split()
        if parts and parts[0] == topic:
            return int(parts[1])
    raise AssertionError(f"{topic} not in the replay table:\n{stdout}")


# ----------------------------------------------------------------------------- rewrite_bag itself
def test_drop_joints_keeps_the_arrays_aligned(drive, tmp_path):
    out = rewrite_bag(drive, tmp_path / "fewer_joints", duration_s=1.0,
                      drop_joints=("wheel_fl", "steering_wheel", "engine_load"))
    for topic in ("/vehicle/joint_states", "/vehicle/powertrain"):
        before = _messages(drive, topic)
        after = _messages(out, topic)
        assert len(after) == 100
        for (_, old), (_, new) in zip(before, after):
            keep = [i for i, n in enumerate(old.name) if n not in ("wheel_fl", "steering_wheel", "engine_load")]
            assert new.name == [old.name[i] for i in keep]
            assert len(keep) < len(old.name)
            for attr in ("position", "velocity", "effort"):
                np.testing.assert_array_equal(getattr(new, attr), getattr(old, attr)[keep])  # NaN == NaN here
            assert _fields(new.header) == _fields(old.header)


def test_edit_changes_the_messages_of_one_topic_in_place(drive, tmp_path):
    def add_index(msg, index):
        msg.linear_acceleration.y += 0.001 * index

    out = rewrite_bag(drive, tmp_path / "edited", duration_s=1.0, edit={"imu/data": add_index})
    before, after = _messages(drive, "/imu/data"), _messages(out, "/imu/data")
    assert len(after) == 200
    for index, ((_, old), (_, new)) in enumerate(zip(before, after)):
        assert new.linear_acceleration.y == old.linear_acceleration.y + 0.001 * index
        assert _fields(new, drop=("linear_acceleration",)) == _fields(old, drop=("linear_acceleration",))
    assert _fields(_messages(out, "/vehicle/speed")[0][1]) == _fields(_messages(drive, "/vehicle/speed")[0][1])
    with pytest.raises(ValueError, match="edit"):
        rewrite_bag(drive, tmp_path / "bad", edit={"no/such_topic": add_index})


def test_start_at_zero_shifts_header_stamps_and_log_times(drive, tmp_path):
    out = rewrite_bag(drive, tmp_path / "zero", start_at_s=0.0, duration_s=1.0)
    with AnyReader([drive]) as reader:
        offset = reader.start_time
    with AnyReader([out]) as reader:
        assert reader.start_time == 0
    for topic in ("/imu/data", "/gnss/fix", "/vehicle/speed", "/ground_truth/odometry"):
        before, after = _messages(drive, topic), _messages(out, topic)
        assert len(after) == sum(1 for t, _ in before if t < offset + 10**9) > 0
        for (t_old, old), (t_new, new) in zip(before, after):
            assert t_new == t_old - offset
            stamp_old = old.header.stamp.sec * 10**9 + old.header.stamp.nanosec
            stamp_new = new.header.stamp.sec * 10**9 + new.header.stamp.nanosec
            assert stamp_new == stamp_old - offset
            # nothing but the stamp changes
            assert _fields(new, drop=("stamp",)) == _fields(old, drop=("stamp",))
    first = _messages(out, "/imu/data")[0][1]
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (0, 0)


def test_ros1_round_trip_equals_the_original_except_seq(drive, tmp_path):
    bag = rewrite_bag(drive, tmp_path / "drive.bag", duration_s=1.0, storage="ros1")
    with AnyReader([bag]) as reader:
        assert not reader.is2
        msgdefs = {c.topic: c.digest for c in reader.connections}
    noetic = get_typestore(Stores.ROS1_NOETIC)
    assert msgdefs["/imu/data"] == noetic.generate_msgdef("sensor_msgs/msg/Imu")[1]
    back = rewrite_bag(bag, tmp_path / "back", storage="sqlite3")
    with AnyReader([drive]) as reader:
        t_first = reader.start_time
    for topic in _counts(drive):
        original = [(t, m) for t, m in _messages(drive, topic) if t < t_first + 10**9]
        ros1 = _messages(bag, topic)
        ros2 = _messages(back, topic)
        assert len(original) == len(ros1) == len(ros2) > 0, topic
        for (t0, m0), (t1, m1), (t2, m2) in zip(original, ros1, ros2):
            assert t0 == t1 == t2
            if hasattr(m1, "header"):
                assert m1.header.seq == 0
            # NaN-aware comparison of nested dicts and lists
            np.testing.assert_equal(_fields(m1, drop=("seq",)), _fields(m0), err_msg=topic)
            np.testing.assert_equal(_fields(m2), _fields(m0), err_msg=topic)


def test_rewrite_bag_names_what_is_wrong(drive, tmp_path):
    with pytest.raises(ValueError, match="/no/such/topic"):
        rewrite_bag(drive, tmp_path / "a", drop_topics=("/no/such/topic",))
    with pytest.raises(ValueError, match="keep_every"):
        rewrite_bag(drive, tmp_path / "b", keep_every={"imu/data": 0})
    with pytest.raises(ValueError, match="storage"):
        rewrite_bag(drive, tmp_path / "c", storage="db3")
    with pytest.raises(ValueError, match=r"\.bag"):
        rewrite_bag(drive, tmp_path / "d", storage="ros1")
    with pytest.raises(ValueError, match="both"):
        rewrite_bag(drive, tmp_path / "e", rename={"/imu/data": "/gnss/fix"})
    assert not any(tmp_path.iterdir())


# ----------------------------------------------------------------------------- launcher options
def test_remap_option_and_node_argv():
    args = build_parser().parse_args(["run", "--remap", "imu/data:=/sensors/imu", "--remap", "gnss/fix:=/gps"])
    assert args.remap == [("imu/data", "/sensors/imu"), ("gnss/fix", "/gps")]
    group = NodeGroup([Path("params.yaml")], remaps=args.remap)
    for node in group.nodes:
        ros_args = node.argv[node.argv.index("--ros-args"):]
        assert ["-r", "imu/data:=/sensors/imu"] == ros_args[3:5] and ["-r", "gnss/fix:=/gps"] == ros_args[5:7]
    for bad in ("imu/data", "imu/data:=", ":=imu/data", "a:=b:=c", "a b:=c"):
        proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", "bag", "--record", "out",
                               "--remap", bad], check=False, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert "argument --remap" in proc.stderr and "FROM:=TO" in proc.stderr, proc.stderr


def test_handshake_clock_is_never_negative():
    from vehicle_estimation.launcher.replay_driver import handshake_ns
    assert handshake_ns(0) == 0
    assert handshake_ns(400_000_000) == 0
    assert handshake_ns(1_700_000_000 * 10**9) == 1_699_999_999 * 10**9


# ----------------------------------------------------------------------------- replays
def test_replay_a_ros1_bag_whose_stamps_start_at_zero(drive, tmp_path):
    bag = rewrite_bag(drive, tmp_path / "drive.bag", start_at_s=0.0, storage="ros1")
    with AnyReader([bag]) as reader:
        assert not reader.is2 and reader.start_time == 0
    out = tmp_path / "estimates"
    proc = _replay(bag, out)
    assert _read_column(proc.stdout, "/imu/data") == 4400
    counts = _counts(out)
    assert counts.get("/ground_truth/mass") == 2200       # truth converted to CDR and copied
    with AnyReader([out], default_typestore=TS) as reader:
        truth = next(c for c in reader.connections if c.topic == "/ground_truth/mass")
        _, t, data = next(reader.messages(connections=[truth]))
        assert t < 10**8 and reader.deserialize(data, truth.msgtype).data > 1000.0


def _with_extra_topics(src: Path, dst: Path) -> Path:
    """``src`` plus topics no node reads: a String log and an IMU of another name."""
    with AnyReader([src], default_typestore=TS) as reader, \
            Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=TS) for c in reader.connections}
        notes = writer.add_connection("/driver/notes", "std_msgs/msg/String", typestore=TS)
        spare = writer.add_connection("/imu/unused", "sensor_msgs/msg/Imu", typestore=TS)
        for conn, timestamp, data in reader.messages():
            writer.write(conns[conn.id], timestamp, data)
            if conn.topic == "/sensors/imu":
                writer.write(spare, timestamp, data)
            elif conn.topic == "/sensors/gnss":
                writer.write(notes, timestamp, bytes(TS.serialize_cdr(TS.types["std_msgs/msg/String"](
                    data="not a sensor"), "std_msgs/msg/String")))
    return dst


def test_replay_a_remapped_bag_with_extra_topics(drive, tmp_path):
    renamed = rewrite_bag(drive, tmp_path / "vendor", rename=VENDOR_NAMES)
    bag = _with_extra_topics(renamed, tmp_path / "vendor_extra")
    assert {"/sensors/imu", "/can/speed", "/driver/notes", "/imu/unused"} <= set(_counts(bag))
    assert "/imu/data" not in _counts(bag)
    remaps = []
    for i, (contract, vendor) in enumerate(VENDOR_NAMES.items()):
        # with and without the leading '/', on either side
        remaps += ["--remap", f"{vendor}:={contract.lstrip('/')}" if i % 2 else f"{vendor.lstrip('/')}:={contract}"]
    proc = _replay(bag, tmp_path / "estimates", *remaps)
    table = proc.stdout.split("replayed")[0]
    for contract in VENDOR_NAMES:
        assert _read_column(proc.stdout, contract) > 0        # the table names the contract topic
    assert "/sensors/imu" not in table and "/driver/notes" not in table and "/imu/unused" not in table
    assert _read_column(proc.stdout, "/imu/data") == 4400
    assert "/driver/notes" not in _counts(tmp_path / "estimates")


def test_replay_a_bag_with_100_hz_imu_and_1_hz_gnss(drive, tmp_path):
    bag = rewrite_bag(drive, tmp_path / "slow_rates", keep_every={"imu/data": 2, "/gnss/fix": 10},
                      storage="sqlite3")
    counts = _counts(bag)
    assert counts["/imu/data"] == 2200 and counts["/gnss/fix"] == 22 and counts["/vehicle/speed"] == 2200
    imu = _messages(bag, "/imu/data")
    assert imu[1][0] - imu[0][0] == 10_000_000            # 100 Hz
    proc = _replay(bag, tmp_path / "estimates")
    assert _read_column(proc.stdout, "/imu/data") == 2200
    assert _read_column(proc.stdout, "/gnss/fix") == 22


def test_replay_refuses_a_remap_to_a_topic_outside_the_contract(drive, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(drive), "--record",
                           str(tmp_path / "out"), "--quiet", "--remap", "/imu/data:=imu/raw"],
                          check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    assert "the bag has no topic imu/raw" in proc.stderr, proc.stderr
    assert topics.IMU in proc.stderr


def test_a_second_clock_in_the_domain_stops_the_replay_with_a_clear_message(drive, tmp_path):
    """Two replays (or a replay beside a simulator) in one ROS domain hear each other's /clock:
    every node jumps back and resets. The replay refuses to go on and says what to do."""
    import rclpy
    from rosgraph_msgs.msg import Clock

    # long enough for the replay's once-a-second look to see the other participant's publisher
    short = rewrite_bag(drive, tmp_path / "short", duration_s=12.0)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("another_clock", context=context)
    try:
        node.create_publisher(Clock, "/clock", 10)
        proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(short), "--record",
                               str(tmp_path / "out"), "--quiet"], capture_output=True, text=True, timeout=300)
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
    assert proc.returncode != 0
    assert "another node publishes /clock" in proc.stdout + proc.stderr, proc.stdout[-2000:] + proc.stderr[-2000:]
