"""Restarts and persisted state: kill -9 a node in the middle of a replay; the launcher respawns
it and the mass node resumes from its persisted estimate and covariance, not from its prior. The
fusion's learnt speed scale starts the next drive."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from vehicle_estimation.ros.persistence import StateFileError, load_state, save_state
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

PRIOR_KG = 1000.0     # params/estimation.yaml: mass.initial_mass (paper 003)


def _children(pid: int) -> dict[int, str]:
    out = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
                cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except (OSError, IndexError, ValueError):
                continue
            if ppid == pid:
                out[int(entry.name)] = cmdline
    return out


def _mass_series(bag: Path) -> list[tuple[float, float, float]]:
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/estimation/mass_stamped"]
        out = []
        for conn, _, data in reader.messages(connections=conns):
            m = reader.deserialize(data, conn.msgtype)
            out.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.vector.x, m.vector.y))
    return out


def _diagnostic_events(bag: Path, node: str) -> list[str]:
    events = []
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/diagnostics"]
        for conn, _, data in reader.messages(connections=conns):
            for status in reader.deserialize(data, conn.msgtype).status:
                if status.name.endswith("/" + node):
                    events += [kv.value for kv in status.values if kv.key == "last event"]
    return events


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp("restart") / "drive"
    write_bag(simulate(scenario_by_name("short")), bag)   # mass updates from ~25 s of its 60 s
    return bag


def _replay_killing(bag: Path, out: Path, victims: list[tuple[str, float]], tmp: Path) -> tuple[int, str, str]:
    """Replay ``bag``; SIGKILL node ``name`` at ``seconds`` of bag time, for each victim.

    The replay pauses at each kill time (``VEHICLE_ESTIMATION_REPLAY_PAUSE``) until the test has
    killed the node, so the kill lands at that bag time however fast or slow the machine is.
    """
    resume = [tmp / f"resume_{i}" for i in range(len(victims))]
    env = dict(os.environ, VEHICLE_ESTIMATION_REPLAY_PAUSE=",".join(
        f"{seconds}:{path}" for (_, seconds), path in zip(victims, resume)))
    proc = subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "replay", str(bag),
                             "--record", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    err: list[str] = []
    paused = threading.Semaphore(0)

    def read_stderr() -> None:
        buf = b""
        while True:
            ch = proc.stderr.read(1)
            if not ch:
                break
            if ch in b"\r\n":
                line = buf.decode(errors="replace")
                err.append(line)
                if line.startswith("replay: paused at"):
                    paused.release()
                buf = b""
            else:
                buf += ch

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    for (name, _), path in zip(victims, resume):
        assert paused.acquire(timeout=600), "the replay never paused: " + "\n".join(err[-20:])
        pids = [pid for pid, cmd in _children(proc.pid).items() if f"vehicle_estimation.ros.{name}" in cmd]
        assert len(pids) == 1, _children(proc.pid)
        os.kill(pids[0], signal.SIGKILL)
        path.touch()
    # Not communicate(): it would read stderr too, racing the reader thread for its lines.
    stdout = proc.stdout.read()
    proc.wait(timeout=600)
    reader.join(timeout=10)
    return proc.returncode, stdout.decode(), "\n".join(err)


def test_kill_9_mid_replay_respawns_and_mass_resumes(drive, tmp_path):
    out = tmp_path / "estimates"
    code, stdout, stderr = _replay_killing(drive, out, [("mass_node", 42.0), ("fusion_node", 48.0)], tmp_path)
    assert code == 0, stdout + stderr[-3000:]
    assert "mass exited with -9; respawning" in stderr and "fusion exited with -9; respawning" in stderr
    assert "2 node respawn(s)" in stdout

    series = _mass_series(out)
    gaps = [i for i in range(1, len(series)) if series[i][0] - series[i - 1][0] > 0.15]
    assert gaps, "no gap in the mass output where the node was down"
    i = gaps[0]
    (_, before, var_before), (_, after, var_after) = series[i - 1], series[i]
    # The estimate had left its prior before the kill, and the new process starts where the
    # old one was (at most one persistence period, 1 s, of updates lost), not from the prior.
    assert abs(before - PRIOR_KG) > 200.0, (before, PRIOR_KG)
    assert abs(after - before) < 0.02 * before, (before, after)
    assert var_after < 10.0 * var_before and var_after < 1e6, (var_before, var_after)
    assert any("resumed from the persisted mass" in e for e in _diagnostic_events(out, "mass"))
    # ... and everything still publishes to the end of the drive, finite.
    assert series[-1][0] - series[0][0] > 55.0
    assert all(abs(m) < 1e6 and m == m for _, m, _ in series)


def test_state_file_is_atomic_and_validated(tmp_path):
    path = tmp_path / "state" / "mass.json"
    save_state(path, "mass/rls", 12.5, {"mass": 1500.0, "gain": 3.0}, vehicle="sedan")
    stamp, state, meta = load_state(path, "mass/rls")
    assert (stamp, state, meta) == (12.5, {"mass": 1500.0, "gain": 3.0}, {"vehicle": "sedan"})
    assert [p.name for p in path.parent.iterdir()] == ["mass.json"]     # no temporary left over
    assert load_state(tmp_path / "missing.json", "mass/rls") is None
    with pytest.raises(ValueError):
        save_state(path, "mass/rls", 13.0, {"mass": float("nan"), "gain": 3.0})
    assert load_state(path, "mass/rls")[0] == 12.5                       # the old file survives
    with pytest.raises(StateFileError, match="mass/ffrls"):
        load_state(path, "mass/ffrls")
    for damaged in ("{", json.dumps({"format": "x"}), path.read_text().replace("1500.0", "NaN"),
                    path.read_text()[:-7]):
        path.write_text(damaged)
        with pytest.raises(StateFileError):
            load_state(path, "mass/rls")


def test_the_fusion_resumes_its_speed_scale_and_refuses_a_state_that_is_not_one(tmp_path):
    """The fusion's ``persist.path`` (``run`` and ``replay --state-dir`` set it): a drive starts
    from the scale an earlier one learnt, with the earlier variance plus the resume term; a file
    without a variance, for another vehicle, or with a scale no tyre gives is refused, counted
    and named, and the fusion starts from its prior."""
    import rclpy
    from rclpy.parameter import Parameter
    from rosharness import init_rclpy, vehicle_overrides

    from vehicle_estimation.estimators.fusion.config import FusionConfig
    from vehicle_estimation.ros.fusion_node import FusionNode

    path = tmp_path / "fusion_root.json"

    def start():
        return FusionNode(parameter_overrides=vehicle_overrides() + [
            Parameter("fusion.estimate_speed_scale", value=True), Parameter("persist.path", value=str(path))])

    init_rclpy()
    try:
        save_state(path, "fusion/speed_scale", 5.0, {"scale": 1.03, "variance": 1e-6}, vehicle="sedan_d_class")
        node = start()
        resume = FusionConfig().speed_scale_resume_sigma
        assert node.ekf.speed_scale == pytest.approx(1.03)
        assert node.ekf.speed_scale_filter_variance == pytest.approx(1e-6 + resume ** 2)
        assert any("resumed the speed scale 1.0300" in e for e in node.health.events), node.health.events
        node.destroy_node()
        for state, vehicle in (({"scale": 1.03}, "sedan_d_class"), ({"scale": 1.03, "variance": 1e-6}, "heavy_truck"),
                               ({"scale": 1.5, "variance": 0.0}, "sedan_d_class")):
            save_state(path, "fusion/speed_scale", 5.0, state, vehicle=vehicle)
            node = start()
            assert node.ekf.speed_scale == 1.0 and node.ekf.speed_scale_filter_variance == pytest.approx(0.02 ** 2)
            assert node.health.rejected["persist:unusable_state_file"] == 1, state
            assert any("ignoring persisted speed scale" in e for e in node.health.events), node.health.events
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
