"""Declaring node parameters with descriptors and ranges; a bad value stops the node at start-up.

Every ``declare_*`` method raises :class:`ParameterError`, whose message names the parameter,
and the node executable exits with it (``spin.run_node``). Configs are dataclasses: each field
is declared as ``<prefix>.<field>`` with its documentation taken from the dataclass itself, so
that the parameter reference in the README (``ros.paramdoc``) is generated, never written.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
from typing import Any, Sequence

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.parameter import Parameter

from vehicle_estimation.contract.vehicle import VehicleParams


class ParameterError(ValueError):
    """A parameter is invalid; the message names it. Raised at start-up only."""


def descriptor(description: str, *, low: float | int | None = None, high: float | int | None = None,
               read_only: bool = True, additional: str = "") -> ParameterDescriptor:
    """A read-only descriptor with a description and, given both bounds, an integer or float range."""
    desc = ParameterDescriptor(description=description, read_only=read_only, additional_constraints=additional)
    if low is not None and high is not None:
        if isinstance(low, int) and isinstance(high, int) and not isinstance(low, bool):
            desc.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    return desc


def config_field_docs(cls: type) -> dict[str, str]:
    """One line of documentation per dataclass field, from the field's trailing comment or
    the class docstring's ``Attributes:`` entry or ``* ``name``: text`` bullet (base classes
    included)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        doc = inspect.cleandoc(klass.__doc__ or "")
        attrs = re.search(r"Attributes:\n(.*?)(?:\n\s*\n|\Z)", doc, re.S)
        if attrs:
            entry = None
            for line in attrs.group(1).splitlines():
                m = re.match(r" {4}([\w, ]+):\s*(.*)", line)
                if m and not line.startswith(" " * 5):
                    entry = [n.strip() for n in m.group(1).split(",")]
                    for name in entry:
                        docs[name] = m.group(2).strip()
                elif entry:
                    for name in entry:
                        docs[name] += " " + line.strip()
        # "* ``name``: text" bullets (one or more names), continued on indented lines
        for m in re.finditer(r"^\* ((?:``\w+``(?:, | and )?)+)(?: \([^)]*\))?:\s*(.+?)(?=^\* |^\S|\Z)",
                             doc, re.M | re.S):
            text = " ".join(m.group(2).split())
            for name in re.findall(r"``(\w+)``", m.group(1)):
                docs.setdefault(name, text)
        for m in re.finditer(r"^    (\w+): [^=\n]+=[^#\n]*#\s*(.+)$", source, re.M):
            docs[m.group(1)] = m.group(2).strip()
    return docs


class ParameterDeclarations:
    """The ``declare_*`` methods of an estimator node (a mixin of ``rclpy.node.Node``)."""

    def _declare(self, name: str, default: Any, desc: ParameterDescriptor) -> Any:
        try:
            value = self.declare_parameter(name, default, desc).value  # type: ignore[attr-defined]
        except Exception as exc:  # rclpy raises several types for range/type violations
            raise ParameterError(f"parameter '{name}': {exc}") from exc
        return value

    def declare_float(self, name: str, default: float, description: str,
                      low: float | None = None, high: float | None = None, *, allow_nan: bool = False) -> float:
        """A double parameter; non-finite values stop the node, except NaN with ``allow_nan``
        (where NaN means "automatic", as the config's docs say)."""
        value = float(self._declare(name, float(default), descriptor(description, low=low, high=high)))
        if allow_nan and math.isnan(value):
            return value
        if not math.isfinite(value):
            raise ParameterError(f"parameter '{name}' must be finite, got {value}")
        return value

    def declare_int(self, name: str, default: int, description: str,
                    low: int | None = None, high: int | None = None) -> int:
        return int(self._declare(name, int(default), descriptor(description, low=low, high=high)))

    def declare_bool(self, name: str, default: bool, description: str) -> bool:
        return bool(self._declare(name, bool(default), descriptor(description)))

    def declare_str(self, name: str, default: str, description: str,
                    choices: Sequence[str] | None = None) -> str:
        extra = f"one of: {', '.join(choices)}" if choices else ""
        value = str(self._declare(name, default, descriptor(description, additional=extra)))
        if choices is not None and value not in choices:
            raise ParameterError(f"parameter '{name}' must be one of {list(choices)}, got '{value}'")
        return value

    def declare_float_array(self, name: str, default: Sequence[float], description: str) -> list[float]:
        desc = descriptor(description)
        desc.type = ParameterType.PARAMETER_DOUBLE_ARRAY
        # rclpy infers a parameter's type from its default, and types an empty list as a byte
        # array, which would refuse every double array a params file gives (a calibrated
        # torque map). Declared by type instead, it has no value until a file sets one.
        initial: Any = [float(v) for v in default] if default else Parameter.Type.DOUBLE_ARRAY
        value = self._declare(name, initial, desc)
        return [float(v) for v in value] if value is not None else []

    def declare_config(self, prefix: str, defaults: Any, exclude: tuple[str, ...] = ()) -> Any:
        """Declare every scalar, bool, str and tuple/list field of the dataclass instance
        ``defaults`` as ``<prefix>.<field>`` and return a validated copy with the values.

        Fields that are None or arrays keep their defaults (they are not ROS-parameter
        shaped), as do the fields named in ``exclude`` (set by a node-level parameter).
        ``validate()`` errors become a :class:`ParameterError` that names the field.
        """
        values: dict[str, Any] = {}
        field_docs = config_field_docs(type(defaults))
        for field in dataclasses.fields(defaults):
            if field.name in exclude:
                continue
            value = getattr(defaults, field.name)
            name = f"{prefix}.{field.name}"
            doc = field_docs.get(field.name) or f"{type(defaults).__name__}.{field.name}"
            if isinstance(value, bool):
                values[field.name] = self.declare_bool(name, value, doc)
            elif isinstance(value, int):
                values[field.name] = self.declare_int(name, value, doc)
            elif isinstance(value, float):
                # A NaN default means "automatic" (validate() checks the rest).
                values[field.name] = self.declare_float(name, value, doc, allow_nan=math.isnan(value))
            elif isinstance(value, str):
                values[field.name] = self.declare_str(name, value, doc)
            elif isinstance(value, (tuple, list)) and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                values[field.name] = type(value)(self.declare_float_array(name, value, doc))
        try:
            config = dataclasses.replace(defaults, **values)
            config.validate()
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"{prefix}.*: {exc}") from exc
        return config

    def declare_vehicle(self) -> VehicleParams:
        """Declare ``vehicle.*`` with the ranges and docs of :class:`VehicleParams` and build it."""
        defaults = VehicleParams()
        values: dict[str, Any] = {}
        for field in VehicleParams.field_names():
            name = f"vehicle.{field}"
            default = getattr(defaults, field)
            ranged = VehicleParams.field_range(field)
            if field in ("name", "driven_axle"):
                choices = ("front", "rear", "all") if field == "driven_axle" else None
                values[field] = self.declare_str(name, default, f"Vehicle {field.replace('_', ' ')}", choices)
            elif field == "gear_ratios":
                values[field] = self.declare_float_array(
                    name, default, "Transmission ratios i_t,j, first gear first")
            elif ranged is not None:
                low, high, description = ranged
                values[field] = self.declare_float(name, default, description, low, high)
            else:
                raise TypeError(f"VehicleParams.{field} has no range: declare it with _ranged()")
        try:
            return VehicleParams.from_mapping(values)
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc
