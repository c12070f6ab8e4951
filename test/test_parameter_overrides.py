"""A value a params file gives a node that the node never declares stops it, naming it.

rclpy ignores an undeclared override silently: a misspelt name, or one outside its prefix
(``speed_error_correlation_s`` where the fusion reads ``fusion.speed_error_correlation_s``),
would leave the default running while the user believes the file. Parameters of a method the
node did not select are not unknown: one params file serves every method.
"""

from __future__ import annotations

from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")
from rclpy.parameter import Parameter  # noqa: E402

from vehicle_estimation.ros.fusion_node import FusionNode  # noqa: E402
from vehicle_estimation.ros.mass_node import MassNode  # noqa: E402
from vehicle_estimation.ros.runtime.parameters import ParameterError  # noqa: E402
from vehicle_estimation.ros.slope_node import SlopeNode  # noqa: E402
from vehicle_estimation.ros.state_node import StateNode  # noqa: E402

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
#: (node class, selector, every method it offers)
NODES = ((FusionNode, None, (None,)), (StateNode, "filter", ("vbackf", "ckf", "aoukf")),
         (SlopeNode, "method", ("auto", "cubic_prediction", "classical", "fusion_pitch")),
         (MassNode, "method", ("ffrls", "rls", "ta_aekf")))


def _check(files: list[Path], node_class, selector=None, value=None) -> None:
    context = rclpy.Context()
    rclpy.init(args=["--ros-args"] + [a for f in files for a in ("--params-file", str(f))], context=context)
    try:
        overrides = [] if selector is None else [Parameter(selector, value=value)]
        node = node_class(context=context, parameter_overrides=overrides)
        try:
            node.check_parameter_overrides()
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize("node_class,selector,values", NODES, ids=[n[0].__name__ for n in NODES])
def test_the_shipped_params_serve_every_method(node_class, selector, values):
    for value in values:
        _check([PARAMS_DIR / "sedan_d_class.yaml", PARAMS_DIR / "estimation.yaml"], node_class, selector, value)


@pytest.mark.parametrize("text,message", [
    ("fusion:\n  ros__parameters:\n    speed_error_correlation_s: 1.0\n",
     "'speed_error_correlation_s' (did you mean 'fusion.speed_error_correlation_s'?)"),
    ("fusion:\n  ros__parameters:\n    fusion.speed_eror_correlation_s: 1.0\n",
     "'fusion.speed_eror_correlation_s' (did you mean 'fusion.speed_error_correlation_s'?)"),
    ("/**:\n  ros__parameters:\n    odometry_rates_hz: 5.0\n", "'odometry_rates_hz'"),
])
def test_an_unread_value_stops_the_node_naming_it(tmp_path, text, message):
    path = tmp_path / "typo.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ParameterError, match="not a parameter of node 'fusion'") as err:
        _check([PARAMS_DIR / "estimation.yaml", path], FusionNode)
    assert message in str(err.value)


def test_another_methods_parameters_are_not_unknown_but_a_typo_in_them_is(tmp_path):
    path = tmp_path / "layer.yaml"
    path.write_text("vehicle_state:\n  ros__parameters:\n    aoukf.outlier_c: 4.0\n", encoding="utf-8")
    _check([PARAMS_DIR / "estimation.yaml", path], StateNode, "filter", "vbackf")
    path.write_text("vehicle_state:\n  ros__parameters:\n    aoukf.outlier_k: 4.0\n", encoding="utf-8")
    with pytest.raises(ParameterError, match="aoukf.outlier_k"):
        _check([PARAMS_DIR / "estimation.yaml", path], StateNode, "filter", "vbackf")
