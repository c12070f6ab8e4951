"""Crash-safe persistence of an estimator's state (plain JSON, written atomically).

A mass estimate takes minutes of driving to converge; a node that is killed and respawned
must not fall back to its prior. :func:`save_state` writes the state to a temporary file in
the same directory, flushes and fsyncs it, and renames it over the old file: a rename is
atomic on POSIX, so a crash at any point leaves either the old file or the new one, never a
torn one. :func:`load_state` refuses anything that is not exactly what :func:`save_state`
wrote (wrong kind, non-finite numbers), so a damaged file costs the prior, not a NaN.
Only JSON is read: nothing is ever unpickled.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

from vehicle_estimation.ros.stamps import STAMP_TOLERANCE_S

FORMAT = "vehicle_estimation.estimator_state"
VERSION = 1


class StateFileError(ValueError):
    """A state file that exists but cannot be used (unreadable, foreign or damaged)."""


def save_state(path: Path, kind: str, stamp: float, state: dict[str, float], **meta: str) -> None:
    """Write ``state`` (finite floats) for estimator ``kind`` at bag/sensor time ``stamp``."""
    values = {k: float(v) for k, v in state.items()}
    if not all(math.isfinite(v) for v in values.values()) or not math.isfinite(stamp):
        raise ValueError(f"refusing to persist a non-finite state: {values}")
    payload = {"format": FORMAT, "version": VERSION, "kind": kind, "stamp": float(stamp),
               "meta": {k: str(v) for k, v in meta.items()}, "state": values}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except OSError:
        pass


def load_state(path: Path, kind: str) -> tuple[float, dict[str, float], dict[str, str]] | None:
    """``(stamp, state, meta)`` from ``path``; None if there is no file.

    Raises :class:`StateFileError` for a file that is not a valid state of ``kind``.
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        payload: Any = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise StateFileError(f"{path}: unreadable state file ({exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT or payload.get("version") != VERSION:
        raise StateFileError(f"{path}: not a {FORMAT} v{VERSION} file")
    if payload.get("kind") != kind:
        raise StateFileError(f"{path}: holds a {payload.get('kind')!r} state, not {kind!r}")
    state, stamp, meta = payload.get("state"), payload.get("stamp"), payload.get("meta", {})
    if not isinstance(state, dict) or not isinstance(meta, dict):
        raise StateFileError(f"{path}: malformed state")
    try:
        values = {str(k): float(v) for k, v in state.items()}
        stamp = float(stamp)
    except (TypeError, ValueError):
        raise StateFileError(f"{path}: non-numeric state") from None
    if not all(math.isfinite(v) for v in values.values()) or not math.isfinite(stamp):
        raise StateFileError(f"{path}: non-finite state")
    return stamp, values, {str(k): str(v) for k, v in meta.items()}


class PersistedState:
    """A node's state file: resumed once at start-up, saved every ``period_s`` of message time.

    ``node`` gives ``reject(reason)`` (a counted rejection in ``/diagnostics``), ``note_event``
    and ``get_logger``; ``what`` names the state in its messages. A file for another kind or
    vehicle, or a damaged one, is refused, counted and named, and the node starts from its
    prior; a failed write is counted and logged, never raised."""

    def __init__(self, node: Any, path: str, kind: str, vehicle: str, period_s: float, what: str) -> None:
        self.node, self.path, self.kind, self.vehicle = node, Path(path) if path else None, kind, vehicle
        self.period_s, self.what = period_s, what
        self._last_save = -math.inf

    def resume(self) -> tuple[float, dict[str, float]] | None:
        """``(stamp, state)`` of the file, or None (persistence off, no file, or refused)."""
        if self.path is None:
            return None
        try:
            loaded = load_state(self.path, self.kind)
            if loaded is None:
                self.node.note_event(f"no persisted {self.what} at {self.path}: starting from the prior")
                return None
            stamp, state, meta = loaded
            if meta.get("vehicle") != self.vehicle:
                raise StateFileError(f"state is for vehicle {meta.get('vehicle')!r}, not {self.vehicle!r}")
        except StateFileError as exc:
            self.refuse(exc)
            return None
        return stamp, state

    def refuse(self, reason: Exception) -> None:
        """A state that cannot be used (also one the estimator itself refuses on loading)."""
        self.node.reject("persist:unusable_state_file")
        self.node.note_event(f"ignoring persisted {self.what} ({reason}): starting from the prior")

    def due(self, t: float) -> bool:
        return self.path is not None and t - self._last_save >= self.period_s - STAMP_TOLERANCE_S

    def save(self, t: float, state: dict[str, float]) -> None:
        self._last_save = t
        assert self.path is not None
        try:
            save_state(self.path, self.kind, t, state, vehicle=self.vehicle)
        except (OSError, ValueError) as exc:
            self.node.reject("persist:write_failed")
            self.node.get_logger().error(f"cannot persist the {self.what}: {exc}", throttle_duration_sec=30.0)
