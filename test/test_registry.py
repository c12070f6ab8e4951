"""Every registered method builds a core that offers what its kind's protocol promises, so a
node that only talks to the protocol works with each of them."""

from __future__ import annotations

from pathlib import Path

import pytest

from vehicle_estimation.contract.vehicle import load_vehicle_params
from vehicle_estimation.estimators.interfaces import MassEstimator
from vehicle_estimation.estimators.registry import MASS_METHODS, lookup

SEDAN = load_vehicle_params(Path(__file__).resolve().parents[1] / "params" / "sedan_d_class.yaml")


@pytest.mark.parametrize("name", sorted(MASS_METHODS))
def test_mass_methods_build_mass_estimators(name):
    method = MASS_METHODS[name]
    core = method.build(SEDAN, method.config_type())
    assert isinstance(core, MassEstimator)
    assert core.window_brake in ("max", "mean") and isinstance(core.steps_on_windows, bool)
    assert isinstance(core.status(), dict)
    state = core.state_dict()
    core.reset()
    core.load_state_dict(state)


def test_an_unknown_method_lists_the_known_ones():
    with pytest.raises(ValueError, match="ffrls"):
        lookup(MASS_METHODS, "bogus", "mass")
