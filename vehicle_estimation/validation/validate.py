"""``vehicle-estimation validate``: every estimator against a textbook baseline, through the nodes,
on drives that our simulator did not make.

Each case is a bag in our topic contract, made here from a public source, replayed through the
four node processes with the shipped ``params/estimation.yaml`` and the case's vehicle file.
The recorded estimates are scored against the bag's ground truth, and so is the case's textbook
baseline, computed offline on the same bag in the same run; the table's ``ratio`` is ours /
the baseline's RMSE (below 1: ours is better).

Cases (``--cases``; default: all that can be made here):

* ``commonroad_<manoeuvre>``, ``commonroad_<manoeuvre>_vib4`` and
  ``commonroad_<manoeuvre>_no_gnss_no_wheels``: lane change, slalom and step steer of the
  CommonRoad multi-body BMW 320i (:mod:`.commonroad`), clean, with 4 m/s² of 10-60 Hz IMU
  vibration, and clean without GNSS and wheel speeds (the fallbacks). Lateral: sideslip and vy
  against the linear single-track KF
  (:func:`vehicle_estimation.validation.baselines.baseline_linear_kf`, given the vehicle file's
  cornering stiffnesses and the CAN speed).
* ``fastsim_hills`` and its variants without GNSS and without wheel speeds, when FASTSim is
  installed (:mod:`.fastsim_drive`). Longitudinal: slope against the causal kinematic grade,
  mass against the offline batch least squares over the whole drive (:mod:`.baselines`).
* ``fastsim_truck`` and ``fastsim_truck_no_gnss`` (:mod:`.fastsim_truck`): a 36 t truck
  cruising a gentle long-haul road for 30 minutes in FASTSim, the low-excitation mass case
  (the regressor varies by ~0.07 m/s^2); longitudinal, as the FASTSim car. Each again as
  ``..._ta_aekf`` with ``params/heavy_truck_ta_aekf.yaml`` layered on (paper 000's TA-AEKF).
* ``..._imu_facing_left`` (``turned_imu``): the FASTSim car with and without GNSS and the three
  clean CommonRoad manoeuvres, their IMU turned by :data:`TURNED_IMU_RPY_DEG` and the replay
  given only the nominal mounting :data:`TURNED_IMU_NOMINAL_DEG` (the fusion learns the rest).
* ``..._seed<n>`` (``seeds``): the FASTSim car with and without GNSS, its sensors drawn with
  other seeds (:data:`ENSEMBLE_SEEDS`); ``validation.md`` sums up each drive's consistency
  over the seeds, for a lasting error is one draw per drive.
* ``sim_hills``: *our own* simulator's hilly drive, labelled as such: the filters share its
  model, so it is a reference row, not evidence.
* ``methods``: every method a node offers besides the shipped one (the other state filters on
  the nine CommonRoad drives; the other slope and mass methods on the FASTSim car drive with and
  without GNSS), each as ``<drive>_<method>`` with one parameter layer that selects it, scored
  against the same baselines.

On every case, a second table holds the motion outputs against the raw sensor a user would
otherwise take: the fusion's speed (the CAN speed), pitch (the accelerometer's kinematic tilt),
roll (the accelerometer tilt less v r, where the drive rolls the car) and, with GNSS, heading (the
course of the fixes over 1 s); the vehicle state's vx (the CAN speed) and yaw rate (the raw gyro).

``--params FILE`` (repeatable) layers a tuning over ``estimation.yaml`` in every case, below a
case's own layer, so that a change is scored on the whole set beside the same baselines.

The real Stanford drive has its own command, ``vehicle-estimation stanford`` (the same kind of
table, with its raw and vibration variants, and the same ``--params``).

Output in ``--out`` (default ``out/validate``): ``validation.json`` (every row, the commands'
settings), ``validation.md`` (the table), one plot per case, and the bags and recorded
estimates under ``bags/`` and ``runs/``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from vehicle_estimation.contract import topics as T
from vehicle_estimation.paths import params_file
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.estimators.common.rotations import wrap_angle
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.launcher.options import add_namespace_option, add_tuning_option, node_group_factory
from vehicle_estimation.evaluation.validation_tables import format_table
from vehicle_estimation.validation import baselines

DEFAULT_OUT = Path("out") / "validate"
#: Metrics start after this much of each drive: filters and baselines alike start from nothing.
WARMUP_S = 5.0
#: The mass is scored over the last half of the drive, as every mass figure of this package.
MASS_FROM_FRACTION = 0.5
COMMONROAD_SOURCE = "CommonRoad MB model 3.0.2 (BMW 320i)"


@dataclass
class Case:
    name: str
    source: str                 # who made the data
    bag: Path
    vehicle: Path
    kinds: tuple[str, ...]      # "lateral", "longitudinal"
    independent: bool = True    # False: our own simulator
    notes: list[str] = field(default_factory=list)
    #: Node parameter files layered over the vehicle file, in order (names under params/, or paths).
    params: tuple[str, ...] = ("estimation",)
    #: A method case's node (the one whose method the last layer selects): only its rows are
    #: scored; "": every node's.
    node: str = ""
    #: Cases that are one drive with other noise draws share it: their consistency is also
    #: summed up over the drives (a lasting error is one draw per drive).
    ensemble: str = ""


# ------------------------------------------------------------------------------------ cases
def _commonroad_bags(folder: Path, *, quick: bool, **generate) -> tuple[list[str], list[Path], Path]:
    """CommonRoad's manoeuvres (``--quick``: a short lane change) in ``folder``, made with
    ``generate``'s options (:func:`.commonroad.generate`) unless an earlier group of this run
    made them: (manoeuvres, bags, vehicle file)."""
    from vehicle_estimation.validation import commonroad

    manoeuvres = ["dlc"] if quick else list(commonroad.MANOEUVRES)
    paths = [folder / f"commonroad_{m}" for m in manoeuvres]
    if not all(p.exists() for p in paths):
        paths = commonroad.generate(folder, **generate, manoeuvres=manoeuvres, duration=14.0 if quick else None)
    return manoeuvres, paths, folder / f"{commonroad.VEHICLE_NAME}.yaml"


def _commonroad_cases(root: Path, *, quick: bool) -> list[Case]:
    cases = []
    for vibration, suffix in ((0.0, ""), (4.0, "_vib4")):
        if quick and vibration:
            continue
        manoeuvres, paths, vehicle = _commonroad_bags(root / f"commonroad{suffix}", quick=quick,
                                                      vibration_std=vibration)
        for name, bag in zip(manoeuvres, paths):
            cases.append(Case(f"commonroad_{name}{suffix}", COMMONROAD_SOURCE, bag, vehicle, ("lateral",),
                              notes=[f"IMU vibration {vibration:g} m/s^2 (10-60 Hz)"] if vibration else []))
            if not vibration and not quick:
                cases.append(Case(f"commonroad_{name}_no_gnss_no_wheels", COMMONROAD_SOURCE,
                                  _without_gnss_and_wheels(bag), vehicle, ("lateral",),
                                  notes=["no GNSS, no wheel speeds: the fusion dead-reckons, the state node "
                                         "runs on vehicle/speed"]))
    return cases


def _without_gnss_and_wheels(bag: Path) -> Path:
    """The drive ``bag`` without ``gnss/fix`` and the wheel speeds, beside it (made once)."""
    from vehicle_estimation.io.bagtools import rewrite_bag

    out = bag.with_name(f"{bag.name}_no_gnss_no_wheels")
    if not out.exists():
        rewrite_bag(bag, out, drop_topics=[T.GNSS], drop_joints=T.WHEEL_JOINTS)
    return out


def _fastsim_cases(root: Path, *, quick: bool, folder_name: str = "fastsim",
                  imu_rpy_deg=(0.0, 0.0, 0.0), seed: int = 0) -> list[Case]:
    """The FASTSim car drive's variants in ``root/folder_name``, its IMU at ``imu_rpy_deg`` in
    base_link, its sensors drawn with ``seed`` (:func:`.fastsim_drive.generate`); [] without FASTSim."""
    try:
        from vehicle_estimation.validation import fastsim_drive
    except ImportError:
        return []
    try:
        folder = root / folder_name
        paths = [folder / name for name in fastsim_drive.VARIANTS]
        if not all(p.exists() for p in paths):      # else made by an earlier group of this run
            paths = fastsim_drive.generate(folder, duration=120.0 if quick else None, imu_rpy_deg=imu_rpy_deg,
                                           seed=seed)
    except ImportError as exc:          # the module is there, the library is not
        print(f"[validate] no FASTSim cases: {exc}")
        return []
    vehicle = folder / f"{fastsim_drive.VEHICLE_NAME}.yaml"
    source = f"NREL FASTSim 3.1.0 ({fastsim_drive.VEHICLE_RESOURCE.removesuffix('.yaml')})"
    return [Case(Path(p).name, source, Path(p), vehicle, ("longitudinal",)) for p in paths]


#: The turned-IMU cases' IMU: facing left, 0.5 deg nose-down, 0.3 deg off in yaw (roll, pitch,
#: yaw of imu_link in base_link [deg]), and the nominal mounting the replay is given.
TURNED_IMU_RPY_DEG, TURNED_IMU_NOMINAL_DEG = (0.5, 0.0, 90.3), (0.0, 0.0, 90.0)


def _turned_imu_cases(root: Path, *, quick: bool) -> list[Case]:
    """The FASTSim car drive with and without GNSS and CommonRoad's three manoeuvres, their IMU
    facing left and a little off, and the vehicle file saying only that it faces left: the
    mounting states learn the rest."""
    cases = [c for c in _fastsim_cases(root, quick=quick, folder_name="fastsim_turned_imu",
                                       imu_rpy_deg=TURNED_IMU_RPY_DEG) if c.name in METHOD_FASTSIM_DRIVES]
    _, paths, vehicle = _commonroad_bags(root / "commonroad_turned_imu", quick=quick, imu_rpy_deg=TURNED_IMU_RPY_DEG)
    cases += [Case(p.name, COMMONROAD_SOURCE, p, vehicle, ("lateral",)) for p in paths]
    layer = root / "layers" / "imu_facing_left.yaml"
    layer.parent.mkdir(parents=True, exist_ok=True)
    nominal = ", ".join(repr(math.radians(a)) for a in TURNED_IMU_NOMINAL_DEG)
    layer.write_text(f"/**:\n  ros__parameters:\n    vehicle.imu_mounting_rpy: [{nominal}]\n", encoding="utf-8")
    turned = ", the IMU turned: roll, pitch, yaw " + ", ".join(f"{a:g}" for a in TURNED_IMU_RPY_DEG)
    return [replace(c, name=f"{c.name}_imu_facing_left", source=c.source + turned, params=("estimation", str(layer)))
            for c in cases]


#: The ``seeds`` group's sensor draws of the FASTSim car drive (the ``fastsim`` group's is 0).
ENSEMBLE_SEEDS = tuple(range(1, 7))


def _seed_cases(root: Path, *, quick: bool) -> list[Case]:
    """The FASTSim car drive with and without GNSS, its noise and IMU biases drawn with each of
    :data:`ENSEMBLE_SEEDS` (``--quick``: the first): one drive's mass error is one draw of the
    bias the fusion has not learnt, and only many drives show whether sigma is its size."""
    return [replace(c, name=f"{c.name}_seed{seed}", ensemble=c.name)
            for seed in ENSEMBLE_SEEDS[:1 if quick else None]
            for c in _fastsim_cases(root, quick=quick, folder_name=f"fastsim_seed{seed}", seed=seed)
            if c.name in METHOD_FASTSIM_DRIVES]


def _truck_cases(root: Path, *, quick: bool) -> list[Case]:
    try:
        from vehicle_estimation.validation import fastsim_truck
        paths = fastsim_truck.generate(root / "truck", duration=600.0 if quick else None)
    except ImportError as exc:
        print(f"[validate] no FASTSim truck cases: {exc}")
        return []
    vehicle = root / "truck" / f"{fastsim_truck.VEHICLE_NAME}.yaml"
    source = "NREL FASTSim 3.1.0 (Conv re-parametrised: 36 t class-8 truck, low excitation)"
    # each drive twice: the shipped estimation.yaml, and the heavy-truck layer (paper 000's
    # TA-AEKF, the README's recommendation for trucks), on the same bag
    return [Case(Path(p).name + suffix, source, Path(p), vehicle, ("longitudinal",), params=params)
            for p in paths for suffix, params in (("", ("estimation",)),
                                                  ("_ta_aekf", ("estimation", "heavy_truck_ta_aekf")))]


def _sim_cases(root: Path, *, quick: bool) -> list[Case]:
    from vehicle_estimation.sim import scenario_by_name, simulate, write_bag

    bag = root / "sim" / "sim_hills"
    if not bag.exists():
        bag.parent.mkdir(parents=True, exist_ok=True)
        if quick:   # the first 35 s of the short drive: the mass has updated by then
            from vehicle_estimation.io.bagtools import rewrite_bag
            full = write_bag(simulate(scenario_by_name("short")), root / "sim" / "short_drive")
            rewrite_bag(full, bag, duration_s=35.0)
        else:
            write_bag(simulate(scenario_by_name("default")), bag)   # the demo's drive
    return [Case("sim_hills", "vehicle_estimation.sim (ours: the filters share its model)", bag,
                 params_file("sedan_d_class"), ("longitudinal", "lateral"), independent=False)]


#: The drives that score each node's other methods: the lateral drives for the state filters,
#: the hilly car drive with and without GNSS for the slope and the mass (not the truck's four
#: half hours; ``validate --cases truck`` runs paper 000's TA-AEKF there).
METHOD_DRIVES = {"vehicle_state": ("filter", "commonroad"), "road_slope": ("method", "fastsim"),
                 "mass": ("method", "fastsim")}
METHOD_FASTSIM_DRIVES = ("fastsim_hills", "fastsim_hills_no_gnss")
#: The consistency rows (:func:`consistency_rows`' quantities) of each node's estimates.
NODE_ESTIMATES = {"vehicle_state": ("sideslip", "vx", "vy", "yaw_rate"), "road_slope": ("slope",),
                  "mass": ("mass",)}


def _method_cases(root: Path, *, quick: bool) -> list[Case]:
    """Every method a node offers besides the shipped one, through the nodes on the drives of
    :data:`METHOD_DRIVES`: the shipped params with one layer that selects the method (written to
    ``root/layers``), each case named ``<drive>_<method>``. ``--quick``: the lane change and the
    drive with GNSS."""
    from vehicle_estimation.estimators import registry

    offered = {"vehicle_state": registry.STATE_FILTERS, "road_slope": registry.SLOPE_METHODS,
               "mass": registry.MASS_METHODS}
    fastsim = METHOD_FASTSIM_DRIVES[:1] if quick else METHOD_FASTSIM_DRIVES
    drives = {"commonroad": _commonroad_cases(root, quick=quick),
              "fastsim": [c for c in _fastsim_cases(root, quick=quick) if c.name in fastsim]}
    shipped = _shipped_methods()
    (root / "layers").mkdir(parents=True, exist_ok=True)
    cases = []
    for node, (key, group) in METHOD_DRIVES.items():
        for method in sorted(set(offered[node]) - {shipped[node]}):
            layer = root / "layers" / f"{node}_{method}.yaml"
            layer.write_text(f"{node}:\n  ros__parameters:\n    {key}: {method}\n", encoding="utf-8")
            cases += [replace(c, name=f"{c.name}_{method}", params=(*c.params, str(layer)), node=node)
                      for c in drives[group]]
    return cases


CASE_BUILDERS: dict[str, Callable[..., list[Case]]] = {
    "commonroad": _commonroad_cases, "fastsim": _fastsim_cases, "turned_imu": _turned_imu_cases,
    "truck": _truck_cases, "sim": _sim_cases, "methods": _method_cases, "seeds": _seed_cases}


# ------------------------------------------------------------------------------------ scoring
def _errors(t_est, y_est, t_true, y_true, start: float, mode: str = "linear"):
    t, e, r = metrics.align(t_est, y_est, t_true, y_true, mode=mode)
    sel = t >= start
    return t[sel], e[sel], r[sel]


def _row(case: Case, quantity: str, unit: str, estimator: str, baseline: str,
         ours: tuple[np.ndarray, np.ndarray], base: tuple[np.ndarray, np.ndarray] | None,
         scale: float = 1.0, extra: dict | None = None) -> dict[str, Any]:
    def stats(pair):
        est, true = pair
        if est.size == 0:
            return {"mae": math.nan, "rmse": math.nan, "max_abs_error": math.nan}
        return {"mae": scale * metrics.mae(est, true), "rmse": scale * metrics.rmse(est, true),
                "max_abs_error": scale * float(np.max(np.abs(est - true)))}

    mine = stats(ours)
    theirs = stats(base) if base is not None else {"mae": math.nan, "rmse": math.nan, "max_abs_error": math.nan}
    ratio = mine["rmse"] / theirs["rmse"] if theirs["rmse"] > 0 else math.nan
    return {"case": case.name, "independent": case.independent, "quantity": quantity, "unit": unit,
            "estimator": estimator, "baseline": baseline, "ours": mine, "base": theirs, "ratio": ratio,
            **(extra or {})}


def _read_estimates(bag: Path) -> dict:
    from vehicle_estimation.evaluation.report import read_bag
    from vehicle_estimation.evaluation.consistency import POSE_AND_BIAS_TOPICS
    return read_bag(bag, [T.VEHICLE_STATE, T.SIDESLIP, T.ROAD_SLOPE, T.MASS, T.ODOMETRY, T.GT_MASS,
                          T.GT_ROAD_SLOPE, T.GT_SIDESLIP, T.GT_VEHICLE_STATE, T.GT_ODOMETRY, *POSE_AND_BIAS_TOPICS])


def consistency_rows(case: Case, est: dict) -> list[dict]:
    """Per estimate with a variance: its errors against its own sigma (evaluation.metrics.consistency)."""
    from vehicle_estimation.evaluation.consistency import consistency_group

    checked, _ = consistency_group(est, WARMUP_S)
    return [{"case": case.name, "independent": case.independent, "quantity": quantity, **values}
            for quantity, values in (checked or {}).items()]


def lateral_rows(case: Case, est: dict, vehicle: VehicleParams, filter_name: str) -> tuple[list, dict]:
    from vehicle_estimation.validation import lateral

    drive = lateral.read_drive(case.bag, vehicle.imu_mounting_rpy)
    truth = drive["truth"]
    base = lateral.run_baseline(drive, vehicle)
    start = float(truth["t"][0]) + WARMUP_S
    rows, series = [], {"truth_sideslip": (truth["sideslip_t"], truth["sideslip"]),
                        "base_sideslip": (base["t"], base["sideslip"])}
    beta = est.get(T.SIDESLIP)
    state = est.get(T.VEHICLE_STATE)
    name = f"vehicle_state ({filter_name})"
    if beta is not None:
        series["ours_sideslip"] = (beta["t"], beta["value"])
        rows.append(_row(case, "sideslip", "deg", name, "linear single-track KF",
                         _errors(beta["t"], beta["value"], truth["sideslip_t"], truth["sideslip"], start)[1:],
                         _errors(base["t"], base["sideslip"], truth["sideslip_t"], truth["sideslip"], start)[1:],
                         scale=180.0 / math.pi))
    if state is not None:
        rows.append(_row(case, "vy", "m/s", name, "linear single-track KF",
                         _errors(state["t"], state["vy"], truth["t"], truth["vy"], start)[1:],
                         _errors(base["t"], base["vy"], truth["t"], truth["vy"], start)[1:]))
    return rows, series


def _wrapped(t_est, y_est, t_true, y_true, start: float) -> tuple[np.ndarray, np.ndarray]:
    """(angle error wrapped to [-pi, pi), zeros) after ``start``: an angle's error as a pair for :func:`_row`."""
    _, e, r = _errors(t_est, np.unwrap(y_est), t_true, np.unwrap(y_true), start)
    err = wrap_angle(e - r)
    return err, np.zeros_like(err)


