"""In-process topics: the estimator nodes in one process, exchanging messages without DDS.

A replay through DDS pays for every message several times: serialisation, the middleware's
discovery and transport, one executor wake-up per message and node, and the lock-step
protocol's sync/ack round trips (``sync``). :class:`InProcessBus` stands in for the
middleware when the same node classes run in one process (``replay --in-process``): a node
created with ``transport=bus`` asks the bus, not rclpy, for its publishers, subscriptions and
diagnostics timer, and the replay drives it tick by tick with :meth:`InProcessBus.tick`.

It keeps what makes the DDS replay deterministic, so both give the same bytes:

* A subscription gets what it would get from rclpy: the serialised CDR bytes when it asked
  for ``raw`` (the bag's bytes as they are, a node's message serialised once per publish),
  else a message object.
* Messages are delivered in publication order per topic; across topics the order does not
  matter, because every node queues its inputs in stamp order (``input_queue``) and looks up
  other nodes' estimates "as of" a stamp (``upstream``).
* At tick T every node releases what is stamped before ``T - sync.release_delay`` and the
  messages it publishes reach their subscribers before the next tick: the quiescence that the
  DDS protocol waits for is here a drained queue.

Node clocks run on the replay's ticks (ROS time override, as ``/clock`` would set it), and
timers (``/diagnostics``) fire on them.

:class:`LiveBus` is the same bus for nodes composed into one live process (``run
--in-process``): each outside topic is received once from DDS for all nodes, and the estimates
go out to DDS as well as to the other nodes.
"""

from __future__ import annotations

import heapq
import itertools
from collections import defaultdict, deque
from typing import Any, Callable

from rclpy.serialization import deserialize_message, serialize_message
from rclpy.time import Time

from vehicle_estimation.ros.runtime.sync import TickRelease

Callback = Callable[[Any], None]


class _Message:
    """One publication: the object and/or its CDR bytes, each made at most once.

    ``canonical``: the bytes are the canonical serialization (zero padding, as a DDS writer and
    rosbags make them): a node published them pre-serialized (``ros.cdr``). Bytes that
    rclpy serialized from an object keep whatever its buffer held in the padding.
    """

    __slots__ = ("msg_type", "_obj", "_data", "canonical")

    def __init__(self, msg_type: Any, obj: Any = None, data: bytes | None = None, canonical: bool = False) -> None:
        self.msg_type, self._obj, self._data, self.canonical = msg_type, obj, data, canonical

    @property
    def data(self) -> bytes:
        if self._data is None:
            self._data = serialize_message(self._obj)
        return self._data

    @property
    def as_published(self) -> Any:
        """What the publisher handed over (its bytes, else its object), for an rclpy publisher."""
        return self._data if self.canonical or self._obj is None else self._obj

    @property
    def obj(self) -> Any:
        if self._obj is None:
            self._obj = deserialize_message(self._data, self.msg_type)
        return self._obj


class InProcessPublisher:
    """What :meth:`rclpy.node.Node.create_publisher` returns, as far as the nodes use it."""

    def __init__(self, bus: InProcessBus, msg_type: Any, topic_name: str) -> None:
        self.bus, self.msg_type, self.topic_name = bus, msg_type, topic_name

    def publish(self, msg: Any) -> None:
        if isinstance(msg, (bytes, bytearray, memoryview)):
            self.bus.post(self.topic_name, _Message(self.msg_type, data=bytes(msg), canonical=True))
        else:
            self.bus.post(self.topic_name, _Message(self.msg_type, obj=msg))

    def get_subscription_count(self) -> int:
        return len(self.bus.subscribers[self.topic_name])


class InProcessSubscription:
    def __init__(self, bus: InProcessBus, topic_name: str, callback: Callback, raw: bool) -> None:
        self.bus, self.topic_name, self.callback, self.raw = bus, topic_name, callback, raw

    def deliver(self, message: _Message) -> None:
        self.callback(message.data if self.raw else message.obj)

    def get_publisher_count(self) -> int:
        return len(self.bus.publishers[self.topic_name])


class _Recording(InProcessSubscription):
    """A recorder's subscription: the bytes and whether they are canonical (see ``_Message``)."""

    def deliver(self, message: _Message) -> None:
        self.callback((message.data, message.canonical))


class _Timer:
    __slots__ = ("period_ns", "callback", "next_ns")

    def __init__(self, period_ns: int, callback: Callable[[], None], next_ns: int) -> None:
        self.period_ns, self.callback, self.next_ns = period_ns, callback, next_ns


