"""QoS profiles of the estimator nodes: sensor data in, reliable estimates out, replay sync."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def sensor_qos(depth: int) -> QoSProfile:
    """Sensor-data QoS (best effort, volatile, keep last) with a configurable depth.

    Best-effort subscriptions match both best-effort and reliable publishers, so the node
    works with any driver and with ``ros2 bag play``. The depth is larger than the preset's
    5 so that a burst (a replay tick, a 1 kHz IMU) is not dropped before the executor runs.
    """
    return QoSProfile(
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
    )


def output_qos(depth: int) -> QoSProfile:
    """Estimates are published reliable keep-last: controllers may ask for either."""
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
    )


def latched_qos() -> QoSProfile:
    """A value set once (the datum): reliable, transient local, so that a late subscriber
    (a controller started after the first fix) still gets it."""
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
        history=HistoryPolicy.KEEP_LAST,
        depth=1,
    )


def replay_qos() -> QoSProfile:
    """The player's sync requests and the nodes' acks: none may be lost."""
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=100,
    )