def motion_rows(case: Case, est: dict, inputs: dict, vehicle: VehicleParams, filter_name: str) -> list[dict]:
    """The fusion's speed, pitch, roll and heading and the vehicle state's vx and yaw rate, each
    against the raw sensor a user would otherwise take (:mod:`.baselines`)."""
    rows: list[dict] = []
    odo, gt = est.get(T.ODOMETRY), est.get(T.GT_ODOMETRY)
    state, gt_state = est.get(T.VEHICLE_STATE), est.get(T.GT_VEHICLE_STATE)
    have_can = inputs["speed"].size > 1
    can = (inputs["speed_t"], inputs["speed"])
    deg = 180.0 / math.pi
    if gt is not None and odo is not None:
        start = float(gt["t"][0]) + WARMUP_S
        fusion = "fusion (ES-EKF)"
        rows.append(_row(case, "speed", "m/s", fusion, "CAN speed",
                         _errors(odo["t"], odo["speed"], gt["t"], gt["speed"], start)[1:],
                         _errors(*can, gt["t"], gt["speed"], start)[1:] if have_can else None))
        if have_can and inputs["imu_t"].size > 1:
            kt, kgrade = baselines.kinematic_grade(inputs["imu_t"], inputs["fx"], *can, gravity=vehicle.gravity)
            # REP-103 pitch is nose down positive: a climbing car's accelerometer tilt is -grade
            rows.append(_row(case, "pitch", "deg", fusion, "accelerometer tilt (kinematic grade)",
                             _errors(odo["t"], odo["pitch"], gt["t"], gt["pitch"], start)[1:],
                             _errors(kt, -kgrade, gt["t"], gt["pitch"], start)[1:], scale=deg))
            if np.ptp(gt["roll"]) > math.radians(0.5):    # a drive that rolls the car
                rt, roll = baselines.kinematic_roll(inputs["imu_t"], inputs["fy"], inputs["wz"], *can,
                                                    gravity=vehicle.gravity)
                rows.append(_row(case, "roll", "deg", fusion, "accelerometer tilt less v r",
                                 _errors(odo["t"], odo["roll"], gt["t"], gt["roll"], start)[1:],
                                 _errors(rt, roll, gt["t"], gt["roll"], start)[1:], scale=deg))
        if inputs["gnss_t"].size > 1:     # without GNSS the heading is free: no absolute figure
            ct, course = baselines.gnss_course(inputs["gnss_t"], inputs["east"], inputs["north"])
            if ct.size > 1:
                rows.append(_row(case, "heading", "deg", fusion, "GNSS course over 1 s",
                                 _wrapped(odo["t"], odo["yaw"], gt["t"], gt["yaw"], start),
                                 _wrapped(ct, course, gt["t"], gt["yaw"], start), scale=deg))
    if gt_state is not None and state is not None:
        start = float(gt_state["t"][0]) + WARMUP_S
        name = f"vehicle_state ({filter_name})"
        rows.append(_row(case, "vx", "m/s", name, "CAN speed",
                         _errors(state["t"], state["vx"], gt_state["t"], gt_state["vx"], start)[1:],
                         _errors(*can, gt_state["t"], gt_state["vx"], start)[1:] if have_can else None))
        if inputs["imu_t"].size > 1:
            rows.append(_row(case, "yaw rate", "deg/s", name, "gyro (raw)",
                             _errors(state["t"], state["yaw_rate"], gt_state["t"], gt_state["yaw_rate"], start)[1:],
                             _errors(inputs["imu_t"], inputs["wz"], gt_state["t"], gt_state["yaw_rate"], start)[1:],
                             scale=deg))
    return rows


