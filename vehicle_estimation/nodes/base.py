"""What every estimator node shares: parameters, QoS, input ordering, replay sync, diagnostics.

The nodes are thin: they turn messages into arrays, hand them to a core in
``vehicle_estimation.core`` and turn the result back into messages. This module holds the
machinery around that so that each node file reads as "which topics, which core".

Input ordering and deterministic replay
---------------------------------------
Sensor messages of different topics reach a node in no guaranteed order. Each node therefore
pushes its sensor ("primary") inputs into a queue ordered by header stamp and *releases* them
to the estimator in stamp order up to a horizon:

* live (default): the horizon is +inf, every message is processed as it arrives, and a
  message older than the last one processed is handed to the core as it is (the cores reject
  stamps that go backwards and count them);
* replay (``sync.enabled``): the launcher's player publishes one batch of bag messages, then a
  sync request carrying the tick time T and how many messages it has published per topic.
  The node releases everything stamped before ``T - sync.release_delay`` once it has received
  all of them, then answers with its per-topic receive/publish counts. The player moves on
  only when every count matches. Values from *other nodes* (slope, mass, state, fusion bias)
  are looked up in stamp-indexed histories (:class:`UpstreamHistory`) at the primary
  message's stamp minus a lag, never "whatever arrived last". Because each node's release
  delay is a tick larger than that of everything it feeds on, and feedback edges of the
  paper-004 loop (state <-> slope, state <-> mass) use a lag of two ticks, every lookup is
  answered from data that has provably arrived: replaying a bag twice gives the same output
  bit for bit.

Time
----
Estimators step on header stamps, never wall time. A stamp that jumps back by more than
``time_jump_reset_s`` (a bag played in a loop, a restarted player) resets the node's
estimators and histories and says so in the log and in ``/diagnostics``.
"""

from __future__ import annotations

import bisect
import heapq
import itertools
import math
import sys
import traceback
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import rclpy
import rclpy.clock
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import Imu
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.task import Future
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from vehicle_estimation import topics
from vehicle_estimation.core.rotations import quat_to_rotmat
from vehicle_estimation.nodes.cdr import raw_reader
from vehicle_estimation.vehicle import VehicleParams

SYNC_TOPIC = "replay/sync"
ACK_TOPIC = "replay/ack"

#: Keys in a replay sync/ack DiagnosticStatus.
RX_PREFIX = "rx:"
TX_PREFIX = "tx:"
MATCHED_PREFIX = "matched:"
SOURCES_PREFIX = "sources:"


class ParameterError(ValueError):
    """A parameter is invalid; the message names it. Raised at start-up only."""


def sensor_qos(depth: int) -> QoSProfile:
    """Sensor-data QoS (best effort, volatile, keep last) with a configurable depth.

    Best-effort subscriptions match both best-effort and reliable publishers, so the node
    works with any driver and with ``ros2 bag play``. The depth is larger than the preset's
    5 so that a burst (a replay tick, a 1 kHz IMU) is not dropped before the executor runs.
    """
    return QoSProfile(
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
    )


def output_qos(depth: int) -> QoSProfile:
    """Estimates are published reliable keep-last: controllers may ask for either."""
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
    )


def replay_qos() -> QoSProfile:
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=100,
    )


#: Tolerance of comparisons between stamps in float seconds: near 1.7e9 s (any ROS epoch stamp)
#: a float64 resolves only 2.4e-7 s, so a 10 ms period can come out as 9.99976 ms.
STAMP_TOLERANCE_S = 1e-6


def stamp_to_sec(stamp: Any) -> float:
    """Float seconds of a builtin_interfaces/Time, via integer ns (the same float every node gets)."""
    return (int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)) * 1e-9


def sec_to_stamp(t: float, msg_stamp: Any) -> Any:
    """Fill a builtin_interfaces/Time from float seconds (rounded to the nanosecond)."""
    ns = int(round(t * 1e9))
    msg_stamp.sec = ns // 1_000_000_000
    msg_stamp.nanosec = ns % 1_000_000_000
    return msg_stamp


def finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


@dataclass
class StampedValue:
    """A value from another node: estimate, variance, converged flag, at a stamp."""

    stamp: float
    value: float
    variance: float
    converged: bool


