"""Import column data (CSV or whitespace text) into a rosbag2 (MCAP) that follows the topic contract.

Usage::

    vehicle-estimation import MAPPING --out BAG [--data-dir DIR] [--vehicle FILE] [--rows N]

``MAPPING`` is a YAML file (a path, or a name in ``params/import_maps/``) that says where
the data is, which column is which signal of the contract, and in which unit. The importer
converts every signal to the contract's units (SI; latitude/longitude in degrees), builds
the messages and writes a new MCAP bag that ``replay`` and ``report`` read like a simulated
one. Bring your own CAN/IMU/GNSS logs by writing such a file; nothing else is needed.

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

Rules:

* Stamps (header and log time) are the converted time plus the offset, rounded to 1 us.
* Output rates follow the input: one message per row that has any of the topic's signals.
  A topic whose signals come from sources with different time bases is built on the time base
  with the most samples; the other signals are linearly interpolated onto it (NaN outside
  their span).
* Missing signals are simply absent: a topic with no mapped signal is not written; a joint
  with no mapped field is left out of the JointState; a mapped field of a joint that another
  field has but this row lacks is NaN (the contract's "missing" value). Rows whose time is not
  a number are dropped; time must increase.
* IMU (REP-145): ``linear_acceleration`` is the specific force, +g on z at rest. Axes that are
  not mapped are written as 0 (angular velocity, acceleration x/y) and +g (acceleration z:
  level road assumed); with ``imu.gravity_removed: true`` +g is added to z as well.
* ``wheel_speeds_from_speed`` (for a log that has a vehicle speed but no wheel speeds; the
  vehicle-state node needs wheel speeds for vx): ``kinematic: true`` gives each wheel the
  forward speed of its centre for the logged speed v, yaw rate r and road-wheel angle δ with
  vy neglected (front: (v ∓ b_F/2 r) cos δ + l_F r sin δ, rear: v ∓ b_R/2 r), divided by the
  wheel radius, i.e. free-rolling wheels; it needs ``imu.angular_velocity.z`` and the
  steering signal. ``false``: all four are v / R.
* A bad mapping raises :class:`MappingError` whose message names the offending key
  (``signals.imu.angular_velocity.z.unit: unknown unit 'deg/sec' ...``).
"""

from __future__ import annotations

import argparse
import difflib
import math
import sys
from dataclasses import dataclass, field
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


def _signal_table() -> dict[str, SignalSpec]:
    table: dict[str, SignalSpec] = {}
    for axis in "xyz":
        table[f"imu.linear_acceleration.{axis}"] = SignalSpec(T.IMU, "acceleration")
        table[f"imu.angular_velocity.{axis}"] = SignalSpec(T.IMU, "angular rate")
    table["gnss.latitude"] = SignalSpec(T.GNSS, "angle", 180.0 / math.pi)
    table["gnss.longitude"] = SignalSpec(T.GNSS, "angle", 180.0 / math.pi)
    table["gnss.altitude"] = SignalSpec(T.GNSS, "length")
    table["gnss.status"] = SignalSpec(T.GNSS, "number")
    table["gnss.horizontal_std"] = SignalSpec(T.GNSS, "length")
    table["gnss.vertical_std"] = SignalSpec(T.GNSS, "length")
    table["speed.vx"] = SignalSpec(T.SPEED, "velocity")
    table["speed.vx_std"] = SignalSpec(T.SPEED, "velocity")
    for wheel in T.WHEEL_JOINTS:
        table[f"joint_states.{wheel}.velocity"] = SignalSpec(T.JOINT_STATES, "wheel")
        table[f"joint_states.{wheel}.effort"] = SignalSpec(T.JOINT_STATES, "torque")
    table[f"joint_states.{T.STEERING_JOINT}.position"] = SignalSpec(T.JOINT_STATES, "angle")
    table[f"powertrain.{T.ENGINE_JOINT}.velocity"] = SignalSpec(T.POWERTRAIN, "angular rate")
    table[f"powertrain.{T.ENGINE_JOINT}.effort"] = SignalSpec(T.POWERTRAIN, "torque")
    table[f"powertrain.{T.ENGINE_LOAD_JOINT}.position"] = SignalSpec(T.POWERTRAIN, "ratio")
    table[f"powertrain.{T.GEAR_JOINT}.position"] = SignalSpec(T.POWERTRAIN, "number")
    table[f"powertrain.{T.DRIVE_JOINT}.effort"] = SignalSpec(T.POWERTRAIN, "force")
    table["ground_truth.vehicle_state.vx"] = SignalSpec(T.GT_VEHICLE_STATE, "velocity")
    table["ground_truth.vehicle_state.vy"] = SignalSpec(T.GT_VEHICLE_STATE, "velocity")
    table["ground_truth.vehicle_state.yaw_rate"] = SignalSpec(T.GT_VEHICLE_STATE, "angular rate")
    table["ground_truth.sideslip"] = SignalSpec(T.GT_SIDESLIP, "angle")
    table["ground_truth.road_slope"] = SignalSpec(T.GT_ROAD_SLOPE, "angle")
    table["ground_truth.mass"] = SignalSpec(T.GT_MASS, "mass")
    return table


