"""Paper 003's calibration workflow end to end through the nodes, and every params file the
package writes layered over every file it ships.

A car whose OBD-II reports only engine speed and load (PID 0C and 04: no torque, no drive
force, no gear): one drive at a known mass goes through ``calibrate``; a second drive is
replayed with ``--vehicle calibrated.yaml`` and the shipped params, and the mass must come out
right. No other test takes a calibrated file through the nodes.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rosbags.highlevel import AnyReader

from vehicle_estimation.nodes.base import ParameterError
from vehicle_estimation.nodes.fusion_node import FusionNode
from vehicle_estimation.nodes.mass_node import MassNode
from vehicle_estimation.nodes.slope_node import SlopeNode
from vehicle_estimation.nodes.state_node import StateNode
from vehicle_estimation.sim.bag import write_bag
from vehicle_estimation.sim.profiles import SpeedProfile
from vehicle_estimation.sim.road import RoadSpec
from vehicle_estimation.sim.scenario import Scenario, SensorConfig
from vehicle_estimation.sim.simulate import simulate
from vehicle_estimation.vehicle import load_vehicle_params

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
SHIPPED = sorted(PARAMS_DIR.glob("*.yaml"))
AUDI = load_vehicle_params(PARAMS_DIR / "audi_a4.yaml")
OBD_ONLY = ("engine_speed", "engine_load")
POINTS = ((0, 0), (14, 30), (20, 30), (30, 12), (42, 38), (70, 38), (80, 25), (95, 25), (102, 8),
          (110, 8), (118, 20), (130, 14), (140, 0), (144, 0))


def _obd_only_drive(seed: int, duration: float = 150.0) -> Scenario:
    return Scenario(name="obd", vehicle=AUDI, duration_s=duration, seed=seed,
                    speed_profile=SpeedProfile(kind="points", points=POINTS),
                    road=RoadSpec(kind="random", grade_max=0.04),
                    sensors=dataclasses.replace(SensorConfig(), powertrain_reports=OBD_ONLY))


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> tuple[Path, int]:
    from vehicle_estimation.tools import calibrate

    tmp = tmp_path_factory.mktemp("calibrated")
    result = simulate(_obd_only_drive(seed=9))
    gears = len(set(result.truth["gear"][result.truth["vx"] > 3.0].tolist()))
    bag = write_bag(result, tmp / "training_drive")
    out = tmp / "calibrated.yaml"
    parser = argparse.ArgumentParser()
    calibrate.add_arguments(parser)
    args = parser.parse_args([str(bag), "--mass", str(AUDI.mass), "--out", str(out), "--gears", str(gears),
                              "--vehicle", str(PARAMS_DIR / "audi_a4.yaml")])
    assert calibrate.main(args) == 0
    return out, gears


def test_the_obd_only_sensor_config_reports_nothing_else():
    sensors = simulate(_obd_only_drive(seed=1, duration=20.0)).sensors["powertrain"]
    assert np.isfinite(sensors["engine_speed"]).all() and np.isfinite(sensors["load"]).all()
    for name in ("engine_torque", "gear", "drive_force"):
        assert np.isnan(sensors[name]).all(), name


def _start_every_node(files: list[Path]) -> None:
    """Construct the four nodes in-process with the layered files (a later file wins)."""
    context = rclpy.Context()
    args = ["--ros-args"] + [a for f in files for a in ("--params-file", str(f))]
    rclpy.init(args=args, context=context)
    try:
        for node_class in (FusionNode, StateNode, SlopeNode, MassNode):
            node_class(context=context).destroy_node()
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize("shipped", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_the_calibrated_file_layers_over_every_shipped_file(calibrated, shipped):
    out, _ = calibrated
    for files in ([out, shipped], [shipped, out]):
        try:
            _start_every_node(files)
        except ParameterError as exc:   # the message names the parameter
            pytest.fail(f"{[f.name for f in files]}: {exc}")


def test_the_rls_node_takes_the_fitted_torque_map(calibrated):
    out, _ = calibrated
    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(out), "--params-file",
                     str(PARAMS_DIR / "estimation.yaml")], context=context)
    try:
        node = MassNode(context=context)
        assert node.method == "rls" and len(node.config.torque_regression) == 4
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_a_calibrated_obd_only_car_through_the_nodes(calibrated, tmp_path):
    """calibrate -> replay --vehicle calibrated.yaml with the shipped params: the mass within
    +-5 % over the last half of a drive the calibration never saw (prior 1000 kg)."""
    out, gears = calibrated
    result = simulate(_obd_only_drive(seed=21))
    assert len(set(result.truth["gear"][result.truth["vx"] > 3.0].tolist())) <= gears
    bag = write_bag(result, tmp_path / "drive")
    estimates = tmp_path / "estimates"
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record",
                           str(estimates), "--vehicle", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "lossless: True" in proc.stdout
    t, mass = [], []
    with AnyReader([estimates]) as reader:
        conns = [c for c in reader.connections if c.topic == "/estimation/mass_stamped"]
        for conn, _, data in reader.messages(connections=conns):
            msg = reader.deserialize(data, conn.msgtype)
            t.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)
            mass.append(msg.vector.x)
    t, mass = np.array(t), np.array(mass)
    last_half = t >= t[0] + 0.5 * (t[-1] - t[0])
    error = np.abs(mass[last_half] / AUDI.mass - 1.0)
    assert error.max() < 0.05, f"last-half mass error up to {100 * error.max():.1f} %"
