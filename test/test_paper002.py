"""Smoke run of the paper-002 comparison command (short drives) and its table."""

from __future__ import annotations

import json
import subprocess
import sys


def test_paper002_command_prints_the_table_and_writes_json_and_plots(tmp_path):
    out = tmp_path / "p002"
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation.experiments.paper002_aoukf_gabpnn", "--out", str(out),
                           "--duration", "8", "--no-paper-observations"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "| AO-UKF + GA-BPNN |" in proc.stdout and "paper Table 2: GA-BPNN" in proc.stdout
    comparison = json.loads((out / "comparison.json").read_text())
    assert set(comparison["scenarios"]) == {"paper002_dlc", "paper002_mixed"}
    dlc = comparison["scenarios"]["paper002_dlc"]
    assert list(dlc["rows"]) == ["EKF", "UKF", "AO-UKF", "AO-UKF + GA-BPNN", "VB-ACKF"]
    for row in dlc["rows"].values():
        for metric in ("mae", "rmse"):
            assert all(0.0 <= row[metric][k] < 1.0 for k in ("vx", "vy", "r")), row
    assert dlc["rows"]["AO-UKF"]["counters"]["isolated_zero_gain"] > 0
    assert (out / "paper002_dlc.png").stat().st_size > 10_000
    assert (out / "paper002_mixed.png").exists()
