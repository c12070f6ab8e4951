"""Header stamps as integer nanoseconds and float seconds: the one conversion every node uses."""

from __future__ import annotations

from typing import Any

#: Tolerance of comparisons between stamps in float seconds: near 1.7e9 s (any ROS epoch stamp)
#: a float64 resolves only 2.4e-7 s, so a 10 ms period can come out as 9.99976 ms.
STAMP_TOLERANCE_S = 1e-6


def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time: exact, so every node orders alike."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_to_sec(stamp: Any) -> float:
    """Float seconds of a builtin_interfaces/Time, via integer ns (the same float every node gets)."""
    return stamp_ns(stamp) * 1e-9


def sec_to_stamp(t: float, msg_stamp: Any) -> Any:
    """Fill a builtin_interfaces/Time from float seconds (rounded to the nanosecond)."""
    ns = int(round(t * 1e9))
    msg_stamp.sec = ns // 1_000_000_000
    msg_stamp.nanosec = ns % 1_000_000_000
    return msg_stamp
