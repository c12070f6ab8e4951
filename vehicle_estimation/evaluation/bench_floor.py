"""The floors of the bench: what a run costs before our nodes do anything with a message.

* Live (``--sections live``): :class:`FrameworkFloorNode`, a node that does nothing but
  receive the sensor topics, raw (CDR bytes, no deserialisation), with the nodes' sensor-data
  QoS, spun by the nodes' own main loop (:func:`run_node`: the same executor and spin). The
  bench runs it beside the four estimator nodes and reports their CPU against four of it: what
  our nodes cost above rclpy's own per-message cost. Run as ``python -m
  vehicle_estimation.evaluation.bench_floor``; it prints ``ready`` once subscribed.
* In-process replay (``--sections pipeline``): :func:`handlers_switched_off`, the same replay
  (bag reading, the bus's delivery of every message to every subscribing node, the decoding
  into a view, each node's stamp-ordered queue and its ticks) with every queued message
  dropped where it would go to its handler: no checks, no estimator, nothing published.
"""

from __future__ import annotations

import contextlib
import heapq
import sys
from collections.abc import Iterator
from unittest import mock

from rclpy.node import Node

from vehicle_estimation.contract import topics
from vehicle_estimation.launcher.replay_driver import msg_class
from vehicle_estimation.ros.runtime.input_queue import StampOrderedInputs
from vehicle_estimation.ros.runtime.qos import sensor_qos
from vehicle_estimation.ros.runtime.spin import run_node

__all__ = ["FrameworkFloorNode", "handlers_switched_off", "main"]


@contextlib.contextmanager
def handlers_switched_off() -> Iterator[None]:
    """Within the block, every node's input queue releases its messages to nobody."""

    def release(self: StampOrderedInputs, horizon_ns: float) -> None:
        heap = self._heap
        while heap and heap[0][0] < horizon_ns:
            heapq.heappop(heap)

    with mock.patch.object(StampOrderedInputs, "release", release):
        yield


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
