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

The player/recorder node and the per-tick protocol are :mod:`.replay_driver`; this module
plays a bag through them and is the command ``vehicle-estimation replay``.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import rclpy
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from tqdm import tqdm

from vehicle_estimation.contract import topics
from vehicle_estimation.io.msgconvert import jazzy_typestore, ros1_to_cdr
from vehicle_estimation.launcher.options import persisted_state_overrides
from vehicle_estimation.launcher.processes import claim_domain_id
from vehicle_estimation.launcher.replay_driver import (
    ReplayDriver,
    ReplayError,
    check_clock_owner,
    handshake,
    say,
    tick,
)
from vehicle_estimation.ros import PIPELINE
from vehicle_estimation.ros.runtime.spin import make_executor

DEFAULT_TICK_S = 0.1


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


class _DdsReplay:
    """The node processes of ``group``, played to over DDS by a :class:`ReplayDriver`."""

    def __init__(self, group: Any, namespace: str, writer: Writer | None, typestore: Any,
                 stall_timeout: float) -> None:
        self.group = group
        self.stall_timeout = stall_timeout
        rclpy.init(args=["--ros-args", "-p", "use_sim_time:=false"])
        self.driver = ReplayDriver(namespace, [s.name for s in PIPELINE], writer, typestore)
        self.executor = make_executor()
        self.executor.add_node(self.driver)
        group.start()

    def add_input(self, topic: str, type_name: str) -> str:
        return self.driver.raw_publisher(topic, type_name).topic_name

    def handshake(self, t_start_ns: int, timeout: float) -> None:
        handshake(self.driver, self.executor, self.group, t_start_ns, timeout)

    def publish(self, topic: str, data: bytes) -> None:
        self.driver.publish_raw(topic, data)

    def tick(self, tick_ns: int) -> None:
        tick(self.driver, self.executor, self.group, tick_ns, self.stall_timeout)

    def finish(self) -> None:
        check_clock_owner(self.driver)      # a replay shorter than discovery: one last look

    def close(self, stats: ReplayStats) -> None:
        self.group.stop()
        driver = self.driver
        for topic in stats.read:
            counts = [ack["rx"][topic] + driver.rx_offsets.get(name, Counter())[topic]
                      for name, ack in driver.acks.items() if topic in ack["rx"]]
            stats.processed[topic] = min(counts) if counts else 0
        stats.recorded = Counter(driver.recorded)
        stats.respawns = sum(n.restarts for n in self.group.nodes)
        self.executor.shutdown()
        driver.destroy_node()
        rclpy.try_shutdown()