def longitudinal_rows(case: Case, est: dict, inputs: dict, vehicle: VehicleParams, mass_method: str,
                      slope_method: str) -> tuple[list, dict]:
    rows: list[dict] = []
    series: dict = {}
    gt_slope, gt_mass = est.get(T.GT_ROAD_SLOPE), est.get(T.GT_MASS)
    if gt_slope is None or gt_mass is None or inputs["speed"].size < 2:
        return rows, series
    t0 = float(gt_slope["t"][0])
    start = t0 + WARMUP_S
    kt, kgrade = baselines.kinematic_grade(inputs["imu_t"], inputs["fx"], inputs["speed_t"], inputs["speed"],
                                           gravity=vehicle.gravity)
    series.update(truth_slope=(gt_slope["t"], gt_slope["value"]), base_slope=(kt, kgrade))
    slope = est.get(T.ROAD_SLOPE)
    if slope is not None:
        series["ours_slope"] = (slope["t"], slope["value"])
        rows.append(_row(case, "slope", "deg", f"road_slope ({slope_method})", "kinematic grade, low-passed",
                         _errors(slope["t"], slope["value"], gt_slope["t"], gt_slope["value"], start)[1:],
                         _errors(kt, kgrade, gt_slope["t"], gt_slope["value"], start)[1:], scale=180.0 / math.pi))
    mass = est.get(T.MASS)
    true_mass = float(np.median(gt_mass["value"]))
    if mass is not None and np.isfinite(inputs["force"]).sum() > 10:
        t_end = float(mass["t"][-1])
        half = mass["t"] >= t0 + MASS_FROM_FRACTION * (t_end - t0)
        ours = (mass["value"][half], np.full(int(half.sum()), true_mass))
        lsq_true = baselines.batch_ls_mass(inputs["force_t"], inputs["force"], inputs["speed_t"], inputs["speed"],
                                           gt_slope["t"], gt_slope["value"], vehicle)
        lsq_ours = baselines.batch_ls_mass(inputs["force_t"], inputs["force"], inputs["speed_t"], inputs["speed"],
                                           slope["t"], slope["value"], vehicle) if slope is not None else None
        extra = {"true_mass": true_mass, "batch_ls_true_grade_kg": lsq_true["mass"],
                 "batch_ls_our_slope_kg": lsq_ours["mass"] if lsq_ours else math.nan,
                 "last_half_max_error_pct": 100.0 * float(np.max(np.abs(ours[0] / true_mass - 1.0)))
                 if ours[0].size else math.nan}
        pct = (100.0 * ours[0] / true_mass, 100.0 * ours[1] / true_mass)
        for label, lsq in (("true grade", lsq_true), ("our slope", lsq_ours)):
            if lsq is None:
                continue
            base = ((100.0 * np.array([lsq["mass"]]) / true_mass, np.array([100.0]))
                    if math.isfinite(lsq["mass"]) else None)
            rows.append(_row(case, "mass (last half)", "%", f"mass ({mass_method})",
                             f"batch LS over the drive, {label}", pct, base, extra=extra))
        series.update(ours_mass=(mass["t"], mass["value"]), truth_mass=(gt_mass["t"], gt_mass["value"]))
        if math.isfinite(lsq_true["mass"]):
            series["base_mass"] = (mass["t"][[0, -1]], np.full(2, lsq_true["mass"]))
    return rows, series


