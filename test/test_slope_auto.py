"""The ``auto`` slope source selection (estimators/slope/auto.py): fusion grade, else the observer."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from vehicle_estimation.estimators.slope.auto import (
    SOURCE_FUSION, SOURCE_OBSERVER, AutoSlope, AutoSlopeConfig)


@dataclass
class FixedSlope:
    slope: float
    variance: float
    converged: bool = True


def test_switches_without_a_jump_and_the_offset_fades_into_the_variance():
    fusion, observer = FixedSlope(0.030, 1e-6), FixedSlope(0.020, 4e-6)
    auto = AutoSlope(fusion, observer, AutoSlopeConfig(switch_time_constant_s=2.0))
    auto.update(0.0, fusion_usable=True)
    assert auto.source == SOURCE_FUSION and auto.slope == pytest.approx(0.030)
    assert auto.variance == pytest.approx(1e-6)
    auto.update(1.0, fusion_usable=False)          # the fusion grade drops out
    assert auto.source == SOURCE_OBSERVER and auto.switches == 2
    assert auto.slope == pytest.approx(0.030)      # no jump at the switch
    assert auto.variance == pytest.approx(4e-6 + 0.010 ** 2)
    auto.update(3.0, fusion_usable=False)          # one time constant later
    offset = 0.010 * math.exp(-1.0)
    assert auto.slope == pytest.approx(0.020 + offset)
    assert auto.variance == pytest.approx(4e-6 + offset ** 2)
    auto.update(30.0, fusion_usable=False)
    assert auto.slope == pytest.approx(0.020, abs=1e-8)
    auto.update(31.0, fusion_usable=True)          # and back
    assert auto.source == SOURCE_FUSION and auto.slope == pytest.approx(0.020, abs=1e-8)


def test_observer_extra_variance_counts_only_while_the_observer_is_in_use():
    auto = AutoSlope(FixedSlope(0.0, 1e-6), FixedSlope(0.0, 2e-6))
    auto.update(0.0, fusion_usable=False, observer_extra_variance=5e-6)
    assert auto.variance == pytest.approx(7e-6)
    auto.update(0.1, fusion_usable=True, observer_extra_variance=5e-6)
    assert auto.variance == pytest.approx(1e-6)


def test_does_not_switch_to_a_source_without_an_estimate():
    fusion = FixedSlope(math.nan, math.inf, converged=False)
    auto = AutoSlope(fusion, FixedSlope(0.01, 1e-6))
    auto.update(0.0, fusion_usable=True)
    assert auto.source == SOURCE_OBSERVER and auto.slope == pytest.approx(0.01)
    auto.reset()
    assert auto.source == SOURCE_OBSERVER


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="switch_time_constant_s"):
        AutoSlopeConfig(switch_time_constant_s=0.0).validate()