class UpstreamHistory:
    """Stamp-indexed recent values of one upstream topic, looked up "as of" a stamp.

    ``at(t)`` returns the newest entry with stamp <= t - lag. Entries are kept for
    ``horizon_s`` seconds of stamp time. Out-of-order arrivals are inserted in order.
    """

    def __init__(self, lag_s: float = 0.0, horizon_s: float = 5.0) -> None:
        self.lag_s = lag_s
        self.horizon_s = horizon_s
        self._stamps: list[float] = []
        self._values: list[Any] = []
        self.received = 0

    def add(self, stamp: float, value: Any) -> None:
        self.received += 1
        i = bisect.bisect_right(self._stamps, stamp)
        self._stamps.insert(i, stamp)
        self._values.insert(i, value)
        cutoff = self._stamps[-1] - self.horizon_s
        if self._stamps[0] < cutoff:
            k = bisect.bisect_left(self._stamps, cutoff)
            del self._stamps[:k]
            del self._values[:k]

    def at(self, t: float) -> Any | None:
        i = bisect.bisect_right(self._stamps, t - self.lag_s)
        return self._values[i - 1] if i > 0 else None

    def clear(self) -> None:
        self._stamps.clear()
        self._values.clear()

    @property
    def latest_stamp(self) -> float | None:
        return self._stamps[-1] if self._stamps else None


