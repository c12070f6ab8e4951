"""The launcher: `run` starts every node and stops them all; `replay` reads sqlite3 bags too."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.nodes import PIPELINE
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag


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


def test_replay_reads_a_sqlite3_bag(tmp_path):
    mcap = tmp_path / "drive_mcap"
    write_bag(simulate(scenario_by_name("short")), mcap)
    sqlite = tmp_path / "drive_sqlite"
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with AnyReader([mcap], default_typestore=typestore) as reader, \
            Writer(sqlite, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=typestore) for c in reader.connections}
        end = reader.start_time + 20 * 10**9  # the first 20 s are enough
        for conn, timestamp, data in reader.messages():
            if timestamp < end:
                writer.write(conns[conn.id], timestamp, data)
    out = tmp_path / "estimates"
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(sqlite),
                           "--record", str(out), "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "lossless: True" in proc.stdout
    with AnyReader([out]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    assert counts.get("/estimation/odometry", 0) > 100
    assert counts.get("/estimation/mass", 0) > 10