class InProcessBus:
    """Topics, timers and the tick loop of nodes living in one process (see the module doc)."""

    def __init__(self) -> None:
        self.publishers: dict[str, list[InProcessPublisher]] = defaultdict(list)
        self.subscribers: dict[str, list[InProcessSubscription]] = defaultdict(list)
        self.nodes: list[Any] = []
        self._releases: list[TickRelease] = []
        self._timers: list[tuple[int, int, _Timer]] = []     # heap of (next_ns, order, timer)
        self._timer_order = itertools.count()
        self._queue: deque[tuple[str, _Message]] = deque()
        self.now_ns = 0

    # ------------------------------------------------------------ what nodes ask for
    def attach(self, node: Any) -> None:
        """Run ``node``'s ROS clock on the bus's ticks."""
        clock = node.get_clock()
        clock._set_ros_time_is_active(True)
        clock.set_ros_time_override(Time(nanoseconds=self.now_ns))
        self.nodes.append(node)

    def create_publisher(self, msg_type: Any, topic_name: str, qos: Any = None) -> InProcessPublisher:
        pub = InProcessPublisher(self, msg_type, topic_name)
        self.publishers[topic_name].append(pub)
        return pub

    def create_subscription(self, topic_name: str, callback: Callback, *, raw: bool, msg_type: Any = None,
                            qos: Any = None) -> InProcessSubscription:
        sub = InProcessSubscription(self, topic_name, callback, raw)
        self.subscribers[topic_name].append(sub)
        return sub

    def create_recording(self, topic_name: str, callback: Callable[[tuple[bytes, bool]], None]) -> InProcessSubscription:
        """Subscribe ``callback((data, canonical))`` to every message on ``topic_name``."""
        sub = _Recording(self, topic_name, callback, raw=True)
        self.subscribers[topic_name].append(sub)
        return sub

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> _Timer:
        period_ns = max(1, int(round(period_s * 1e9)))
        timer = _Timer(period_ns, callback, self.now_ns + period_ns)
        heapq.heappush(self._timers, (timer.next_ns, next(self._timer_order), timer))
        return timer

    def create_release(self, **kwargs: Any) -> TickRelease:
        release = TickRelease(**kwargs)
        self._releases.append(release)
        return release

    # ------------------------------------------------------------ what the replay does
    def post(self, topic_name: str, message: _Message) -> None:
        self._queue.append((topic_name, message))

    def publish_bytes(self, topic_name: str, msg_type: Any, data: bytes) -> None:
        """A message from outside the nodes (the bag), delivered at once."""
        self.post(topic_name, _Message(msg_type, data=data))
        self.drain()

    def drain(self) -> None:
        """Deliver every queued message, including what the deliveries publish in turn."""
        queue, subscribers = self._queue, self.subscribers
        while queue:
            topic_name, message = queue.popleft()
            for sub in subscribers.get(topic_name, ()):
                sub.deliver(message)

    def set_time(self, t_ns: int) -> None:
        self.now_ns = t_ns
        now = Time(nanoseconds=t_ns)
        for node in self.nodes:
            node.get_clock().set_ros_time_override(now)
        while self._timers and self._timers[0][0] <= t_ns:
            _, order, timer = heapq.heappop(self._timers)
            timer.callback()
            self.drain()
            # Like an rcl timer after a clock jump: the next period from now, no burst of
            # missed calls.
            timer.next_ns = max(timer.next_ns + timer.period_ns, t_ns + 1)
            heapq.heappush(self._timers, (timer.next_ns, order, timer))

    def tick(self, tick_ns: int) -> None:
        """Advance every node to ``tick_ns``: clocks and timers, then each node's release, in
        pipeline order; every message published on the way is delivered before this returns."""
        self.set_time(tick_ns)
        for release in self._releases:
            release.tick(tick_ns)
            self.drain()


class LiveBus(InProcessBus):
    """The bus of the nodes composed into one live process (``run --in-process``).

    Live, the nodes of separate processes each receive every sensor message from DDS, decode
    and check it, and exchange their estimates through DDS again. Composed, the process takes
    each topic the nodes need from outside with one rclpy subscription (:meth:`connect`) and
    hands it to every node on the bus; what a node publishes reaches the other nodes on the
    bus and the rest of the ROS graph through one DDS publisher per topic. Nodes release their
    inputs as they arrive (no replay ticks); their timers are rclpy timers of ``host``, on
    its clock.
    """

    def __init__(self, host: Any) -> None:
        super().__init__()
        self.host = host
        self._outside: dict[str, Any] = {}                   # topic -> its DDS publisher
        self._wanted: dict[str, tuple[Any, Any]] = {}        # topic -> (type, QoS) the nodes take
        self._inputs: dict[str, Any] = {}                    # topic -> its DDS subscription

    def attach(self, node: Any) -> None:
        self.nodes.append(node)          # the node's clock stays its own

    def create_publisher(self, msg_type: Any, topic_name: str, qos: Any = None) -> InProcessPublisher:
        if topic_name not in self._outside:
            self._outside[topic_name] = self.host.create_publisher(msg_type, topic_name, qos if qos is not None else 10)
        return super().create_publisher(msg_type, topic_name)

    def create_subscription(self, topic_name: str, callback: Callback, *, raw: bool, msg_type: Any = None,
                            qos: Any = None) -> InProcessSubscription:
        if msg_type is None or qos is None:
            raise ValueError(f"{topic_name}: a live bus subscribes outside with the type and QoS")
        self._wanted.setdefault(topic_name, (msg_type, qos))
        return super().create_subscription(topic_name, callback, raw=raw)

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        def fire() -> None:
            callback()
            self.drain()
        return self.host.create_timer(period_s, fire)

    def create_release(self, **kwargs: Any) -> None:
        return None                      # live: every input is released as it arrives

    def connect(self) -> None:
        """Once every node is made: one DDS subscription for each topic the nodes take that no
        node of the bus publishes (the sensors; an upstream node running elsewhere)."""
        for topic_name, (msg_type, qos) in self._wanted.items():
            if self.publishers.get(topic_name) or topic_name in self._inputs:
                continue
            self._inputs[topic_name] = self.host.create_subscription(
                msg_type, topic_name, lambda data, name=topic_name, kind=msg_type: self.publish_bytes(name, kind, data),
                qos, raw=True)

    def post(self, topic_name: str, message: _Message) -> None:
        outside = self._outside.get(topic_name)
        if outside is not None:
            outside.publish(message.as_published)
        super().post(topic_name, message)