def replay(bag: Path, out: Path | None, group_factory, *, namespace: str = "/",
           tick_s: float = DEFAULT_TICK_S, progress: bool = True, startup_timeout: float = 60.0,
           stall_timeout: float = 60.0,
           tick_callback: Callable[[float], None] | None = None,
           remap: dict[str, str] | None = None, in_process: bool = False,
           state_dir: Path | None = None) -> ReplayStats:
    """Play ``bag`` through nodes started by ``group_factory(overrides)``; record to ``out``.

    ``remap``: ``{FROM: TO}`` pairs as ``--remap FROM:=TO`` gives them, the contract topic on
    one side and the bag's on the other (:func:`vehicle_estimation.contract.topics.bag_to_contract`;
    a leading '/' does not matter).

    ``in_process``: the same nodes, with the same parameters, in this process without DDS
    (:mod:`.replay_in_process`); the recorded estimates are the same bytes.

    ``state_dir``: the nodes resume from the state files there and leave theirs (the mass, the
    fusion's speed scale), as ``run`` does under ``--state-dir``: bags replayed one after the
    other as a vehicle's consecutive drives. None: a fresh directory, removed at the end.

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
    # Without a state_dir, fresh state files per replay: a respawned node resumes from them,
    # while a new replay never inherits another run's estimate (that would break replay
    # determinism). Nothing is respawned in one process, where the files (an fsync a second of
    # bag) would only cost time.
    keep_state = state_dir is not None
    if state_dir is None:
        state_dir = Path(tempfile.mkdtemp(prefix="vehicle_estimation_replay_"))
    if keep_state or not in_process:
        for node, values in persisted_state_overrides(state_dir, namespace).items():
            overrides.setdefault(node, {}).update(values)
    writer = None
    if out is not None:
        if out.exists():
            raise ReplayError(f"output bag {out} exists already")
        if out.suffix == ".bag":
            raise ReplayError(f"output bag {out}: a rosbag2 directory must not end in '.bag' (it would be "
                              f"read as a ROS 1 bag file); name it e.g. {out.with_suffix('')}")
    if in_process:
        for values in overrides.values():
            values["use_sim_time"] = "false"     # the bus sets the clocks, not /clock
            values["sync.enabled"] = "false"
    group = group_factory(overrides)
    if out is not None:
        writer = Writer(out, version=8, storage_plugin=StoragePlugin.MCAP)
        writer.open()
    engine: Any = None
    wall0 = time.monotonic()
    bar = None
    claim = None
    try:
        if not in_process and "ROS_DOMAIN_ID" not in os.environ:
            # A domain of its own: another replay, or the vehicle stack, must not share our
            # /clock and sync topics. The nodes inherit it with the environment.
            try:
                claim = claim_domain_id()
            except RuntimeError as exc:
                raise ReplayError(str(exc)) from None
            os.environ["ROS_DOMAIN_ID"] = str(claim.domain)
            say(f"replay: in ROS domain {claim.domain} (set ROS_DOMAIN_ID to choose one)")
        if in_process:
            from vehicle_estimation.launcher.replay_in_process import InProcessReplay
            engine = InProcessReplay(group, namespace, writer, typestore)
        else:
            engine = _DdsReplay(group, namespace, writer, typestore, stall_timeout)
        wall0 = time.monotonic()
        with AnyReader([bag], default_typestore=typestore) as reader:
            play_ids, truth_ids = _topic_plan(reader.connections, remap, input_topics, truth_topics)
            play = [c for c in reader.connections if c.id in play_ids]
            truth = [c for c in reader.connections if c.id in truth_ids]
            if not play:
                raise ReplayError(f"{bag}: none of the input topics {sorted(input_topics)} is in the bag "
                                  "(use --remap FROM:=TO for a bag with other topic names)")
            played_as = {}
            for conn in play:
                played_as[play_ids[conn.id]] = engine.add_input(play_ids[conn.id], conn.msgtype)
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
            engine.handshake(t_start, startup_timeout)
            bar = _progress_bar(progress, (t_end - t_start) * 1e-9)
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
                    engine.tick(next_tick)
                    stats.ticks += 1
                    next_tick += tick_ns
                    if tick_callback is not None:
                        tick_callback((next_tick - t_start) * 1e-9)
                    bar.update(min((next_tick - t_start) * 1e-9, bar.total) - bar.n)
                topic = play_ids[conn.id]
                engine.publish(topic, to_cdr(conn.id, data))
                stats.read[played_as[topic]] += 1
            # Flush: advance past the end by the deepest release delay plus two ticks.
            flush_end = t_end + int((len(PIPELINE) + 2) * tick_ns)
            while next_tick <= flush_end:
                engine.tick(next_tick)
                stats.ticks += 1
                next_tick += tick_ns
            engine.finish()
            bar.update(bar.total - bar.n)
            stats.bag_s = (t_end - t_start) * 1e-9
    finally:
        stats.wall_s = time.monotonic() - wall0
        if bar is not None:
            bar.close()
        if engine is not None:
            engine.close(stats)
        else:
            group.stop()
        if not keep_state:
            shutil.rmtree(state_dir, ignore_errors=True)
        if writer is not None:
            writer.close()
        if claim is not None:
            os.environ.pop("ROS_DOMAIN_ID", None)
            claim.release()
    return stats


def _progress_bar(enabled: bool, total_s: float) -> tqdm:
    """Seconds of bag played. Drawn on a terminal only (``disable=None``): a log gets no frames."""
    return tqdm(total=total_s, desc="replay", unit="s", file=sys.stderr, mininterval=0.5,
                disable=None if enabled else True,
                bar_format="{desc} {percentage:5.1f}%|{bar:30}| bag {n:.1f}/{total:.1f} s "
                           "[{elapsed}<{remaining}, {rate_noinv_fmt}]")


#: Fault injection for tests: ``SECONDS:FILE[,SECONDS:FILE...]``. Once the replay has played
#: SECONDS of the bag it says so on stderr and waits until FILE exists, so that a test can kill
#: a node at a known bag time instead of racing the replay.
PAUSE_ENV = "VEHICLE_ESTIMATION_REPLAY_PAUSE"


def _pauses_from_environment() -> list[tuple[float, Path]]:
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
        say(f"replay: paused at {seconds:.1f} s of bag until {path} exists")
        while not path.exists():
            time.sleep(0.05)
    return pauses


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


# ------------------------------------------------------------------------------ command
def add_arguments(p: argparse.ArgumentParser) -> None:
    from vehicle_estimation.launcher.options import add_node_options, add_remap_option
    p.add_argument("bag", help="rosbag2 directory (MCAP or sqlite3) or ROS 1 .bag file; stamps may start at 0 s")
    p.add_argument("--record", required=True, help="output bag directory (MCAP)")
    p.add_argument("--tick", type=float, default=DEFAULT_TICK_S, help="replay tick of bag time [s]")
    p.add_argument("--log-dir", default=None, help="write each node's log here")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--in-process", action="store_true",
                   help="run the nodes in this process without DDS (the same estimates, on one core at about "
                        "half the CPU; node logs go to this process's stderr)")
    p.add_argument("--state-dir", default=None,
                   help="resume the mass and the fusion's learnt speed scale from the state files here and "
                        "leave them there (as `run --state-dir`): replay bags one after the other as a "
                        "vehicle's consecutive drives; default: a fresh directory per replay")
    add_remap_option(p, "play a bag topic as a contract topic, ROS-style CONTRACT:=BAG_TOPIC (e.g. "
                        "imu/data:=/sensors/imu; the reverse order is taken too)")
    add_node_options(p)


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.io.inspect_bag import InspectError, format_summary, summarize
    from vehicle_estimation.launcher.options import node_group, params_files
    # What `inspect` says of this bag with these params: the sources and fallbacks each node
    # will use, and what will stay empty, before minutes of replay.
    try:
        print(format_summary(summarize(Path(args.bag), params_files(args), dict(args.remap))), file=sys.stderr)
    except (InspectError, OSError, ValueError) as exc:
        print(f"replay: cannot inspect {args.bag} ({exc}); replaying anyway", file=sys.stderr)
    record = Path(args.record) if args.record else None
    log_dir = Path(args.log_dir) if args.log_dir else None
    if log_dir:
        log_dir.mkdir(parents=True, exist_ok=True)
    try:
        stats = replay(Path(args.bag), record, lambda ov: node_group(args, ov, log_dir),
                       namespace=args.namespace, tick_s=args.tick, progress=not args.quiet,
                       remap=dict(args.remap), in_process=args.in_process,
                       state_dir=Path(args.state_dir) if args.state_dir else None)
    except ReplayError as exc:
        print(f"replay failed: {exc}", file=sys.stderr)
        return 1
    print_stats(stats)
    return 0 if stats.lossless else 1
