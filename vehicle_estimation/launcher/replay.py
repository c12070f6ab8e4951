"""Replay a bag through the nodes, losslessly and deterministically, and record the outputs.

The player reads a bag (rosbag2 MCAP or sqlite3, or a ROS 1 ``.bag``, written by anyone) with
``rosbags`` and publishes the raw CDR of every input topic of the contract; a ROS 1 bag's
messages are converted to the ROS 2 Jazzy types of the same name first (``msgconvert``).
``remap`` plays a bag topic under a contract name (a recorder's own names); topics that are
neither inputs nor ground truth are ignored. Stamps may start at 0 s. Time advances in ticks of
``tick_s`` of bag time. For each tick the player

1. publishes the bag messages logged in the tick, and ``/clock``;
2. publishes a sync request (``replay/sync``) carrying the tick time and how many messages it
   has published on each topic;
3. waits until every node has received all of them, processed its inputs up to the tick
   minus its release delay, and every estimate published so far has reached every
   subscriber (including the recorder).

So no message is lost however slow a node is, the replay runs as fast as the slowest node
allows, and the result does not depend on scheduling (see ``ros.runtime``). Ground-truth
topics of the input bag are copied to the output bag (as Jazzy CDR).
"""

from __future__ import annotations

import importlib
import math
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import rclpy
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosgraph_msgs.msg import Clock

