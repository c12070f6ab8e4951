"""``vehicle-estimation bench`` end to end, briefly: its tables and JSON, never its timings
(the figures depend on the machine; the targets are printed, not asserted)."""

from __future__ import annotations

import json
import subprocess
import sys

from vehicle_estimation.estimators.common import compiled


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
