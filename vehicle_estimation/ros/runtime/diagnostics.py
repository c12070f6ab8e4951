"""What a node tells ``/diagnostics``: counts per topic, rejections, missing inputs, events."""

from __future__ import annotations

from collections import Counter, deque
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue


class NodeHealth:
    """A node's bookkeeping: messages in and out per topic, rejections by reason, the inputs it
    misses (a fallback is running), its last events and how often it reset."""

    def __init__(self) -> None:
        self.rx: Counter[str] = Counter()
        self.tx: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.events: deque[str] = deque(maxlen=5)
        self.missing: set[str] = set()
        self.resets = 0

    def set_missing(self, what: str, missing: bool) -> None:
        if missing:
            self.missing.add(what)
        else:
            self.missing.discard(what)

    def summary(self) -> tuple[int, str]:
        """WARN naming the missing inputs, else OK."""
        if self.missing:
            return DiagnosticStatus.WARN, "missing: " + ", ".join(sorted(self.missing))
        return DiagnosticStatus.OK, "running"

    def array(self, node_name: str, level: int, message: str, queue_now: int, queue_max: int,
              extra: dict[str, str], stamp: Any) -> DiagnosticArray:
        """The ``/diagnostics`` message: one status named ``vehicle_estimation/<node>``."""
        status = DiagnosticStatus(level=level, name=f"vehicle_estimation/{node_name}",
                                  hardware_id="vehicle_estimation", message=message)
        values = {f"received {k}": str(v) for k, v in self.rx.items()}
        values.update({f"published {k}": str(v) for k, v in self.tx.items()})
        values.update({f"rejected {k}": str(v) for k, v in self.rejected.items()})
        values["rejected total"] = str(sum(self.rejected.values()))
        values["resets"] = str(self.resets)
        values["input queue: now / max"] = f"{queue_now} / {queue_max}"
        if self.events:
            values["last event"] = self.events[-1]
        values.update(extra)
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = stamp
        return array
