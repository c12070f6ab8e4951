"""``replay --in-process``: the four nodes in the replay's own process, without DDS.

The node classes, their parameters (the same command-line arguments that the node processes
get: params files, namespace, ``-p`` overrides) and their handlers are those of the DDS
replay; only the transport differs (:class:`~vehicle_estimation.ros.runtime.in_process.InProcessBus`).
The player hands the bag's CDR bytes to the bus, ticks it, and records what the nodes publish
with the tick as log time, exactly as the DDS recorder does, so the two replays write the same
bytes (a test compares them).

The nodes live in an rclpy context of their own with automatic discovery off: nothing of a
replay is visible on the machine's ROS graph, and any number of in-process replays (``batch``
workers) run side by side, each in its own process.
"""

from __future__ import annotations

import os
from collections import Counter
from typing import Any

import rclpy
from rclpy.expand_topic_name import expand_topic_name
from rosbags.rosbag2 import Writer

from vehicle_estimation.launcher.replay_driver import DIAGNOSTICS_TYPE, RECORDED_TOPICS, ReplayError, msg_class
from vehicle_estimation.ros.runtime.in_process import InProcessBus
from vehicle_estimation.ros.runtime.parameters import ParameterError

#: The node name topics are resolved as (as the DDS replay's player node): it only matters for
#: private names, which the contract does not use.
PLAYER = "replay_player"

def _isolated_context() -> rclpy.Context:
    """An rclpy context that discovers nothing: the nodes' only traffic is the bus."""
    context = rclpy.Context()
    saved = os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE")
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    try:
        rclpy.init(args=[], context=context)
    finally:
        if saved is None:
            os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
        else:
            os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = saved
    return context


class InProcessReplay:
    """The replay engine of :func:`vehicle_estimation.launcher.replay.replay` for ``in_process``.

    ``group`` is the :class:`~vehicle_estimation.launcher.processes.NodeGroup` the DDS replay
    would start; its nodes' arguments are used as they are, its processes never started.
    """

    def __init__(self, group: Any, namespace: str, writer: Writer | None, typestore: Any) -> None:
        self.namespace = namespace
        self.writer = writer
        self.bus = InProcessBus()
        self.recorded: Counter[str] = Counter()
        self._inputs: dict[str, tuple[str, Any]] = {}    # contract topic -> (resolved name, type)
        self.context = _isolated_context()
        self.nodes: list[Any] = []
        try:
            try:
                group.make_in_process(self.nodes, transport=self.bus, context=self.context, enable_rosout=False,
                                      start_parameter_services=False)
            except ParameterError as exc:
                raise ReplayError(str(exc)) from None
            self._record(list(RECORDED_TOPICS) + [("/diagnostics", DIAGNOSTICS_TYPE)], typestore)
        except BaseException:
            self._shutdown()
            raise

    def _record(self, recorded: list[tuple[str, str]], typestore: Any) -> None:
        for topic, type_name in recorded:
            name = expand_topic_name(topic, PLAYER, self.namespace)
            connection = (self.writer.add_connection(name, type_name, typestore=typestore)
                          if self.writer is not None else None)

            def write(message: tuple[bytes, bool], name: str = name, connection: Any = connection,
                      type_name: str = type_name) -> None:
                self.recorded[name] += 1
                if connection is not None:
                    data, canonical = message
                    if not canonical:
                        # rclpy's serializer leaves the CDR alignment padding as it finds it in
                        # memory, where a DDS writer zeroes it: the same values, other bytes.
                        # Written again by rosbags, the padding is zero as in the DDS recording.
                        # A DDS writer also pads the payload to a multiple of 4 bytes (a message
                        # that ends in a uint8, as NavSatFix does), which rosbags does not.
                        data = bytes(typestore.serialize_cdr(typestore.deserialize_cdr(data, type_name), type_name))
                        data += bytes(-len(data) % 4)
                    self.writer.write(connection, self.bus.now_ns, data)

            self.bus.create_recording(name, write)

    # ------------------------------------------------------------ the replay's engine interface
    def add_input(self, topic: str, type_name: str) -> str:
        name = expand_topic_name(topic, PLAYER, self.namespace)
        self._inputs[topic] = (name, msg_class(type_name))
        return name

    def handshake(self, t_start_ns: int, timeout: float) -> None:
        from vehicle_estimation.launcher.replay_driver import handshake_ns
        # The DDS replay's start-up sync: the same clock and release, so both start alike.
        self.bus.tick(handshake_ns(t_start_ns))

    def publish(self, topic: str, data: bytes) -> None:
        name, msg_type = self._inputs[topic]
        self.bus.publish_bytes(name, msg_type, data)

    def tick(self, tick_ns: int) -> None:
        self.bus.tick(tick_ns)

    def finish(self) -> None:
        pass

    def close(self, stats: Any) -> None:
        for topic in stats.read:
            counts = [node.health.rx[topic] for node in self.nodes if topic in node.health.rx]
            stats.processed[topic] = min(counts) if counts else 0
        stats.recorded = Counter(self.recorded)
        self._shutdown()

    def _shutdown(self) -> None:
        for node in self.nodes:
            node.destroy_node()
        self.nodes = []
        rclpy.try_shutdown(context=self.context)