SIGNALS = _signal_table()
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


# --------------------------------------------------------------------------- reading
@dataclass
class Table:
    """One source: its columns (name -> array) and names in file order."""

    columns: list[np.ndarray]
    names: list[str] | None
    time: np.ndarray | None = None       # absolute stamps [s] once resolved

    def column(self, ref: Any, where: str) -> np.ndarray:
        if ref is None:
            if len(self.columns) != 1:
                names = self.names or list(range(len(self.columns)))
                raise MappingError(f"{where}: the source has {len(self.columns)} columns, say which "
                                   f"(column: one of {names})")
            return self.columns[0]
        if isinstance(ref, bool):
            raise MappingError(f"{where}: column must be a name or a 0-based index, got {ref!r}")
        if isinstance(ref, int):
            if not 0 <= ref < len(self.columns):
                raise MappingError(f"{where}: column index {ref} outside 0..{len(self.columns) - 1}")
            return self.columns[ref]
        if self.names is None:
            if str(ref).isdigit():
                return self.column(int(ref), where)
            raise MappingError(f"{where}: the source has no header row, refer to columns by index")
        if str(ref) not in self.names:
            close = difflib.get_close_matches(str(ref), self.names, n=3)
            hint = f"; did you mean {close}?" if close else f" (columns: {self.names})"
            raise MappingError(f"{where}: no column {ref!r}{hint}")
        return self.columns[self.names.index(str(ref))]


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return text.strip().lower() in ("", "nan", "inf", "-inf")


def read_table(path: Path, *, fmt: str | None = None, delimiter: str = ",", header: Any = "auto",
               skip_rows: int = 0, comment: str = "#", max_rows: int | None = None,
               where: str = "sources") -> Table:
    """Read a CSV or whitespace-separated text file into columns (empty cells -> NaN)."""
    if not path.is_file():
        raise MappingError(f"{where}.file: no such file {str(path)!r}")
    fmt = fmt or ("csv" if path.suffix.lower() == ".csv" else "whitespace")
    if fmt not in ("csv", "whitespace"):
        raise MappingError(f"{where}.format: must be 'csv' or 'whitespace', got {fmt!r}")
    sep = delimiter if fmt == "csv" else None
    rows: list[list[str]] = []
    names: list[str] | None = None
    with open(path, "r", encoding="utf-8-sig") as handle:
        for _ in range(skip_rows):
            handle.readline()
        first = True
        for line in handle:
            if comment and line.lstrip().startswith(comment):
                continue
            if not line.strip():
                continue
            cells = [c.strip() for c in (line.split(sep) if sep else line.split())]
            if first:
                first = False
                is_header = (header is True) or (header == "auto" and not all(_is_number(c) for c in cells))
                if header not in (True, False, "auto"):
                    raise MappingError(f"{where}.header: must be true, false or auto, got {header!r}")
                if is_header:
                    names = [c.strip('"').strip("'") for c in cells]
                    continue
            rows.append(cells)
            if max_rows is not None and len(rows) >= max_rows:
                break
    if not rows:
        raise MappingError(f"{where}.file: {str(path)!r} has no data rows")
    width = len(names) if names is not None else len(rows[0])
    data = np.full((len(rows), width), np.nan)
    for i, cells in enumerate(rows):
        if len(cells) != width:
            raise MappingError(f"{where}.file: {path.name} line {i + 1 + skip_rows + (names is not None)} "
                               f"has {len(cells)} cells, expected {width}")
        for j, c in enumerate(cells):
            if c:
                try:
                    data[i, j] = float(c)
                except ValueError:
                    raise MappingError(f"{where}.file: {path.name} row {i + 1}, column {j}: "
                                       f"not a number: {c!r}") from None
    return Table([data[:, j].copy() for j in range(width)], names)


