"""contract.settings: a field's documentation, range and choices written once and checked."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest

from vehicle_estimation.contract.settings import Bounds, check_settings, field_bounds, field_doc, setting


@dataclasses.dataclass
class _Tuning:
    gain: float = setting(0.5, "Gain [-]", low=0.0, high=1.0, low_open=True)
    count: int = setting(3, "How many [-]", low=1)
    mode: str = setting("fast", "Mode", choices=("fast", "slow"))
    label: str = setting("", "Free text")
    enabled: bool = setting(True, "On or off")
    auto: float = setting(math.nan, "NaN: automatic [s]", low=0.0, allow_nan=True)
    ratios: list[float] = setting([1.0, 2.0], "Ratios", low=0.0, low_open=True, each=True)


def test_metadata_is_readable_and_lists_are_not_shared():
    assert field_doc(_Tuning, "gain") == "Gain [-]"
    assert field_bounds(_Tuning, "gain") == Bounds(0.0, 1.0, True, False)
    a, b = _Tuning(), _Tuning()
    a.ratios.append(3.0)
    assert b.ratios == [1.0, 2.0]
    check_settings(_Tuning())


@pytest.mark.parametrize("field, value, words", [
    ("gain", 0.0, "gain must be in (0, 1]"), ("gain", 1.5, "gain"), ("gain", math.nan, "gain must be finite"),
    ("gain", "x", "gain must be a number"), ("count", 0, "count"), ("count", 2.5, "count must be an integer"),
    ("mode", "medium", "mode must be one of"), ("label", 3, "label must be a string"),
    ("enabled", 1, "enabled must be true or false"), ("auto", -1.0, "auto"), ("ratios", [1.0, -2.0], "ratios[1]"),
])
def test_a_bad_value_names_its_field(field, value, words):
    with pytest.raises(ValueError, match=re.escape(words)):
        check_settings(dataclasses.replace(_Tuning(), **{field: value}))


def test_nan_only_where_allowed_and_the_prefix_names_the_parameter():
    check_settings(dataclasses.replace(_Tuning(), auto=math.nan))
    with pytest.raises(ValueError, match=r"^vehicle\.gain "):
        check_settings(dataclasses.replace(_Tuning(), gain=2.0), prefix="vehicle.")
