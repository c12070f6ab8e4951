"""Every params file the package writes, layered over every file it ships, and paper 003's
calibrated file taken by the nodes.

A car whose OBD-II reports only engine speed and load (PID 0C and 04: no torque, no drive
force, no gear): one drive of our simulator at a known mass goes through ``calibrate``; its
file must start every node over (and under) every shipped file, and give the rls node its
fitted torque map. The same workflow end to end through the nodes, on the independent WLTP
gear-shift tool's drives, is ``test/test_validation_wltp.py``. The vehicle files that the
validation generators write (CommonRoad, FASTSim, WLTP) are layered here too.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rclpy

from vehicle_estimation.contract.vehicle import load_vehicle_params
from vehicle_estimation.ros.fusion_node import FusionNode
from vehicle_estimation.ros.mass_node import MassNode
from vehicle_estimation.ros.runtime.parameters import ParameterError
from vehicle_estimation.ros.slope_node import SlopeNode
from vehicle_estimation.ros.state_node import StateNode
from vehicle_estimation.sim.bag import write_bag
from vehicle_estimation.sim.profiles import SpeedProfile
from vehicle_estimation.sim.road import RoadSpec
from vehicle_estimation.sim.scenario import Scenario, SensorConfig
from vehicle_estimation.sim.simulate import simulate

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

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
    from vehicle_estimation.training import calibrate

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
            node = node_class(context=context)
            try:
                node.check_parameter_overrides()      # no value in the files goes unread
            finally:
                node.destroy_node()
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
        # the fit's joint covariance (map and vehicle values) reaches the core's variance
        assert node.core.lasting_force_covariance is not None
        assert node.core.lasting_force_covariance.shape == (8, 8)
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def _written_vehicle_files() -> dict[str, str]:
    """The vehicle files the validation generators write, by generator (installed ones only)."""
    import importlib.util

    from vehicle_estimation.validation import commonroad

    files = {"commonroad": commonroad.params_yaml()}
    if importlib.util.find_spec("fastsim") is not None:
        from vehicle_estimation.validation import fastsim_drive
        files["fastsim"] = fastsim_drive.params_yaml()
    if importlib.util.find_spec("wltp") is not None:
        from vehicle_estimation.validation import wltp_drive
        files["wltp"] = wltp_drive.params_yaml()
    return files


def test_every_written_vehicle_file_layers_over_every_shipped_file(tmp_path):
    written = _written_vehicle_files()
    assert "commonroad" in written
    for name, text in written.items():
        path = tmp_path / f"{name}.yaml"
        path.write_text(text, encoding="utf-8")
        for shipped in SHIPPED:
            for files in ([path, shipped], [shipped, path]):
                try:
                    _start_every_node(files)
                except ParameterError as exc:
                    pytest.fail(f"{[f.name for f in files]}: {exc}")


def test_inspect_says_whether_the_calibration_s_error_is_in_the_mass_variance(calibrated, tmp_path):
    """The calibrated file carries its fit's joint covariance; a file written before that
    (only the map) or a hand-written map is named as such, with what to do."""
    import yaml

    from vehicle_estimation.io.inspect_bag import summarize

    out, _ = calibrated
    bag = out.parent / "training_drive"
    estimation = PARAMS_DIR / "estimation.yaml"

    def mass_text(files):
        return "\n".join(summarize(bag, files, {})["nodes"]["mass"]["lines"])

    assert "mass.torque_model_covariance) is in the mass variance" in mass_text([out, estimation])
    doc = yaml.safe_load(out.read_text(encoding="utf-8"))
    section = doc["mass"]["ros__parameters"]["mass"]
    section.pop("torque_model_covariance")
    older = tmp_path / "older.yaml"
    older.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert "no mass.torque_model_covariance: run calibrate again" in mass_text([older, estimation])
    section.pop("torque_regression_relative_std")
    older.write_text(yaml.safe_dump(doc), encoding="utf-8")
    assert "the map is taken as exact in the mass variance" in mass_text([older, estimation])
