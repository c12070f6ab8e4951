"""Tests that talk over DDS run alone; every other test may run beside another (pytest-xdist).

A live ROS graph (nodes in their own processes, a player, a test's own rclpy node) delivers
sensor data best effort and keeps start-up deadlines: on a busy CPU it drops samples and the
test fails for no fault of the code. Such tests carry the ``dds`` mark. Workers share a
readers-writer lock (``flock`` on two files that the first process creates): a ``dds`` test
holds it exclusively, any other test shared, and a worker keeps the exclusive lock from one
``dds`` test to the next. A turnstile gives the exclusive side priority, so a stream of
shared holders cannot starve it. Without xdist the lock is never contended.

A test that starts DDS without the mark fails (rclpy initialised in the test process, a node
process, or a ``vehicle_estimation`` command that replays over DDS): the mark is what keeps
the run reliable, so it cannot be forgotten.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import pytest

_LOCK_DIR_ENV = "VEHICLE_ESTIMATION_TEST_LOCK_DIR"
# `vehicle-estimation` commands that never start DDS (the others replay or run nodes over DDS
# unless given --in-process).
_OFFLINE_COMMANDS = {"report", "inspect", "calibrate", "simulate", "params", "import", "truck-data",
                     "train-mass-transformer", "train-gabpnn", "paper000", "paper002", "campaign"}

if _LOCK_DIR_ENV not in os.environ:       # the first process (controller or lone runner) decides
    os.environ[_LOCK_DIR_ENV] = tempfile.mkdtemp(prefix="vehicle_estimation_test_lock_")


class _ReadersWriterLock:
    def __init__(self, directory: Path) -> None:
        self._gate = open(directory / "gate", "a+")       # noqa: SIM115 - held for the session
        self._rw = open(directory / "rw", "a+")           # noqa: SIM115
        self.mode: str | None = None

    def acquire(self, exclusive: bool) -> None:
        want = "exclusive" if exclusive else "shared"
        if self.mode == want:
            return
        self.release()
        fcntl.flock(self._gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(self._rw, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(self._gate, fcntl.LOCK_UN)
        self.mode = want

    def release(self) -> None:
        if self.mode is not None:
            fcntl.flock(self._rw, fcntl.LOCK_UN)
            self.mode = None


_LOCK = _ReadersWriterLock(Path(os.environ[_LOCK_DIR_ENV]))
_started_dds: list[str] = []


def _replays_over_dds(argv: list[str]) -> bool:
    """A node process (``--ros-args``), or a ``vehicle-estimation`` command that starts nodes
    over DDS."""
    if "--ros-args" in argv:
        return True
    module = "vehicle_estimation" in argv[:3]          # python -m vehicle_estimation COMMAND
    if not module and not (argv and Path(argv[0]).name == "vehicle-estimation"):
        return False
    start = argv.index("vehicle_estimation") + 1 if module else 1
    command = argv[start] if start < len(argv) else ""
    return command not in _OFFLINE_COMMANDS and "--in-process" not in argv


class _WatchedPopen(subprocess.Popen):
    def __init__(self, args: Any, *rest: Any, **kwargs: Any) -> None:
        argv = [str(a) for a in args] if isinstance(args, (list, tuple)) else str(args).split()
        if _replays_over_dds(argv):
            _started_dds.append(" ".join(argv[:6]))
        super().__init__(args, *rest, **kwargs)


def _watch_rclpy() -> None:
    try:
        from rclpy.context import Context
    except ImportError:
        return
    init = Context.init

    def watched_init(self: Any, *args: Any, **kwargs: Any) -> Any:
        _started_dds.append("rclpy initialised in the test process")
        return init(self, *args, **kwargs)

    Context.init = watched_init  # type: ignore[method-assign]


subprocess.Popen = _WatchedPopen  # type: ignore[misc]
_watch_rclpy()


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "dds: the test starts a live ROS graph; it runs alone (test/dds_serial.py)")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    dds = item.get_closest_marker("dds") is not None
    _LOCK.acquire(exclusive=dds)
    _started_dds.clear()
    try:
        return (yield)
    finally:
        # an exclusive holder keeps the lock only while its next test is known and needs it too
        if not dds or nextitem is None or nextitem.get_closest_marker("dds") is None:
            _LOCK.release()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Any:
    result = yield
    if item.get_closest_marker("dds") is None and _started_dds:
        raise AssertionError(f"{item.nodeid} starts DDS without the 'dds' mark "
                             f"(test/dds_serial.py): {_started_dds[0]}")
    return result


def pytest_sessionfinish(session: pytest.Session) -> None:
    _LOCK.release()


def workers_wanted() -> int:
    """Two or more cores: one worker each, at most four (each holds torch and the nodes'
    imports); one core: none."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(cores, 4) if cores > 1 else 0

