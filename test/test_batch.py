"""``batch``: many bags on a local Dask cluster (in-process replays), a corrupt bag among them,
``--resume``; and two DDS replays side by side, each in a ROS domain of its own."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

pytest.importorskip("distributed")

DRIVE_S = 8.0


@pytest.fixture(scope="module")
def fleet(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fleet") / "bags"
    root.mkdir()
    for seed in range(1, 5):
        scenario = dataclasses.replace(scenario_by_name("short"), duration_s=DRIVE_S, seed=seed)
        write_bag(simulate(scenario), root / f"drive_{seed}")
    corrupt = root / "corrupt"
    corrupt.mkdir()
    (corrupt / "corrupt_0.mcap").write_bytes(b"not an MCAP file")
    return root


def _batch(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vehicle_estimation", "batch", *args, "--quiet"],
                          capture_output=True, text=True, timeout=900)


def test_batch_replays_every_bag_and_survives_a_corrupt_one(fleet, tmp_path):
    out = tmp_path / "out"
    proc = _batch(str(fleet), "--out", str(out), "--workers", "2")
    assert proc.returncode == 1, proc.stdout + proc.stderr        # one bag failed
    summary = json.loads((out / "summary.json").read_text())
    rows = {r["bag"]: r for r in summary["rows"]}
    assert set(rows) == {"corrupt", "drive_1", "drive_2", "drive_3", "drive_4"}
    assert rows["corrupt"]["status"] == "failed" and rows["corrupt"]["reason"]
    for key in ("drive_1", "drive_2", "drive_3", "drive_4"):
        row = rows[key]
        assert row["status"] == "ok", row
        assert abs(row["duration_s"] - DRIVE_S) < 0.5
        assert 500.0 < row["final"]["mass"] < 5000.0
        assert row["metrics"]["vx RMSE [m/s]"] < 0.5            # the bags carry ground truth
        assert (out / key / "estimates").is_dir()
        assert (out / key / "report" / "report.json").exists()
    assert summary["ok"] == 4 and summary["failed"] == 1
    assert (out / "fleet_metrics.png").stat().st_size > 0
    text = (out / "summary.md").read_text()
    assert "| corrupt |" in text and "failed" in text and "| drive_4 |" in text

    # A rerun skips what is done and tries the failed bag again.
    again = _batch(str(fleet), "--out", str(out), "--workers", "2", "--resume")
    assert again.returncode == 1, again.stdout + again.stderr
    assert "5 bags, 1 to replay, 4 done before" in again.stderr
    rows = {r["bag"]: r for r in json.loads((out / "summary.json").read_text())["rows"]}
    assert all(rows[f"drive_{i}"]["skipped"] for i in range(1, 5))
    assert not rows["corrupt"]["skipped"]


def test_batch_calibrates_each_vehicle_and_replays_its_bags_with_the_calibrated_file(tmp_path):
    """Paper 003's training phase per vehicle id (``--calibrate --mass-from``), on a calibration
    drive that the CSV names, then the vehicle's bag replayed with the written params file."""
    from test_calibrated_pipeline import AUDI, _obd_only_drive

    training = write_bag(simulate(_obd_only_drive(seed=9)), tmp_path / "calibration" / "training_drive")
    fleet = tmp_path / "bags"
    write_bag(simulate(_obd_only_drive(seed=4, duration=DRIVE_S)), fleet / "audi_drive")
    table = tmp_path / "vehicles.csv"
    table.write_text("bag,vehicle,mass_kg\n"
                     f"calibration/{training.name},audi_1,{AUDI.mass}\n"
                     "audi_drive,audi_1,\n")
    out = tmp_path / "out"
    proc = _batch(str(fleet), "--out", str(out), "--workers", "1", "--vehicle", "audi_a4",
                  "--calibrate", "--mass-from", str(table))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "calibration of audi_1 on training_drive: ok" in proc.stderr
    params = out / "calibration" / "audi_1.yaml"
    fitted = yaml.safe_load(params.read_text())["mass"]["ros__parameters"]
    assert len(fitted["mass"]["torque_regression"]) >= 3
    result = json.loads((out / "audi_drive" / "result.json").read_text())
    assert result["status"] == "ok" and result["vehicle_id"] == "audi_1"
    assert Path(result["params"][0]) == params
    assert math.isfinite(result["final"]["mass"])


def test_two_dds_replays_side_by_side_take_a_domain_each(fleet, tmp_path):
    """Without ROS_DOMAIN_ID each replay claims a free domain: run together, neither stalls."""
    env = {k: v for k, v in os.environ.items() if k != "ROS_DOMAIN_ID"}
    procs = [subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "replay", str(fleet / f"drive_{i}"),
                               "--record", str(tmp_path / f"out{i}"), "--quiet"], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in (1, 2)]
    outputs = [p.communicate(timeout=600) for p in procs]
    domains = set()
    for p, (stdout, stderr) in zip(procs, outputs):
        assert p.returncode == 0, stdout + stderr
        assert "lossless: True" in stdout
        line = next(ln for ln in stderr.splitlines() if "in ROS domain" in ln)
        domains.add(line.split("in ROS domain")[1].split()[0])
    assert len(domains) == 2


def test_batch_runs_on_a_running_scheduler(fleet, tmp_path):
    """``--scheduler ADDRESS``: the bags go to a cluster that someone else started (here a
    local one, as ``dask scheduler`` / ``dask worker`` would be on other machines)."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        out = tmp_path / "out"
        proc = _batch(str(fleet / "drive_3"), "--out", str(out), "--scheduler", cluster.scheduler_address)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ok"] == 1 and summary["workers"] is None
    assert "the cluster's workers" in (out / "summary.md").read_text()
