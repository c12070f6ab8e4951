"""The replay's player/recorder node and the lock-step protocol it runs with the nodes.

:class:`ReplayDriver` lives in the launcher process: it publishes the bag's messages (raw CDR)
and ``/clock``, records the nodes' estimates, and keeps the counts of the sync protocol
(``ros.runtime.sync``). :func:`handshake` waits until every node and connection is up;
:func:`tick` advances the clock by one tick and waits until every node has processed it
(respawning a node that died on the way, :func:`_respawn`). :mod:`.replay` drives a bag
through them.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
from collections import Counter
from typing import Any, Iterable

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import Writer
from rosgraph_msgs.msg import Clock
from tqdm import tqdm

from vehicle_estimation.contract import topics
from vehicle_estimation.ros.runtime.qos import replay_qos
from vehicle_estimation.ros.runtime.sync import (
    ACK_TOPIC,
    MATCHED_PREFIX,
    RX_PREFIX,
    SOURCES_PREFIX,
    SYNC_TOPIC,
    TX_PREFIX,
)

#: Estimates recorded to the output bag (relative names, resolved in the node namespace).
RECORDED_TOPICS = (
    (topics.ODOMETRY, "nav_msgs/msg/Odometry"),
    (topics.IMU_COMPENSATED, "sensor_msgs/msg/Imu"),
    (topics.IMU_BIAS, "sensor_msgs/msg/Imu"),
    (topics.FUSION_GRADE, "geometry_msgs/msg/Vector3Stamped"),
    (topics.SPEED_SCALE, "geometry_msgs/msg/Vector3Stamped"),
    (topics.DATUM, "sensor_msgs/msg/NavSatFix"),
    (topics.ROAD_SLOPE, "std_msgs/msg/Float64"),
    (topics.ROAD_SLOPE_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
    (topics.VEHICLE_STATE, "geometry_msgs/msg/TwistWithCovarianceStamped"),
    (topics.SIDESLIP, "std_msgs/msg/Float64"),
    (topics.SIDESLIP_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
    (topics.MASS, "std_msgs/msg/Float64"),
    (topics.MASS_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
)
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"

#: Nodes acknowledge by themselves whenever their counts change after a sync; a resend is
#: only a safety net.
RESEND_S = 0.25


class ReplayError(RuntimeError):
    pass


def msg_class(type_name: str) -> Any:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def say(text: str) -> None:
    """One line on stderr, printed above a progress bar on a terminal rather than through it."""
    tqdm.write(text, file=sys.stderr)
    sys.stderr.flush()


class ReplayDriver(Node):
    """The player and recorder node living in the launcher process."""

    def __init__(self, namespace: str, node_names: Iterable[str], writer: Writer | None,
                 typestore: Any, diagnostics: bool = True) -> None:
        super().__init__("replay_player", namespace=namespace)
        self.expected_nodes = {self._fq(namespace, n) for n in node_names}
        self.acks: dict[str, dict[str, Any]] = {}
        self.tx: Counter[str] = Counter()
        self.raw_publishers: dict[str, Any] = {}
        self.writer = writer
        self.typestore = typestore
        self.recorded: Counter[str] = Counter()
        self._rec_connections: dict[str, Any] = {}
        self.now_ns = 0
        self.clock_checked = 0.0       # wall time of the last look for a second /clock (0: the first tick looks)
        self.dirty = False
        # Count bookkeeping across a node respawn (see rebaseline): what each process
        # will never see, and what dead processes had published.
        self.rx_offsets: dict[str, Counter[str]] = {}
        self.recorded_offsets: Counter[str] = Counter()
        self.tx_dead: Counter[str] = Counter()
        self.ack_seq = 0
        reliable = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                              history=HistoryPolicy.KEEP_LAST, depth=10000)
        self.reliable = reliable
        self.clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.sync_pub = self.create_publisher(DiagnosticStatus, SYNC_TOPIC, replay_qos())
        self.create_subscription(DiagnosticStatus, ACK_TOPIC, self._on_ack, replay_qos())
        self.record_subs = {}
        recorded = list(RECORDED_TOPICS) + ([("/diagnostics", DIAGNOSTICS_TYPE)] if diagnostics else [])
        for topic, type_name in recorded:
            holder: dict[str, str] = {}
            sub = self.create_subscription(
                msg_class(type_name), topic,
                lambda data, h=holder: self._on_record(h["topic"], data), reliable, raw=True)
            holder["topic"] = sub.topic_name
            self.record_subs[sub.topic_name] = sub
            if writer is not None:
                self._rec_connections[sub.topic_name] = writer.add_connection(
                    sub.topic_name, type_name, typestore=typestore)

    @staticmethod
    def _fq(namespace: str, name: str) -> str:
        ns = namespace.rstrip("/")
        return f"{ns}/{name}" if ns else f"/{name}"

    def _on_record(self, topic: str, data: bytes) -> None:
        self.recorded[topic] += 1
        self.dirty = True
        if self.writer is not None:
            self.writer.write(self._rec_connections[topic], self.now_ns, data)

    def raw_publisher(self, topic: str, type_name: str) -> Any:
        if topic not in self.raw_publishers:
            pub = self.create_publisher(msg_class(type_name), topic, self.reliable)
            self.raw_publishers[topic] = pub
        return self.raw_publishers[topic]

    def _on_ack(self, msg: DiagnosticStatus) -> None:
        self.ack_seq += 1
        entry: dict[str, Any] = {"tick": msg.message, "rx": {}, "tx": {}, "matched": {}, "sources": {},
                                 "seq": self.ack_seq}
        for kv in msg.values:
            for prefix, key in ((RX_PREFIX, "rx"), (TX_PREFIX, "tx"), (MATCHED_PREFIX, "matched"),
                                (SOURCES_PREFIX, "sources")):
                if kv.key.startswith(prefix):
                    entry[key][kv.key[len(prefix):]] = int(kv.value)
        self.acks[msg.name] = entry
        self.dirty = True

    # ---------------------------------------------------------------- protocol
    def send_sync(self, tick_label: str, handshake: bool = False) -> None:
        # level WARN asks the nodes to add their connection state (start-up handshake only)
        msg = DiagnosticStatus(name="replay", message=tick_label,
                               level=DiagnosticStatus.WARN if handshake else DiagnosticStatus.OK)
        msg.values = [KeyValue(key=TX_PREFIX + pub.topic_name, value=str(self.tx[pub.topic_name]))
                      for pub in self.raw_publishers.values()]
        self.sync_pub.publish(msg)

    def publish_raw(self, topic: str, data: bytes) -> None:
        pub = self.raw_publishers[topic]
        pub.publish(data)
        self.tx[pub.topic_name] += 1

    def totals(self) -> Counter[str]:
        total = Counter(self.tx)
        total.update(self.tx_dead)
        for ack in self.acks.values():
            total.update(ack["tx"])
        return total

    def forget_node(self, name: str) -> None:
        """A node process died: keep what it published in the totals, drop its ack."""
        ack = self.acks.pop(name, None)
        if ack is not None:
            self.tx_dead.update(ack["tx"])
        self.rx_offsets.pop(name, None)

    def counts_snapshot(self) -> tuple:
        return (tuple(sorted((n, tuple(sorted(a["rx"].items())), tuple(sorted(a["tx"].items())))
                             for n, a in self.acks.items())),
                tuple(sorted(self.recorded.items())))

    def rebaseline(self) -> None:
        """After a respawn: what every subscriber has now is, from here on, complete.

        Messages in flight to or from the dead process are lost with it; a new process
        starts counting from zero. Offsets make every count match the totals again, so the
        protocol carries on (lossless from here, not across the crash).
        """
        total = self.totals()
        for name, ack in self.acks.items():
            self.rx_offsets[name] = Counter({t: total.get(t, 0) - n for t, n in ack["rx"].items()})
        for topic in self.record_subs:
            self.recorded_offsets[topic] = total.get(topic, 0) - self.recorded[topic]

    def quiescent(self, tick_label: str) -> bool:
        if set(self.acks) < self.expected_nodes:
            return False
        if any(self.acks[n]["tick"] != tick_label for n in self.expected_nodes):
            return False
        total = self.totals()
        for name in self.expected_nodes:
            offsets = self.rx_offsets.get(name, Counter())
            for topic, n in self.acks[name]["rx"].items():
                if n + offsets[topic] != total.get(topic, 0):
                    return False
        return all(self.recorded[t] + self.recorded_offsets[t] == total.get(t, 0)
                   for t in self.record_subs if t != "/diagnostics")

    def acked_since(self, seq: int, tick_label: str) -> bool:
        """Every node has acknowledged ``tick_label`` after ack number ``seq``."""
        return set(self.acks) >= self.expected_nodes and all(
            self.acks[n]["tick"] == tick_label and self.acks[n]["seq"] > seq for n in self.expected_nodes)

    def connected(self) -> bool:
        """Every publisher sees every subscriber of its topic, and vice versa."""
        if set(self.acks) < self.expected_nodes:
            return False
        readers: Counter[str] = Counter()
        for name in self.expected_nodes:
            readers.update(self.acks[name]["rx"].keys())
        for topic in self.record_subs:
            readers[topic] += 1
        for topic, pub in self.raw_publishers.items():
            if pub.get_subscription_count() < readers[pub.topic_name]:
                return False
        for name in self.expected_nodes:
            ack = self.acks[name]
            for topic, matched in ack["matched"].items():
                if matched < readers[topic]:
                    return False
            for topic, sources in ack["sources"].items():
                publishers = int(any(p.topic_name == topic for p in self.raw_publishers.values())
                                 or any(topic in self.acks[o]["matched"] for o in self.acks))
                if sources < publishers:
                    return False
        for topic, sub in self.record_subs.items():
            if topic != "/diagnostics" and sub.get_publisher_count() < 1:
                return False
        return True


#: A node that keeps dying is not respawned forever.
MAX_RESPAWNS = 3


def _spin_until(driver, executor, group, predicate, resend, timeout: float, what: str,
                tick_label: str | None = None) -> None:
    deadline = time.monotonic() + timeout
    last_send = time.monotonic()
    resend()
    driver.dirty = True
    while True:
        if driver.dirty:
            driver.dirty = False
            if predicate():
                return
        executor.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if now - last_send > RESEND_S:
            check_clock_owner(driver)      # a stalled step is where a second clock shows
            dead = group.check()
            if dead:
                names = ", ".join(f"{n.spec.name} (exit {n.process.returncode}"
                                  + (f": {words}" if (words := n.last_words()) else "") + ")" for n in dead)
                # Exit 2 is a bad parameter: a respawn would only repeat it.
                if tick_label is None or any(n.process.returncode == 2 or n.restarts >= MAX_RESPAWNS
                                             for n in dead):
                    raise ReplayError(f"node process exited during {what}: {names}")
                _respawn(driver, executor, group, dead, tick_label, timeout)
                deadline = time.monotonic() + timeout
            resend()
            last_send = now
        if now > deadline:
            raise ReplayError(f"timed out during {what}; acks: {driver.acks}")


def check_clock_owner(driver) -> None:
    """A replay owns ``/clock`` in its domain: a second publisher (another replay, a simulator,
    a bag player) makes every node hear two clocks, jump back and reset, and the replay stall."""
    if driver.count_publishers("/clock") > 1:
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        raise ReplayError(
            f"another node publishes /clock in ROS_DOMAIN_ID={domain} (another replay, a simulator or "
            "a bag player?): a replay owns the clock of its domain; run it in a free one, e.g. "
            "ROS_DOMAIN_ID=42 vehicle-estimation replay ...")


def _respawn(driver, executor, group, dead, tick_label: str, timeout: float) -> None:
    """Restart crashed nodes mid-replay and carry on from where every process stands.

    Like the live launcher, the replay respawns a node that died (a crash, ``kill -9``); the
    mass node resumes from its persisted state (``persist.path``). The new process is waited
    for with handshake syncs at the current tick until it is connected and every count has
    settled; then the player re-baselines its bookkeeping (:meth:`ReplayDriver.rebaseline`).
    What was in flight to the dead process is lost with it: the replay stays lossless from the
    respawn on, and says how many messages the crash cost.
    """
    for node in dead:
        name = driver._fq(group.namespace, node.spec.name)
        say(f"replay: {node.spec.name} exited with {node.process.returncode}; respawning "
            f"(restart {node.restarts + 1})")
        driver.forget_node(name)
        node.restarts += 1
        group.restart(node)
    deadline = time.monotonic() + timeout
    previous = None
    while True:
        seq = driver.ack_seq
        driver.send_sync(tick_label, handshake=True)
        last_send = time.monotonic()
        while not (driver.acked_since(seq, tick_label) and driver.connected()):
            executor.spin_once(timeout_sec=0.05)
            if time.monotonic() > deadline:
                raise ReplayError(f"respawned node never came back; acks: {driver.acks}")
            if time.monotonic() - last_send > RESEND_S:
                seq = driver.ack_seq
                driver.send_sync(tick_label, handshake=True)
                last_send = time.monotonic()
        snapshot = driver.counts_snapshot()
        if snapshot == previous:
            break
        previous = snapshot
        end = time.monotonic() + 0.2
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
    driver.rebaseline()


def handshake_ns(t_start_ns: int) -> int:
    """Clock and sync label of the start-up handshake: 1 s before the bag, but never negative.

    ROS time cannot be negative (rclpy raises on it in every node), and bags from simulators,
    CSV exports and many loggers start at 0 s. The handshake only has to come before the first
    tick (``t_start + tick``), which 0 does.
    """
    return max(t_start_ns - 10**9, 0)


def handshake(driver, executor, group, t_start_ns: int, timeout: float) -> None:
    t_ns = handshake_ns(t_start_ns)
    label = str(t_ns)
    _spin_until(driver, executor, group, lambda: driver.connected() and driver.quiescent(label),
                lambda: (driver.clock_pub.publish(_clock(t_ns)), driver.send_sync(label, handshake=True)),
                timeout, "start-up (waiting for every node and connection)")


#: Wall time between two looks for a second /clock while the replay runs [s]: discovery of a
#: participant that starts later takes up to a few seconds, and a look costs a graph query.
CLOCK_CHECK_PERIOD_S = 1.0


def tick(driver, executor, group, tick_ns: int, timeout: float) -> None:
    now = time.monotonic()
    if now - driver.clock_checked > CLOCK_CHECK_PERIOD_S:
        driver.clock_checked = now
        check_clock_owner(driver)
    driver.now_ns = tick_ns
    driver.clock_pub.publish(_clock(tick_ns))
    label = str(tick_ns)
    _spin_until(driver, executor, group, lambda: driver.quiescent(label),
                lambda: driver.send_sync(label), timeout, f"tick {label}", tick_label=label)


def _clock(ns: int) -> Clock:
    msg = Clock()
    msg.clock.sec = ns // 1_000_000_000
    msg.clock.nanosec = ns % 1_000_000_000
    return msg
