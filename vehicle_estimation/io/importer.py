"""Import column data (CSV or whitespace text) into a rosbag2 (MCAP) that follows the topic contract.

Usage::

    vehicle-estimation import MAPPING --out BAG [--data-dir DIR] [--vehicle FILE] [--rows N]

``MAPPING`` is a YAML file (a path, or a name in ``params/import_maps/``) that says where
the data is, which column is which signal of the contract, and in which unit. The importer
converts every signal to the contract's units (SI; latitude/longitude in degrees), builds
the messages and writes a new MCAP bag that ``replay`` and ``report`` read like a simulated
one. Bring your own CAN/IMU/GNSS logs by writing such a file; nothing else is needed.

The mapping's format, the signals and their units are :mod:`vehicle_estimation.io.import_map`.

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

from vehicle_estimation.contract import topics as T
from vehicle_estimation.io.import_map import (
    G,
    SIGNALS,
    STEERING_KEY,
    UNITS,
    WHEEL_VELOCITY_KEYS,
    YAW_RATE_KEY,
    MappingError,
    convert,
    mapped_number,
    load_mapping,
    needs_vehicle,
    validate_mapping,
)


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
    if needs_vehicle(mapping) and params is None:
        raise MappingError(f"vehicle: required by {needs_vehicle(mapping)}")

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
        return t + mapped_number(spec.get("offset"), where + ".offset", 0.0)

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
        raw = (raw * mapped_number(spec.get("scale"), where + ".scale", 1.0)
               + mapped_number(spec.get("offset"), where + ".offset", 0.0))
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
                    "(mapping format: see the module docstring of vehicle_estimation.io.import_map).",
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
