"""The textbook baselines of ``validate`` on synthetic arrays, and the command end to end."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from replay_values import diagnostic_statuses
from vehicle_estimation.paths import params_file
from vehicle_estimation.validation import baselines
from vehicle_estimation.contract.vehicle import load_vehicle_params

# a live ROS graph: runs alone (test/dds_serial.py)
pytestmark = pytest.mark.dds

VEHICLE = load_vehicle_params(params_file("sedan_d_class"))
G = VEHICLE.gravity


def _hill_drive(seed: int = 0, duration: float = 300.0):
    """Exact longitudinal signals of a drive over hills: speed, f_x, drive force, grade."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 0.01)
    grade = 0.05 * np.sin(2 * np.pi * t / 90.0) + 0.02 * np.sin(2 * np.pi * t / 37.0)
    v = 15.0 + 5.0 * np.sin(2 * np.pi * t / 60.0)
    a = np.gradient(v, t)
    fx = a + G * np.sin(grade)
    p = VEHICLE
    force = ((p.mass + p.wheel_inertia / p.wheel_radius ** 2) * a
             + p.mass * G * (np.sin(grade) + p.rolling_resistance * np.cos(grade))
             + 0.5 * p.air_density * p.drag_area * v ** 2)
    return t, v, fx + 0.05 * rng.standard_normal(t.size), force, grade


def test_kinematic_grade_recovers_a_hill_profile():
    t, v, fx, _, grade = _hill_drive()
    tk, gk = baselines.kinematic_grade(t, fx, t, v, gravity=G)
    sel = tk > 20.0
    err = gk[sel] - np.interp(tk[sel], t, grade)
    # Causal: a lag of a few tenths of a second on a grade that changes over tens of seconds.
    assert math.degrees(np.sqrt(np.mean(err ** 2))) < 0.2
    # ... and it is not trivially right: with the speed derivative ignored it is far off.
    tk0, gk0 = baselines.kinematic_grade(t, fx, t, np.full_like(v, 15.0), gravity=G)
    err0 = gk0[tk0 > 20.0] - np.interp(tk0[tk0 > 20.0], t, grade)
    assert math.degrees(np.sqrt(np.mean(err0 ** 2))) > 1.0


def test_batch_ls_mass_is_exact_on_exact_data_and_biased_by_a_wrong_grade():
    t, v, _, force, grade = _hill_drive()
    est = baselines.batch_ls_mass(t, force, t, v, t, grade, VEHICLE)
    assert est["samples"] > 1000
    assert est["mass"] == pytest.approx(VEHICLE.mass, rel=0.005)
    level = baselines.batch_ls_mass(t, force, t, v, t, np.zeros_like(grade), VEHICLE)
    assert abs(level["mass"] / VEHICLE.mass - 1.0) > 0.05      # the grade matters
    none = baselines.batch_ls_mass(t, np.full_like(force, np.nan), t, v, t, grade, VEHICLE)
    assert math.isnan(none["mass"]) and none["samples"] == 0


def test_kinematic_roll_reads_the_gravity_across_a_rolled_car_in_a_turn():
    """A car turning steadily (v r = 4 m/s^2) rolled 3 deg: the baseline takes the centripetal
    part out; without the yaw rate it would read the turn as ~24 deg of roll."""
    t = np.arange(0.0, 60.0, 0.01)
    v, r, roll = np.full_like(t, 20.0), np.full_like(t, 0.2), np.radians(3.0) * np.minimum(t / 10.0, 1.0)
    fy = v * r + G * np.sin(roll)
    tk, phi = baselines.kinematic_roll(t, fy, r, t, v, gravity=G)
    sel = tk > 30.0
    assert np.degrees(np.max(np.abs(phi[sel] - np.interp(tk[sel], t, roll)))) < 0.05
    _, phi0 = baselines.kinematic_roll(t, fy, np.zeros_like(r), t, v, gravity=G)
    assert np.degrees(phi0[-1]) > 20.0


