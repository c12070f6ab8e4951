"""The floors of the bench: what a run costs before our nodes do anything with a message.

* Live (``--sections live``): :class:`FrameworkFloorNode`, a node that does nothing but
  receive the sensor topics, raw (CDR bytes, no deserialisation), with the nodes' sensor-data
  QoS, spun by the nodes' own main loop (:func:`run_node`: the same executor and spin). The
  bench runs it beside the four estimator nodes and reports their CPU against four of it: what
  our nodes cost above rclpy's own per-message cost. Run as ``python -m
  vehicle_estimation.evaluation.bench_floor``; it prints ``ready`` once subscribed.
* Replays (``--sections pipeline``): :func:`handlers_switched_off`, the same replay (bag
  reading, the delivery of every message to every subscribing node, DDS's or the in-process
  bus's, the decoding, each node's stamp-ordered queue, the ticks and, through DDS, the
  lock-step protocol) with every queued message dropped where it would go to its handler
  (``input_queue.HANDLERS_OFF_ENV``): no checks, no estimator, nothing published.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator

from rclpy.node import Node

from vehicle_estimation.contract import topics
from vehicle_estimation.launcher.replay_driver import msg_class
from vehicle_estimation.ros.runtime.input_queue import HANDLERS_OFF_ENV
from vehicle_estimation.ros.runtime.qos import sensor_qos
from vehicle_estimation.ros.runtime.spin import run_node

__all__ = ["FrameworkFloorNode", "handlers_switched_off", "main"]


@contextlib.contextmanager
def handlers_switched_off() -> Iterator[None]:
    """Nodes made within the block (in this process, or started from it: they inherit the
    environment) receive, decode and queue their inputs and release them to nobody."""
    saved = os.environ.get(HANDLERS_OFF_ENV)
    os.environ[HANDLERS_OFF_ENV] = "1"
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop(HANDLERS_OFF_ENV, None)
        else:
            os.environ[HANDLERS_OFF_ENV] = saved


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
