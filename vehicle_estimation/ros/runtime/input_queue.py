"""The stamp-ordered queue of a node's sensor inputs, and the checks every input passes.

Sensor messages of different topics reach a node in no guaranteed order, so each node pushes
them into this queue and releases them to their handlers in stamp order up to a horizon:
+inf live (every message as it arrives), ``T - sync.release_delay`` at a replay tick T.

Ties on the stamp are broken by topic name, then arrival order within the topic (FIFO per
topic), never by arrival order across topics: that is not reproducible. Stamps are integer
nanoseconds: stamps on a replay tick boundary must fall on the same side of it in every node,
which float seconds near 1.7e9 cannot promise.
"""

from __future__ import annotations

import heapq
import itertools
import math
import os
import traceback
from typing import Any, Callable, Protocol


class InputOwner(Protocol):
    """What the queue asks of the node that owns it."""

    def reject(self, reason: str) -> None: ...
    def set_missing(self, what: str, missing: bool) -> None: ...
    def on_time_jump(self, text: str) -> None: ...
    def get_logger(self) -> Any: ...


Handler = Callable[[float, Any], None]

#: ``1`` switches every handler off (development: the bench's floors, ``evaluation.bench_floor``):
#: inputs are received, decoded, queued and released to nobody. Read when a queue is made.
HANDLERS_OFF_ENV = "VEHICLE_ESTIMATION_HANDLERS_OFF"


class StampOrderedInputs:
    """Sensor inputs ordered by (stamp ns, topic, arrival), released to their handlers.

    Before a handler runs, a message passes the checks of :meth:`_consistent`; a handler that
    raises is counted as ``<topic>:handler_error`` and logged, never fatal. A topic whose own
    stamps jump back by more than ``time_jump_reset_s`` (a bag loop, a restarted driver) makes
    the owner reset its estimators.
    """

    def __init__(self, owner: InputOwner, time_jump_reset_s: float, frozen_imu_samples: int) -> None:
        self.owner = owner
        self.time_jump_reset_s = time_jump_reset_s
        self.frozen_imu_samples = frozen_imu_samples
        self._heap: list[tuple[int, str, int, Handler, Any]] = []
        self._seq = itertools.count()
        self._last_stamp_by_topic: dict[str, float] = {}
        self._frames: dict[str, str] = {}
        self._imu_repeat: dict[str, tuple[tuple[float, ...], int]] = {}
        self._frozen: set[str] = set()      # topics now flagged frozen
        self.max_len = 0      # longest the queue has been (load check)
        self.handlers_off = os.environ.get(HANDLERS_OFF_ENV) == "1"
        if self.handlers_off:
            owner.get_logger().warn(f"{HANDLERS_OFF_ENV}=1: every input is dropped unhandled (a bench floor)")

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, ns: int, topic: str, handler: Handler, msg: Any) -> None:
        heapq.heappush(self._heap, (ns, topic, next(self._seq), handler, msg))
        self.max_len = max(self.max_len, len(self._heap))

    def drop_all(self) -> None:
        """Forget queued inputs and each topic's last stamp (the replay clock went back)."""
        self._heap.clear()
        self._last_stamp_by_topic.clear()

    def release(self, horizon_ns: float) -> None:
        """Hand queued inputs stamped before ``horizon_ns`` (integer ns, or inf) to their handlers."""
        if self.handlers_off:
            while self._heap and self._heap[0][0] < horizon_ns:
                heapq.heappop(self._heap)
            return
        while self._heap and self._heap[0][0] < horizon_ns:
            ns, topic, _, handler, msg = heapq.heappop(self._heap)
            t = ns * 1e-9
            # A jump back is judged per topic: a bag played in a loop or a restarted driver makes
            # a topic's own stamps go backwards, while a topic that is merely processed late
            # behind a busier one (a backlog in live mode) keeps its own order.
            last = self._last_stamp_by_topic.get(topic, -math.inf)
            if t < last - self.time_jump_reset_s:
                self._last_stamp_by_topic.clear()
                self._frames.clear()
                self.owner.on_time_jump(
                    f"time jumped back {last - t:.3f} s on {topic}: "
                    "resetting estimators (bag loop or restarted source)")
            self._last_stamp_by_topic[topic] = t if t > last or t < last - self.time_jump_reset_s else last
            if not self._consistent(topic, msg):
                continue
            try:
                handler(t, msg)
            except Exception:  # never let one bad message take the node down
                self.owner.reject(f"{topic}:handler_error")
                self.owner.get_logger().error(
                    f"error handling {topic} at t={t:.3f}:\n{traceback.format_exc(limit=4)}",
                    throttle_duration_sec=5.0)

    def _consistent(self, topic: str, msg: Any) -> bool:
        """Checks every sensor input gets before its handler (rejections are counted):

        * ``frame_id``: the frame of a topic's first message is its frame; a message in another
          frame is a second source on the topic or a misconfigured driver (``<topic>:frame_id``).
          The nodes do not transform: the contract fixes each input's frame (README).
        * a frozen IMU (``frozen_imu_samples``): ``<topic>:frozen``.
        """
        header = getattr(msg, "header", None)
        if header is not None:
            frame = header.frame_id
            expected = self._frames.get(topic)
            if expected is None:
                self._frames[topic] = expected = frame
            if frame != expected:
                self.owner.reject(f"{topic}:frame_id")
                self.owner.get_logger().warn(f"{topic}: frame_id '{frame}', expected '{expected}': rejected",
                                             throttle_duration_sec=5.0)
                return False
        if self.frozen_imu_samples > 0 and hasattr(msg, "linear_acceleration"):
            a, w = msg.linear_acceleration, msg.angular_velocity
            key = (a.x, a.y, a.z, w.x, w.y, w.z)
            last, repeats = self._imu_repeat.get(topic, ((), 0))
            repeats = repeats + 1 if key == last else 0
            self._imu_repeat[topic] = (key, repeats)
            if repeats >= self.frozen_imu_samples:
                self.owner.reject(f"{topic}:frozen")
                self.owner.set_missing(f"{topic} (frozen)", True)
                self._frozen.add(topic)
                return False
            if topic in self._frozen:
                self._frozen.discard(topic)
                self.owner.set_missing(f"{topic} (frozen)", False)
        return True
