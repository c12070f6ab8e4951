"""The lock-step replay protocol, both ends: the constants the player imports, the node's side.

The launcher's player publishes one batch of bag messages, then a sync request (a
``DiagnosticStatus`` on ``replay/sync``) carrying the tick time T in integer nanoseconds and how
many messages it has published per topic (``tx:<topic>``). A node answers on ``replay/ack``
once it has received all of them and released everything stamped before
``T - sync.release_delay``, with its own per-topic receive and publish counts (``rx:``, ``tx:``).
The player moves on only when every count matches. Messages that reach a node after its ack
(estimates of other nodes) are acknowledged again, coalesced over 1 ms of steady time, so the
player never polls.

Each node's release delay is a tick larger than that of everything it feeds on, and the
feedback edges of the paper-004 loop (state <-> slope, state <-> mass) use a lag of the whole
pipeline, so every "as of" lookup (``upstream.UpstreamHistory``) is answered from data that has
provably arrived: replaying a bag twice gives the same output bit for bit.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any, Callable

import rclpy.clock
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from vehicle_estimation.ros.runtime.qos import replay_qos

SYNC_TOPIC = "replay/sync"
ACK_TOPIC = "replay/ack"

#: Keys in a replay sync/ack DiagnosticStatus.
RX_PREFIX = "rx:"
TX_PREFIX = "tx:"
MATCHED_PREFIX = "matched:"
SOURCES_PREFIX = "sources:"


class TickRelease:
    """The release rule of a replay tick: a clock that went back resets the node, then its
    inputs stamped before ``tick - release_delay`` go to their handlers. The DDS protocol
    (:class:`ReplaySyncResponder`) applies it once a sync's counts have arrived; the in-process
    bus (``in_process``) at each of its ticks, where :meth:`try_complete` and
    :meth:`schedule_reack` have nothing to wait for."""

    def __init__(self, *, release: Callable[[int], None], on_clock_jump: Callable[[str], None],
                 release_delay_s: float, time_jump_reset_s: float) -> None:
        self.release = release
        self.on_clock_jump = on_clock_jump
        self.release_delay_ns = int(round(release_delay_s * 1e9))
        self.time_jump_reset_s = time_jump_reset_s
        self._last_tick = -math.inf

    def tick(self, tick_ns: int) -> None:
        tick = tick_ns * 1e-9
        if tick < self._last_tick - self.time_jump_reset_s:
            self.on_clock_jump(f"replay clock jumped back to {tick:.3f}: resetting estimators")
        self._last_tick = tick
        self.release(tick_ns - self.release_delay_ns)

    def try_complete(self) -> None:
        pass

    def schedule_reack(self) -> None:
        pass


class ReplaySyncResponder:
    """A node's side of the protocol: wait for the counts, release, acknowledge.

    ``release(horizon_ns)`` hands the node's queued inputs to their handlers;
    ``on_clock_jump(text)`` resets the node when the player's clock goes back (a second replay
    into a running node). ``rx``/``tx`` are the node's live per-topic counters, and
    ``publishers``/``subscriptions`` its endpoints by resolved topic name.
    """

    def __init__(self, node: Any, *, rx: Counter[str], tx: Counter[str], publishers: dict[str, Any],
                 subscriptions: dict[str, Any], release: Callable[[int], None],
                 on_clock_jump: Callable[[str], None], release_delay_s: float, time_jump_reset_s: float) -> None:
        self.node = node
        self.rx, self.tx = rx, tx
        self.publishers, self.subscriptions = publishers, subscriptions
        self._release = TickRelease(release=release, on_clock_jump=on_clock_jump,
                                    release_delay_s=release_delay_s, time_jump_reset_s=time_jump_reset_s)
        self._pending: DiagnosticStatus | None = None
        # The player's per-topic counts in the first sync this process sees: zero at a normal
        # start; the counts so far when the launcher respawns this node mid-replay.
        self._base: dict[str, int] | None = None
        self._last: DiagnosticStatus | None = None
        self._ack_pub = node.create_publisher(DiagnosticStatus, ACK_TOPIC, replay_qos())
        node.create_subscription(DiagnosticStatus, SYNC_TOPIC, self._on_sync, replay_qos())
        self._reack_timer = node.create_timer(
            0.001, self._reack, clock=rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.STEADY_TIME))
        self._reack_timer.cancel()

    def _on_sync(self, msg: DiagnosticStatus) -> None:
        self._pending = msg
        self.try_complete()

    def try_complete(self) -> None:
        """Complete the pending sync if every message it counts has arrived."""
        msg = self._pending
        if msg is None:
            return
        tick_ns = int(msg.message)  # the player's tick, integer nanoseconds of bag time
        sent = {kv.key[len(TX_PREFIX):]: int(kv.value) for kv in msg.values if kv.key.startswith(TX_PREFIX)}
        if self._base is None:
            self._base = sent
        for topic, count in sent.items():
            if topic in self.rx and self.rx[topic] < count - self._base.get(topic, 0):
                return  # not everything published before this sync has arrived yet
        self._release.tick(tick_ns)
        self._pending = None
        self._last = msg
        self._send_ack()

    def schedule_reack(self) -> None:
        """An upstream estimate arrived: acknowledge again shortly (coalesced)."""
        if self._last is not None and self._reack_timer.is_canceled():
            self._reack_timer.reset()

    def _reack(self) -> None:
        self._reack_timer.cancel()
        if self._pending is None and self._last is not None:
            self._send_ack()

    def _send_ack(self) -> None:
        msg = self._last
        ack = DiagnosticStatus(name=self.node.get_fully_qualified_name(), message=msg.message)
        ack.values = [KeyValue(key=RX_PREFIX + k, value=str(v)) for k, v in self.rx.items()]
        ack.values += [KeyValue(key=TX_PREFIX + k, value=str(self.tx[k])) for k in self.publishers]
        if msg.level != DiagnosticStatus.OK:  # the player asks for connection state at start-up
            ack.values += [KeyValue(key=MATCHED_PREFIX + k, value=str(p.get_subscription_count()))
                           for k, p in self.publishers.items()]
            ack.values += [KeyValue(key=SOURCES_PREFIX + k, value=str(s.get_publisher_count()))
                           for k, s in self.subscriptions.items()]
        self._ack_pub.publish(ack)