def _read_fast(path: Path, max_rows: int | None) -> Table | None:
    """One-number-per-line files (the common 'one file per signal' case) via numpy."""
    try:
        data = np.loadtxt(path, dtype=float, max_rows=max_rows, ndmin=2, comments="#")
    except (ValueError, OSError):
        return None
    return Table([data[:, j].copy() for j in range(data.shape[1])], None)


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


def _number(value: Any, where: str, default: float | None = None) -> float:
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
    sources = _require_dict(mapping.get("sources"), "sources")
    if not sources:
        raise MappingError("sources: at least one source is needed")
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
    signals = _require_dict(mapping.get("signals"), "signals")
    if not signals:
        raise MappingError("signals: at least one signal is needed")
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
    if _needs_vehicle(mapping) and not mapping.get("vehicle"):
        raise MappingError(f"vehicle: required by {_needs_vehicle(mapping)} (a params file: name in params/ or path)")


def _needs_vehicle(mapping: Mapping) -> str | None:
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
    _number(spec.get("scale"), where + ".scale", 1.0)
    _number(spec.get("offset"), where + ".offset", 0.0)


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
    _number(spec.get("offset"), where + ".offset", 0.0)


# --------------------------------------------------------------------------- signals
@dataclass
class Signal:
    """One converted signal: absolute stamps [s] and values in contract units."""

    t: np.ndarray
    values: np.ndarray


@dataclass
class ImportResult:
    bag: Path | None
    signals: dict[str, Signal]
    counts: dict[str, int] = field(default_factory=dict)   # topic -> messages written
    start: float = math.nan
    end: float = math.nan
    notes: list[str] = field(default_factory=list)


def _resolve_vehicle(mapping: Mapping, vehicle: str | Path | None):
    from vehicle_estimation.paths import params_file
    from vehicle_estimation.contract.vehicle import load_vehicle_params
    ref = vehicle or mapping.get("vehicle")
    if not ref:
        return None
    try:
        return load_vehicle_params(params_file(ref))
    except (FileNotFoundError, ValueError) as exc:
        raise MappingError(f"vehicle: {exc}") from None


