"""The nodes' messages read from and written to their serialized CDR bytes, without rclpy.

Reading: the high-rate inputs.

rclpy turns every received message into Python message objects: a sensor_msgs/Imu is an Imu,
a Header, a Time, a Quaternion and three Vector3, each built by generated ``__init__`` code
(~18 µs an Imu on a 2-core x86 machine). At 200 Hz on four nodes that is a fifth of the
pipeline's CPU. The nodes subscribe to these types with ``raw=True`` instead and read the fields they use
with one ``struct.unpack_from`` into small ``__slots__`` views that have the same attribute
names as the messages (``msg.header.stamp.sec``, ``msg.linear_acceleration.x``, ...), so the
handlers and conversions are unchanged and also accept real messages (tests publish those).

The layout is the ROS 2 wire format: a 4-byte encapsulation header (``00 01``: CDR little
endian), then the fields in order, each primitive aligned to its size relative to the start of
the payload; a string is a uint32 length (with the NUL) and its bytes, a sequence a uint32
count and its elements. Anything else (big-endian CDR, a truncated or inconsistent buffer)
is handed to rclpy's own deserializer, so a view is only ever an optimisation.

Writing: the nodes' outputs, packed in one go (:class:`StampedLayout`, section below).
"""

from __future__ import annotations

import functools
import struct
from typing import Any, Callable, Iterable, TypeVar

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState

_LE = b"\x00\x01"
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")


class DecodeError(ValueError):
    pass


class Stamp:
    __slots__ = ("sec", "nanosec")

    def __init__(self, sec: int, nanosec: int) -> None:
        self.sec, self.nanosec = sec, nanosec

    def to_msg(self) -> Time:
        return Time(sec=self.sec, nanosec=self.nanosec)


class Header:
    __slots__ = ("stamp", "frame_id")

    def __init__(self, stamp: Stamp, frame_id: str) -> None:
        self.stamp, self.frame_id = stamp, frame_id


class Vector3:
    __slots__ = ("x", "y", "z")

    def __init__(self, x: float, y: float, z: float) -> None:
        self.x, self.y, self.z = x, y, z


class Quaternion:
    __slots__ = ("x", "y", "z", "w")

    def __init__(self, x: float, y: float, z: float, w: float) -> None:
        self.x, self.y, self.z, self.w = x, y, z, w


class ImuView:
    """sensor_msgs/Imu."""
    __slots__ = ("header", "orientation", "orientation_covariance", "angular_velocity",
                 "angular_velocity_covariance", "linear_acceleration", "linear_acceleration_covariance", "memo")


class Twist:
    __slots__ = ("linear", "angular")

    def __init__(self, linear: Vector3, angular: Vector3) -> None:
        self.linear, self.angular = linear, angular


class TwistWithCovariance:
    __slots__ = ("twist", "covariance")

    def __init__(self, twist: Twist, covariance: tuple[float, ...]) -> None:
        self.twist, self.covariance = twist, covariance


class TwistWithCovarianceStampedView:
    """geometry_msgs/TwistWithCovarianceStamped."""
    __slots__ = ("header", "twist", "memo")


class Pose:
    __slots__ = ("position", "orientation")


class PoseWithCovariance:
    __slots__ = ("pose", "covariance")


class OdometryView:
    """nav_msgs/Odometry."""
    __slots__ = ("header", "child_frame_id", "pose", "twist", "memo")


class Vector3StampedView:
    """geometry_msgs/Vector3Stamped."""
    __slots__ = ("header", "vector", "memo")


class JointStateView:
    """sensor_msgs/JointState."""
    __slots__ = ("header", "name", "position", "velocity", "effort", "memo")


def _check(data: bytes) -> None:
    if len(data) < 16 or data[:2] != _LE:
        raise DecodeError("not little-endian CDR")


def _string(data: bytes, pos: int) -> tuple[str, int]:
    """A CDR string at payload offset ``pos`` (already 4-aligned); returns (text, next pos)."""
    (n,) = _U32.unpack_from(data, 4 + pos)
    start = 4 + pos + 4
    end = start + n
    if n == 0 or end > len(data):
        raise DecodeError("bad string")
    return data[start:end - 1].decode("utf-8", "replace"), pos + 4 + n


def _header(data: bytes) -> tuple[Header, int]:
    sec, nanosec = _STAMP.unpack_from(data, 4)
    frame_id, pos = _string(data, 8)
    return Header(Stamp(sec, nanosec), frame_id), pos


