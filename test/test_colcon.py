"""The package builds with colcon into a fresh workspace and its installed node executables run."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

REPO = Path(__file__).resolve().parent.parent
PACKAGE_FILES = ("package.xml", "setup.py", "setup.cfg", "README.md", "resource", "params",
                 "vehicle_estimation")
NODES = ("fusion_node", "slope_node", "state_node", "mass_node")


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent)) or shutil.which("colcon")
    if colcon is None:
        pytest.fail("colcon is not installed (pip install colcon-common-extensions)")
    ws = tmp_path_factory.mktemp("colcon_ws")
    src = ws / "src" / "vehicle_estimation"
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / name)
    proc = subprocess.run([colcon, "build", "--base-paths", "src"], cwd=ws, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return ws / "install" / "vehicle_estimation"


def _env(install: Path) -> dict[str, str]:
    env = dict(os.environ)
    site = next((install / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")])
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([str(install), env.get("AMENT_PREFIX_PATH", "")])
    return env


def test_colcon_installs_executables_and_params(workspace):
    for node in NODES:
        assert (workspace / "lib" / "vehicle_estimation" / node).is_file(), node
    params = sorted(p.name for p in (workspace / "share" / "vehicle_estimation" / "params").glob("*.yaml"))
    assert {"estimation.yaml", "sedan_d_class.yaml", "audi_a4.yaml", "heavy_truck.yaml"} <= set(params)
    maps = workspace / "share" / "vehicle_estimation" / "params" / "import_maps"
    assert (maps / "stanford_sideslip_2014.yaml").is_file()
    assert (workspace / "share" / "ament_index" / "resource_index" / "packages" / "vehicle_estimation").is_file()


def test_installed_node_starts_and_stops_cleanly(workspace):
    exe = workspace / "lib" / "vehicle_estimation" / "mass_node"
    params = workspace / "share" / "vehicle_estimation" / "params"
    proc = subprocess.Popen([str(exe), "--ros-args", "--params-file", str(params / "sedan_d_class.yaml"),
                             "--params-file", str(params / "estimation.yaml")],
                            env=_env(workspace), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        time.sleep(4.0)
        assert proc.poll() is None, proc.communicate()[0]
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert "Traceback" not in out


def test_installed_params_are_found_through_the_ament_index(workspace):
    code = "from vehicle_estimation.paths import params_dir; print(params_dir())"
    out = subprocess.run([sys.executable, "-c", code], env=_env(workspace), capture_output=True,
                         text=True, timeout=60, cwd=workspace)
    assert out.returncode == 0, out.stderr
    assert Path(out.stdout.strip()) == workspace / "share" / "vehicle_estimation" / "params"
