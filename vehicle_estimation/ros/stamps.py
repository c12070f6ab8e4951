"""Header stamps as integer nanoseconds and float seconds: the one conversion every node uses."""

from __future__ import annotations

from typing import Any

from vehicle_estimation.estimators.common.guard import STAMP_TOLERANCE_S

__all__ = ["STAMP_TOLERANCE_S", "stamp_ns", "stamp_to_sec", "sec_to_ns", "sec_to_stamp"]


def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time: exact, so every node orders alike."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_to_sec(stamp: Any) -> float:
    """Float seconds of a builtin_interfaces/Time, via integer ns (the same float every node gets)."""
    return stamp_ns(stamp) * 1e-9


def sec_to_ns(t: float) -> int:
    """Integer nanoseconds of float seconds (rounded to the nanosecond)."""
    return int(round(t * 1e9))


def sec_to_stamp(t: float, msg_stamp: Any) -> Any:
    """Fill a builtin_interfaces/Time from float seconds (rounded to the nanosecond)."""
    ns = sec_to_ns(t)
    msg_stamp.sec = ns // 1_000_000_000
    msg_stamp.nanosec = ns % 1_000_000_000
    return msg_stamp
