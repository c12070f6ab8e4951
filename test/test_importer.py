"""The column-log importer: units, sources, mapping errors, and the Stanford map into a bag."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")

from vehicle_estimation.contract import topics as T  # noqa: E402
from vehicle_estimation.paths import params_file, shared_data_dir  # noqa: E402
from vehicle_estimation.io import importer  # noqa: E402
from vehicle_estimation.io.import_map import MappingError, convert  # noqa: E402
from replay_values import diagnostic_statuses  # noqa: E402
from vehicle_estimation.io.importer import import_logs, load_signals  # noqa: E402
from vehicle_estimation.contract.vehicle import load_vehicle_params  # noqa: E402

STANFORD_DIR = shared_data_dir("stanford_sideslip_2014")


def _read(bag: Path) -> dict[str, list]:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    out: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, log_ns, raw in reader.messages():
            out.setdefault(conn.topic.lstrip("/"), []).append((log_ns, reader.deserialize(raw, conn.msgtype)))
    return out


# --------------------------------------------------------------------- units
@pytest.mark.parametrize("unit,kind,raw,si", [
    ("deg", "angle", 180.0, math.pi),
    ("deg/s", "angular rate", 90.0, math.pi / 2),
    ("rpm", "angular rate", 60.0, 2 * math.pi),
    ("km/h", "velocity", 36.0, 10.0),
    ("mph", "velocity", 1.0, 0.44704),
    ("g", "acceleration", 1.0, 9.80665),
    ("%", "ratio", 50.0, 0.5),
    ("ms", "time", 1500.0, 1.5),
    ("kN", "force", 2.0, 2000.0),
])
def test_unit_conversions(unit, kind, raw, si):
    assert convert(np.array([raw]), unit, kind)[0] == pytest.approx(si)


def test_unknown_unit_names_the_key():
    with pytest.raises(MappingError, match=r"here: unknown unit 'deg/sec' for an angular rate"):
        convert(np.zeros(1), "deg/sec", "angular rate", "here")


# --------------------------------------------------------------------- sources
def _write_per_file(tmp: Path, n: int = 50) -> dict:
    t = 10.0 + 0.01 * np.arange(n)
    np.savetxt(tmp / "t.txt", t)
    np.savetxt(tmp / "gz.txt", np.full(n, 10.0))            # deg/s
    np.savetxt(tmp / "ax.txt", np.full(n, 0.1))             # g
    np.savetxt(tmp / "v.txt", np.full(n, 72.0))             # km/h
    return {
        "version": 1, "data_dir": str(tmp), "vehicle": "sedan_d_class",
        "sources": {"t": {"file": "t.txt"}, "gz": {"file": "gz.txt"}, "ax": {"file": "ax.txt"},
                    "v": {"file": "v.txt"}},
        "time": {"source": "t", "unit": "s", "offset": 1.0e9},
        "imu": {"gravity_removed": True},
        "signals": {
            "imu.angular_velocity.z": {"source": "gz", "unit": "deg/s"},
            "imu.linear_acceleration.x": {"source": "ax", "unit": "g"},
            "joint_states.wheel_rl.velocity": {"source": "v", "unit": "km/h"},
            "speed.vx": {"source": "v", "unit": "km/h", "scale": 0.5, "offset": 2.0},
        },
    }


def _write_table(tmp: Path, n: int = 50) -> dict:
    t_ms = 1000.0 * (10.0 + 0.01 * np.arange(n))
    with open(tmp / "log.csv", "w", encoding="utf-8") as handle:
        handle.write("# exported log\n")
        handle.write("time_ms,yaw_dps,ax_g,speed_kmh\n")
        for i in range(n):
            handle.write(f"{t_ms[i]:.1f},10.0,0.1,72.0\n")
    with open(tmp / "gnss.txt", "w", encoding="utf-8") as handle:   # whitespace, no header, own time
        for i in range(5):
            handle.write(f"{10.0 + 0.1 * i:.1f}  37.4  -122.1  30.0\n")
    return {
        "version": 1, "data_dir": str(tmp), "vehicle": "sedan_d_class",
        "sources": {
            "can": {"file": "log.csv", "time": {"column": "time_ms", "unit": "ms", "offset": 1.0e9}},
            "gnss": {"file": "gnss.txt", "time": {"column": 0, "unit": "s", "offset": 1.0e9}},
        },
        "imu": {"gravity_removed": True},
        "signals": {
            "imu.angular_velocity.z": {"source": "can", "column": "yaw_dps", "unit": "deg/s"},
            "imu.linear_acceleration.x": {"source": "can", "column": "ax_g", "unit": "g"},
            "joint_states.wheel_rl.velocity": {"source": "can", "column": "speed_kmh", "unit": "km/h"},
            "speed.vx": {"source": "can", "column": 3, "unit": "km/h", "scale": 0.5, "offset": 2.0},
            "gnss.latitude": {"source": "gnss", "column": 1, "unit": "deg"},
            "gnss.longitude": {"source": "gnss", "column": 2, "unit": "deg"},
            "gnss.altitude": {"source": "gnss", "column": 3, "unit": "m"},
        },
    }


@pytest.mark.parametrize("layout", ["per_file", "table"])
def test_per_file_and_table_sources_give_the_same_messages(tmp_path, layout):
    mapping = (_write_per_file if layout == "per_file" else _write_table)(tmp_path)
    result = import_logs(mapping, tmp_path / "bag")
    msgs = _read(tmp_path / "bag")
    radius = load_vehicle_params(params_file("sedan_d_class")).wheel_radius
    imu = [m for _, m in msgs[T.IMU]]
    assert len(imu) == 50
    assert imu[0].angular_velocity.z == pytest.approx(math.radians(10.0))
    assert imu[0].linear_acceleration.x == pytest.approx(0.1 * 9.80665)
    assert imu[0].linear_acceleration.z == pytest.approx(9.80665)       # gravity added (REP-145)
    assert imu[0].angular_velocity.x == 0.0
    log_ns, first = msgs[T.IMU][0]
    assert first.header.stamp.sec == 1_000_000_010 and first.header.stamp.nanosec == 0
    assert log_ns == 1_000_000_010 * 10**9
    assert imu[1].header.stamp.nanosec == 10_000_000                   # exact 10 ms steps
    joints = [m for _, m in msgs[T.JOINT_STATES]]
    assert list(joints[0].name) == ["wheel_rl"]                         # only what the log has
    assert joints[0].velocity[0] == pytest.approx(20.0 / radius)        # 72 km/h / R
    assert math.isnan(joints[0].position[0]) and math.isnan(joints[0].effort[0])
    speed = [m for _, m in msgs[T.SPEED]]
    assert speed[0].twist.twist.linear.x == pytest.approx((72.0 * 0.5 + 2.0) / 3.6)  # scale/offset before unit
    assert T.POWERTRAIN not in msgs                                      # missing signals are absent
    if layout == "table":
        fixes = [m for _, m in msgs[T.GNSS]]
        assert len(fixes) == 5 and fixes[0].latitude == pytest.approx(37.4) and fixes[0].status.status == 0
    assert result.counts[T.IMU] == 50


def test_road_wheel_angle_and_kinematic_wheel_speeds(tmp_path):
    n = 20
    np.savetxt(tmp_path / "cols.txt", np.column_stack([np.arange(n) * 0.01 + 1.0, np.full(n, 0.05),
                                                        np.full(n, 0.2), np.full(n, 20.0)]))
    mapping = {
        "version": 1, "data_dir": str(tmp_path), "vehicle": "sedan_d_class",
        "sources": {"log": {"file": "cols.txt", "time": {"column": 0, "unit": "s"}}},
        "signals": {
            "joint_states.steering_wheel.position": {"column": 1, "unit": "rad", "road_wheel_angle": True},
            "imu.angular_velocity.z": {"column": 2, "unit": "rad/s"},
        },
        "wheel_speeds_from_speed": {"column": 3, "unit": "m/s", "kinematic": True},
    }
    signals, notes = load_signals(mapping)
    vp = load_vehicle_params(params_file("sedan_d_class"))
    assert signals["joint_states.steering_wheel.position"].values[0] == pytest.approx(0.05 * vp.steering_ratio)
    rl = signals["joint_states.wheel_rl.velocity"].values[0] * vp.wheel_radius
    rr = signals["joint_states.wheel_rr.velocity"].values[0] * vp.wheel_radius
    fl = signals["joint_states.wheel_fl.velocity"].values[0] * vp.wheel_radius
    assert rl == pytest.approx(20.0 - 0.5 * vp.track_rear * 0.2)
    assert rr == pytest.approx(20.0 + 0.5 * vp.track_rear * 0.2)
    assert fl == pytest.approx((20.0 - 0.5 * vp.track_front * 0.2) * math.cos(0.05) + vp.lf * 0.2 * math.sin(0.05))
    assert notes
    # the node's own model gives the same forward wheel-centre speeds for vy = 0
    from vehicle_estimation.estimators.state.vehicle_model import wheel_forward_speeds
    vt = wheel_forward_speeds(np.array([20.0, 0.0, 0.2, 0.0, 0.0]), 0.05, vp)
    assert [fl, rl, rr] == pytest.approx([vt[0], vt[2], vt[3]])


# --------------------------------------------------------------------- bad mappings
@pytest.mark.parametrize("edit,key", [
    (lambda m: m["signals"]["imu.angular_velocity.z"].update(unit="deg/sec"), r"signals\.imu\.angular_velocity\.z\.unit"),
    (lambda m: m["signals"].update({"imu.angular_velocity.q": {"source": "gz", "unit": "rad/s"}}),
     r"signals\.imu\.angular_velocity\.q: unknown signal"),
    (lambda m: m["signals"]["speed.vx"].update(source="nope"), r"signals\.speed\.vx\.source: no source 'nope'"),
    (lambda m: m["signals"]["speed.vx"].pop("unit"), r"signals\.speed\.vx\.unit: required"),
    (lambda m: m["signals"]["speed.vx"].update(scale="x"), r"signals\.speed\.vx\.scale: must be a finite number"),
    (lambda m: m["sources"]["gz"].update(fille="x"), r"sources\.gz\.fille: unknown key \(did you mean 'file'\?\)"),
    (lambda m: m["time"].update(unit="sec"), r"time\.unit: unknown unit 'sec'"),
    (lambda m: m.update(tiem=1), r"tiem: unknown key"),
    (lambda m: m.pop("vehicle"), r"vehicle: required by"),
    (lambda m: m["imu"].update(gravity_removed="yes"), r"imu\.gravity_removed"),
    (lambda m: m["sources"]["gz"].update(file="missing.txt"), r"sources\.gz\.file: no such file"),
    (lambda m: m["signals"]["imu.angular_velocity.z"].update(column="yaw"),
     r"signals\.imu\.angular_velocity\.z\.column: the source has no header row"),
    (lambda m: m["time"].update(offset=-100.0), r"time\.offset: stamps must be positive"),
])
def test_bad_mapping_names_the_key(tmp_path, edit, key):
    mapping = _write_per_file(tmp_path)
    edit(mapping)
    with pytest.raises(MappingError, match=key):
        import_logs(mapping, None)


def test_cli_reports_a_bad_mapping(tmp_path, capsys):
    mapping = _write_per_file(tmp_path)
    mapping["signals"]["imu.angular_velocity.z"]["unit"] = "deg/sec"
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(mapping), encoding="utf-8")
    assert importer.main([str(path), "--out", str(tmp_path / "bag")]) == 2
    assert "signals.imu.angular_velocity.z.unit" in capsys.readouterr().err
    assert not (tmp_path / "bag").exists()


# --------------------------------------------------------------------- the Stanford map
@pytest.mark.skipif(not (STANFORD_DIR / "t.txt").is_file(), reason="Stanford data not available")
def test_stanford_map_imports_into_a_bag_the_report_reads(tmp_path):
    from vehicle_estimation.evaluation import report
    bag = tmp_path / "stanford"
    result = import_logs("stanford_sideslip_2014", bag, base_dir=STANFORD_DIR, max_rows=300)
    assert result.counts == {T.IMU: 300, T.JOINT_STATES: 300, T.GT_VEHICLE_STATE: 300, T.GT_SIDESLIP: 300}
    data = report.read_bag(bag, [T.GT_VEHICLE_STATE, T.GT_SIDESLIP])
    raw = {name: np.loadtxt(STANFORD_DIR / f"{name}.txt", max_rows=300)
           for name in ("t", "vx", "vy", "beta_true", "yawRateFilt", "yawRate", "delta")}
    state = data[T.GT_VEHICLE_STATE]
    np.testing.assert_allclose(state["t"], raw["t"] + 1393027200.0, atol=1e-6)
    np.testing.assert_allclose(state["vx"], raw["vx"])
    np.testing.assert_allclose(state["vy"], raw["vy"])
    np.testing.assert_allclose(state["yaw_rate"], np.radians(raw["yawRateFilt"]))   # deg/s in the file
    np.testing.assert_allclose(data[T.GT_SIDESLIP]["value"], raw["beta_true"])
    msgs = _read(bag)
    imu = msgs[T.IMU][0][1]
    assert imu.angular_velocity.z == pytest.approx(raw["yawRate"][0])
    assert imu.linear_acceleration.z == pytest.approx(9.80665)
    joints = msgs[T.JOINT_STATES][0][1]
    ratio = load_vehicle_params(params_file("stanford_2014")).steering_ratio
    assert list(joints.name) == ["steering_wheel"]
    assert joints.position[0] == pytest.approx(raw["delta"][0] * ratio)
    # the report's groups find the truth (no estimates in an input bag: "no data", no crash)
    groups, _ = report.compute_groups(data)
    assert groups["vehicle_state"]["status"] == "no data"


def test_stanford_vehicle_params_load():
    vp = load_vehicle_params(params_file("stanford_2014"))
    assert vp.mass == 982.0 and vp.lf == 1.33 and vp.lr == 1.07
    assert vp.yaw_inertia == pytest.approx(982.0 / 12.0 * (1.7 ** 2 + 4.09 ** 2), rel=1e-4)
    assert 2 * vp.cornering_stiffness_front == 0.7e5 and 2 * vp.cornering_stiffness_rear == 1.2e5


def test_baseline_kf_tracks_a_linear_single_track_model():
    """The baseline recovers beta of data generated by its own model (no noise)."""
    from vehicle_estimation.validation.baselines import baseline_linear_kf
    m, lf, lr, iz, cf, cr = 982.0, 1.33, 1.07, 1605.0, 7e4, 1.2e5
    n, dt, v = 3000, 0.01, 25.0
    t = np.arange(n) * dt
    rng = np.random.default_rng(1)
    delta = 0.03 * np.sin(0.5 * t) + 1e-4 * rng.standard_normal(n)
    beta, r = np.zeros(n), np.zeros(n)
    for i in range(1, n):
        b, w = beta[i - 1], r[i - 1]
        beta[i] = b + dt * (-(cf + cr) / (m * v) * b - (1 + (lf * cf - lr * cr) / (m * v * v)) * w + cf / (m * v) * delta[i - 1])
        r[i] = w + dt * (-(lf * cf - lr * cr) / iz * b - (lf * lf * cf + lr * lr * cr) / (iz * v) * w + lf * cf / iz * delta[i - 1])
    ay = -(cf + cr) / m * beta - (lf * cf - lr * cr) / (m * v) * r + cf / m * delta
    ay += 0.05 * rng.standard_normal(n)
    est_beta, est_r = baseline_linear_kf(t, ay, r, delta, np.full(n, v), m=m, lf=lf, lr=lr, iz=iz, cf=cf, cr=cr)
    assert np.sqrt(np.mean((est_beta[500:] - beta[500:]) ** 2)) < math.radians(0.05)


@pytest.mark.skipif(not (STANFORD_DIR / "t.txt").is_file(), reason="Stanford data not available")
@pytest.mark.dds
def test_stanford_command_smoke(tmp_path, capfd):
    """`vehicle-estimation stanford` on the first 8 s: import, replay (ckf, assumed speed),
    baseline, table, JSON and PNG."""
    pytest.importorskip("rclpy")
    import json
    from vehicle_estimation import cli
    out = tmp_path / "stanford"
    # a user's layer (--params) reaches every replay: here one that only doubles /diagnostics
    layer = tmp_path / "diagnostics_twice.yaml"
    layer.write_text("/**:\n  ros__parameters:\n    diagnostics_period_s: 0.5\n", encoding="utf-8")
    code = cli.main(["stanford", "--out", str(out), "--rows", "800", "--filters", "ckf", "--speed", "ref",
                     "--warmup", "2", "--params", str(layer), "--quiet"])
    assert code == 0
    result = json.loads((out / "comparison.json").read_text(encoding="utf-8"))
    assert result["layers"] == [str(layer)]
    statuses = diagnostic_statuses(out / "runs" / "ckf_ref" / "estimates", "vehicle_state")
    assert len(statuses) > 1.5 * 8.0, len(statuses)     # 8 s of drive at 2 Hz
    names = [row["filter"] for row in result["rows"]]
    assert names == ["baseline", "ckf"]
    ckf = result["rows"][1]
    assert ckf["lossless"] and ckf["metrics"]["sideslip"]["n"] > 500
    assert ckf["metrics"]["sideslip"]["rmse"] < 2.0          # deg
    assert ckf["metrics"]["vx"]["rmse"] < 1.0                # m/s, from the synthesised wheel speeds
    # every published state variance is checked against the reference (issue 17)
    assert set(ckf["consistency"]) == {"sideslip", "vy", "yaw_rate"}
    assert all(c["n"] > 500 and 0.0 <= c["within_2sigma"] <= 1.0 for c in ckf["consistency"].values())
    # the table says how much of the flagged sideslip lies beyond 3 sigma (issue 17: at most 1 %)
    beyond = ckf["consistency"]["sideslip"]["converged_beyond_3sigma"]
    row = [line for line in capfd.readouterr().out.splitlines() if line.startswith("ckf / ASSUMED")][-1]
    assert row.rstrip().endswith(f"% / {100 * beyond:.1f} %"), row
    assert (out / "comparison.png").is_file()


@pytest.mark.skipif(not (STANFORD_DIR / "t.txt").is_file(), reason="Stanford data not available")
@pytest.mark.dds
def test_stanford_command_with_a_wheel_dropout(tmp_path, capfd):
    """`--wheel-dropout 2:4` on the first 8 s with the AO-UKF: the wheel speeds are NaN for
    2 s, the node runs the no-speed filter from 3 to 5 s and the AO-UKF again by the end, and
    the errors over the stretch are in the JSON and the table."""
    pytest.importorskip("rclpy")
    import json
    from vehicle_estimation import cli
    out = tmp_path / "stanford"
    code = cli.main(["stanford", "--out", str(out), "--rows", "800", "--filters", "aoukf", "--speed", "ref",
                     "--warmup", "1", "--wheel-dropout", "2:4", "--quiet"])
    assert code == 0
    result = json.loads((out / "comparison.json").read_text(encoding="utf-8"))
    assert result["wheel_dropout_s"] == [2.0, 4.0]
    aoukf = result["rows"][1]
    assert aoukf["dropout_metrics"]["sideslip"]["n"] > 150
    assert aoukf["final_diagnostics"]["filter"] == "aoukf"
    assert "a speed for 1 s: filter 'aoukf' runs again" in aoukf["final_diagnostics"]["last event"]
    assert aoukf["metrics"]["vy"]["max_abs_error"] < 1.0
    assert any(line.startswith("aoukf / ASSUMED") and "wheel dropout 2-4 s: beta RMSE" in line
               for line in capfd.readouterr().out.splitlines())
