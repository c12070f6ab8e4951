"""Declaring node parameters with descriptors and ranges; a bad value stops the node at start-up.

Every ``declare_*`` method raises :class:`ParameterError`, whose message names the parameter,
and the node executable exits with it (``spin.run_node``). Configs are dataclasses: each field
is declared as ``<prefix>.<field>`` with its documentation taken from the dataclass itself, so
that the parameter reference in the README (``ros.paramdoc``) is generated, never written.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
)
from rclpy.parameter import Parameter

from vehicle_estimation.contract.settings import Bounds
from vehicle_estimation.contract.vehicle import VehicleParams


class ParameterError(ValueError):
    """A parameter is invalid; the message names it. Raised at start-up only."""


#: Parameters a params file's ``/**`` section may set for every node although only some nodes
#: declare them (rclpy's own, the vehicle, the facts several nodes must agree on).
SHARED_PARAMETERS = ("use_sim_time", "start_type_description_service", "gnss_aiding_timeout_s")
SHARED_PREFIXES = ("vehicle.", "qos_overrides.")
#: Parameters that moved: a params file that still gives the old name is told the new one.
MOVED_PARAMETERS = {"fusion.mounting_rpy": "vehicle.imu_mounting_rpy", "fusion.gravity": "vehicle.gravity",
                    "auto.uncompensated_accel_bias_std": "cubic_prediction.uncompensated_accel_bias_std"}


def descriptor(description: str, *, bounds: Bounds | None = None, integer: bool = False,
               read_only: bool = True, additional: str = "") -> ParameterDescriptor:
    """A read-only descriptor with a description and, given ``bounds``, an integer or float
    range (an open bound is given as closed: ``validate()`` excludes the bound itself)."""
    desc = ParameterDescriptor(description=description, read_only=read_only, additional_constraints=additional)
    if bounds is not None:
        if integer:
            desc.integer_range = [IntegerRange(
                from_value=int(bounds.low) if bounds.low is not None else -(2 ** 63),
                to_value=int(bounds.high) if bounds.high is not None else 2 ** 63 - 1, step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(bounds.low) if bounds.low is not None else -math.inf,
                to_value=float(bounds.high) if bounds.high is not None else math.inf, step=0.0)]
        if bounds.low_open or bounds.high_open:
            desc.additional_constraints = f"in {bounds}" + (f"; {additional}" if additional else "")
    return desc


class ParameterDeclarations:
    """The ``declare_*`` methods of an estimator node (a mixin of ``rclpy.node.Node``)."""

    def _declare(self, name: str, default: Any, desc: ParameterDescriptor) -> Any:
        try:
            value = self.declare_parameter(name, default, desc).value  # type: ignore[attr-defined]
        except Exception as exc:  # rclpy raises several types for range/type violations
            raise ParameterError(f"parameter '{name}': {exc}") from exc
        return value

    def declare_float(self, name: str, default: float, description: str,
                      low: float | None = None, high: float | None = None, *, allow_nan: bool = False,
                      bounds: Bounds | None = None) -> float:
        """A double parameter; non-finite values stop the node, except NaN with ``allow_nan``
        (where NaN means "automatic", as the config's docs say)."""
        if bounds is None and (low is not None or high is not None):
            bounds = Bounds(low, high)
        value = float(self._declare(name, float(default), descriptor(description, bounds=bounds)))
        if allow_nan and math.isnan(value):
            return value
        if not math.isfinite(value):
            raise ParameterError(f"parameter '{name}' must be finite, got {value}")
        return value

    def declare_int(self, name: str, default: int, description: str,
                    low: int | None = None, high: int | None = None, *, bounds: Bounds | None = None) -> int:
        if bounds is None and (low is not None or high is not None):
            bounds = Bounds(low, high)
        return int(self._declare(name, int(default), descriptor(description, bounds=bounds, integer=True)))

    def declare_bool(self, name: str, default: bool, description: str) -> bool:
        return bool(self._declare(name, bool(default), descriptor(description)))

    def declare_str(self, name: str, default: str, description: str,
                    choices: Sequence[str] | None = None) -> str:
        extra = f"one of: {', '.join(c or repr(c) for c in choices)}" if choices else ""
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
        ``defaults`` as ``<prefix>.<field>``, with the documentation, range and choices of its
        :func:`~vehicle_estimation.contract.settings.setting`, and return a validated copy
        with the values.

        Fields that are None or arrays keep their defaults (they are not ROS-parameter
        shaped), as do the fields named in ``exclude`` (set by a node-level parameter).
        ``validate()`` errors become a :class:`ParameterError` that names the field.
        """
        values: dict[str, Any] = {}
        for field in dataclasses.fields(defaults):
            if field.name in exclude:
                continue
            value = getattr(defaults, field.name)
            name = f"{prefix}.{field.name}"
            meta = field.metadata
            doc = meta.get("doc") or f"{type(defaults).__name__}.{field.name}"
            bounds = None if meta.get("each") else meta.get("bounds")
            if isinstance(value, bool):
                values[field.name] = self.declare_bool(name, value, doc)
            elif isinstance(value, int):
                values[field.name] = self.declare_int(name, value, doc, bounds=bounds)
            elif isinstance(value, float):
                allow_nan = bool(meta.get("allow_nan"))
                if allow_nan and bounds is not None:
                    # rclpy's range check refuses NaN ("automatic"): validate() checks the range
                    doc, bounds = f"{doc}; else in {bounds}", None
                values[field.name] = self.declare_float(name, value, doc, allow_nan=allow_nan, bounds=bounds)
            elif isinstance(value, str):
                values[field.name] = self.declare_str(name, value, doc, meta.get("choices"))
            elif isinstance(value, (tuple, list)) and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                values[field.name] = type(value)(self.declare_float_array(name, value, doc))
        try:
            config = dataclasses.replace(defaults, **values)
            config.validate()
        except (TypeError, ValueError) as exc:
            text = str(exc)
            raise ParameterError(text if text.startswith(f"{prefix}.") else f"{prefix}.*: {text}") from exc
        return config

    def declare_shared_setting(self, config_type: Any, field_name: str) -> Any:
        """:meth:`declare_setting` for a fact that several nodes must agree on, set once in a
        params file's ``/**`` section."""
        return self.declare_setting(config_type, field_name, shared=True)

    def declare_setting(self, config_type: Any, field_name: str, *, shared: bool = False) -> Any:
        """Declare the bool or float ``config_type`` field ``field_name`` as a node-level
        parameter of that name, with the field's default, documentation and range."""
        field = next(f for f in dataclasses.fields(config_type) if f.name == field_name)
        default = field.default
        doc = field.metadata['doc']
        if shared:
            doc += " (shared by the nodes that use it: set it under /**)"
        if isinstance(default, bool):
            return self.declare_bool(field_name, default, doc)
        return self.declare_float(field_name, default, doc, bounds=field.metadata.get("bounds"))

    def check_parameter_overrides(self) -> None:
        """Raise :class:`ParameterError` for a value a params file (or ``-p``) gives this node
        that it never declared: rclpy ignores it silently, so a misspelt or misplaced name
        (``speed_error_correlation_s`` where the node reads ``fusion.speed_error_correlation_s``)
        would leave the default running. Call once every parameter is declared."""
        import difflib
        overrides = getattr(self, "_parameter_overrides", {}) or {}
        unknown = sorted(name for name in overrides
                         if not self.has_parameter(name)  # type: ignore[attr-defined]
                         and name not in SHARED_PARAMETERS and not name.startswith(SHARED_PREFIXES)
                         and not self.parameter_of_another_method(name))
        if unknown:
            declared = list(self._parameters)  # type: ignore[attr-defined]
            hints = []
            for name in unknown:
                if name in MOVED_PARAMETERS:
                    hints.append(f"'{name}' (now '{MOVED_PARAMETERS[name]}')")
                    continue
                close = difflib.get_close_matches(name, declared, n=1, cutoff=0.6) or \
                    [d for d in declared if d.endswith("." + name)][:1]
                hints.append(f"'{name}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
            raise ParameterError(f"parameter {', '.join(hints)}: not a parameter of node "
                                 f"'{self.get_name()}'")  # type: ignore[attr-defined]

    def parameter_of_another_method(self, name: str) -> bool:
        """True for a parameter that a method this node did not select would declare (one
        params file serves every method); nodes with methods override it."""
        return False

    def declare_vehicle(self) -> VehicleParams:
        """Declare ``vehicle.*`` with the ranges and docs of :class:`VehicleParams` and build it."""
        return self.declare_config("vehicle", VehicleParams())


def declared_by_a_method(methods: Any, name: str) -> bool:
    """True when ``name`` is ``<config_prefix>.<field>`` of one of ``methods`` (a registry:
    name -> object with ``config_prefix`` and ``config_type``). Loads only the configs whose
    prefix matches (a method's config may import heavy modules)."""
    prefix, _, field_name = name.partition(".")
    for method in methods.values():
        if method.config_prefix != prefix or not field_name:
            continue
        config = method.config_type()
        if config is not None and any(f.name == field_name for f in dataclasses.fields(config)):
            return True
    return False