def _align(pos: int, n: int) -> int:
    return (pos + n - 1) // n * n


def _doubles(data: bytes, pos: int, count: int) -> tuple[tuple[float, ...], int]:
    pos = _align(pos, 8)
    if 4 + pos + 8 * count > len(data):
        raise DecodeError("truncated")
    return struct.unpack_from(f"<{count}d", data, 4 + pos), pos + 8 * count


def _double_sequence(data: bytes, pos: int) -> tuple[tuple[float, ...], int]:
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(data, 4 + pos)
    if n > 100_000:
        raise DecodeError("absurd sequence length")
    return _doubles(data, pos + 4, n) if n else ((), pos + 4)


def decode_imu(data: bytes) -> ImuView:
    _check(data)
    m = ImuView()
    m.header, pos = _header(data)
    d, _ = _doubles(data, pos, 37)
    m.orientation = Quaternion(*d[0:4])
    m.orientation_covariance = d[4:13]
    m.angular_velocity = Vector3(*d[13:16])
    m.angular_velocity_covariance = d[16:25]
    m.linear_acceleration = Vector3(*d[25:28])
    m.linear_acceleration_covariance = d[28:37]
    return m


def _twist_with_covariance(d: tuple[float, ...]) -> TwistWithCovariance:
    return TwistWithCovariance(Twist(Vector3(*d[0:3]), Vector3(*d[3:6])), d[6:42])


def decode_twist_with_covariance_stamped(data: bytes) -> TwistWithCovarianceStampedView:
    _check(data)
    m = TwistWithCovarianceStampedView()
    m.header, pos = _header(data)
    d, _ = _doubles(data, pos, 42)
    m.twist = _twist_with_covariance(d)
    return m


def decode_odometry(data: bytes) -> OdometryView:
    _check(data)
    m = OdometryView()
    m.header, pos = _header(data)
    m.child_frame_id, pos = _string(data, _align(pos, 4))
    d, _ = _doubles(data, pos, 7 + 36 + 42)
    pose = Pose()
    pose.position, pose.orientation = Vector3(*d[0:3]), Quaternion(*d[3:7])
    m.pose = PoseWithCovariance()
    m.pose.pose, m.pose.covariance = pose, d[7:43]
    m.twist = _twist_with_covariance(d[43:85])
    return m


def decode_vector3_stamped(data: bytes) -> Vector3StampedView:
    _check(data)
    m = Vector3StampedView()
    m.header, pos = _header(data)
    d, _ = _doubles(data, pos, 3)
    m.vector = Vector3(*d)
    return m


def decode_joint_state(data: bytes) -> JointStateView:
    _check(data)
    m = JointStateView()
    m.header, pos = _header(data)
    pos = _align(pos, 4)
    (n,) = _U32.unpack_from(data, 4 + pos)
    if n > 10_000:
        raise DecodeError("absurd name count")
    pos += 4
    names = []
    for _ in range(n):
        name, pos = _string(data, _align(pos, 4))
        names.append(name)
    m.name = names
    m.position, pos = _double_sequence(data, pos)
    m.velocity, pos = _double_sequence(data, pos)
    m.effort, pos = _double_sequence(data, pos)
    return m


DECODERS: dict[Any, Callable[[bytes], Any]] = {
    Imu: decode_imu,
    TwistWithCovarianceStamped: decode_twist_with_covariance_stamped,
    Odometry: decode_odometry,
    Vector3Stamped: decode_vector3_stamped,
    JointState: decode_joint_state,
}


_READERS: dict[Any, Callable[[bytes], Any]] = {}
_VIEWS = (ImuView, TwistWithCovarianceStampedView, OdometryView, Vector3StampedView, JointStateView)
T = TypeVar("T")


def per_view(read: Callable[[Any], T]) -> Callable[[Any], T]:
    """``read`` remembering on a view what it returned for it: the in-process bus hands every
    node the same view of a message (:func:`raw_reader`), so what the nodes read from it is
    computed once (the result must not be changed by its users). A message object is read
    every time: its owner may change it between calls."""

    @functools.wraps(read)
    def cached(msg: Any) -> T:
        if type(msg) not in _VIEWS:
            return read(msg)
        try:
            memo = msg.memo
        except AttributeError:
            memo = msg.memo = {}
        try:
            return memo[cached]
        except KeyError:
            value = memo[cached] = read(msg)
            return value

    return cached


