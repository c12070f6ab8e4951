"""``EstimatorNode``: the base class of the four estimator nodes, wiring the runtime together.

The nodes are thin: they turn messages into arrays, hand them to a core in
``vehicle_estimation.estimators`` and turn the result back into messages. What surrounds that
lives in one module per job: ``parameters`` (declaring with descriptors), ``input_queue``
(stamp order and input checks), ``upstream`` (other nodes' values "as of" a stamp), ``sync``
(the lock-step replay protocol), ``diagnostics`` and ``spin`` (the executable's loop). Created with ``transport=`` an
:class:`~vehicle_estimation.ros.runtime.in_process.InProcessBus`, a node takes its endpoints
from the bus instead of rclpy (``replay --in-process``): the handlers are the same code.

Time: estimators step on header stamps, never wall time. A stamp that jumps back by more than
``time_jump_reset_s`` (a bag played in a loop, a restarted player) resets the node's estimators
and histories and says so in the log and in ``/diagnostics``.
"""

from __future__ import annotations

import math
from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Imu

from vehicle_estimation.contract import topics
from vehicle_estimation.ros.cdr import raw_reader
from vehicle_estimation.ros.conversions import checked_imu_arrays, speed_reading
from vehicle_estimation.ros.runtime.diagnostics import NodeHealth
from vehicle_estimation.ros.runtime.in_process import InProcessBus
from vehicle_estimation.ros.runtime.input_queue import StampOrderedInputs
from vehicle_estimation.ros.runtime.parameters import ParameterDeclarations
from vehicle_estimation.ros.runtime.qos import latched_qos, output_qos, sensor_qos
from vehicle_estimation.ros.stamps import stamp_ns
from vehicle_estimation.ros.runtime.sync import ReplaySyncResponder, TickRelease
from vehicle_estimation.ros.runtime.upstream import FusionImuBias, UpstreamHistory


