"""The numbers a replay published, for the regression oracle of ``test_end_to_end``.

Every estimate message is decoded and flattened to the floats it carries (stamps, values,
covariances); every ``STRIDE``-th message of a topic is kept, which follows every estimate
through the drive at 0.5-1 s intervals (an error that matters does not vanish between two
samples) and keeps the committed reference small. Comparing numbers instead of bytes lets a
change that only reorders floating-point sums (a library's geodesy, a vectorised loop, a
compiled kernel) pass, while any change that moves a number by more than ``SCALE_RTOL`` of its
quantity's scale over the drive (the largest magnitude that field takes) fails.

``python test/replay_values.py ESTIMATES_BAG OUT.npz`` writes a reference from a recorded
replay; it uses rosbags and numpy only, so it can record the estimates of an older checkout.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

COMPARED_PREFIX = "/estimation/"
STRIDE = 25
#: Reordered sums move a number by ~1e-13 of its quantity's scale (a library's geodesy moves the
#: odometry by nanometres, 2e-9 m, and a small variance by 1e-7 of its own value: both far below
#: this bound, taken relative to the scale and not to the value itself).
SCALE_RTOL = 1e-9



def recorded_estimates(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Every estimate topic of a recorded replay: its (log time, CDR bytes) in order.

    ``/diagnostics`` is left out: it is published on a timer of the node clock, whose calls
    fall between messages wherever the executor happens to be.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list[tuple[int, bytes]]] = {}
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, log_ns, data in reader.messages():
            if conn.topic.startswith(COMPARED_PREFIX):
                out.setdefault(conn.topic, []).append((log_ns, bytes(data)))
    return out


def diagnostic_statuses(bag: Path, node: str) -> list[dict[str, str]]:
    """Every ``/diagnostics`` status that ``node`` (its name's last segment) published in a
    recorded replay, in order, as its key-value pairs."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: list[dict[str, str]] = []
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/diagnostics"]
        for conn, _, data in reader.messages(connections=conns):
            for status in reader.deserialize(data, conn.msgtype).status:
                if status.name.rsplit("/", 1)[-1] == node:
                    out.append({kv.key: kv.value for kv in status.values})
    return out


def first_difference(a: dict[str, list], b: dict[str, list]) -> str | None:
    """Where two :func:`recorded_estimates` differ first (None: byte for byte the same)."""
    if a.keys() != b.keys():
        return f"topics {sorted(a.keys() ^ b.keys())} are in only one of them"
    for topic in sorted(a):
        if len(a[topic]) != len(b[topic]):
            return f"{topic}: {len(a[topic])} against {len(b[topic])} messages"
        for i, (x, y) in enumerate(zip(a[topic], b[topic])):
            if x != y:
                return f"{topic}: message {i} differs ({'log time' if x[0] != y[0] else 'bytes'})"
    return None

def _flatten(value, out: list[float]) -> None:
    if isinstance(value, (bool, np.bool_)):
        out.append(float(value))
    elif isinstance(value, (int, float, np.integer, np.floating)):
        out.append(float(value))
    elif isinstance(value, np.ndarray):
        if value.dtype.kind in "biuf":
            out.extend(float(v) for v in value.ravel())
    elif isinstance(value, (list, tuple)):
        for item in value:
            _flatten(item, out)
    elif hasattr(value, "__dataclass_fields__"):
        for name in value.__dataclass_fields__:
            _flatten(getattr(value, name), out)


def estimate_values(bag: Path) -> dict[str, np.ndarray]:
    """``{topic: array (kept messages, floats per message)}``, plus ``topic#count``: the number
    of messages, for every ``/estimation/*`` topic of a recorded replay."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    rows: dict[str, list[list[float]]] = {}
    counts: dict[str, int] = {}
    with AnyReader([Path(bag)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, _, data in reader.messages():
            if not conn.topic.startswith(COMPARED_PREFIX):
                continue
            i = counts.get(conn.topic, 0)
            counts[conn.topic] = i + 1
            if i % STRIDE == 0:
                flat: list[float] = []
                _flatten(reader.deserialize(data, conn.msgtype), flat)
                rows.setdefault(conn.topic, []).append(flat)
    values = {topic: np.array(r, dtype=float) for topic, r in rows.items()}
    values.update({f"{topic}#count": np.array(n) for topic, n in counts.items()})
    return values


def differences(values: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> list[str]:
    """What differs from the reference, one line per topic (empty: the same numbers)."""
    problems = []
    for key in sorted(set(values) | set(reference)):
        if key not in values or key not in reference:
            problems.append(f"{key}: only in {'the replay' if key in values else 'the reference'}")
            continue
        got, want = values[key], reference[key]
        if got.shape != want.shape:
            problems.append(f"{key}: shape {got.shape}, reference {want.shape}")
            continue
        scale = np.maximum(np.nanmax(np.abs(want), axis=0, initial=0.0), 1e-12) if want.ndim > 1 else \
            max(float(np.max(np.abs(want), initial=0.0)), 1e-12)
        close = np.abs(got - want) <= SCALE_RTOL * scale
        bad = ~(close | (np.isnan(got) & np.isnan(want)))
        if np.any(bad):
            i = np.argwhere(bad)[0]
            problems.append(f"{key}: {int(bad.sum())} values differ, first at {tuple(int(k) for k in i)}: "
                            f"{got[tuple(i)]!r} vs {want[tuple(i)]!r}")
    return problems


def save(values: dict[str, np.ndarray], path: Path) -> None:
    # An archive member may not start with '/': topics are stored with ':' for '/'.
    np.savez_compressed(path, **{key.replace("/", ":"): v for key, v in values.items()})


def load(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as archive:
        return {key.replace(":", "/"): archive[key] for key in archive.files}


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: replay_values.py ESTIMATES_BAG OUT.npz")
    save(estimate_values(Path(sys.argv[1])), Path(sys.argv[2]))
