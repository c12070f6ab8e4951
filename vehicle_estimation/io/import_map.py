"""The mapping file of ``vehicle-estimation import`` (:mod:`.importer`): its format, the
contract signals and units it may name, and its validation.

A mapping is a YAML file (a path, or a name in ``params/import_maps/``) that says where the
data is, which column is which signal of the contract, and in which unit.

Mapping file
============

.. code-block:: yaml

    version: 1
    description: free text
    data_dir: /path/to/logs      # where relative file names live (default: the mapping's folder;
                                 # --data-dir overrides)
    vehicle: sedan_d_class       # params file (name in params/ or path); only needed for the
                                 # conversions that use the vehicle (see below); --vehicle overrides
    sources:                     # the files, each one or more columns
      t:   {file: t.txt}                           # one value per line
      yaw: {file: gyro_z.txt}
      can:                                         # a table
        file: can.csv
        format: csv              # csv | whitespace (default: csv for *.csv, else whitespace)
        delimiter: ","           # csv only (default ",")
        header: auto             # true: the first row names the columns; false: columns are
                                 # referred to by index (0-based); auto: true when the first row
                                 # is not numeric (default)
        skip_rows: 0             # lines to skip before the header/data (default 0)
        comment: "#"             # comment character (default "#")
        time: {column: t_ms, unit: ms, offset: 0.0}   # the table's own time column
    time:                        # the time of every source without its own `time`
      source: t                  # (column: may be left out for a one-column source)
      unit: s                    # s | ms | us | ns | min | h
      offset: 1393027200.0       # [s] added after the unit conversion: absolute stamps
    imu:
      gravity_removed: false     # true: the log's accelerations are kinematic (gravity taken
                                 # out): the importer adds +g on z, so the message is REP-145
      frame_id: imu_link
    signals:                     # contract signal -> where and in which unit
      imu.angular_velocity.z:        {source: yaw, unit: deg/s}
      imu.linear_acceleration.x:     {source: can, column: ax, unit: g}
      joint_states.steering_wheel.position: {source: can, column: delta, unit: deg,
                                             road_wheel_angle: true}
      speed.vx:                      {source: can, column: 3, unit: km/h, scale: 0.01, offset: 0}
    wheel_speeds_from_speed:     # optional: four wheel speeds synthesised from one speed signal
      source: can
      column: 3
      unit: km/h
      kinematic: true            # true: per wheel from yaw rate and steering (below); false: v/R each

Signals (``signals:`` keys; ``vehicle-estimation import --help`` lists the units of each kind):

=========================================  ====================================  ==================
key                                        message field                         kind
=========================================  ====================================  ==================
``imu.linear_acceleration.{x,y,z}``        ``imu/data`` specific force           acceleration
``imu.angular_velocity.{x,y,z}``           ``imu/data`` angular velocity         angular rate
``gnss.latitude``, ``gnss.longitude``      ``gnss/fix`` [deg]                    angle
``gnss.altitude``                          ``gnss/fix``                          length
``gnss.status``                            ``gnss/fix`` status.status (default 0 = fix)  number
``gnss.horizontal_std``, ``gnss.vertical_std``  ``position_covariance`` diagonal  length
``speed.vx``, ``speed.vx_std``             ``vehicle/speed`` linear.x, covariance[0]  velocity
``joint_states.wheel_{fl,fr,rl,rr}.velocity``  wheel speed                      angular rate, or a
                                                                                 velocity (÷ wheel radius)
``joint_states.wheel_{fl,fr,rl,rr}.effort``    brake torque                     torque
``joint_states.steering_wheel.position``   steering-wheel angle                  angle
``powertrain.engine.velocity``             engine speed                          angular rate
``powertrain.engine.effort``               engine torque                         torque
``powertrain.engine_load.position``        OBD-II load 0..1                      ratio (``1`` or ``%``)
``powertrain.gear.position``               gear number                           number
``powertrain.drive.effort``                driveline force                       force
``ground_truth.vehicle_state.{vx,vy}``     ``ground_truth/vehicle_state``        velocity
``ground_truth.vehicle_state.yaw_rate``    ``ground_truth/vehicle_state``        angular rate
``ground_truth.sideslip``                  ``ground_truth/sideslip``             angle
``ground_truth.road_slope``                ``ground_truth/road_slope``           angle
``ground_truth.mass``                      ``ground_truth/mass``                 mass
=========================================  ====================================  ==================

Per signal: ``source`` (may be left out when there is one source only), ``column`` (name or
0-based index; may be left out for a one-column source), ``unit`` (required), ``scale`` and
``offset`` (default 1, 0). The value is ``convert(raw * scale + offset)``: scale and offset
apply in the log's unit, before the unit conversion (as a CAN database's factor and offset);
``scale: -1`` flips an axis (e.g. a NED/FRD IMU to REP-103 FLU). The steering signal takes
``road_wheel_angle: true`` when the log has the road-wheel angle: it is multiplied by the
vehicle's ``steering_ratio`` (the node divides by the same ratio). A wheel speed in a
velocity unit (m/s, km/h, ...) is divided by the vehicle's ``wheel_radius``.

A bad mapping raises :class:`MappingError` whose message names the offending key
(``signals.imu.angular_velocity.z.unit: unknown unit 'deg/sec' ...``); :func:`validate_mapping`
checks the structure without reading the data.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import yaml

from vehicle_estimation.contract import topics as T
from vehicle_estimation.contract.vehicle import GRAVITY

G = GRAVITY
MAPPING_VERSION = 1

# --------------------------------------------------------------------------- units
#: kind -> {unit: (factor, offset)}: SI value = raw * factor + offset.
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "acceleration": {"m/s^2": (1.0, 0.0), "m/s2": (1.0, 0.0), "m/s²": (1.0, 0.0), "g": (G, 0.0),
                     "mg": (G * 1e-3, 0.0), "ft/s^2": (0.3048, 0.0)},
    "angular rate": {"rad/s": (1.0, 0.0), "deg/s": (math.pi / 180.0, 0.0), "rpm": (math.pi / 30.0, 0.0),
                     "rev/s": (2.0 * math.pi, 0.0), "mrad/s": (1e-3, 0.0)},
    "angle": {"rad": (1.0, 0.0), "deg": (math.pi / 180.0, 0.0), "mrad": (1e-3, 0.0)},
    "velocity": {"m/s": (1.0, 0.0), "km/h": (1.0 / 3.6, 0.0), "kph": (1.0 / 3.6, 0.0),
                 "mph": (0.44704, 0.0), "kn": (1852.0 / 3600.0, 0.0), "ft/s": (0.3048, 0.0)},
    "length": {"m": (1.0, 0.0), "cm": (0.01, 0.0), "mm": (1e-3, 0.0), "km": (1e3, 0.0), "ft": (0.3048, 0.0)},
    "torque": {"N*m": (1.0, 0.0), "Nm": (1.0, 0.0), "N.m": (1.0, 0.0), "N·m": (1.0, 0.0),
               "kN*m": (1e3, 0.0), "lbf*ft": (1.3558179483314004, 0.0)},
    "force": {"N": (1.0, 0.0), "kN": (1e3, 0.0), "lbf": (4.4482216152605, 0.0)},
    "mass": {"kg": (1.0, 0.0), "t": (1e3, 0.0), "lb": (0.45359237, 0.0)},
    "ratio": {"1": (1.0, 0.0), "-": (1.0, 0.0), "%": (0.01, 0.0), "percent": (0.01, 0.0)},
    "number": {"1": (1.0, 0.0), "-": (1.0, 0.0)},
    "time": {"s": (1.0, 0.0), "ms": (1e-3, 0.0), "us": (1e-6, 0.0), "ns": (1e-9, 0.0),
             "min": (60.0, 0.0), "h": (3600.0, 0.0)},
}


@dataclass(frozen=True)
class SignalSpec:
    topic: str          # contract topic
    kind: str           # unit kind (UNITS key); "wheel" = angular rate or velocity
    out_scale: float = 1.0   # applied after the SI conversion (lat/lon: rad -> deg)


#: Contract topic -> {signal key: unit kind} of the signals it carries (``wheel``: an
#: angular rate, or a velocity divided by the wheel radius). The order is the ``--help`` order.
_SIGNAL_KINDS: dict[str, dict[str, str]] = {
    T.IMU: {f"imu.{group}.{axis}": kind for axis in "xyz"
            for group, kind in (("linear_acceleration", "acceleration"), ("angular_velocity", "angular rate"))},
    T.GNSS: {"gnss.latitude": "angle", "gnss.longitude": "angle", "gnss.altitude": "length",
             "gnss.status": "number", "gnss.horizontal_std": "length", "gnss.vertical_std": "length"},
    T.SPEED: {"speed.vx": "velocity", "speed.vx_std": "velocity"},
    T.JOINT_STATES: {**{f"joint_states.{wheel}.{name}": kind for wheel in T.WHEEL_JOINTS
                        for name, kind in (("velocity", "wheel"), ("effort", "torque"))},
                     f"joint_states.{T.STEERING_JOINT}.position": "angle"},
    T.POWERTRAIN: {f"powertrain.{T.ENGINE_JOINT}.velocity": "angular rate",
                   f"powertrain.{T.ENGINE_JOINT}.effort": "torque",
                   f"powertrain.{T.ENGINE_LOAD_JOINT}.position": "ratio",
                   f"powertrain.{T.GEAR_JOINT}.position": "number",
                   f"powertrain.{T.DRIVE_JOINT}.effort": "force"},
    T.GT_VEHICLE_STATE: {"ground_truth.vehicle_state.vx": "velocity", "ground_truth.vehicle_state.vy": "velocity",
                         "ground_truth.vehicle_state.yaw_rate": "angular rate"},
    T.GT_SIDESLIP: {"ground_truth.sideslip": "angle"},
    T.GT_ROAD_SLOPE: {"ground_truth.road_slope": "angle"},
    T.GT_MASS: {"ground_truth.mass": "mass"},
}
#: Latitude and longitude convert to radians as any angle; the message wants degrees.
_OUT_SCALE = {"gnss.latitude": 180.0 / math.pi, "gnss.longitude": 180.0 / math.pi}

SIGNALS = {key: SignalSpec(topic, kind, _OUT_SCALE.get(key, 1.0))
           for topic, kinds in _SIGNAL_KINDS.items() for key, kind in kinds.items()}
STEERING_KEY = f"joint_states.{T.STEERING_JOINT}.position"
YAW_RATE_KEY = "imu.angular_velocity.z"
WHEEL_VELOCITY_KEYS = tuple(f"joint_states.{w}.velocity" for w in T.WHEEL_JOINTS)

_TOP_KEYS = {"version", "description", "data_dir", "vehicle", "sources", "time", "imu", "signals",
             "wheel_speeds_from_speed"}
_SOURCE_KEYS = {"file", "format", "delimiter", "header", "skip_rows", "comment", "time"}
_TIME_KEYS = {"source", "column", "unit", "offset"}
_SIGNAL_KEYS = {"source", "column", "unit", "scale", "offset", "road_wheel_angle"}
_IMU_KEYS = {"gravity_removed", "frame_id"}
_DERIVE_KEYS = _SIGNAL_KEYS - {"road_wheel_angle"} | {"kinematic"}


class MappingError(ValueError):
    """The mapping file (or the data it points to) is wrong; the message names the key."""


def convert(values: np.ndarray, unit: str, kind: str, where: str = "unit") -> np.ndarray:
    """``values`` in ``unit`` to SI for a signal of ``kind`` (a key of :data:`UNITS`)."""
    table = UNITS[kind]
    if unit not in table:
        raise MappingError(f"{where}: unknown unit {unit!r} for {kind_label(kind)} "
                           f"(known: {', '.join(table)})")
    factor, offset = table[unit]
    return np.asarray(values, dtype=float) * factor + offset


def kind_label(kind: str) -> str:
    return "an " + kind if kind[0] in "aeiou" else "a " + kind


# --------------------------------------------------------------------------- mapping
def load_mapping(path_or_name: str | Path) -> tuple[dict, Path]:
    """The mapping dict of a YAML file (path, or name in ``params/import_maps``) and its path."""
    path = Path(path_or_name)
    if not path.is_file():
        from vehicle_estimation.paths import params_dir
        name = path.name if path.suffix in (".yaml", ".yml") else f"{path.name}.yaml"
        candidate = params_dir() / "import_maps" / name
        if not candidate.is_file():
            raise MappingError(f"no mapping file {str(path_or_name)!r} (not a file, not in "
                               f"{params_dir() / 'import_maps'})")
        path = candidate
    with open(path, "r", encoding="utf-8") as handle:
        try:
            mapping = yaml.safe_load(handle)
        except yaml.YAMLError as exc:
            raise MappingError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(mapping, dict):
        raise MappingError(f"{path}: the mapping must be a YAML mapping (key: value), got {type(mapping).__name__}")
    return mapping, path


def _unknown_keys(given: Mapping, known: set[str], where: str) -> None:
    for key in given:
        if key not in known:
            close = difflib.get_close_matches(str(key), sorted(known), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f" (known: {', '.join(sorted(known))})"
            raise MappingError(f"{where}{key}: unknown key{hint}")


def _require_dict(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise MappingError(f"{where}: must be a mapping (key: value), got {value!r}")
    return value


def _non_empty_section(mapping: Mapping, section: str, entry: str) -> dict:
    entries = _require_dict(mapping.get(section), section)
    if not entries:
        raise MappingError(f"{section}: at least one {entry} is needed")
    return entries


def mapped_number(value: Any, where: str, default: float | None = None) -> float:
    """A finite number of the mapping at ``where`` (``default`` when absent), else MappingError."""
    if value is None and default is not None:
        return default
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MappingError(f"{where}: must be a finite number, got {value!r}")
    return float(value)


def validate_mapping(mapping: Mapping) -> None:
    """Check the structure of a mapping (keys, units, references); raise :class:`MappingError`.

    The data files are not read here (see :func:`load_signals`).
    """
    _require_dict(mapping, "mapping")
    _unknown_keys(mapping, _TOP_KEYS, "")
    version = mapping.get("version", MAPPING_VERSION)
    if version != MAPPING_VERSION:
        raise MappingError(f"version: this importer reads version {MAPPING_VERSION}, got {version!r}")
    sources = _non_empty_section(mapping, "sources", "source")
    for name, spec in sources.items():
        where = f"sources.{name}"
        spec = _require_dict(spec, where)
        _unknown_keys(spec, _SOURCE_KEYS, where + ".")
        if not isinstance(spec.get("file"), str):
            raise MappingError(f"{where}.file: required (a file name), got {spec.get('file')!r}")
        if "time" in spec:
            _validate_time(spec["time"], f"{where}.time", sources, own=name)
        if "skip_rows" in spec and (isinstance(spec["skip_rows"], bool) or not isinstance(spec["skip_rows"], int)
                                    or spec["skip_rows"] < 0):
            raise MappingError(f"{where}.skip_rows: must be an integer >= 0, got {spec['skip_rows']!r}")
    needs_global_time = any("time" not in s for s in sources.values())
    if needs_global_time:
        if "time" not in mapping:
            missing = [n for n, s in sources.items() if "time" not in s]
            raise MappingError(f"time: required (sources {missing} have no time of their own)")
        _validate_time(mapping["time"], "time", sources)
    imu = _require_dict(mapping.get("imu", {}), "imu")
    _unknown_keys(imu, _IMU_KEYS, "imu.")
    if not isinstance(imu.get("gravity_removed", False), bool):
        raise MappingError(f"imu.gravity_removed: must be true or false, got {imu['gravity_removed']!r}")
    signals = _non_empty_section(mapping, "signals", "signal")
    for key, spec in signals.items():
        where = f"signals.{key}"
        if key not in SIGNALS:
            close = difflib.get_close_matches(str(key), list(SIGNALS), n=3)
            hint = f"; did you mean {close}?" if close else "; see the importer's documentation for the list"
            raise MappingError(f"{where}: unknown signal{hint}")
        _validate_signal(spec, where, SIGNALS[key].kind, sources, _SIGNAL_KEYS)
        if "road_wheel_angle" in spec:
            if key != STEERING_KEY:
                raise MappingError(f"{where}.road_wheel_angle: only for {STEERING_KEY}")
            if not isinstance(spec["road_wheel_angle"], bool):
                raise MappingError(f"{where}.road_wheel_angle: must be true or false")
    derive = mapping.get("wheel_speeds_from_speed")
    if derive is not None:
        where = "wheel_speeds_from_speed"
        _validate_signal(derive, where, "velocity", sources, _DERIVE_KEYS)
        if not isinstance(derive.get("kinematic", True), bool):
            raise MappingError(f"{where}.kinematic: must be true or false")
        clash = [k for k in WHEEL_VELOCITY_KEYS if k in signals]
        if clash:
            raise MappingError(f"{where}: the wheel speeds are mapped already ({clash}); use one or the other")
        if derive.get("kinematic", True):
            for needed in (YAW_RATE_KEY, STEERING_KEY):
                if needed not in signals:
                    raise MappingError(f"{where}.kinematic: needs signals.{needed} (or set kinematic: false)")
    if needs_vehicle(mapping) and not mapping.get("vehicle"):
        raise MappingError(f"vehicle: required by {needs_vehicle(mapping)} (a params file: name in params/ or path)")


def needs_vehicle(mapping: Mapping) -> str | None:
    signals = mapping.get("signals") or {}
    if mapping.get("wheel_speeds_from_speed") is not None:
        return "wheel_speeds_from_speed"
    steer = signals.get(STEERING_KEY)
    if isinstance(steer, dict) and steer.get("road_wheel_angle"):
        return f"signals.{STEERING_KEY}.road_wheel_angle"
    for key in WHEEL_VELOCITY_KEYS:
        spec = signals.get(key)
        if isinstance(spec, dict) and spec.get("unit") in UNITS["velocity"]:
            return f"signals.{key}.unit (a velocity)"
    return None


def _check_source_ref(spec: Mapping, where: str, sources: Mapping) -> None:
    src = spec.get("source")
    if src is None:
        if len(sources) != 1:
            raise MappingError(f"{where}.source: required when there is more than one source "
                               f"(one of {list(sources)})")
    elif src not in sources:
        close = difflib.get_close_matches(str(src), [str(s) for s in sources], n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else f" (sources: {list(sources)})"
        raise MappingError(f"{where}.source: no source {src!r}{hint}")


def _validate_signal(spec: Any, where: str, kind: str, sources: Mapping, keys: set[str]) -> None:
    spec = _require_dict(spec, where)
    _unknown_keys(spec, keys, where + ".")
    _check_source_ref(spec, where, sources)
    unit = spec.get("unit")
    if unit is None:
        raise MappingError(f"{where}.unit: required")
    unit = str(unit)
    kinds = ("angular rate", "velocity") if kind == "wheel" else (kind,)
    if not any(unit in UNITS[k] for k in kinds):
        known = [u for k in kinds for u in UNITS[k]]
        label = "a wheel speed" if kind == "wheel" else kind_label(kind)
        raise MappingError(f"{where}.unit: unknown unit {unit!r} for {label} (known: {', '.join(known)})")
    mapped_number(spec.get("scale"), where + ".scale", 1.0)
    mapped_number(spec.get("offset"), where + ".offset", 0.0)


def _validate_time(spec: Any, where: str, sources: Mapping, own: str | None = None) -> None:
    spec = _require_dict(spec, where)
    _unknown_keys(spec, _TIME_KEYS, where + ".")
    if own is not None:   # a source's own time: same file
        if spec.get("source", own) != own:
            raise MappingError(f"{where}.source: a source's own time comes from the same file")
    else:
        _check_source_ref(spec, where, sources)
    unit = str(spec.get("unit", "s"))
    if unit not in UNITS["time"]:
        raise MappingError(f"{where}.unit: unknown unit {unit!r} for a time (known: {', '.join(UNITS['time'])})")
    mapped_number(spec.get("offset"), where + ".offset", 0.0)
