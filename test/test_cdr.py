"""The fast CDR views read exactly what rclpy's deserializer reads, and fall back to it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import TwistWithCovarianceStamped, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import Imu
from std_msgs.msg import Float64

from vehicle_estimation.ros.cdr import DECODERS, DecodeError, raw_reader
from vehicle_estimation.ros.cdr import StampedLayout, float64_bytes


def _fill(msg, rng: np.random.Generator, depth: int = 0):
    """Random values in every field (odd-length strings and sequences, NaN and inf too)."""
    specials = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308]
    for name, kind in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        if kind == "double":
            setattr(msg, name, float(rng.choice(specials)) if rng.random() < 0.1 else float(rng.normal(0, 100)))
        elif kind in ("int32", "uint32"):
            setattr(msg, name, int(rng.integers(0, 2**31 - 1)))
        elif kind == "string":
            setattr(msg, name, "x" * int(rng.integers(0, 13)) + "é")
        elif kind.startswith("double["):
            setattr(msg, name, [float(rng.normal()) for _ in range(len(value))])
        elif kind == "sequence<double>":
            setattr(msg, name, [float(rng.normal()) for _ in range(int(rng.integers(0, 7)))])
        elif kind == "sequence<string>":
            setattr(msg, name, ["j" * int(rng.integers(1, 9)) for _ in range(int(rng.integers(0, 7)))])
        elif hasattr(value, "get_fields_and_field_types"):
            _fill(value, rng, depth + 1)
    return msg


def _same(view, msg, path="msg"):
    for name in msg.get_fields_and_field_types():
        a, b = getattr(view, name), getattr(msg, name)
        if hasattr(b, "get_fields_and_field_types"):
            _same(a, b, f"{path}.{name}")
        elif isinstance(b, (float, int, str)):
            assert (a == b) or (isinstance(b, float) and math.isnan(a) and math.isnan(b)), f"{path}.{name}"
        else:
            assert list(a) == list(b), f"{path}.{name}"


@pytest.mark.parametrize("msg_type", list(DECODERS))
def test_views_match_rclpy(msg_type):
    rng = np.random.default_rng(7)
    read = raw_reader(msg_type)
    for _ in range(50):
        msg = _fill(msg_type(), rng)
        view = DECODERS[msg_type](serialize_message(msg))
        _same(view, msg)
        assert type(read(serialize_message(msg))) is not msg_type   # the fast path was taken


@pytest.mark.parametrize("msg_type", list(DECODERS))
def test_unreadable_bytes_go_to_rclpy(msg_type):
    data = serialize_message(_fill(msg_type(), np.random.default_rng(1)))
    with pytest.raises(DecodeError):     # big-endian encapsulation: not read by the view ...
        DECODERS[msg_type](data[:1] + b"\x00" + data[2:])
    with pytest.raises(Exception):       # ... truncated bytes: rclpy's error, for the node to count
        raw_reader(msg_type)(data[:11])


# ---------------------------------------------------------------- writing (ros.cdr)
LAYOUTS = {Vector3Stamped: 3, TwistWithCovarianceStamped: 42, Imu: 37, Odometry: 85}


def _doubles_in_field_order(msg) -> list[float]:
    """Every float64 of a message but its header, nested structs and fixed arrays flattened."""
    out: list[float] = []
    for name, kind in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        if kind == "double":
            out.append(value)
        elif kind.startswith("double["):
            out.extend(float(v) for v in value)
        elif hasattr(value, "get_fields_and_field_types") and kind != "std_msgs/Header":
            out.extend(_doubles_in_field_order(value))
    return out


@pytest.mark.parametrize("msg_type", list(LAYOUTS))
def test_written_bytes_are_the_canonical_serialization(msg_type):
    """Byte for byte what rosbags writes (zero padding, every frame-name length against the
    alignment), and read back by rclpy as the message it was made from."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    type_name = msg_type.__module__.split(".")[0] + "/msg/" + msg_type.__name__
    rng = np.random.default_rng(3)
    for n in range(24):
        msg = _fill(msg_type(), rng)
        msg.header.frame_id = "f" * (n % 9)
        msg.header.stamp.nanosec %= 1_000_000_000
        child = None
        if hasattr(msg, "child_frame_id"):
            msg.child_frame_id = child = "c" * (n // 3)
        values = _doubles_in_field_order(msg)
        assert len(values) == LAYOUTS[msg_type]
        stamp = msg.header.stamp
        data = StampedLayout(msg.header.frame_id, len(values), child).pack(
            stamp.sec * 1_000_000_000 + stamp.nanosec, values)
        canonical = typestore.serialize_cdr(typestore.deserialize_cdr(serialize_message(msg), type_name), type_name)
        assert data == bytes(canonical)
        _same(deserialize_message(data, msg_type), msg)


def test_float64_bytes():
    for value in (0.0, -1.5, 1e308, math.inf, math.nan):
        assert float64_bytes(value) == serialize_message(Float64(data=value))
