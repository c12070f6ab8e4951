"""The fast CDR views read exactly what rclpy's deserializer reads, and fall back to it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from vehicle_estimation.ros.cdr import DECODERS, DecodeError, raw_reader


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
