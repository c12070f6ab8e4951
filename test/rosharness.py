"""Small helpers for rclpy tests: one executor, a probe node that publishes and collects, and
replays run side by side."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from vehicle_estimation.contract.vehicle import load_vehicle_params
from vehicle_estimation.paths import params_file

RELIABLE = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                      history=HistoryPolicy.KEEP_LAST, depth=1000)


def sec_to_time(t: float, stamp: Any) -> Any:
    ns = int(round(t * 1e9))
    stamp.sec, stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return stamp


def vehicle_overrides(name: str = "sedan_d_class") -> list[Parameter]:
    vehicle = load_vehicle_params(params_file(name))
    return [Parameter(f"vehicle.{k}", value=(list(v) if isinstance(v, (list, tuple)) else v))
            for k, v in vehicle.as_mapping().items()]


class Probe(Node):
    """Publishes inputs and records every message of the topics it watches."""

    def __init__(self) -> None:
        super().__init__("test_probe")
        self.pubs: dict[str, Any] = {}
        self.received: dict[str, list[Any]] = {}

    def publisher_for(self, msg_type: Any, topic: str) -> Any:
        if topic not in self.pubs:
            self.pubs[topic] = self.create_publisher(msg_type, topic, RELIABLE)
        return self.pubs[topic]

    def watch(self, msg_type: Any, topic: str) -> list[Any]:
        store = self.received.setdefault(topic, [])
        self.create_subscription(msg_type, topic, store.append, RELIABLE)
        return store


class Harness:
    def __init__(self, node: Node) -> None:
        self.node = node
        self.probe = Probe()
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(node)
        self.executor.add_node(self.probe)

    def spin(self, seconds: float = 0.05) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.005)

    def wait_for(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return predicate()

    def connect(self, topics: list[str], timeout: float = 10.0) -> None:
        """Wait until every probe publisher sees the node's subscription."""
        ok = self.wait_for(lambda: all(self.probe.pubs[t].get_subscription_count() > 0 for t in topics),
                           timeout)
        assert ok, f"node never subscribed to {topics}"

    def publish_stream(self, items: list[tuple[str, Any]], chunk: int = 20) -> None:
        """Publish (topic, msg) in order, a chunk at a time, each chunk received before the next.

        Waiting on the node's receive counters keeps the topics within one chunk of each
        other, as they are live, instead of letting one topic's backlog starve another.
        """
        from collections import Counter
        sent: Counter[str] = Counter()
        health = getattr(self.node, "health", None)     # an EstimatorNode's per-topic counters
        rx = health.rx if health is not None else None
        # counts so far: a second call must wait for its own messages, not earlier calls' ones
        base = Counter(rx) if rx is not None else Counter()
        for start in range(0, len(items), chunk):
            for topic, msg in items[start:start + chunk]:
                pub = self.probe.pubs[topic]
                pub.publish(msg)
                sent[pub.topic_name] += 1
            if rx is None:
                self.spin(0.02)
            else:
                ok = self.wait_for(lambda: all(rx[t] - base[t] >= n for t, n in sent.items()), timeout=10.0)
                assert ok, f"node received {dict(rx)} of {dict(sent)}"
        self.spin(0.3)

    def close(self) -> None:
        self.executor.shutdown()
        self.probe.destroy_node()
        self.node.destroy_node()


def init_rclpy() -> None:
    if not rclpy.ok():
        rclpy.init()


def replay_side_by_side(runs: dict[str, list[str]], out_dir: Path, timeout_s: float = 900.0) -> dict[str, Path]:
    """``vehicle-estimation replay ARGS --in-process`` for each ``name: ARGS`` at once (one core
    each), recorded to ``out_dir / estimates_<name>``: the record of each, once all have ended
    well."""
    records = {name: out_dir / f"estimates_{name}" for name in runs}
    procs = {name: subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "replay", *args, "--record",
                                     str(records[name]), "--quiet", "--in-process"],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for name, args in runs.items()}
    for proc in procs.values():
        output, _ = proc.communicate(timeout=timeout_s)
        assert proc.returncode == 0, output[-3000:]
    return records