# ------------------------------------------------------------------------------------ run
def _case_vehicle(case: Case) -> VehicleParams:
    """The vehicle as the case's nodes read it: its vehicle file with the case's layers over it
    (a layer may say how the IMU is mounted)."""
    from vehicle_estimation.launcher.node_plan import layered_params

    layered = layered_params([case.vehicle, *(params_file(name) for name in case.params)])["mass"]
    return VehicleParams.from_mapping({k.removeprefix("vehicle."): v for k, v in layered.items()
                                       if k.startswith("vehicle.")})


def _shipped_methods(params: Sequence[str] = ("estimation",)) -> dict[str, str]:
    """Each node's method under the parameter files ``params`` layered in order, as the nodes
    read them (``/**`` and the node's section; the node's default where no file sets it)."""
    from vehicle_estimation.launcher.node_plan import layered_params

    layered = layered_params([params_file(name) for name in params])
    return {node: str(layered[node][key])
            for node, key in (("vehicle_state", "filter"), ("mass", "method"), ("road_slope", "method"))}


def run(out: Path, node_group: Callable[[list[Path], Any, Path], Any], *, cases: Sequence[str] | None = None,
        quick: bool = False, progress: bool = True, params: Sequence[str | Path] = ()) -> dict:
    """Make the cases, replay each, score it with its baseline; returns ``validation.json``'s content.

    ``params``: parameter files (or names under params/) layered over ``estimation.yaml`` in
    every case, below a case's own layer (the truck's TA-AEKF profile, a method case's method):
    a tuning scored on the whole set, beside the same baselines.

    Raises :class:`FileExistsError` when ``out`` holds the bags or runs of an earlier run: the
    drives are generated afresh (a new library version may change them) and never mixed with
    an earlier run's, whatever the case kinds; :class:`FileNotFoundError` when a ``params``
    file does not exist (before anything is made).
    """
    from vehicle_estimation.launcher.replay import ReplayError, replay

    layers = tuple(str(params_file(name)) for name in params)
    out = Path(out)
    for used in (out / "bags", out / "runs"):
        if used.exists():
            raise FileExistsError(f"{used} exists")
    out.mkdir(parents=True, exist_ok=True)
    groups = list(cases or CASE_BUILDERS)
    unknown = [g for g in groups if g not in CASE_BUILDERS]
    if unknown:
        raise ValueError(f"unknown case group(s) {unknown} (known: {', '.join(CASE_BUILDERS)})")
    methods = _shipped_methods(("estimation", *layers))
    all_cases = [replace(c, params=(c.params[0], *layers, *c.params[1:]))
                 for g in groups for c in CASE_BUILDERS[g](out / "bags", quick=quick)]
    rows, replays, consistency, motion = [], [], [], []
    for case in all_cases:
        run_dir = out / "runs" / case.name
        estimates = run_dir / "estimates"
        if progress:
            print(f"[validate] {case.name}: replay {case.bag} -> {estimates}")
        wall = time.monotonic()
        try:
            stats = replay(case.bag, estimates, lambda ov, case=case, run_dir=run_dir: node_group(
                [case.vehicle, *(params_file(name) for name in case.params)], ov, run_dir / "logs"),
                progress=progress)
        except ReplayError as exc:
            raise RuntimeError(f"replay of {case.name} failed: {exc}; logs in {run_dir / 'logs'}") from exc
        vehicle = _case_vehicle(case)
        case_methods = _shipped_methods(case.params)
        est = _read_estimates(estimates)     # once: both kinds score the same recording
        inputs = baselines.read_sensor_inputs(case.bag, vehicle.imu_mounting_rpy)
        series: dict = {}
        case_rows = []
        if "lateral" in case.kinds:
            r, s = lateral_rows(case, est, vehicle, case_methods["vehicle_state"])
            case_rows += r
            series.update(s)
        if "longitudinal" in case.kinds:
            r, s = longitudinal_rows(case, est, inputs, vehicle, case_methods["mass"], case_methods["road_slope"])
            case_rows += r
            series.update(s)
        if case.node:       # a method case: the other nodes ran as in the shipped case of its drive
            # every row's estimator reads "<node> (<method>)"
            rows += [r for r in case_rows if r["estimator"].startswith(case.node + " (")]
            consistency += [r for r in consistency_rows(case, est) if r["quantity"] in NODE_ESTIMATES[case.node]]
        else:
            rows += case_rows
            consistency += [{**r, "ensemble": case.ensemble} if case.ensemble else r
                            for r in consistency_rows(case, est)]
            motion += motion_rows(case, est, inputs, vehicle, case_methods["vehicle_state"])
        _plot(case, series, out / f"{case.name}.png")
        replays.append({"case": case.name, "source": case.source, "bag": str(case.bag),
                        "vehicle": str(case.vehicle), "params": list(case.params),
                        "independent": case.independent, "notes": case.notes,
                        "lossless": stats.lossless, "wall_s": time.monotonic() - wall})
    result = {"params": "params/estimation.yaml", "layers": list(layers), "methods": methods, "warmup_s": WARMUP_S,
              "quick": quick, "cases": replays, "rows": rows, "motion": motion, "consistency": consistency}
    (out / "validation.json").write_text(json.dumps(result, indent=2, default=float) + "\n", encoding="utf-8")
    (out / "validation.md").write_text(format_table(result) + "\n", encoding="utf-8")
    return result


