"""The launcher: `run` starts every node and stops them all (sqlite3 replays: test_any_bag)."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from vehicle_estimation.ros import PIPELINE

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds


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


@contextlib.contextmanager
def _launched(*args: str) -> Iterator[subprocess.Popen]:
    """``vehicle-estimation run ARGS`` (stdout and stderr as one text stream), killed if it is
    still running at the end."""
    launcher = subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "run", *args],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        yield launcher
    finally:
        if launcher.poll() is None:
            launcher.kill()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_starts_every_node_and_stops_them_all(sig):
    with _launched("--namespace", "/t") as launcher:
        deadline = time.monotonic() + 30
        while len(_children(launcher.pid)) < len(PIPELINE) and time.monotonic() < deadline:
            time.sleep(0.2)
        children = _children(launcher.pid)
        assert len(children) == len(PIPELINE), launcher.stdout.read() if launcher.poll() is not None else children
        time.sleep(2.0)  # let them finish starting up
        assert all(_alive(c) for c in children)
        launcher.send_signal(sig)
        launcher.wait(timeout=30)
    assert launcher.returncode == 0
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(c) for c in children), "orphan node processes left behind"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_in_process_composes_the_nodes_and_stops_cleanly(sig):
    """`run --in-process`: every node in the launcher's own process (no child), stopped by a
    signal with exit 0. Its topics end to end: test_bench (live, composed)."""
    with _launched("--in-process", "--namespace", "/t", "--state-dir", "") as launcher:
        started = ""
        for line in launcher.stdout:
            if line.startswith("started "):
                started = line
                break
        assert all(spec.name in started for spec in PIPELINE), started
        assert _children(launcher.pid) == []
        launcher.send_signal(sig)
        launcher.wait(timeout=30)
    assert launcher.returncode == 0


def test_run_in_process_refuses_a_bad_parameter_naming_it(tmp_path):
    params = tmp_path / "bad.yaml"
    params.write_text("mass:\n  ros__parameters:\n    time_jump_reset_s: 0.0\n")
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "run", "--in-process", "--params", "estimation",
                           "--params", str(params), "--state-dir", ""], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "mass: invalid parameter" in proc.stderr and "time_jump_reset_s" in proc.stderr


def test_a_node_process_s_last_words_are_the_last_line_of_its_log(tmp_path):
    """Where a node's output goes to a file (validate, stanford, batch), the reason it stopped is
    the log's last non-empty line; a replay that loses the node quotes it."""
    from vehicle_estimation.launcher.processes import NodeProcess

    log = tmp_path / "vehicle_state.log"
    node = NodeProcess(PIPELINE[0], ["true"], log_path=log)
    assert node.last_words() == ""                       # no log yet
    log.write_text("starting\n" + "x" * 5000 + "\n[vehicle_estimation] invalid parameter: 'filter_rate_hz'\n\n",
                   encoding="utf-8")
    assert node.last_words() == "[vehicle_estimation] invalid parameter: 'filter_rate_hz'"
    log.write_text("y" * 1000 + "\n", encoding="utf-8")
    assert node.last_words(max_chars=50) == "y" * 50
    assert NodeProcess(PIPELINE[0], ["true"]).last_words() == ""      # output to the terminal


def test_a_shutdown_under_a_publishing_callback_is_a_clean_stop():
    """A SIGTERM shuts rclpy's context down at any moment. A callback that publishes just after
    it raises rclpy's RCLError; spin() takes that for the stop it is. Under load the launcher
    exited 1 with a traceback instead of 0."""
    import rclpy
    from rclpy.node import Node
    from std_msgs.msg import Float64

    from vehicle_estimation.ros.runtime.spin import spin

    rclpy.init()
    node = Node("shutdown_probe")
    publisher = node.create_publisher(Float64, "shutdown_probe", 1)

    def shut_down_then_publish() -> None:
        rclpy.shutdown()
        publisher.publish(Float64())

    node.create_timer(0.01, shut_down_then_publish)
    try:
        spin([node], "shutdown_probe")         # returns: no RCLError escapes
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    assert not rclpy.ok()
