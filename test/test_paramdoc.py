"""The README's parameter reference is generated from the nodes' declarations and kept fresh."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from vehicle_estimation.ros.paramdoc import BEGIN, END, replace_section

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_parameter_reference_is_current():
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "params", "--check", str(README)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr + "\n(refresh: vehicle-estimation params --write README.md)"


def test_reference_lists_every_node_and_method_specific_rows():
    text = README.read_text(encoding="utf-8")
    section = text[text.index(BEGIN):text.index(END)]
    for heading in ("### `fusion`", "### `vehicle_state`", "### `road_slope`", "### `mass`"):
        assert heading in section
    for row in ("`fusion.estimate_mounting`", "`vbackf.rho`", "`cubic_prediction.fit_window_s`",
                "`ffrls.forgetting_factor`", "`mass.forgetting_factor`", "`vehicle.mass`"):
        assert row in section
    assert "*(only with: rls)*" in section


def test_replace_section_detects_staleness_and_missing_markers():
    text = f"intro\n{BEGIN}\nold\n{END}\noutro\n"
    assert replace_section(text, f"{BEGIN}\nnew\n{END}\n") == f"intro\n{BEGIN}\nnew\n{END}\noutro\n"
    with pytest.raises(ValueError, match="markers"):
        replace_section("no markers here", f"{BEGIN}\n{END}\n")


@pytest.mark.dds
def test_every_declared_parameter_is_documented_from_one_source():
    """Each parameter's description comes from its ``setting()`` (or the node's own declaration),
    never the ``Class.field`` stand-in of an undocumented field."""
    import re

    from rosharness import init_rclpy

    from vehicle_estimation.ros.paramdoc import collect

    init_rclpy()
    undocumented = [f"{node}: {row.name}" for node, rows in collect().items() for row in rows.values()
                    if not row.description or re.fullmatch(r"[A-Z]\w*\.\w+", row.description)]
    assert not undocumented, undocumented