from vehicle_estimation.contract import topics
from vehicle_estimation.io.msgconvert import jazzy_typestore, ros1_to_cdr
from vehicle_estimation.ros import PIPELINE
from vehicle_estimation.ros.runtime.qos import replay_qos
from vehicle_estimation.ros.runtime.spin import make_executor
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
    (topics.ROAD_SLOPE, "std_msgs/msg/Float64"),
    (topics.ROAD_SLOPE_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
    (topics.VEHICLE_STATE, "geometry_msgs/msg/TwistWithCovarianceStamped"),
    (topics.SIDESLIP, "std_msgs/msg/Float64"),
    (topics.SIDESLIP_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
    (topics.MASS, "std_msgs/msg/Float64"),
    (topics.MASS_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
)
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"

DEFAULT_TICK_S = 0.1
#: Nodes acknowledge by themselves whenever their counts change after a sync; a resend is
#: only a safety net.
RESEND_S = 0.25


class ReplayError(RuntimeError):
    pass


def release_delays(tick_s: float) -> dict[str, dict[str, str]]:
    """Per-node ``-p`` overrides for deterministic replay (see ``ros.runtime``)."""
    overrides = {}
    for spec in PIPELINE:
        overrides[spec.name] = {
            "use_sim_time": "true",
            "sync.enabled": "true",
            "sync.release_delay": repr(spec.depth * tick_s),
            # A feedback edge goes from a deeper node back to a shallower one: its values are
            # produced up to (depth difference + 1) ticks later, so lag by the whole pipeline.
            "sync.feedback_lag": repr((len(PIPELINE) + 1) * tick_s),
        }
    return overrides


def msg_class(type_name: str) -> Any:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)



def _topic_plan(connections, remap: dict[str, str], input_topics: set[str],
                truth_topics: set[str]) -> tuple[dict[int, str], dict[int, str]]:
    """Bag connection id -> contract topic, for the inputs to play and the truth to copy.

    ``remap``: bag topic -> contract topic (:func:`vehicle_estimation.contract.topics.bag_to_contract`);
    a bag topic that is neither an input nor ground truth (after remapping) is ignored.
    """
    in_bag = {topics.relative(c.topic) for c in connections}
    for source, target in remap.items():
        if source not in in_bag:
            raise ReplayError(f"--remap {source}:={target}: the bag has no topic {source} "
                              f"(it has {', '.join(sorted(in_bag))})")
    play: dict[int, str] = {}
    truth: dict[int, str] = {}
    played_from: dict[str, str] = {}
    for conn in connections:
        source = topics.relative(conn.topic)
        target = remap.get(source, source)
        if target in input_topics:
            if played_from.setdefault(target, source) != source:
                raise ReplayError(f"bag topics {played_from[target]} and {source} would both be played as "
                                  f"{target}; remap or drop one of them")
            if conn.msgtype != topics.INPUT_TYPES.get(target, conn.msgtype):
                raise ReplayError(f"bag topic {conn.topic} (played as {target}) has type {conn.msgtype}; "
                                  f"the contract wants {topics.INPUT_TYPES[target]}")
            play[conn.id] = target
        elif target in truth_topics:
            truth[conn.id] = target
    return play, truth


@dataclass
class ReplayStats:
    read: Counter = field(default_factory=Counter)        # topic -> messages read from the bag
    processed: dict[str, int] = field(default_factory=dict)  # topic -> min received over nodes
    recorded: Counter = field(default_factory=Counter)
    wall_s: float = 0.0
    bag_s: float = 0.0
    ticks: int = 0
    respawns: int = 0                  # node processes restarted after a crash

    @property
    def lossless(self) -> bool:
        return all(self.processed.get(t, -1) == n for t, n in self.read.items())


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
        # Count bookkeeping across a node respawn (see respawn_baseline): what each process
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


def replay(bag: Path, out: Path | None, group_factory, *, namespace: str = "/",
           tick_s: float = DEFAULT_TICK_S, progress: bool = True, startup_timeout: float = 60.0,
           stall_timeout: float = 60.0,
           tick_callback: Callable[[float], None] | None = None,
           remap: dict[str, str] | None = None) -> ReplayStats:
    """Play ``bag`` through nodes started by ``group_factory(overrides)``; record to ``out``.

    ``remap``: ``{FROM: TO}`` pairs as ``--remap FROM:=TO`` gives them, the contract topic on
    one side and the bag's on the other (:func:`vehicle_estimation.contract.topics.bag_to_contract`;
    a leading '/' does not matter).

    ``tick_callback(bag_seconds_done)`` is called after every tick (the benchmark samples
    memory with it).
    """
    stats = ReplayStats()
    typestore = jazzy_typestore()
    input_topics = {t for t in topics.INPUT_TOPICS}
    truth_topics = {t for t in topics.GROUND_TRUTH_TOPICS}
    try:
        remap = topics.bag_to_contract((remap or {}).items(), input_topics | truth_topics)
    except ValueError as exc:
        raise ReplayError(str(exc)) from None
    overrides = release_delays(tick_s)
    # A fresh state file per replay: a respawned mass node resumes from it, while a new replay
    # never inherits another run's estimate (that would break replay determinism).
    state_dir = Path(tempfile.mkdtemp(prefix="vehicle_estimation_replay_"))
    overrides.setdefault("mass", {})["persist.path"] = str(state_dir / "mass_state.json")
    group = group_factory(overrides)
    writer = None
    if out is not None:
        if out.exists():
            raise ReplayError(f"output bag {out} exists already")
        if out.suffix == ".bag":
            raise ReplayError(f"output bag {out}: a rosbag2 directory must not end in '.bag' (it would be "
                              f"read as a ROS 1 bag file); name it e.g. {out.with_suffix('')}")
        writer = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP)
        writer.open()
    rclpy.init(args=["--ros-args", "-p", "use_sim_time:=false"])
    driver = ReplayDriver(namespace, [s.name for s in PIPELINE], writer, typestore)
    executor = make_executor()
    executor.add_node(driver)
    group.start()
    wall0 = time.monotonic()
    try:
        with AnyReader([bag], default_typestore=typestore) as reader:
            play_ids, truth_ids = _topic_plan(reader.connections, remap, input_topics, truth_topics)
            play = [c for c in reader.connections if c.id in play_ids]
            truth = [c for c in reader.connections if c.id in truth_ids]
            if not play:
                raise ReplayError(f"{bag}: none of the input topics {sorted(input_topics)} is in the bag "
                                  "(use --remap FROM:=TO for a bag with other topic names)")
            for conn in play:
                driver.raw_publisher(play_ids[conn.id], conn.msgtype)
            truth_conns = {}
            if writer is not None:
                for conn in truth:
                    topic = "/" + truth_ids[conn.id]
                    if topic not in truth_conns:   # a ROS 1 bag may hold one connection per publisher
                        truth_conns[topic] = writer.add_connection(topic, conn.msgtype, typestore=typestore)
            # A ROS 1 bag holds ROS 1 serialisation: every message is converted to Jazzy CDR.
            types = {c.id: c.msgtype for c in play + truth}
            if reader.is2:
                def to_cdr(conn_id: int, data: Any) -> bytes:
                    return bytes(data)
            else:
                def to_cdr(conn_id: int, data: Any) -> bytes:
                    return ros1_to_cdr(reader.deserialize(data, types[conn_id]), types[conn_id], typestore)
            t_start, t_end = reader.start_time, reader.end_time
            _handshake(driver, executor, group, t_start, startup_timeout)
            tick_ns = int(round(tick_s * 1e9))
            pauses = _pauses_from_environment()
            next_tick = t_start + tick_ns
            for conn, timestamp, data in reader.messages(connections=play + truth):
                if conn.id not in play_ids:   # ground truth: copied when recording
                    if writer is not None:
                        writer.write(truth_conns["/" + truth_ids[conn.id]], timestamp, to_cdr(conn.id, data))
                    continue
                while timestamp >= next_tick:
                    pauses = _pause_if_asked(pauses, (next_tick - t_start) * 1e-9)
                    _tick(driver, executor, group, next_tick, stall_timeout)
                    stats.ticks += 1
                    next_tick += tick_ns
                    if tick_callback is not None:
                        tick_callback((next_tick - t_start) * 1e-9)
                    if progress:
                        _progress(next_tick - t_start, t_end - t_start, wall0)
                topic = play_ids[conn.id]
                driver.publish_raw(topic, to_cdr(conn.id, data))
                stats.read[driver.raw_publishers[topic].topic_name] += 1
            # Flush: advance past the end by the deepest release delay plus two ticks.
            flush_end = t_end + int((len(PIPELINE) + 2) * tick_ns)
            while next_tick <= flush_end:
                _tick(driver, executor, group, next_tick, stall_timeout)
                stats.ticks += 1
                next_tick += tick_ns
            _check_clock_owner(driver)      # a replay shorter than discovery: one last look
            if progress:
                _progress(t_end - t_start, t_end - t_start, wall0)
                print(file=sys.stderr)
            stats.bag_s = (t_end - t_start) * 1e-9
    finally:
        stats.wall_s = time.monotonic() - wall0
        group.stop()
        for topic in stats.read:
            counts = [ack["rx"][topic] + driver.rx_offsets.get(name, Counter())[topic]
                      for name, ack in driver.acks.items() if topic in ack["rx"]]
            stats.processed[topic] = min(counts) if counts else 0
        stats.recorded = Counter(driver.recorded)
        stats.respawns = sum(n.restarts for n in group.nodes)
        shutil.rmtree(state_dir, ignore_errors=True)
        executor.shutdown()
        driver.destroy_node()
        rclpy.try_shutdown()
        if writer is not None:
            writer.close()
    return stats


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
            _check_clock_owner(driver)      # a stalled step is where a second clock shows
            dead = group.check()
            if dead:
                names = ", ".join(f"{n.spec.name} (exit {n.process.returncode})" for n in dead)
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