def _plot(case: Case, series: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(q, scale, unit) for q, scale, unit in (("sideslip", 180 / math.pi, "deg"),
                                                      ("slope", 180 / math.pi, "deg"), ("mass", 1.0, "kg"))
              if f"truth_{q}" in series]
    if not panels:
        return
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.6 * len(panels)), squeeze=False)
    for ax, (q, scale, unit) in zip(axes[:, 0], panels):
        for key, style, label in ((f"base_{q}", "C1-", "baseline"), (f"ours_{q}", "C0-", "ours"),
                                  (f"truth_{q}", "k--", "truth")):
            if key in series:
                t, y = series[key]
                ax.plot(np.asarray(t) - series[f"truth_{q}"][0][0], np.asarray(y) * scale, style, lw=1, label=label)
        ax.set_ylabel(f"{q} [{unit}]")
        ax.legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{case.name}: {case.source}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output directory (default: {DEFAULT_OUT})")
    p.add_argument("--cases", default=",".join(CASE_BUILDERS),
                   help=f"comma-separated case groups (default: {','.join(CASE_BUILDERS)})")
    p.add_argument("--quick", action="store_true", help="one short drive per group (a smoke run)")
    add_tuning_option(p, "a case's own layer (a method case's method, the truck's TA-AEKF profile)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_namespace_option(p)


def main(args: argparse.Namespace) -> int:
    try:
        result = run(args.out, node_group_factory(args.namespace), cases=[c for c in args.cases.split(",") if c], quick=args.quick,
                     progress=not args.quiet, params=args.params)
    except FileExistsError as exc:
        print(f"validate: {exc} (from an earlier run): remove {args.out} or choose another --out",
              file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"validate: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:         # a replay failed: the node's own words are in the message
        print(f"validate: {exc}", file=sys.stderr)
        return 1
    print(format_table(result))
    print(f"wrote {args.out / 'validation.json'}, {args.out / 'validation.md'} and one plot per case")
    return 0
