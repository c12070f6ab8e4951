"""The launcher: `run` starts every node and stops them all (sqlite3 replays: test_any_bag)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vehicle_estimation.ros import PIPELINE


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            if ppid == pid:
                out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_starts_every_node_and_stops_them_all(sig):
    launcher = subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "run", "--namespace", "/t"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while len(_children(launcher.pid)) < len(PIPELINE) and time.monotonic() < deadline:
            time.sleep(0.2)
        children = _children(launcher.pid)
        assert len(children) == len(PIPELINE), launcher.stdout.read() if launcher.poll() is not None else children
        time.sleep(2.0)  # let them finish starting up
        assert all(_alive(c) for c in children)
        launcher.send_signal(sig)
        launcher.wait(timeout=30)
    finally:
        if launcher.poll() is None:
            launcher.kill()
    assert launcher.returncode == 0
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(c) for c in children), "orphan node processes left behind"

