"""``vehicle-estimation bench`` end to end, briefly: its tables and JSON, never its timings
(the figures depend on the machine; the targets are printed, not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from vehicle_estimation.estimators.common import compiled


@pytest.mark.dds
def test_bench_cores_and_live_print_the_side_by_side_figures(tmp_path):
    out = tmp_path / "bench"
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "bench", "--sections", "cores,live",
                           "--core-seconds", "8", "--live-seconds", "5", "--out", str(out),
                           "--workdir", str(tmp_path / "work")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads((out / "bench.json").read_text())
    names = [row["name"] for row in result["cores"]]
    assert any(name.startswith("vehicle state: VB-ACKF, N = 10 (shipped), numpy") for name in names)
    live = result["live"]
    assert set(live["cpu_share"]) == {"fusion", "vehicle_state", "road_slope", "mass"}
    assert 0.0 < live["floor_share"] < live["cpu_share_total"]   # our nodes cost more than doing nothing
    assert live["latency_ms"]
    composed = live["in_process"]                                # run --in-process, same run
    assert composed["cpu_share_total"] > 0.0 and composed["latency_ms"]
    assert set(composed["latency_ms"]) == set(live["latency_ms"])   # every output came out
    report = (out / "bench.md").read_text()
    assert "Framework floor, same run" in report
    assert "the nodes composed into one process" in report
    if compiled.enabled():
        assert "against the same maths in numpy" in report and "VB-ACKF, N = 10 (shipped): compiled" in report


@pytest.mark.dds
def test_the_in_process_floor_delivers_every_message_and_handles_none(tmp_path):
    """The pipeline section's floor: the same in-process replay with the handlers switched off
    reads, delivers and queues every message (lossless) but no node estimates anything; the
    report puts it beside the replay."""
    from rosbags.highlevel import AnyReader

    from vehicle_estimation.evaluation.bench import _params_files, format_report
    from vehicle_estimation.evaluation.bench_floor import handlers_switched_off
    from vehicle_estimation.launcher.processes import NodeGroup
    from vehicle_estimation.launcher.replay import replay
    from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

    bag = write_bag(simulate(scenario_by_name("short")), tmp_path / "drive")
    with handlers_switched_off():
        stats = replay(bag, tmp_path / "floor", lambda o: NodeGroup(_params_files(), overrides=o),
                       progress=False, in_process=True)
    assert stats.lossless and sum(stats.read.values()) > 1000
    with AnyReader([tmp_path / "floor"]) as reader:
        estimates = [c.topic for c in reader.connections if c.topic.startswith("/estimation/") and c.msgcount]
    assert estimates == []
    pipeline = {"bag_s": 120.0, "wall_s": 17.0, "rt_factor": 7.1, "lossless": True, "rss_minute_1": {},
                "nodes": {"fusion": {"cpu_s": 5.0, "rss_mib": 80.0}},
                "in_process": {"wall_s": 6.0, "cpu_s": 6.5, "rt_factor": 20.0, "lossless": True,
                               "floor": {"wall_s": 1.0, "rt_factor": 120.0}},
                "floor": {"wall_s": 8.5, "rt_factor": 14.1}}
    report = format_report({"pipeline": pipeline})
    assert "Floor of the in-process replay, the same replay with every handler switched off" in report
    assert "take the other 5.0 s, 83 % of the replay" in report
    assert "Floor of the DDS replay" in report and "**14.1x real time** (20x is beyond it)" in report