class EstimatorNode(ParameterDeclarations, Node):
    """Base class of the four estimator nodes. See the module docstring."""

    def __init__(self, node_name: str, *, transport: InProcessBus | None = None, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self.transport = transport
        self.health = NodeHealth()
        self._publishers_by_topic: dict[str, Any] = {}
        self._subscriptions_by_topic: dict[str, Any] = {}

        self.input_depth = self.declare_int(
            "qos.input_depth", 200, "Keep-last depth of sensor-data subscriptions", 1, 100000)
        self.output_depth = self.declare_int(
            "qos.output_depth", 100, "Keep-last depth of the reliable estimate publishers", 1, 100000)
        self.sync_enabled = self.declare_bool(
            "sync.enabled", False,
            "Deterministic replay: release inputs on the player's sync requests (set by the launcher)")
        self.release_delay = self.declare_float(
            "sync.release_delay", 0.0,
            "Replay only: process inputs stamped before T - release_delay at sync time T [s]", 0.0, 10.0)
        self.feedback_lag = self.declare_float(
            "sync.feedback_lag", 0.0,
            "Lag applied to values fed back from downstream nodes (paper-004 loop) [s]", 0.0, 10.0)
        self.time_jump_reset_s = self.declare_float(
            "time_jump_reset_s", 1.0,
            "A stamp this far behind the last one processed resets the estimators [s]", 0.001, 3600.0)
        self.diagnostics_period = self.declare_float(
            "diagnostics_period_s", 1.0, "Period of /diagnostics on the node clock [s]", 0.01, 60.0)
        self.frozen_imu_samples = self.declare_int(
            "frozen_imu_samples", 0,
            "After this many bit-identical IMU samples in a row, further repeats are rejected as a "
            "frozen sensor (a real IMU's noise never repeats; a hung driver republishes); 0: off", 0, 100000)
        self.inputs = StampOrderedInputs(self, self.time_jump_reset_s, self.frozen_imu_samples)

        self._sync: ReplaySyncResponder | TickRelease | None = None
        if transport is not None:
            transport.attach(self)
            self._diag_pub = transport.create_publisher(DiagnosticArray, self.resolve_topic_name("/diagnostics"))
            transport.create_timer(self.diagnostics_period, self._publish_diagnostics)
            self._sync = transport.create_release(
                release=self.inputs.release, on_clock_jump=self._on_replay_clock_jump,
                release_delay_s=self.release_delay, time_jump_reset_s=self.time_jump_reset_s)
            return
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(self.diagnostics_period, self._publish_diagnostics)
        if self.sync_enabled:
            self._sync = ReplaySyncResponder(
                self, rx=self.health.rx, tx=self.health.tx, publishers=self._publishers_by_topic,
                subscriptions=self._subscriptions_by_topic, release=self.inputs.release,
                on_clock_jump=self._on_replay_clock_jump, release_delay_s=self.release_delay,
                time_jump_reset_s=self.time_jump_reset_s)

    # ------------------------------------------------------------------ topics
    def publisher(self, msg_type: Any, topic: str, *, latched: bool = False) -> Any:
        qos = latched_qos() if latched else output_qos(self.output_depth)
        if self.transport is not None:
            pub = self.transport.create_publisher(msg_type, self.resolve_topic_name(topic), qos)
        else:
            pub = self.create_publisher(msg_type, topic, qos)
        self._publishers_by_topic[pub.topic_name] = pub
        return pub

    def publish(self, pub: Any, msg: Any) -> None:
        pub.publish(msg)
        self.health.tx[pub.topic_name] += 1

    def _subscribe_counted(self, msg_type: Any, topic: str, qos: Any,
                           deliver: Callable[[str, Any, Callable[[Any], Any]], None]) -> Any:
        """A subscription that counts each message under its resolved topic name and hands it
        to ``deliver(topic, message, read)``; ``read`` turns the message into what handlers
        take (a view of its CDR bytes for the high-rate types, else the message itself), and
        ``deliver`` calls it where it can handle a malformed message."""
        holder: dict[str, str] = {}
        view = raw_reader(msg_type)
        read: Callable[[Any], Any] = view if view is not None else (lambda msg: msg)
        rx = self.health.rx

        def on_message(msg: Any) -> None:
            name = holder["topic"]
            rx[name] += 1
            deliver(name, msg, read)

        if self.transport is not None:
            sub = self.transport.create_subscription(self.resolve_topic_name(topic), on_message, raw=view is not None,
                                                     msg_type=msg_type, qos=qos)
        else:
            sub = self.create_subscription(msg_type, topic, on_message, qos, raw=view is not None)
        holder["topic"] = sub.topic_name
        rx[sub.topic_name] += 0
        self._subscriptions_by_topic[sub.topic_name] = sub
        return sub

    def subscribe_primary(self, msg_type: Any, topic: str, handler: Callable[[float, Any], None]) -> Any:
        """Subscribe a sensor input that is processed in stamp order (sensor-data QoS)."""
        inputs, push = self.inputs, self.inputs.push

        def deliver(name: str, msg: Any, read: Callable[[Any], Any]) -> None:
            try:
                msg = read(msg)
                ns = stamp_ns(msg.header.stamp)
            except Exception:  # malformed message: no usable stamp
                ns = -1
            # 0 s is a valid stamp: simulators, CSV exports and many loggers start there.
            if ns < 0:
                self.reject(f"{name}:bad_stamp")
                return
            push(ns, name, handler, msg)
            if self._sync is None:
                inputs.release(math.inf)
            else:
                self._sync.try_complete()

        return self._subscribe_counted(msg_type, topic, sensor_qos(self.input_depth), deliver)

    def subscribe_imu_bias(self, bias: FusionImuBias) -> Any:
        """Subscribe the fusion node's IMU bias estimate (see :class:`FusionImuBias`)."""
        return self.subscribe_upstream(Imu, topics.IMU_BIAS, bias.history, bias.convert)

    def subscribe_upstream(self, msg_type: Any, topic: str, history: UpstreamHistory,
                           convert: Callable[[Any], tuple[float, Any] | None]) -> Any:
        """Subscribe an estimate of another node into a stamp-indexed history (reliable QoS)."""

        def deliver(name: str, msg: Any, read: Callable[[Any], Any]) -> None:
            if self._sync is not None:
                self._sync.schedule_reack()
            try:
                item = convert(read(msg))
            except Exception:
                item = None
            if item is None or not math.isfinite(item[0]):
                self.reject(f"{name}:invalid")
                return
            history.add(*item)

        return self._subscribe_counted(msg_type, topic, output_qos(self.output_depth), deliver)

    def _on_replay_clock_jump(self, text: str) -> None:
        self.note_event(text)
        self.health.resets += 1
        self.inputs.drop_all()
        self.reset_estimators()

    def on_time_jump(self, text: str) -> None:
        """A topic's stamps went back (input queue): reset, and say so."""
        self.note_event(text)
        self.health.resets += 1
        self.reset_estimators()

    # ------------------------------------------------------------------ bookkeeping
    @property
    def missing(self) -> set[str]:
        """Inputs this node runs without (a fallback is active); ``/diagnostics`` names them."""
        return self.health.missing

    def read_imu(self, msg: Any) -> tuple[Any, Any] | None:
        """Specific force and angular rate of an IMU message (arrays, body frame), or None for
        a non-finite or physically absurd sample, which is rejected and counted."""
        f, w, reason = checked_imu_arrays(msg)
        if reason is not None:
            self.reject(reason)
            return None
        return f, w

    def read_speed(self, msg: Any) -> tuple[float, float] | None:
        """(speed, variance or NaN) of a ``vehicle/speed`` message, or None for a non-finite or
        absurd speed, which is rejected and counted."""
        reading = speed_reading(msg)
        if reading is None:
            self.reject("speed:invalid")
        return reading

    def reject(self, reason: str) -> None:
        self.health.rejected[reason] += 1
        self.get_logger().warn(f"rejected input ({reason}); {self.health.rejected[reason]} so far",
                               throttle_duration_sec=5.0)

    def note_event(self, text: str) -> None:
        self.health.events.append(text)
        self.get_logger().info(text)

    def set_missing(self, what: str, missing: bool) -> None:
        self.health.set_missing(what, missing)

    def reset_estimators(self) -> None:
        """Subclasses reset cores and histories here (bag loop, restarted source)."""

    def status_values(self) -> dict[str, str]:
        """Subclasses add estimator state for /diagnostics."""
        return {}

    def status_summary(self) -> tuple[int, str]:
        """Level and one-line message for /diagnostics; subclasses refine."""
        return self.health.summary()

    def _publish_diagnostics(self) -> None:
        if not self.context.ok():       # a timer that fires after a signal has shut rclpy down
            return
        level, message = self.status_summary()
        self._diag_pub.publish(self.health.array(
            self.get_name(), level, message, len(self.inputs), self.inputs.max_len, self.status_values(),
            self.get_clock().now().to_msg()))