def raw_reader(msg_type: Any) -> Callable[[bytes], Any] | None:
    """``bytes -> message or view`` for ``msg_type`` (None: no fast path, subscribe normally).

    Falls back to rclpy's deserializer when the fast path cannot read the bytes, so the
    result is always the message's content. One reader per type, which remembers the last
    bytes object it read: the in-process bus hands every subscriber the same bytes, so a
    message is decoded once for all nodes of the process (handlers never write to a view).
    """
    reader = _READERS.get(msg_type)
    if reader is not None or msg_type not in DECODERS:
        return reader
    decoder = DECODERS[msg_type]
    last: list[tuple[Any, Any]] = [(None, None)]

    def read(data: bytes) -> Any:
        seen, view = last[0]
        if data is seen:
            return view
        try:
            view = decoder(data)
        except (DecodeError, struct.error, IndexError, TypeError):
            view = deserialize_message(data, msg_type)
        last[0] = (data, view)      # one assignment: a reader shared by threads stays consistent
        return view

    _READERS[msg_type] = read
    return read

# ---------------------------------------------------------------------------------- writing
# The nodes' estimates written straight to serialized CDR bytes.
#
# Building a nav_msgs/Odometry in rclpy creates a dozen Python message objects and converts two
# 36-element covariance lists to arrays field by field; rclpy then serializes the lot again. The
# nodes' outputs are fixed layouts, a header and a run of float64, so each publisher packs its
# message with one ``struct.pack`` instead (rclpy publishes ``bytes`` as a serialized message,
# and the in-process bus hands them on as they are).
#
# The bytes are the canonical ROS 2 wire form (what ``rosbags`` and a DDS writer produce: CDR
# little endian, alignment padding zero), so a recording is the same whichever transport carried
# the message, and ``test_cdr`` holds every layout to rosbags' serializer byte for byte.
# Layout: the 4-byte encapsulation header ``00 01 00 00``, then the fields in order, each
# primitive aligned to its size relative to the end of that header; a string is a uint32 length
# (counting its NUL), its bytes and the NUL.

_ENCAPSULATION = b"\x00\x01\x00\x00"
_FLOAT64 = struct.Struct("<d")


def _string_bytes(text: str, pos: int) -> tuple[bytes, int]:
    """``text`` as a CDR string starting at payload offset ``pos`` (4-aligned), and the end."""
    pad = -pos % 4
    raw = text.encode() + b"\x00"
    return b"\x00" * pad + _U32.pack(len(raw)) + raw, pos + pad + 4 + len(raw)


class StampedLayout:
    """A message that is a std_msgs/Header, optionally a second frame string, and ``doubles``
    float64 values in field order (nested structs and fixed arrays flatten to that):

    ====================================  =======  ==============================================
    message                               doubles  order
    ====================================  =======  ==============================================
    geometry_msgs/Vector3Stamped          3        x y z
    geometry_msgs/TwistWithCovarianceStamped 42    linear, angular, covariance (36)
    sensor_msgs/Imu                       37       orientation (4), its covariance (9), angular
                                                   velocity (3), its covariance, linear
                                                   acceleration (3), its covariance
    nav_msgs/Odometry (``child_frame_id``) 85      position (3), orientation (4), pose covariance
                                                   (36), linear, angular, twist covariance (36)
    ====================================  =======  ==============================================
    """

    def __init__(self, frame_id: str, doubles: int, child_frame_id: str | None = None) -> None:
        frames, pos = _string_bytes(frame_id, _STAMP.size)
        if child_frame_id is not None:
            child, pos = _string_bytes(child_frame_id, pos)
            frames += child
        frames += b"\x00" * (-pos % 8)
        self._frames = frames
        self._values = struct.Struct(f"<{doubles}d")
        self.doubles = doubles

    def pack(self, stamp_ns: int, values: Iterable[float]) -> bytes:
        """The message stamped ``stamp_ns`` (integer nanoseconds) carrying ``values``."""
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return _ENCAPSULATION + _STAMP.pack(sec, nanosec) + self._frames + self._values.pack(*values)


def float64_bytes(value: float) -> bytes:
    """A std_msgs/Float64."""
    return _ENCAPSULATION + _FLOAT64.pack(value)
