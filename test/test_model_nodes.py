"""The learned-model methods inside their nodes: TA-AEKF (paper 000) in the mass node, the
AO-UKF with its GA-BPNN correction (paper 002) in the vehicle-state node.

* A short simulated truck drive replayed through every node with ``method: ta_aekf``: the mass
  leaves the transformer's prior (the training set's mean, ~28 t) for the truck's 18 t.
* Model files that were tampered with, have the wrong shapes or are not model files at all
  stop the node at start-up with a message naming the parameter; nothing is unpickled.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore
from replay_values import diagnostic_statuses
from rosharness import init_rclpy, vehicle_overrides

from vehicle_estimation.estimators.mass.ta_aekf import DEFAULT_MODEL_STEM
from vehicle_estimation.estimators.state.gabpnn import default_weights_path
from vehicle_estimation.ros.mass_node import MassNode
from vehicle_estimation.ros.runtime.parameters import ParameterError
from vehicle_estimation.ros.state_node import StateNode
from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

TRUCK_MASS = 18042.0     # payload 12 t: far from the prior of the network's training mean


def test_truck_bag_through_the_mass_node_with_ta_aekf(tmp_path):
    import dataclasses
    scenario = scenario_by_name("truck_hwfet")
    scenario = dataclasses.replace(scenario, duration_s=50.0, vehicle=scenario.vehicle.with_mass(TRUCK_MASS))
    bag = tmp_path / "truck"
    write_bag(simulate(scenario), bag)
    out = tmp_path / "estimates"
    proc = subprocess.run(
        [sys.executable, "-m", "vehicle_estimation", "replay", str(bag), "--record", str(out), "--quiet",
         "--vehicle", "heavy_truck", "--params", "estimation", "--params", "heavy_truck_ta_aekf", "--in-process"],
        capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    masses, variances = [], []
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/estimation/mass_stamped"]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            masses.append(msg.vector.x)
            variances.append(msg.vector.y)
    masses, variances = np.array(masses), np.array(variances)
    assert masses.size > 300 and np.all(np.isfinite(masses)) and np.all(np.isfinite(variances))
    assert masses[0] > 24000.0                     # the prior: the training set's mean gross mass
    assert abs(masses[-1] - TRUCK_MASS) / TRUCK_MASS < 0.05, masses[-1]
    assert variances[-1] < 0.1 * variances[0]
    statuses = diagnostic_statuses(out, "mass")
    diag = statuses[-1] if statuses else {}
    assert diag.get("method") == "ta_aekf"
    tau = float(diag["confidence level tau (Eq. 19)"])
    assert 0.0 < tau <= 1.0
    # the slope node's variance reaches the filter's grade error state
    assert 0.0 < float(diag["slope's grade error std [m/s^2]"]) < 0.5


# ------------------------------------------------------------------ model files
@pytest.fixture
def ros():
    init_rclpy()
    yield
    rclpy.try_shutdown()


def _copy_transformer(tmp_path: Path) -> Path:
    stem = tmp_path / "model"
    for suffix in (".safetensors", ".json"):
        shutil.copyfile(DEFAULT_MODEL_STEM.with_suffix(suffix), stem.with_suffix(suffix))
    return stem


def _flip_byte(path: Path, offset_from_end: int = 100) -> None:
    data = bytearray(path.read_bytes())
    data[-offset_from_end] ^= 0x01
    path.write_bytes(bytes(data))


def _start_mass_node(stem: Path) -> None:
    node = MassNode(parameter_overrides=vehicle_overrides("heavy_truck") + [
        Parameter("method", value="ta_aekf"), Parameter("ta_aekf.model_path", value=str(stem))])
    node.destroy_node()


@pytest.mark.dds
def test_shipped_transformer_starts_the_mass_node(ros, tmp_path):
    _start_mass_node(_copy_transformer(tmp_path))


@pytest.mark.parametrize("damage", ["flipped weight bit", "hash edited to match", "wrong shape", "pickle"])
@pytest.mark.dds
def test_damaged_transformer_files_stop_the_mass_node(ros, tmp_path, damage):
    stem = _copy_transformer(tmp_path)
    weights, meta = stem.with_suffix(".safetensors"), stem.with_suffix(".json")
    if damage == "flipped weight bit":
        _flip_byte(weights)                                   # the SHA-256 no longer matches
        expected = "SHA-256"
    elif damage in ("hash edited to match", "wrong shape"):
        from safetensors.numpy import load_file, save_file
        tensors = load_file(str(weights))
        name = sorted(k for k, v in tensors.items() if v.ndim == 2)[0]
        if damage == "wrong shape":
            tensors[name] = np.zeros((tensors[name].shape[0] + 1, tensors[name].shape[1]), tensors[name].dtype)
            expected = name
        else:
            tensors[name] = tensors[name] + np.float32(np.nan)   # non-finite weights, hash updated
            expected = "non-finite"
        save_file(tensors, str(weights))
        import hashlib
        doc = json.loads(meta.read_text())
        doc["weights_sha256"] = hashlib.sha256(weights.read_bytes()).hexdigest()
        meta.write_text(json.dumps(doc))
    else:   # a pickle where the safetensors file should be: refused, never loaded
        import pickle
        weights.write_bytes(pickle.dumps({"a": 1}))
        expected = "SHA-256"
    with pytest.raises(ParameterError) as err:
        _start_mass_node(stem)
    assert "ta_aekf.model_path" in str(err.value) and expected in str(err.value), str(err.value)


def _start_state_node(correction: str) -> StateNode:
    return StateNode(parameter_overrides=vehicle_overrides() + [
        Parameter("filter", value="aoukf"), Parameter("aoukf_correction", value=correction)])


@pytest.mark.dds
def test_state_node_loads_the_shipped_gabpnn_and_can_run_without(ros):
    node = _start_state_node("auto")
    assert node.core.correction is not None
    node.destroy_node()
    node = _start_state_node("")
    assert node.core.correction is None
    node.destroy_node()


@pytest.mark.parametrize("damage", ["truncated", "wrong shape", "object array"])
@pytest.mark.dds
def test_damaged_gabpnn_files_stop_the_state_node(ros, tmp_path, damage):
    path = tmp_path / "weights.npz"
    if damage == "truncated":
        data = default_weights_path("sedan_d_class").read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        with np.load(default_weights_path("sedan_d_class"), allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        if damage == "wrong shape":
            arrays["vx_w1"] = np.zeros((6, 2))
        else:
            arrays["vx_w1"] = np.array([{"payload": 1}], dtype=object)
        with open(path, "wb") as handle:
            np.savez(handle, **arrays)
    with pytest.raises(ParameterError) as err:
        _start_state_node(str(path))
    assert "aoukf_correction" in str(err.value), str(err.value)