def _check_clock_owner(driver) -> None:
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
        print(f"\nreplay: {node.spec.name} exited with {node.process.returncode}; respawning "
              f"(restart {node.restarts + 1})", file=sys.stderr)
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


def _handshake(driver, executor, group, t_start_ns: int, timeout: float) -> None:
    t_ns = handshake_ns(t_start_ns)
    label = str(t_ns)
    _spin_until(driver, executor, group, lambda: driver.connected() and driver.quiescent(label),
                lambda: (driver.clock_pub.publish(_clock(t_ns)), driver.send_sync(label, handshake=True)),
                timeout, "start-up (waiting for every node and connection)")


#: Wall time between two looks for a second /clock while the replay runs [s]: discovery of a
#: participant that starts later takes up to a few seconds, and a look costs a graph query.
CLOCK_CHECK_PERIOD_S = 1.0


def _tick(driver, executor, group, tick_ns: int, timeout: float) -> None:
    now = time.monotonic()
    if now - driver.clock_checked > CLOCK_CHECK_PERIOD_S:
        driver.clock_checked = now
        _check_clock_owner(driver)
    driver.now_ns = tick_ns
    driver.clock_pub.publish(_clock(tick_ns))
    label = str(tick_ns)
    _spin_until(driver, executor, group, lambda: driver.quiescent(label),
                lambda: driver.send_sync(label), timeout, f"tick {label}", tick_label=label)