def load_signals(mapping: Mapping, *, base_dir: str | Path | None = None, vehicle: str | Path | None = None,
                 max_rows: int | None = None, mapping_dir: Path | None = None) -> tuple[dict[str, Signal], list[str]]:
    """Validate ``mapping``, read its sources and return ``{signal key: Signal}`` in contract units.

    Includes the synthesised wheel speeds of ``wheel_speeds_from_speed``. ``max_rows`` reads
    only the first rows of every file (tests, quick looks). Returns the signals and notes.
    """
    validate_mapping(mapping)
    notes: list[str] = []
    here = mapping_dir or Path.cwd()
    if base_dir is not None:
        root = Path(base_dir).expanduser()
    elif mapping.get("data_dir"):
        root = here / Path(str(mapping["data_dir"])).expanduser()   # an absolute data_dir wins
    else:
        root = here
    params = _resolve_vehicle(mapping, vehicle)
    if _needs_vehicle(mapping) and params is None:
        raise MappingError(f"vehicle: required by {_needs_vehicle(mapping)}")

    sources = mapping["sources"]
    tables: dict[str, Table] = {}
    for name, spec in sources.items():
        where = f"sources.{name}"
        path = Path(spec["file"]).expanduser()
        path = path if path.is_absolute() else root / path
        table = None
        simple = spec.get("header", "auto") in ("auto", False) and spec.get("format", "whitespace") == "whitespace" \
            and not spec.get("skip_rows") and path.suffix.lower() != ".csv"
        if simple and path.is_file():
            table = _read_fast(path, max_rows)
        if table is None:
            table = read_table(path, fmt=spec.get("format"), delimiter=str(spec.get("delimiter", ",")),
                               header=spec.get("header", "auto"), skip_rows=int(spec.get("skip_rows", 0)),
                               comment=str(spec.get("comment", "#")), max_rows=max_rows, where=where)
        tables[name] = table

    def time_of(spec: Mapping, where: str, default_source: str) -> np.ndarray:
        src = spec.get("source", default_source if len(sources) != 1 else next(iter(sources)))
        raw = tables[src].column(spec.get("column"), where + ".column")
        t = convert(raw, str(spec.get("unit", "s")), "time", where + ".unit")
        return t + _number(spec.get("offset"), where + ".offset", 0.0)

    global_time = None
    if "time" in mapping:
        global_time = time_of(mapping["time"], "time", next(iter(sources)))
    for name, spec in sources.items():
        table = tables[name]
        if "time" in spec:
            table.time = time_of(spec["time"], f"sources.{name}.time", name)
        else:
            n = len(table.columns[0])
            if global_time is None or len(global_time) != n:
                raise MappingError(f"sources.{name}: {n} rows but the time column has "
                                   f"{0 if global_time is None else len(global_time)}; give the source "
                                   f"its own time (sources.{name}.time)")
            table.time = global_time
        finite_t = table.time[np.isfinite(table.time)]
        if finite_t.size == 0:
            raise MappingError(f"sources.{name}: no valid time")
        if np.any(np.diff(finite_t) <= 0.0):
            i = int(np.nonzero(np.diff(finite_t) <= 0.0)[0][0])
            raise MappingError(f"sources.{name}: time does not increase at row {i + 1} "
                               f"({finite_t[i]!r} -> {finite_t[i + 1]!r})")
        if finite_t[0] <= 0.0:
            raise MappingError(f"{'sources.' + name + '.time' if 'time' in spec else 'time'}.offset: "
                               f"stamps must be positive (first {finite_t[0]!r} s); add an offset")

    def read_signal(spec: Mapping, where: str, kind: str, key: str | None) -> Signal:
        src = spec.get("source", next(iter(sources)))
        table = tables[src]
        raw = table.column(spec.get("column"), where + ".column")
        raw = raw * _number(spec.get("scale"), where + ".scale", 1.0) + _number(spec.get("offset"), where + ".offset", 0.0)
        unit = str(spec["unit"])
        if kind == "wheel":
            if unit in UNITS["velocity"]:
                values = convert(raw, unit, "velocity", where + ".unit") / params.wheel_radius
            else:
                values = convert(raw, unit, "angular rate", where + ".unit")
        else:
            values = convert(raw, unit, kind, where + ".unit")
        values = values * (SIGNALS[key].out_scale if key else 1.0)
        if key == STEERING_KEY and spec.get("road_wheel_angle"):
            values = values * params.steering_ratio
        ok = np.isfinite(table.time)
        return Signal(table.time[ok].copy(), values[ok].copy())

    signals: dict[str, Signal] = {}
    for key, spec in mapping["signals"].items():
        signals[key] = read_signal(spec, f"signals.{key}", SIGNALS[key].kind, key)
    derive = mapping.get("wheel_speeds_from_speed")
    if derive is not None:
        speed = read_signal(derive, "wheel_speeds_from_speed", "velocity", None)
        for key, values in zip(WHEEL_VELOCITY_KEYS, _wheel_speeds(speed, signals, params, derive.get("kinematic", True))):
            signals[key] = Signal(speed.t, values)
        notes.append("wheel speeds synthesised from a speed signal "
                     f"({'kinematic, vy neglected' if derive.get('kinematic', True) else 'v / R each'})")
    return signals, notes