class ParamSpec:
    """Builder for a parameter descriptor with a description and a range."""

    @staticmethod
    def descriptor(
        description: str,
        *,
        low: float | int | None = None,
        high: float | int | None = None,
        read_only: bool = True,
        additional: str = "",
    ) -> ParameterDescriptor:
        desc = ParameterDescriptor(description=description, read_only=read_only,
                                   additional_constraints=additional)
        if low is not None and high is not None:
            if isinstance(low, int) and isinstance(high, int) and not isinstance(low, bool):
                desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
            else:
                desc.floating_point_range = [
                    FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
        return desc


# Ranges for the vehicle.* parameters every node declares. Wide enough for a city car and a
# 60 t road train, narrow enough to stop a typo (mass in tonnes, radius in mm) at start-up.
VEHICLE_PARAM_RANGES: dict[str, tuple[float, float, str]] = {
    "mass": (100.0, 100000.0, "Nominal gross mass [kg]; estimators use it only as a prior"),
    "curb_mass": (100.0, 100000.0, "Mass without payload [kg]"),
    "lf": (0.2, 10.0, "CoG to front axle [m]"),
    "lr": (0.2, 10.0, "CoG to rear axle [m]"),
    "track_front": (0.5, 4.0, "Front track width b_F [m]"),
    "track_rear": (0.5, 4.0, "Rear track width b_R [m]"),
    "cg_height": (0.1, 4.0, "CoG height h [m]"),
    "yaw_inertia": (100.0, 2.0e6, "Yaw moment of inertia I_z [kg m^2]"),
    "wheel_radius": (0.1, 1.5, "Effective rolling radius [m]"),
    "wheel_inertia": (0.0, 1000.0, "Rotational inertia of all wheels and driveshafts I_w [kg m^2]"),
    "engine_inertia": (0.0, 50.0, "Engine-side rotational inertia I_e [kg m^2]"),
    "frontal_area": (0.5, 20.0, "Frontal area A [m^2]"),
    "drag_coefficient": (0.05, 2.0, "Aerodynamic drag coefficient C_d"),
    "air_density": (0.5, 2.0, "Air density [kg/m^3]"),
    "rolling_resistance": (0.0, 0.1, "Rolling resistance coefficient C_r"),
    "driveline_efficiency": (0.3, 1.0, "Driveline efficiency eta"),
    "final_drive": (0.5, 20.0, "Final drive ratio i_d"),
    "steering_ratio": (1.0, 40.0, "Steering-wheel to road-wheel ratio"),
    "engine_idle_speed": (10.0, 300.0, "Engine idle speed [rad/s]"),
    "engine_max_speed": (50.0, 2000.0, "Engine maximum speed [rad/s]"),
    "engine_max_torque": (10.0, 10000.0, "Engine maximum torque [N m]"),
    "engine_max_power": (1.0e3, 2.0e6, "Engine maximum power [W]"),
    "engine_drag_torque": (0.0, 1000.0, "Engine drag torque at zero load [N m]"),
    "max_brake_torque": (100.0, 100000.0, "Maximum brake torque per wheel [N m]"),
    "brake_front_share": (0.0, 1.0, "Share of brake torque on the front axle"),
    "cornering_stiffness_front": (1.0e3, 2.0e6, "Cornering stiffness per front tyre [N/rad]"),
    "cornering_stiffness_rear": (1.0e3, 2.0e6, "Cornering stiffness per rear tyre [N/rad]"),
    "longitudinal_stiffness": (1.0e3, 5.0e6, "Longitudinal slip stiffness per tyre [N]"),
    "tyre_load_exponent": (0.0, 2.0, "Load sensitivity n of the tyre stiffnesses, C (F_z/F_z0)^n "
                                      "(0 = constant, paper 004)"),
    "road_friction": (0.05, 1.5, "Tyre-road friction coefficient mu"),
    "magic_b": (0.1, 50.0, "Magic Formula stiffness factor B"),
    "magic_c": (0.1, 5.0, "Magic Formula shape factor C"),
    "magic_d": (0.1, 5.0, "Magic Formula peak factor D (times mu F_z)"),
    "magic_e": (-10.0, 1.0, "Magic Formula curvature factor E"),
    "pitch_gain": (0.0, 0.05, "Body pitch per longitudinal acceleration, nose up when accelerating [rad per m/s^2]"),
    "pitch_time_constant": (0.0, 5.0, "Time constant of the suspension pitch response [s]"),
    "gravity": (9.7, 9.9, "Gravitational acceleration [m/s^2]"),
}


class EstimatorNode(Node):
    """Base class of the four estimator nodes. See the module docstring."""

    #: Resolved topic names this node subscribes to as primary (ordered) sensor inputs.
    def __init__(self, node_name: str, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        self._rx: Counter[str] = Counter()
        self._tx: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.events: deque[str] = deque(maxlen=5)
        self._publishers_by_topic: dict[str, Any] = {}
        self._subscriptions_by_topic: dict[str, Any] = {}
        self._queue: list[tuple[int, str, int, Callable[[float, Any], None], Any]] = []
        self._seq = itertools.count()
        self._released_until = -math.inf
        self._last_stamp_by_topic: dict[str, float] = {}
        self._missing: set[str] = set()
        self._pending_sync: DiagnosticStatus | None = None
        # The player's per-topic counts in the first sync this process sees: zero at a normal
        # start; the counts so far when the launcher respawns this node mid-replay.
        self._sync_base: dict[str, int] | None = None
        self._last_sync: DiagnosticStatus | None = None
        self._last_sync_time = -math.inf
        self._reack_timer = None
        self.resets = 0
        self.max_queue = 0      # longest the stamp-ordered input queue has been (load check)

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
        self._frames: dict[str, str] = {}
        self._imu_repeat: dict[str, tuple[tuple[float, ...], int]] = {}

        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(self.diagnostics_period, self._publish_diagnostics)
        if self.sync_enabled:
            self._ack_pub = self.create_publisher(DiagnosticStatus, ACK_TOPIC, replay_qos())
            self.create_subscription(DiagnosticStatus, SYNC_TOPIC, self._on_sync, replay_qos())
            # Messages that arrive after an ack (estimates of other nodes) are acknowledged
            # again, coalesced over 1 ms of steady (wall) time, so the player never polls.
            self._reack_timer = self.create_timer(
                0.001, self._reack, clock=rclpy.clock.Clock(clock_type=rclpy.clock.ClockType.STEADY_TIME))
            self._reack_timer.cancel()

    # ------------------------------------------------------------------ parameters
    def _declare(self, name: str, default: Any, descriptor: ParameterDescriptor) -> Any:
        try:
            value = self.declare_parameter(name, default, descriptor).value
        except Exception as exc:  # rclpy raises several types for range/type violations
            raise ParameterError(f"parameter '{name}': {exc}") from exc
        return value

    def declare_float(self, name: str, default: float, description: str,
                      low: float | None = None, high: float | None = None, *, allow_nan: bool = False) -> float:
        """A double parameter; non-finite values stop the node, except NaN with ``allow_nan``
        (where NaN means "automatic", as the config's docs say)."""
        value = self._declare(name, float(default), ParamSpec.descriptor(description, low=low, high=high))
        value = float(value)
        if allow_nan and math.isnan(value):
            return value
        if not math.isfinite(value):
            raise ParameterError(f"parameter '{name}' must be finite, got {value}")
        return value

    def declare_int(self, name: str, default: int, description: str,
                    low: int | None = None, high: int | None = None) -> int:
        return int(self._declare(name, int(default), ParamSpec.descriptor(description, low=low, high=high)))

    def declare_bool(self, name: str, default: bool, description: str) -> bool:
        return bool(self._declare(name, bool(default), ParamSpec.descriptor(description)))

    def declare_str(self, name: str, default: str, description: str,
                    choices: Sequence[str] | None = None) -> str:
        extra = f"one of: {', '.join(choices)}" if choices else ""
        value = str(self._declare(name, default, ParamSpec.descriptor(description, additional=extra)))
        if choices is not None and value not in choices:
            raise ParameterError(f"parameter '{name}' must be one of {list(choices)}, got '{value}'")
        return value

    def declare_float_array(self, name: str, default: Sequence[float], description: str) -> list[float]:
        descriptor = ParamSpec.descriptor(description)
        descriptor.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        # rclpy infers a parameter's type from its default, and types an empty list as a byte
        # array, which would refuse every double array a params file gives (a calibrated
        # torque map). Declared by type instead, it has no value until a file sets one.
        initial: Any = [float(v) for v in default] if default else Parameter.Type.DOUBLE_ARRAY
        value = self._declare(name, initial, descriptor)
        return [float(v) for v in value] if value is not None else []

    @staticmethod
    def config_field_docs(cls: type) -> dict[str, str]:
        """One line of documentation per dataclass field, from the field's trailing comment or
        the class docstring's ``Attributes:`` entry or ``* ``name``: text`` bullet (base classes
        included)."""
        import inspect
        import re

        docs: dict[str, str] = {}
        for klass in reversed(cls.__mro__):
            try:
                source = inspect.getsource(klass)
            except (OSError, TypeError):
                continue
            doc = inspect.cleandoc(klass.__doc__ or "")
            attrs = re.search(r"Attributes:\n(.*?)(?:\n\s*\n|\Z)", doc, re.S)
            if attrs:
                entry = None
                for line in attrs.group(1).splitlines():
                    m = re.match(r" {4}([\w, ]+):\s*(.*)", line)
                    if m and not line.startswith(" " * 5):
                        entry = [n.strip() for n in m.group(1).split(",")]
                        for name in entry:
                            docs[name] = m.group(2).strip()
                    elif entry:
                        for name in entry:
                            docs[name] += " " + line.strip()
            # "* ``name``: text" bullets (one or more names), continued on indented lines
            for m in re.finditer(r"^\* ((?:``\w+``(?:, | and )?)+)(?: \([^)]*\))?:\s*(.+?)(?=^\* |^\S|\Z)",
                                 doc, re.M | re.S):
                text = " ".join(m.group(2).split())
                for name in re.findall(r"``(\w+)``", m.group(1)):
                    docs.setdefault(name, text)
            for m in re.finditer(r"^    (\w+): [^=\n]+=[^#\n]*#\s*(.+)$", source, re.M):
                docs[m.group(1)] = m.group(2).strip()
        return docs

    def declare_config(self, prefix: str, defaults: Any, exclude: tuple[str, ...] = ()) -> Any:
        """Declare every scalar, bool, str and tuple/list field of the dataclass instance
        ``defaults`` as ``<prefix>.<field>`` and return a validated copy with the values.

        Fields that are None or arrays keep their defaults (they are not ROS-parameter
        shaped), as do the fields named in ``exclude`` (set by a node-level parameter).
        ``validate()`` errors become a :class:`ParameterError` that names the field.
        """
        import dataclasses

        values: dict[str, Any] = {}
        field_docs = self.config_field_docs(type(defaults))
        for field in dataclasses.fields(defaults):
            if field.name in exclude:
                continue
            value = getattr(defaults, field.name)
            name = f"{prefix}.{field.name}"
            doc = field_docs.get(field.name) or f"{type(defaults).__name__}.{field.name}"
            if isinstance(value, bool):
                values[field.name] = self.declare_bool(name, value, doc)
            elif isinstance(value, int):
                values[field.name] = self.declare_int(name, value, doc)
            elif isinstance(value, float):
                # A NaN default means "automatic" (validate() checks the rest).
                values[field.name] = self.declare_float(name, value, doc, allow_nan=math.isnan(value))
            elif isinstance(value, str):
                values[field.name] = self.declare_str(name, value, doc)
            elif isinstance(value, (tuple, list)) and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                values[field.name] = type(value)(self.declare_float_array(name, value, doc))
        try:
            config = dataclasses.replace(defaults, **values)
            config.validate()
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{prefix}.*: {exc}") from exc
        return config

    def declare_vehicle(self) -> VehicleParams:
        """Declare ``vehicle.*`` (ranges in :data:`VEHICLE_PARAM_RANGES`) and build the params."""
        defaults = VehicleParams()
        values: dict[str, Any] = {}
        for field in VehicleParams.field_names():
            name = f"vehicle.{field}"
            default = getattr(defaults, field)
            if field in ("name", "driven_axle"):
                choices = ("front", "rear", "all") if field == "driven_axle" else None
                values[field] = self.declare_str(name, default, f"Vehicle {field.replace('_', ' ')}", choices)
            elif field == "gear_ratios":
                values[field] = self.declare_float_array(
                    name, default, "Transmission ratios i_t,j, first gear first")
            else:
                low, high, description = VEHICLE_PARAM_RANGES[field]
                values[field] = self.declare_float(name, default, description, low, high)
        try:
            return VehicleParams.from_mapping(values)
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc

    # ------------------------------------------------------------------ topics
    def publisher(self, msg_type: Any, topic: str) -> Any:
        pub = self.create_publisher(msg_type, topic, output_qos(self.output_depth))
        self._publishers_by_topic[pub.topic_name] = pub
        return pub

    def publish(self, pub: Any, msg: Any) -> None:
        pub.publish(msg)
        self._tx[pub.topic_name] += 1

    def subscribe_primary(self, msg_type: Any, topic: str,
                          handler: Callable[[float, Any], None],
                          stamp_of: Callable[[Any], float] | None = None) -> Any:
        """Subscribe a sensor input that is processed in stamp order (sensor-data QoS)."""
        stamp_of = stamp_of or (lambda m: stamp_to_sec(m.header.stamp))
        holder: dict[str, str] = {}

        read = raw_reader(msg_type)

        def on_message(msg: Any) -> None:
            name = holder["topic"]
            self._rx[name] += 1
            try:
                if read is not None:
                    msg = read(msg)
                t = stamp_of(msg)
            except Exception:  # malformed message: no usable stamp
                self.reject(f"{name}:bad_stamp")
                return
            # 0 s is a valid stamp: simulators, CSV exports and many loggers start there.
            if not math.isfinite(t) or t < 0.0:
                self.reject(f"{name}:bad_stamp")
                return
            # Ties on the stamp are broken by topic name, then arrival order within the topic
            # (FIFO per topic), never by arrival order across topics: that is not reproducible.
            # Ordered by integer nanoseconds: stamps on a replay tick boundary must fall on the
            # same side of it in every node, which float seconds near 1.7e9 cannot promise.
            ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec) \
                if hasattr(msg, "header") else int(round(t * 1e9))
            heapq.heappush(self._queue, (ns, name, next(self._seq), handler, msg))
            self.max_queue = max(self.max_queue, len(self._queue))
            self._release_available()

        sub = self.create_subscription(msg_type, topic, on_message, sensor_qos(self.input_depth),
                                       raw=read is not None)
        holder["topic"] = sub.topic_name
        self._rx[sub.topic_name] += 0
        self._subscriptions_by_topic[sub.topic_name] = sub
        return sub

    def subscribe_imu_bias(self, bias: "FusionImuBias") -> Any:
        """Subscribe the fusion node's IMU bias estimate (see :class:`FusionImuBias`)."""
        return self.subscribe_upstream(Imu, topics.IMU_BIAS, bias.history, bias.convert)

    def subscribe_upstream(self, msg_type: Any, topic: str, history: UpstreamHistory,
                           convert: Callable[[Any], tuple[float, Any] | None]) -> Any:
        """Subscribe an estimate of another node into a stamp-indexed history (reliable QoS)."""
        holder: dict[str, str] = {}
        read = raw_reader(msg_type)

        def on_message(msg: Any) -> None:
            name = holder["topic"]
            self._rx[name] += 1
            self._schedule_reack()
            try:
                item = convert(msg if read is None else read(msg))
            except Exception:
                item = None
            if item is None or not math.isfinite(item[0]):
                self.reject(f"{name}:invalid")
                return
            history.add(*item)

        sub = self.create_subscription(msg_type, topic, on_message, output_qos(self.output_depth),
                                       raw=read is not None)
        holder["topic"] = sub.topic_name
        self._rx[sub.topic_name] += 0
        self._subscriptions_by_topic[sub.topic_name] = sub
        return sub

    # ------------------------------------------------------------------ ordering and sync
    def _release_available(self) -> None:
        if not self.sync_enabled:
            self._release(math.inf)
        elif self._pending_sync is not None:
            self._try_complete_sync()

    def _release(self, horizon_ns: float) -> None:
        """Hand queued inputs stamped before ``horizon_ns`` (integer ns, or inf) to their handlers."""
        while self._queue and self._queue[0][0] < horizon_ns:
            ns, topic, _, handler, msg = heapq.heappop(self._queue)
            t = ns * 1e-9
            # A jump back is judged per topic: a bag played in a loop or a restarted driver makes
            # a topic's own stamps go backwards, while a topic that is merely processed late
            # behind a busier one (a backlog in live mode) keeps its own order.
            last = self._last_stamp_by_topic.get(topic, -math.inf)
            if t < last - self.time_jump_reset_s:
                self.note_event(
                    f"time jumped back {last - t:.3f} s on {topic}: "
                    "resetting estimators (bag loop or restarted source)")
                self.resets += 1
                self._last_stamp_by_topic.clear()
                self._frames.clear()
                self.reset_estimators()
            self._last_stamp_by_topic[topic] = max(last, t) if t >= last - self.time_jump_reset_s else t
            if not self._input_consistent(topic, msg):
                continue
            try:
                handler(t, msg)
            except Exception:  # never let one bad message take the node down
                self.reject(f"{topic}:handler_error")
                self.get_logger().error(
                    f"error handling {topic} at t={t:.3f}:\n{traceback.format_exc(limit=4)}",
                    throttle_duration_sec=5.0)

    def _input_consistent(self, topic: str, msg: Any) -> bool:
        """Checks every sensor input gets before its handler (rejections are counted):

        * ``frame_id``: the frame of a topic's first message is its frame; a message in another
          frame is a second source on the topic or a misconfigured driver (``<topic>:frame_id``).
          The nodes do not transform: the contract fixes each input's frame (README).
        * a frozen IMU (``frozen_imu_samples``): ``<topic>:frozen``.
        """
        header = getattr(msg, "header", None)
        if header is not None:
            frame = str(header.frame_id)
            expected = self._frames.setdefault(topic, frame)
            if frame != expected:
                self.reject(f"{topic}:frame_id")
                self.get_logger().warn(f"{topic}: frame_id '{frame}', expected '{expected}': rejected",
                                       throttle_duration_sec=5.0)
                return False
        if self.frozen_imu_samples > 0 and hasattr(msg, "linear_acceleration"):
            a, w = msg.linear_acceleration, msg.angular_velocity
            key = (a.x, a.y, a.z, w.x, w.y, w.z)
            last, repeats = self._imu_repeat.get(topic, ((), 0))
            repeats = repeats + 1 if key == last else 0
            self._imu_repeat[topic] = (key, repeats)
            if repeats >= self.frozen_imu_samples:
                self.reject(f"{topic}:frozen")
                self.set_missing(f"{topic} (frozen)", True)
                return False
            self.set_missing(f"{topic} (frozen)", False)
        return True

    def _on_sync(self, msg: DiagnosticStatus) -> None:
        self._pending_sync = msg
        self._try_complete_sync()

    def _try_complete_sync(self) -> None:
        msg = self._pending_sync
        if msg is None:
            return
        tick_ns = int(msg.message)  # the player's tick, integer nanoseconds of bag time
        tick = tick_ns * 1e-9
        sent = {kv.key[len(TX_PREFIX):]: int(kv.value) for kv in msg.values if kv.key.startswith(TX_PREFIX)}
        if self._sync_base is None:
            self._sync_base = sent
        for topic, count in sent.items():
            if topic in self._rx and self._rx[topic] < count - self._sync_base.get(topic, 0):
                return  # not everything published before this sync has arrived yet
        if tick < self._last_sync_time - self.time_jump_reset_s:
            self.note_event(f"replay clock jumped back to {tick:.3f}: resetting estimators")
            self.resets += 1
            self._queue.clear()
            self._last_stamp_by_topic.clear()
            self.reset_estimators()
        self._last_sync_time = tick
        self._release(tick_ns - int(round(self.release_delay * 1e9)))
        self._pending_sync = None
        self._last_sync = msg
        self._send_ack()

    def _schedule_reack(self) -> None:
        if self._reack_timer is not None and self._last_sync is not None and self._reack_timer.is_canceled():
            self._reack_timer.reset()

    def _reack(self) -> None:
        self._reack_timer.cancel()
        if self._pending_sync is None and self._last_sync is not None:
            self._send_ack()

    def _send_ack(self) -> None:
        msg = self._last_sync
        ack = DiagnosticStatus(name=self.get_fully_qualified_name(), message=msg.message)
        ack.values = [KeyValue(key=RX_PREFIX + k, value=str(v)) for k, v in self._rx.items()]
        ack.values += [KeyValue(key=TX_PREFIX + k, value=str(self._tx[k]))
                       for k in self._publishers_by_topic]
        if msg.level != DiagnosticStatus.OK:  # the player asks for connection state at start-up
            ack.values += [KeyValue(key=MATCHED_PREFIX + k, value=str(p.get_subscription_count()))
                           for k, p in self._publishers_by_topic.items()]
            ack.values += [KeyValue(key=SOURCES_PREFIX + k, value=str(s.get_publisher_count()))
                           for k, s in self._subscriptions_by_topic.items()]
        self._ack_pub.publish(ack)

    # ------------------------------------------------------------------ bookkeeping
    def reject(self, reason: str) -> None:
        self.rejected[reason] += 1
        self.get_logger().warn(f"rejected input ({reason}); {self.rejected[reason]} so far",
                               throttle_duration_sec=5.0)

    def note_event(self, text: str) -> None:
        self.events.append(text)
        self.get_logger().info(text)

    def set_missing(self, what: str, missing: bool) -> None:
        if missing:
            self._missing.add(what)
        else:
            self._missing.discard(what)

    def reset_estimators(self) -> None:
        """Subclasses reset cores and histories here (bag loop, restarted source)."""

    def status_values(self) -> dict[str, str]:
        """Subclasses add estimator state for /diagnostics."""
        return {}

    def status_summary(self) -> tuple[int, str]:
        """Level and one-line message for /diagnostics; subclasses refine."""
        if self._missing:
            return DiagnosticStatus.WARN, "missing: " + ", ".join(sorted(self._missing))
        return DiagnosticStatus.OK, "running"

    def _publish_diagnostics(self) -> None:
        level, message = self.status_summary()
        status = DiagnosticStatus(level=level, name=f"vehicle_estimation/{self.get_name()}",
                                  hardware_id="vehicle_estimation", message=message)
        values = {f"received {k}": str(v) for k, v in self._rx.items()}
        values.update({f"published {k}": str(v) for k, v in self._tx.items()})
        values.update({f"rejected {k}": str(v) for k, v in self.rejected.items()})
        values["rejected total"] = str(sum(self.rejected.values()))
        values["resets"] = str(self.resets)
        values["input queue: now / max"] = f"{len(self._queue)} / {self.max_queue}"
        if self.events:
            values["last event"] = self.events[-1]
        values.update(self.status_values())
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(array)


def companion(stamp: float, value: float, variance: float, converged: bool,
              frame_id: str = "base_link") -> Vector3Stamped:
    """The stamped companion of a scalar estimate: x = value, y = variance, z = converged (1/0)."""
    msg = Vector3Stamped()
    sec_to_stamp(stamp, msg.header.stamp)
    msg.header.frame_id = frame_id
    msg.vector.x = float(value)
    msg.vector.y = float(variance)
    msg.vector.z = 1.0 if converged else 0.0
    return msg


def companion_value(msg: Vector3Stamped) -> tuple[float, StampedValue] | None:
    t = stamp_to_sec(msg.header.stamp)
    v = msg.vector
    if not finite(v.x, v.y):
        return None
    return t, StampedValue(t, v.x, v.y, v.z > 0.5)


def make_executor():
    """The C++ events executor of rclpy (Jazzy: ``rclpy.experimental``) when present.

    It dispatches callbacks without rebuilding a wait set in Python for every message, which
    roughly doubles replay speed here; the plain single-threaded executor is the fallback.
    ``VEHICLE_ESTIMATION_EXECUTOR=single_threaded`` forces the fallback.
    """
    import os
    if os.environ.get("VEHICLE_ESTIMATION_EXECUTOR", "events") == "events":
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def run_node(node_factory: Callable[[], EstimatorNode], args: list[str] | None = None) -> int:
    """Entry point shared by the node executables: clear errors, clean shutdown."""
    rclpy.init(args=args if args is not None else sys.argv)
    node = None
    try:
        node = node_factory()
    except ParameterError as exc:
        print(f"[vehicle_estimation] invalid parameter: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = make_executor()
    executor.add_node(node)
    never = Future()
    profiler = _start_profiler()
    try:
        # spin_until_future_complete in slices rather than spin(): the events executor's
        # spin() busy-waits in this rclpy release, and slices let us notice a shutdown.
        while rclpy.ok():
            executor.spin_until_future_complete(never, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if profiler is not None:
            _dump_profile(profiler, node.get_name())
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _start_profiler() -> Any:
    """cProfile of the whole spin when ``VEHICLE_ESTIMATION_PROFILE_DIR`` is set (development:
    ``python -m pstats DIR/<node>.prof`` shows where a node's time goes)."""
    import os
    if not os.environ.get("VEHICLE_ESTIMATION_PROFILE_DIR"):
        return None
    import cProfile
    import time
    profiler = cProfile.Profile(time.process_time)   # CPU time: idle waiting is not a cost
    profiler.enable()
    return profiler


def _dump_profile(profiler: Any, name: str) -> None:
    import os
    from pathlib import Path
    profiler.disable()
    out = Path(os.environ["VEHICLE_ESTIMATION_PROFILE_DIR"])
    out.mkdir(parents=True, exist_ok=True)
    profiler.dump_stats(str(out / f"{name}.prof"))


class FusionImuBias:
    """Bias correction of raw IMU samples with the fusion node's estimate.

    The fusion node publishes its accelerometer and gyro bias estimates on
    ``estimation/imu_bias`` (sensor_msgs/Imu: ``linear_acceleration`` = accelerometer bias,
    ``angular_velocity`` = gyro bias, both in the IMU's own frame, with their covariances;
    ``orientation`` = the IMU mounting, imu_link -> base_link) at a low rate: a bias changes
    over minutes, so 10 Hz is plenty and costs downstream nodes almost nothing.
    :meth:`correct` removes the bias and rotates the sample into base_link. Without fusion
    (not started, not yet initialised) samples pass through unchanged and :attr:`valid` is
    False.
    """

    def __init__(self) -> None:
        self.history = UpstreamHistory(horizon_s=5.0)
        self.valid = False

    @staticmethod
    def convert(msg: Any) -> tuple[float, Any] | None:
        t = stamp_to_sec(msg.header.stamp)
        ba = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
        bg = np.array([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
        if not (np.all(np.isfinite(ba)) and np.all(np.isfinite(bg))):
            return None
        o = msg.orientation
        q = np.array([o.x, o.y, o.z, o.w], dtype=float)
        norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else 0.0
        # A publisher without a mounting leaves the quaternion at zero: identity.
        mount = quat_to_rotmat(q / norm) if norm > 0.5 else np.eye(3)
        var = msg.linear_acceleration_covariance[0]
        return t, (ba, bg, mount, var if math.isfinite(var) and var > 0.0 else 0.0)

    def correct(self, t: float, f: Any, w: Any) -> tuple[Any, Any]:
        entry = self.history.at(t)
        self.valid = entry is not None
        if entry is None:
            return f, w
        ba, bg, mount, _ = entry
        return mount @ (f - ba), mount @ (w - bg)

    def accel_x_variance_at(self, t: float) -> float | None:
        """The along-track bias variance [m^2/s^4] published for stamp ``t``, None without the
        fusion."""
        entry = self.history.at(t)
        return None if entry is None else entry[3]

    def clear(self) -> None:
        self.history.clear()
        self.valid = False