#: Fault injection for tests: ``SECONDS:FILE[,SECONDS:FILE...]``. Once the replay has played
#: SECONDS of the bag it says so on stderr and waits until FILE exists, so that a test can kill
#: a node at a known bag time instead of racing the replay.
PAUSE_ENV = "VEHICLE_ESTIMATION_REPLAY_PAUSE"


def _pauses_from_environment() -> list[tuple[float, Path]]:
    import os
    spec = os.environ.get(PAUSE_ENV, "").strip()
    pauses = []
    for item in filter(None, (part.strip() for part in spec.split(","))):
        seconds, _, path = item.partition(":")
        try:
            pauses.append((float(seconds), Path(path)))
        except ValueError:
            raise ReplayError(f"{PAUSE_ENV}: {item!r} is not SECONDS:FILE") from None
    return sorted(pauses)


def _pause_if_asked(pauses: list[tuple[float, Path]], bag_s: float) -> list[tuple[float, Path]]:
    """Wait for the files of the pauses due at ``bag_s``; returns the pauses still to come.

    The node processes keep running while the player waits; nothing is published meanwhile.
    """
    while pauses and bag_s >= pauses[0][0]:
        seconds, path = pauses.pop(0)
        print(f"\nreplay: paused at {seconds:.1f} s of bag until {path} exists", file=sys.stderr, flush=True)
        while not path.exists():
            time.sleep(0.05)
    return pauses


def _clock(ns: int) -> Clock:
    msg = Clock()
    msg.clock.sec = ns // 1_000_000_000
    msg.clock.nanosec = ns % 1_000_000_000
    return msg


_last_progress = [0.0]


def _progress(done_ns: int, total_ns: int, wall0: float) -> None:
    now = time.monotonic()
    if now - _last_progress[0] < 0.5 and done_ns < total_ns:
        return
    _last_progress[0] = now
    frac = min(1.0, done_ns / total_ns) if total_ns > 0 else 1.0
    bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
    wall = max(now - wall0, 1e-9)
    print(f"\r[{bar}] {100 * frac:5.1f}%  bag {done_ns * 1e-9:7.1f}/{total_ns * 1e-9:.1f} s  "
          f"{done_ns * 1e-9 / wall:5.1f}x real time", end="", file=sys.stderr, flush=True)


def print_stats(stats: ReplayStats, out=sys.stdout) -> None:
    print(f"{'topic':32s} {'read':>9s} {'processed':>10s}", file=out)
    for topic in sorted(stats.read):
        print(f"{topic:32s} {stats.read[topic]:9d} {stats.processed.get(topic, 0):10d}", file=out)
    rate = stats.bag_s / stats.wall_s if stats.wall_s > 0 else math.nan
    print(f"replayed {stats.bag_s:.1f} s of bag in {stats.wall_s:.1f} s ({rate:.1f}x real time), "
          f"{stats.ticks} ticks; lossless: {stats.lossless}", file=out)
    if stats.respawns:
        print(f"{stats.respawns} node respawn(s) after a crash: what a dead process had queued "
              "but not processed is lost with it (counted as processed above)", file=out)
