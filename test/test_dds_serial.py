"""The test runner's own rule: DDS tests alone, the rest side by side (test/dds_serial.py)."""

from __future__ import annotations

import fcntl
import sys
import threading

import pytest

from dds_serial import _ReadersWriterLock, _replays_over_dds


def _can_lock(path, mode) -> bool:
    with open(path, "a+") as handle:
        try:
            fcntl.flock(handle, mode | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(handle, fcntl.LOCK_UN)
        return True


def test_an_exclusive_holder_keeps_everyone_out_and_shared_holders_only_writers(tmp_path):
    lock = _ReadersWriterLock(tmp_path)          # flock: each open file is its own holder
    lock.acquire(exclusive=True)
    assert not _can_lock(tmp_path / "rw", fcntl.LOCK_SH)
    lock.acquire(exclusive=False)                # switching releases first, then waits its turn
    assert lock.mode == "shared"
    assert _can_lock(tmp_path / "rw", fcntl.LOCK_SH) and not _can_lock(tmp_path / "rw", fcntl.LOCK_EX)
    lock.release()
    assert _can_lock(tmp_path / "rw", fcntl.LOCK_EX)


def test_a_waiting_writer_holds_the_turnstile_so_new_readers_queue_behind_it(tmp_path):
    reader, writer = _ReadersWriterLock(tmp_path), _ReadersWriterLock(tmp_path)
    reader.acquire(exclusive=False)
    waiting = threading.Thread(target=writer.acquire, args=(True,), daemon=True)
    waiting.start()
    for _ in range(200):                         # until the writer sits in the turnstile
        if not _can_lock(tmp_path / "gate", fcntl.LOCK_EX):
            break
        waiting.join(0.01)
    assert not _can_lock(tmp_path / "gate", fcntl.LOCK_EX)   # a new reader would wait here
    reader.release()
    waiting.join(10.0)
    assert not waiting.is_alive() and writer.mode == "exclusive"
    writer.release()


@pytest.mark.parametrize(("argv", "dds"), [
    ([sys.executable, "-m", "vehicle_estimation", "replay", "bag", "--record", "out"], True),
    ([sys.executable, "-m", "vehicle_estimation", "replay", "bag", "--record", "out", "--in-process"], False),
    ([sys.executable, "-m", "vehicle_estimation", "validate", "--quick"], True),
    ([sys.executable, "-m", "vehicle_estimation", "report", "rec"], False),
    ([sys.executable, "-m", "vehicle_estimation.ros.fusion_node", "--ros-args", "-r", "__ns:=/"], True),
    (["/ws/.venv/bin/vehicle-estimation", "run"], True),
    (["git", "status"], False),
])
def test_commands_that_replay_over_dds_are_told_apart(argv, dds):
    assert _replays_over_dds(argv) is dds