def test_gnss_course_is_the_direction_of_the_fixes_and_waits_for_distance():
    t = np.arange(0.0, 20.0, 0.1)
    heading = math.radians(30.0)
    speed = np.where(t < 5.0, 0.0, 10.0)                   # standing for 5 s, then 10 m/s
    dist = np.cumsum(speed) * 0.1
    east, north = dist * math.cos(heading), dist * math.sin(heading)
    tc, course = baselines.gnss_course(t, east, north)
    assert tc.size and tc[0] > 5.0                          # nothing from the fixes of a standing car
    np.testing.assert_allclose(course, heading, atol=1e-9)


def test_validate_command_end_to_end(tmp_path):
    """A CommonRoad lane change (lateral) and our short hilly drive (longitudinal) through the
    nodes: every row has our figures, the baseline's and the ratio; plots and JSON written."""
    out = tmp_path / "validate"
    # a user's layer (--params) reaches every node of every case: here one that only doubles
    # the /diagnostics rate, so every figure below is the shipped params' own
    layer = tmp_path / "diagnostics_twice.yaml"
    layer.write_text("/**:\n  ros__parameters:\n    diagnostics_period_s: 0.5\n", encoding="utf-8")
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "validate", "--quick", "--cases",
                           "commonroad,sim", "--out", str(out), "--params", str(layer), "--quiet"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads((out / "validation.json").read_text())
    assert all(c["lossless"] for c in result["cases"])
    assert result["layers"] == [str(layer)] and f"then {layer} in every case" in proc.stdout
    assert all(c["params"] == ["estimation", str(layer)] for c in result["cases"]), result["cases"]
    duration = 14.0     # the quick lane change
    assert len(diagnostic_statuses(out / "runs" / "commonroad_dlc" / "estimates", "vehicle_state")) > 1.5 * duration
    rows = {(r["case"], r["quantity"]): r for r in result["rows"]}
    for key in (("commonroad_dlc", "sideslip"), ("commonroad_dlc", "vy"), ("sim_hills", "slope"),
                ("sim_hills", "mass (last half)")):
        assert key in rows, sorted(rows)
        row = rows[key]
        assert math.isfinite(row["ours"]["rmse"]) and math.isfinite(row["base"]["rmse"]), row
        assert row["ratio"] == pytest.approx(row["ours"]["rmse"] / row["base"]["rmse"])
    assert rows[("sim_hills", "slope")]["independent"] is False
    # the fusion's and the state's motion outputs against the raw sensors
    motion = {(r["case"], r["quantity"]): r for r in result["motion"]}
    for key in (("commonroad_dlc", "speed"), ("commonroad_dlc", "pitch"), ("commonroad_dlc", "roll"),
                ("commonroad_dlc", "heading"), ("commonroad_dlc", "vx"), ("commonroad_dlc", "yaw rate"),
                ("sim_hills", "speed"), ("sim_hills", "pitch"), ("sim_hills", "yaw rate")):
        assert key in motion, sorted(motion)
        row = motion[key]
        assert math.isfinite(row["ours"]["rmse"]) and math.isfinite(row["base"]["rmse"]), row
    assert motion[("commonroad_dlc", "heading")]["ours"]["rmse"] < 5.0     # degrees, wrapped
    assert motion[("commonroad_dlc", "speed")]["ours"]["rmse"] < 0.5
    assert rows[("commonroad_dlc", "sideslip")]["ours"]["rmse"] < 1.0      # degrees: no divergence
    text = (out / "validation.md").read_text()
    assert "| commonroad_dlc | sideslip [deg]" in text
    # every estimate with a published variance is checked against its own sigma
    honesty = {(r["case"], r["quantity"]): r for r in result["consistency"]}
    for key in (("commonroad_dlc", "sideslip"), ("sim_hills", "slope"), ("sim_hills", "mass")):
        assert honesty[key]["n"] > 0 and math.isfinite(honesty[key]["nees"]), honesty.get(key)
    assert "| sim_hills (ours) | slope |" in text and "converged NEES" in text
    # the grade's variance carries the accelerometer bias the fusion cannot yet tell from the
    # pitch (Table 2's calibrated-IMU prior, on this short DLC: 80 % within 2 sigma, 9 % beyond
    # 3 sigma, NEES 4.2; the MEMS prior of the shipped params: 92 %, 4 %)
    slope = honesty[("commonroad_dlc", "slope")]
    assert slope["converged_within_2sigma"] >= 0.9 and slope["converged_beyond_3sigma"] <= 0.05, slope
    assert (out / "commonroad_dlc.png").stat().st_size > 10_000
    assert (out / "sim_hills.png").stat().st_size > 10_000
    # a second run into the same folder stops with a clear message, not a traceback
    again = subprocess.run([sys.executable, "-m", "vehicle_estimation", "validate", "--quick", "--cases",
                            "sim", "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 2 and "Traceback" not in again.stderr, again.stderr
    assert "exists" in again.stderr and "choose another --out" in again.stderr


def test_a_params_layer_sits_over_the_shipped_params_and_under_each_case_layer(tmp_path, monkeypatch):
    """``validate --params``: every case's nodes read estimation.yaml, then the user's layers in
    order, then the case's own layer (a method case's method), which therefore still decides
    what the case's row names; a layer that does not exist stops the run before anything is made."""
    from vehicle_estimation.launcher import replay as replay_module
    from vehicle_estimation.validation import validate

    plain = validate.Case("cr", "s", tmp_path / "cr", params_file("commonroad_bmw320i"), ("lateral",))
    method_layer = tmp_path / "method.yaml"
    method_layer.write_text("vehicle_state:\n  ros__parameters:\n    filter: ckf\n", encoding="utf-8")
    method = validate.Case("cr_ckf", "s", tmp_path / "cr", params_file("commonroad_bmw320i"), ("lateral",),
                           params=("estimation", str(method_layer)), node="vehicle_state")
    mine = [tmp_path / "a.yaml", tmp_path / "b.yaml"]
    for path, rate in zip(mine, (20.0, 25.0)):
        path.write_text(f"vehicle_state:\n  ros__parameters:\n    publish_rate_hz: {rate}\n", encoding="utf-8")
    seen = []

    def node_group(files, overrides, log_dir):
        seen.append([Path(f) for f in files])
        raise replay_module.ReplayError("stopped by the test")

    def replay(bag, estimates, make_nodes, progress=True):
        make_nodes({})

    monkeypatch.setattr(replay_module, "replay", replay)
    for n, case in enumerate((plain, method)):
        monkeypatch.setitem(validate.CASE_BUILDERS, "one", lambda root, quick, case=case: [case])
        with pytest.raises(RuntimeError, match="stopped by the test"):
            validate.run(tmp_path / f"out{n}", node_group, cases=["one"], progress=False,
                         params=[str(p) for p in mine])
    vehicle, shipped = params_file("commonroad_bmw320i"), params_file("estimation")
    assert seen == [[vehicle, shipped, *mine], [vehicle, shipped, *mine, method_layer]]
    assert validate._shipped_methods(tuple(map(str, seen[1][1:])))["vehicle_state"] == "ckf"
    with pytest.raises(FileNotFoundError, match="nowhere.yaml"):
        validate.run(tmp_path / "out2", node_group, cases=["one"], progress=False, params=["nowhere.yaml"])
    assert not (tmp_path / "out2").exists()


def test_validate_with_a_refused_layer_stops_naming_the_parameter(tmp_path):
    """A layer that a node refuses stops the run at the first case's start-up: exit 1 and one
    line that quotes the node's reason (its log's last line), no traceback."""
    layer = tmp_path / "bad.yaml"
    layer.write_text("vehicle_state:\n  ros__parameters:\n    filter_rate_hz: -5.0\n", encoding="utf-8")
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "validate", "--quick", "--cases", "commonroad",
                           "--out", str(tmp_path / "out"), "--params", str(layer), "--quiet"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    line = next(x for x in proc.stderr.splitlines() if x.startswith("validate: "))
    assert "replay of commonroad_dlc failed" in line and "vehicle_state (exit 2: " in line
    assert "'filter_rate_hz'" in line and "out of range" in line


@pytest.mark.parametrize(("cases", "used"), [("commonroad", "bags"), ("fastsim", "runs"), ("sim", "runs"),
                                             ("commonroad,fastsim,sim", "bags")])
def test_validate_into_a_used_out_stops_with_a_message(tmp_path, used, cases):
    """Whatever the case kind, an --out that holds an earlier run's bags/ or runs/ is refused
    before anything is generated: exit 2, one line that says what to do, no traceback."""
    out = tmp_path / "validate"
    (out / used).mkdir(parents=True)
    proc = subprocess.run([sys.executable, "-m", "vehicle_estimation", "validate", "--quick", "--cases", cases,
                           "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert f"{out / used} exists" in proc.stderr and "choose another --out" in proc.stderr
    assert sorted(p.name for p in out.iterdir()) == [used]     # nothing generated


def test_turned_imu_cases_give_the_replay_only_the_nominal_mounting(tmp_path, monkeypatch):
    """The FASTSim drive with and without GNSS and CommonRoad's manoeuvres (the lateral path),
    made with the IMU turned by TURNED_IMU_RPY_DEG; each replay gets a layer with the nominal
    mounting only (facing left), so the fusion has the rest to learn."""
    from vehicle_estimation.contract.vehicle import read_ros_params_file
    from vehicle_estimation.validation import commonroad, fastsim_drive, validate

    calls = []
    monkeypatch.setattr(fastsim_drive, "generate", lambda folder, **kw: calls.append(kw) or [
        folder / name for name in fastsim_drive.VARIANTS])
    monkeypatch.setattr(commonroad, "generate", lambda folder, **kw: calls.append(kw) or [
        folder / f"commonroad_{m}" for m in kw["manoeuvres"]])
    cases = validate._turned_imu_cases(tmp_path, quick=True)
    assert calls == [{"duration": 120.0, "imu_rpy_deg": validate.TURNED_IMU_RPY_DEG, "seed": 0},
                     {"manoeuvres": ["dlc"], "duration": 14.0, "imu_rpy_deg": validate.TURNED_IMU_RPY_DEG}]
    assert [c.name for c in cases] == ["fastsim_hills_imu_facing_left", "fastsim_hills_no_gnss_imu_facing_left",
                                       "commonroad_dlc_imu_facing_left"]
    assert [c.kinds for c in cases] == [("longitudinal",)] * 2 + [("lateral",)]
    layer = Path(cases[0].params[1])
    assert cases[0].params == cases[1].params == cases[2].params == ("estimation", str(layer))
    nominal = read_ros_params_file(layer)["vehicle.imu_mounting_rpy"]
    np.testing.assert_allclose(nominal, np.radians(validate.TURNED_IMU_NOMINAL_DEG), rtol=0, atol=1e-15)


def test_commonroad_cases_include_each_clean_drive_without_gnss_and_wheel_speeds(tmp_path, monkeypatch):
    """The lateral drives also run on the fallbacks: each clean manoeuvre again without
    ``gnss/fix`` and the wheel joints, every other topic and joint (steering, CAN speed, IMU,
    truth) as in the drive."""
    from rosbags.highlevel import AnyReader

    from vehicle_estimation.contract import topics as T
    from vehicle_estimation.validation import commonroad, validate

    generate = commonroad.generate
    monkeypatch.setattr(commonroad, "generate", lambda folder, **kw: generate(folder, **{**kw, "duration": 3.0}))
    cases = {c.name: c for c in validate._commonroad_cases(tmp_path, quick=False)}
    assert set(cases) == {f"commonroad_{m}{s}" for m in commonroad.MANOEUVRES
                          for s in ("", "_vib4", "_no_gnss_no_wheels")}

    def contents(bag):
        with AnyReader([bag]) as reader:
            counts = {c.topic.lstrip("/"): c.msgcount for c in reader.connections}
            conn = next(c for c in reader.connections if c.topic.lstrip("/") == T.JOINT_STATES)
            _, _, raw = next(reader.messages(connections=[conn]))
            return counts, set(reader.deserialize(raw, conn.msgtype).name)

    for m in commonroad.MANOEUVRES:
        full, full_joints = contents(cases[f"commonroad_{m}"].bag)
        fallback, joints = contents(cases[f"commonroad_{m}_no_gnss_no_wheels"].bag)
        assert T.GNSS in full and set(T.WHEEL_JOINTS) <= full_joints
        assert fallback == {k: v for k, v in full.items() if k != T.GNSS}
        assert joints == full_joints - set(T.WHEEL_JOINTS) and joints
    assert not any("no_gnss" in c.name for c in validate._commonroad_cases(tmp_path / "q", quick=True))


def test_a_case_names_its_methods_from_its_own_parameter_layers():
    """The truck cases run twice, the second with the heavy-truck layer: each row must name the
    method that ran, the last layer that sets it winning."""
    from vehicle_estimation.validation.validate import Case, _shipped_methods

    shipped = _shipped_methods()
    layered = _shipped_methods(("estimation", "heavy_truck_ta_aekf"))
    assert shipped["mass"] != "ta_aekf" and layered["mass"] == "ta_aekf"
    assert layered["road_slope"] == shipped["road_slope"] and layered["vehicle_state"] == shipped["vehicle_state"]
    assert Case("x", "s", params_file("estimation"), params_file("estimation"), ("longitudinal",)).params == \
        ("estimation",)


def test_method_cases_select_each_other_method_by_one_layer(tmp_path, monkeypatch):
    """The ``methods`` group: one case per drive and per method a node offers besides the
    shipped one, its last layer selecting that method (and nothing else), named after both."""
    from vehicle_estimation.estimators import registry
    from vehicle_estimation.validation import validate

    lateral = validate.Case("cr", "s", tmp_path / "cr", params_file("commonroad_bmw320i"), ("lateral",))
    longitudinal = [validate.Case(name, "s", tmp_path / name, params_file("sedan_d_class"), ("longitudinal",))
                    for name in ("fastsim_hills", "fastsim_hills_no_gnss", "fastsim_hills_no_gnss_no_wheels")]
    monkeypatch.setattr(validate, "_commonroad_cases", lambda root, quick: [lateral])
    monkeypatch.setattr(validate, "_fastsim_cases", lambda root, quick: longitudinal)
    cases = {c.name: c for c in validate._method_cases(tmp_path, quick=False)}
    shipped = validate._shipped_methods()
    expected = {f"cr_{f}": "vehicle_state" for f in registry.STATE_FILTERS if f != shipped["vehicle_state"]}
    for drive in ("fastsim_hills", "fastsim_hills_no_gnss"):
        expected.update({f"{drive}_{m}": "road_slope" for m in registry.SLOPE_METHODS if m != shipped["road_slope"]})
        expected.update({f"{drive}_{m}": "mass" for m in registry.MASS_METHODS if m != shipped["mass"]})
    assert {name: c.node for name, c in cases.items()} == expected
    for name, case in cases.items():
        method = next(m for m in (*registry.STATE_FILTERS, *registry.SLOPE_METHODS, *registry.MASS_METHODS)
                      if name.endswith("_" + m))
        ran = validate._shipped_methods(case.params)
        assert ran[case.node] == method
        assert {k: v for k, v in ran.items() if k != case.node} == \
            {k: v for k, v in shipped.items() if k != case.node}
    quick = validate._method_cases(tmp_path, quick=True)
    assert {c.name for c in quick if c.node != "vehicle_state"} == \
        {n for n in expected if n.startswith("fastsim_hills_") and "no_gnss" not in n}


def test_a_method_case_runs_through_the_nodes_and_scores_its_own_node(tmp_path, monkeypatch):
    """Another state filter through the nodes on the quick CommonRoad lane change: its rows name
    the filter that ran, beside the same baseline, and only the state's rows are scored (the
    fusion, slope and mass ran as in the shipped case)."""
    from vehicle_estimation.launcher.options import node_group_factory
    from vehicle_estimation.validation import validate

    monkeypatch.setattr(validate, "_fastsim_cases", lambda root, quick: [])
    monkeypatch.setattr(validate, "METHOD_DRIVES", {"vehicle_state": ("filter", "commonroad")})
    result = validate.run(tmp_path / "out", node_group_factory("/"), cases=["methods"], quick=True,
                          progress=False)
    shipped = validate._shipped_methods()["vehicle_state"]
    ran = {c["case"] for c in result["cases"]}
    assert ran == {f"commonroad_dlc_{f}" for f in ("ckf", "vbackf", "aoukf") if f != shipped}
    assert all(c["lossless"] for c in result["cases"])
    for row in result["rows"]:
        method = row["case"].rsplit("_", 1)[-1]
        assert row["estimator"] == f"vehicle_state ({method})", row
        assert row["baseline"] == "linear single-track KF"
        assert math.isfinite(row["ours"]["rmse"]) and row["ratio"] == pytest.approx(
            row["ours"]["rmse"] / row["base"]["rmse"])
        assert row["ours"]["rmse"] < (1.0 if row["quantity"] == "sideslip" else 0.1)     # no divergence
    assert {(r["case"], r["quantity"]) for r in result["rows"]} == {(c, q) for c in ran for q in ("sideslip", "vy")}
    assert {r["quantity"] for r in result["consistency"]} <= {"sideslip", "vx", "vy", "yaw_rate"}
    assert result["motion"] == []
    # the node ran the filter its row names (its /diagnostics, recorded with the estimates)
    for case in ran:
        filters = [status["filter"] for status in diagnostic_statuses(
            tmp_path / "out" / "runs" / case / "estimates", "vehicle_state") if "filter" in status]
        assert filters[0] == case.rsplit("_", 1)[-1]


def test_seed_cases_are_the_car_drive_with_other_draws(tmp_path, monkeypatch):
    from vehicle_estimation.validation import fastsim_drive, validate

    calls = []
    monkeypatch.setattr(fastsim_drive, "generate", lambda folder, **kw: calls.append((folder.name, kw)) or [
        folder / name for name in fastsim_drive.VARIANTS])
    cases = validate._seed_cases(tmp_path, quick=False)
    assert [c for _, c in calls] == [{"duration": None, "imu_rpy_deg": (0.0, 0.0, 0.0), "seed": s}
                                     for s in validate.ENSEMBLE_SEEDS]
    assert len({folder for folder, _ in calls}) == len(validate.ENSEMBLE_SEEDS)      # one folder each
    assert [(c.name, c.ensemble) for c in cases[:2]] == [("fastsim_hills_seed1", "fastsim_hills"),
                                                         ("fastsim_hills_no_gnss_seed1", "fastsim_hills_no_gnss")]
    assert len(cases) == 2 * len(validate.ENSEMBLE_SEEDS)


def test_ensemble_rows_sum_up_the_draws_of_one_drive():
    """Each drive's NEES is one draw of its lasting error: the ensemble's mean NEES and the RMS
    of the drives' errors are what say whether sigma is the error's size."""
    from vehicle_estimation.evaluation.validation_tables import ensemble_rows, format_table

    def consistency(case, nees, within, ensemble="car"):
        return {"case": case, "independent": True, "quantity": "mass", "within_1sigma": within,
                "within_2sigma": within, "within_3sigma": 1.0, "nees": nees, "ensemble": ensemble}

    def row(case, mae):
        return {"case": case, "independent": True, "quantity": "mass (last half)", "unit": "%",
                "estimator": "mass (rls)", "baseline": "batch LS", "ours": {"mae": mae, "rmse": mae},
                "base": {"mae": 0.1, "rmse": 0.1}, "ratio": mae / 0.1}

    result = {"rows": [row("a", 0.1), row("b", 0.2), row("c", 0.3), row("other", 5.0)],
              "consistency": [consistency("a", 0.5, 1.0), consistency("b", 1.0, 0.9), consistency("c", 1.5, 0.8),
                              {**consistency("other", 9.0, 0.1), "ensemble": ""}],
              "warmup_s": 5.0, "methods": {"mass": "rls"}}
    (car,) = ensemble_rows(result)
    assert car["drives"] == 3 and car["nees"] == pytest.approx(1.0) and car["nees_range"] == (0.5, 1.5)
    assert car["mae_rms"] == pytest.approx(math.sqrt((0.01 + 0.04 + 0.09) / 3)) and car["mae_max"] == 0.3
    assert car["within_2sigma"] == pytest.approx(0.9)
    assert "| car | mass | 3 | 0.216 (0.300) % | 90 % | 1.00 (0.50–1.50) |" in format_table(result)
