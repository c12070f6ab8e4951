"""The framework floor of ``vehicle-estimation bench --sections live``: what rclpy itself costs.

A node that does nothing but receive the sensor topics, raw (CDR bytes, no deserialisation),
with the nodes' sensor-data QoS, spun by the nodes' own main loop (:func:`run_node`: the same
executor and spin). The bench runs it beside the four estimator nodes and reports their CPU
against four of it: what our nodes cost above rclpy's own per-message cost. Run as ``python -m
vehicle_estimation.evaluation.bench_floor``; it prints ``ready`` once subscribed.
"""

from __future__ import annotations

import sys

from rclpy.node import Node

from vehicle_estimation.contract import topics
from vehicle_estimation.launcher.replay_driver import msg_class
from vehicle_estimation.ros.runtime.qos import sensor_qos
from vehicle_estimation.ros.runtime.spin import run_node

__all__ = ["FrameworkFloorNode", "main"]


class FrameworkFloorNode(Node):
    """Subscribes to every sensor input, raw, and only counts what arrives."""

    def __init__(self) -> None:
        super().__init__("bench_framework_floor")
        self.received = 0
        for topic in topics.INPUT_TOPICS:
            self.create_subscription(msg_class(topics.INPUT_TYPES[topic]), topic, self._count, sensor_qos(100),
                                     raw=True)
        print("ready", flush=True)

    def _count(self, _: bytes) -> None:
        self.received += 1


def main() -> int:
    return run_node(FrameworkFloorNode)


if __name__ == "__main__":
    sys.exit(main())
