"""Configuration fields whose documentation and range are written once.

Every tunable of an estimator (and every vehicle parameter) is a dataclass field made by
:func:`setting`: its one-line documentation (unit in brackets), its range and, for strings,
its choices live in the field's metadata. Three readers use them and nothing else:

* :func:`check_settings`, called by each config's ``validate()``: a value outside its range
  raises ``ValueError`` naming the field;
* the nodes' parameter declarations (``ros.runtime.parameters``): ROS descriptors with the
  same description and range, so ``ros2 param describe`` shows what the README says;
* the README's parameter reference (``vehicle-estimation params``).

Cross-field rules (``min_mass < max_mass``, a gain vector's length) stay in ``validate()``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable, Sequence


@dataclasses.dataclass(frozen=True)
class Bounds:
    """A closed or half-open interval; ``None`` is unbounded on that side."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        if self.high is not None and (value >= self.high if self.high_open else value > self.high):
            return False
        return True

    def __str__(self) -> str:
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        return f"{'(' if self.low_open or self.low is None else '['}{low}, {high}{')' if self.high_open or self.high is None else ']'}"


def setting(default: Any, doc: str, *, low: float | None = None, high: float | None = None,
            low_open: bool = False, high_open: bool = False, choices: Iterable[str] | None = None,
            allow_nan: bool = False, each: bool = False) -> Any:
    """A dataclass field with its documentation and its valid values.

    ``low``/``high`` bound a number (``low_open``/``high_open`` exclude the bound itself);
    ``each`` applies them to every element of a list or tuple; ``choices`` are a string's
    valid values; ``allow_nan`` lets NaN through where it means "automatic" (the doc says so).
    A list default becomes a ``default_factory``, so instances never share it.
    """
    metadata: dict[str, Any] = {"doc": doc}
    if low is not None or high is not None:
        metadata["bounds"] = Bounds(low, high, low_open, high_open)
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if allow_nan:
        metadata["allow_nan"] = True
    if each:
        metadata["each"] = True
    if isinstance(default, list):
        items = list(default)
        return dataclasses.field(default_factory=lambda: list(items), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def field_doc(cls_or_instance: Any, name: str) -> str | None:
    """The documentation of field ``name``, or None where the field has none."""
    for field in dataclasses.fields(cls_or_instance):
        if field.name == name:
            return field.metadata.get("doc")
    return None


def field_bounds(cls_or_instance: Any, name: str) -> Bounds | None:
    for field in dataclasses.fields(cls_or_instance):
        if field.name == name:
            return field.metadata.get("bounds")
    return None


def field_choices(cls_or_instance: Any, name: str) -> tuple[str, ...] | None:
    for field in dataclasses.fields(cls_or_instance):
        if field.name == name:
            return field.metadata.get("choices")
    return None


def _number(value: Any) -> float | None:
    if isinstance(value, bool):
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def check_settings(config: Any, prefix: str = "", skip: Sequence[str] = ()) -> None:
    """Check every field of ``config`` made by :func:`setting` against its metadata.

    Numbers must be finite (NaN only where ``allow_nan``) and inside their bounds, strings
    one of their choices, bools bools. Raises ``ValueError`` naming the first bad field as
    ``<prefix><name>``.
    """
    for field in dataclasses.fields(config):
        if field.name in skip or "doc" not in field.metadata:
            continue
        meta = field.metadata
        name = f"{prefix}{field.name}"
        value = getattr(config, field.name)
        default = (field.default if field.default is not dataclasses.MISSING
                   else field.default_factory() if field.default_factory is not dataclasses.MISSING else None)
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be true or false, got {value!r}")
            continue
        if "choices" in meta:
            if value not in meta["choices"]:
                raise ValueError(f"{name} must be one of {list(meta['choices'])}, got {value!r}")
            continue
        if isinstance(default, str):
            if not isinstance(value, str):
                raise ValueError(f"{name} must be a string, got {value!r}")
            continue
        values = list(value) if meta.get("each") or isinstance(value, (list, tuple)) else [value]
        for i, item in enumerate(values):
            label = f"{name}[{i}]" if len(values) > 1 or isinstance(value, (list, tuple)) else name
            number = _number(item)
            if number is None:
                raise ValueError(f"{label} must be a number, got {item!r}")
            if math.isnan(number) and meta.get("allow_nan"):
                continue
            if not math.isfinite(number):
                raise ValueError(f"{label} must be finite, got {item!r}")
            bounds = meta.get("bounds")
            if bounds is not None and not bounds.contains(number):
                raise ValueError(f"{label} must be in {bounds}, got {item!r}")
        if isinstance(default, int) and not isinstance(default, bool) and _number(value) is not None \
                and float(value) != int(value):
            raise ValueError(f"{name} must be an integer, got {value!r}")
