"""Lint and type checks (CI): ruff on the package and the tests, mypy on the estimator cores.

mypy reads its configuration from ``setup.cfg`` (``[mypy]``), so both tools run from the
repository root. A test is skipped only when its tool is not installed.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run_tool(module: str, *args: str) -> subprocess.CompletedProcess:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed (pip install -e .[test])")
    return subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, capture_output=True, check=False,
                          text=True, timeout=600)


def _report(proc: subprocess.CompletedProcess) -> str:
    return f"exit {proc.returncode}\n--- stdout ---\n{proc.stdout}\n--- stderr ---\n{proc.stderr}"


def test_ruff_pyflakes_and_syntax():
    proc = _run_tool("ruff", "check", "--select", "F,E9", "vehicle_estimation", "test")
    assert proc.returncode == 0, _report(proc)


def test_mypy_core():
    proc = _run_tool("mypy", "--config-file", "setup.cfg", "vehicle_estimation/estimators")
    assert proc.returncode == 0, _report(proc)
