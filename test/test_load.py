"""Load: a 1 kHz IMU through a replay loses no message and grows no queue."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

IMU_RATE = 1000.0
TICK_S = 0.1             # the replay's default tick


def _queue_maxima(bag: Path) -> dict[str, int]:
    """Largest "input queue: now / max" each node reported in /diagnostics."""
    out: dict[str, int] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/diagnostics"]
        for conn, _, data in reader.messages(connections=conns):
            for status in reader.deserialize(data, conn.msgtype).status:
                for kv in status.values:
                    if kv.key == "input queue: now / max":
                        node = status.name.rsplit("/", 1)[-1]
                        out[node] = max(out.get(node, 0), int(kv.value.split("/")[1]))
    return out


def test_1khz_imu_replay_is_lossless_with_bounded_queues(tmp_path):
    scn = scenario_by_name("short")
    scn = dataclasses.replace(scn, duration_s=25.0,
                              sensors=dataclasses.replace(scn.sensors, imu_rate=IMU_RATE))
    bag, out = tmp_path / "drive_1khz", tmp_path / "estimates"
    sim = simulate(scn)
    assert len(sim.sensors["imu"]["t"]) >= 24_000
    write_bag(sim, bag)
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record", str(out),
                           "--quiet"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    rows = {line.split()[0]: line.split()[1:] for line in proc.stdout.splitlines() if line.startswith("/")}
    read, processed = rows["/imu/data"]
    assert int(read) >= 24_000 and read == processed, rows
    assert "lossless: True" in proc.stdout
    # A node holds at most what its release delay (one tick per pipeline stage, at most 3 for
    # the mass node) plus the current tick bring in: ~500 messages a tick, all topics. Queues
    # that grew with the drive would reach the tens of thousands.
    maxima = _queue_maxima(out)
    assert set(maxima) == {"fusion", "vehicle_state", "road_slope", "mass"}, maxima
    per_tick = (IMU_RATE + 3 * 100.0 + 10.0) * TICK_S
    print("input queue maxima", maxima)
    for node, longest in maxima.items():
        assert 0 < longest <= 6 * per_tick, (node, longest)