def _wheel_speeds(speed: Signal, signals: dict[str, Signal], params, kinematic: bool) -> list[np.ndarray]:
    v = speed.values
    R = params.wheel_radius
    if not kinematic:
        return [v / R] * 4
    r = np.interp(speed.t, signals[YAW_RATE_KEY].t, signals[YAW_RATE_KEY].values, left=np.nan, right=np.nan)
    steer = signals[STEERING_KEY]
    delta = np.interp(speed.t, steer.t, steer.values, left=np.nan, right=np.nan) / params.steering_ratio
    hf, hr = 0.5 * params.track_front, 0.5 * params.track_rear
    cd, sd = np.cos(delta), np.sin(delta)
    lat = params.lf * r * sd
    return [((v - hf * r) * cd + lat) / R, ((v + hf * r) * cd + lat) / R, (v - hr * r) / R, (v + hr * r) / R]


# --------------------------------------------------------------------------- messages
def _on_base(sigs: list[Signal]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Common time base of a topic's signals (the longest; others interpolated onto it)."""
    base = max(sigs, key=lambda s: s.t.size).t
    out = []
    for s in sigs:
        if s.t.size == base.size and (s.t is base or np.array_equal(s.t, base)):
            out.append(s.values)
        else:
            out.append(np.interp(base, s.t, s.values, left=np.nan, right=np.nan) if s.t.size else
                       np.full(base.shape, np.nan))
    return base, out


def _stamps(t: np.ndarray):
    # Absolute stamps in float seconds resolve ~0.24 us at today's epoch: round to 1 us.
    ns = np.round(np.asarray(t, dtype=float) * 1e6).astype(np.int64) * 1000
    return ns, ns // 1_000_000_000, ns % 1_000_000_000


def build_streams(signals: Mapping[str, Signal], *, gravity_removed: bool = False,
                  imu_frame: str = T.IMU_FRAME) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """``(topic, msgtype, stamps ns, byte matrix)`` per topic that has any signal."""
    from vehicle_estimation.sim import bag as simbag

    by_topic: dict[str, list[str]] = {}
    for key in signals:
        by_topic.setdefault(SIGNALS[key].topic, []).append(key)
    streams = []
    nan = float("nan")

    def gather(topic):
        keys = by_topic[topic]
        base, values = _on_base([signals[k] for k in keys])
        cols = dict(zip(keys, values))
        keep = np.zeros(base.shape, dtype=bool)
        for v in values:
            keep |= np.isfinite(v)
        return base[keep], {k: v[keep] for k, v in cols.items()}

    if T.IMU in by_topic:
        t, cols = gather(T.IMU)
        ns, sec, nsec = _stamps(t)
        vals = {"sec": sec, "nsec": nsec, "ocov0": -1.0}   # REP-145: orientation not provided
        for axis in "xyz":
            vals[f"w{axis}"] = cols.get(f"imu.angular_velocity.{axis}", 0.0)
            vals[f"a{axis}"] = cols.get(f"imu.linear_acceleration.{axis}", 0.0)
        az = cols.get("imu.linear_acceleration.z")
        if az is None:
            vals["az"] = G
        elif gravity_removed:
            vals["az"] = az + G
        tpl = simbag._Template("sensor_msgs/msg/Imu", simbag._imu, imu_frame,
                               ["sec", "nsec", "ocov0", "wx", "wy", "wz", "ax", "ay", "az"])
        streams.append((T.IMU, tpl.msgtype, ns, tpl.fill(ns.size, vals)))

    if T.GNSS in by_topic:
        t, cols = gather(T.GNSS)
        ns, sec, nsec = _stamps(t)
        vals = {"sec": sec, "nsec": nsec, "service": 1,
                "lat": cols.get("gnss.latitude", nan), "lon": cols.get("gnss.longitude", nan),
                "alt": cols.get("gnss.altitude", nan)}
        status = cols.get("gnss.status")
        vals["status"] = np.nan_to_num(status, nan=-1).astype(np.int64) if status is not None else 0
        keys = ["sec", "nsec", "status", "service", "lat", "lon", "alt"]
        h, v = cols.get("gnss.horizontal_std"), cols.get("gnss.vertical_std")
        if h is not None or v is not None:
            h = h if h is not None else v
            v = v if v is not None else h
            vals.update({"pcovtype": 2, "pcov0": h * h, "pcov4": h * h, "pcov8": v * v})
            keys += ["pcovtype", "pcov0", "pcov4", "pcov8"]
        tpl = simbag._Template("sensor_msgs/msg/NavSatFix", simbag._navsat, T.GNSS_FRAME, keys)
        streams.append((T.GNSS, tpl.msgtype, ns, tpl.fill(ns.size, vals)))

    if T.SPEED in by_topic:
        t, cols = gather(T.SPEED)
        ns, sec, nsec = _stamps(t)
        std = cols.get("speed.vx_std")
        vals = {"sec": sec, "nsec": nsec, "lx": cols.get("speed.vx", nan),
                "cov0": std * std if std is not None else 0.0}
        tpl = simbag._Template("geometry_msgs/msg/TwistWithCovarianceStamped", simbag._twist_cov_stamped,
                               T.BASE_FRAME, ["sec", "nsec", "lx", "cov0"])
        streams.append((T.SPEED, tpl.msgtype, ns, tpl.fill(ns.size, vals)))

    for topic, prefix, joints in ((T.JOINT_STATES, "joint_states", tuple(T.WHEEL_JOINTS) + (T.STEERING_JOINT,)),
                                  (T.POWERTRAIN, "powertrain", (T.ENGINE_JOINT, T.ENGINE_LOAD_JOINT,
                                                                T.GEAR_JOINT, T.DRIVE_JOINT))):
        if topic not in by_topic:
            continue
        t, cols = gather(topic)
        ns, sec, nsec = _stamps(t)
        names = [j for j in joints if any(f"{prefix}.{j}.{f}" in cols for f in ("position", "velocity", "effort"))]
        vals: dict[str, Any] = {"sec": sec, "nsec": nsec}
        keys = ["sec", "nsec"]
        for i, joint in enumerate(names):
            for short, fld in (("pos", "position"), ("vel", "velocity"), ("eff", "effort")):
                vals[f"{short}{i}"] = cols.get(f"{prefix}.{joint}.{fld}", nan)
                keys.append(f"{short}{i}")
        tpl = simbag._Template("sensor_msgs/msg/JointState", simbag._joint_state(tuple(names)), "", keys)
        streams.append((topic, tpl.msgtype, ns, tpl.fill(ns.size, vals)))

    if T.GT_VEHICLE_STATE in by_topic:
        t, cols = gather(T.GT_VEHICLE_STATE)
        ns, sec, nsec = _stamps(t)
        vals = {"sec": sec, "nsec": nsec, "lx": cols.get("ground_truth.vehicle_state.vx", nan),
                "ly": cols.get("ground_truth.vehicle_state.vy", nan),
                "wz": cols.get("ground_truth.vehicle_state.yaw_rate", nan)}
        tpl = simbag._Template("geometry_msgs/msg/TwistWithCovarianceStamped", simbag._twist_cov_stamped,
                               T.BASE_FRAME, ["sec", "nsec", "lx", "ly", "wz"])
        streams.append((T.GT_VEHICLE_STATE, tpl.msgtype, ns, tpl.fill(ns.size, vals)))

    for topic, key in ((T.GT_SIDESLIP, "ground_truth.sideslip"), (T.GT_ROAD_SLOPE, "ground_truth.road_slope"),
                       (T.GT_MASS, "ground_truth.mass")):
        if topic not in by_topic:
            continue
        t, cols = gather(topic)
        ns, _, _ = _stamps(t)
        tpl = simbag._Template("std_msgs/msg/Float64", simbag._float64, "", ["data"])
        streams.append((topic, tpl.msgtype, ns, tpl.fill(ns.size, {"data": cols[key]})))
    return streams


def write_streams(streams, path: Path) -> dict[str, int]:
    """Write every stream in global stamp order (log time = header stamp) to a new MCAP bag,
    under absolute topic names; returns the message count per topic."""
    from vehicle_estimation.sim import bag as simbag

    simbag.write_streams([("/" + topic, msgtype, ns, rows) for topic, msgtype, ns, rows in streams], path)
    return {topic: int(s.size) for topic, _, s, _ in streams}


def import_logs(mapping: Mapping | str | Path, out: str | Path | None, *, base_dir: str | Path | None = None,
                vehicle: str | Path | None = None, max_rows: int | None = None) -> ImportResult:
    """Import the data a mapping (dict, file or name) describes into a new MCAP bag ``out``.

    ``out=None`` only reads and converts (``ImportResult.signals``), writing nothing.
    """
    mapping_dir = None
    if not isinstance(mapping, Mapping):
        mapping, mapping_path = load_mapping(mapping)
        mapping_dir = mapping_path.parent
    signals, notes = load_signals(mapping, base_dir=base_dir, vehicle=vehicle, max_rows=max_rows,
                                  mapping_dir=mapping_dir)
    imu = mapping.get("imu") or {}
    if any(SIGNALS[k].topic == T.IMU for k in signals):
        missing = [f"imu.{g}.{a}" for g in ("linear_acceleration", "angular_velocity") for a in "xyz"
                   if f"imu.{g}.{a}" not in signals]
        if missing:
            notes.append(f"IMU axes not in the log, written as 0 (acceleration z: +g): {', '.join(missing)}")
    if imu.get("gravity_removed"):
        notes.append("IMU accelerations had gravity removed: +g added on z (REP-145 specific force)")
    result = ImportResult(None, signals, notes=notes)
    starts = [s.t[0] for s in signals.values() if s.t.size]
    ends = [s.t[-1] for s in signals.values() if s.t.size]
    result.start, result.end = (min(starts), max(ends)) if starts else (math.nan, math.nan)
    if out is None:
        return result
    streams = build_streams(signals, gravity_removed=bool(imu.get("gravity_removed", False)),
                            imu_frame=str(imu.get("frame_id", T.IMU_FRAME)))
    result.bag = Path(out)
    result.counts = write_streams(streams, result.bag)
    return result


# --------------------------------------------------------------------------- CLI
def _units_help() -> str:
    lines = ["units per kind (value in SI = raw * factor):"]
    for kind, table in UNITS.items():
        lines.append(f"  {kind:13s} {', '.join(table)}")
    lines.append("  wheel speed   an angular rate, or a velocity (divided by the vehicle's wheel radius)")
    lines.append("signals: " + ", ".join(SIGNALS))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="vehicle-estimation import",
        description="Import CSV/whitespace column logs into a contract-conforming MCAP rosbag2 "
                    "(mapping format: see the module docstring of vehicle_estimation.io.importer).",
        epilog=_units_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mapping", help="mapping YAML (a path, or a name in params/import_maps/)")
    parser.add_argument("--out", required=True, help="output bag directory (must not exist)")
    parser.add_argument("--data-dir", default=None, help="folder of the data files (overrides data_dir)")
    parser.add_argument("--vehicle", default=None, help="vehicle params file or name (overrides vehicle)")
    parser.add_argument("--rows", type=int, default=None, help="import only the first N rows of every file")
    args = parser.parse_args(argv)
    try:
        result = import_logs(args.mapping, Path(args.out), base_dir=args.data_dir, vehicle=args.vehicle,
                             max_rows=args.rows)
    except (MappingError, FileExistsError, ValueError) as exc:
        print(f"import failed: {exc}", file=sys.stderr)
        return 2
    for note in result.notes:
        print(f"note: {note}")
    print(f"wrote {result.bag} ({result.end - result.start:.1f} s of data)")
    for topic, n in sorted(result.counts.items()):
        print(f"  {topic:32s} {n:8d} messages")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
