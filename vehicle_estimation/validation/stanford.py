"""The Stanford sideslip comparison: our vehicle-state filters against a linear single-track KF.

Usage::

    vehicle-estimation stanford [--out DIR] [--data-dir DIR] [--filters ckf,vbackf,aoukf] [--speed none,ref]
                                [--noise data|paper] [--rows N] [--wheel-dropout FROM:TO] [--params FILE ...] [--quiet]

1. Imports the real drive of ``../shared/data/stanford_sideslip_2014`` beside the repository
   (``--data-dir`` gives another place; 550 s at 100 Hz,
   a car driven hard on a track, INS/optical reference) with the import map
   ``params/import_maps/stanford_sideslip_2014.yaml`` into MCAP bags, one per speed source:

   * ``none``: the log as it is: IMU (ax, ay, yaw rate) and the steering angle, nothing else.
     Without wheel speeds the state node dead-reckons vx from the measured ax. Its initial
     vx is the reference's first sample (ASSUMPTION: the node has no way to know it).
   * ``ref``: ASSUMPTION: four free-rolling wheel speeds synthesised from the REFERENCE vx,
     the yaw rate and the steering angle (``wheel_speeds_from_speed``). A real car has wheel
     speeds; this log does not. The baseline uses the same reference vx in every row.

2. Replays each bag through the four nodes (as ``vehicle-estimation replay`` does, on
   ``params/stanford_2014.yaml`` + ``estimation.yaml``), once per state filter, layering a
   params file that selects the filter (:data:`FILTERS`: add a filter there).
3. Runs the baseline, the linear single-track Kalman filter of the data's source repository
   (MBDS/sideslip-angle-vehicle-estimation, ``estimators/matlab_kf/BetaStanfordLinear.m`` and
   ``LinearKF.m``), re-implemented in
   :func:`vehicle_estimation.validation.baselines.baseline_linear_kf`.
4. Prints MAE and RMSE of sideslip, vy and yaw rate against the reference (and vx, and the
   sideslip RMSE change against the baseline), writes ``comparison.json`` and
   ``comparison.png`` into ``--out`` (default ``out/stanford``).

Measurement noise (``--noise``): ``data`` (default) gives both filters ``r_diag`` = the
variance of the high-passed raw ax, ay and yaw rate, the way the baseline sets its own R;
``paper`` keeps paper 004's R (sigma_ay = 0.2 m/s^2, five times below this IMU's noise).
The VB-ACKF learns R online either way.

``--wheel-dropout FROM:TO`` makes the ``ref`` bag's wheel speeds NaN from FROM to TO seconds
after the drive's start (a CAN dropout, or with TO past the end a speed lost for good); each
row then also has ``dropout_metrics``, over that stretch.

Metrics skip the first ``--warmup`` seconds (5 s) of the reference for every row alike.
The yaw-rate reference is the zero-phase filtered yaw rate of the same INS gyro that feeds
the filters: its errors measure smoothing and lag, not gyro accuracy.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vehicle_estimation.contract import topics as T
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.evaluation.report import json_safe
from vehicle_estimation.launcher.options import add_namespace_option, add_tuning_option, node_group_factory
from vehicle_estimation.validation.baselines import baseline_linear_kf, highpass_std

MAPPING = "stanford_sideslip_2014"
VEHICLE = "stanford_2014"
DEFAULT_WARMUP_S = 5.0

#: State filters of the comparison: name -> ``vehicle_state`` parameters layered over
#: estimation.yaml. A new filter of the state node needs one line here.
FILTERS: dict[str, dict[str, Any]] = {
    "ckf": {"filter": "ckf"},
    "vbackf": {"filter": "vbackf"},
    # paper 002: no GA-BPNN weights ship for this car (they are trained on simulator drives of
    # the sedan), so "auto" runs the anti-outlier UKF without the output correction.
    "aoukf": {"filter": "aoukf"},
}

#: Speed sources: name -> (label, extra mapping entries).
SPEED_MODES: dict[str, tuple[str, dict[str, Any]]] = {
    "none": ("no speed (as logged)", {}),
    "ref": ("ASSUMED: wheels from ref. vx",
            {"wheel_speeds_from_speed": {"source": "vx", "unit": "m/s", "kinematic": True}}),
}


def import_bag(bag: Path, speed: str, data_dir: str | None = None, rows: int | None = None):
    """The drive as a bag with the speed source ``speed`` (:data:`SPEED_MODES`), from
    ``data_dir`` (default: the shared data); its first ``rows`` samples, or all. Returns the
    importer's result (counts and signals)."""
    from vehicle_estimation.io import import_map, importer
    from vehicle_estimation.paths import shared_data_dir

    mapping, _ = import_map.load_mapping(MAPPING)
    return importer.import_logs({**mapping, **SPEED_MODES[speed][1]}, bag,
                                base_dir=data_dir or str(shared_data_dir(MAPPING)), max_rows=rows)


def _add_vibration(bags: dict[str, Path], t: np.ndarray, ax: np.ndarray, ay: np.ndarray, std: float,
                   seed: int, progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """The same seeded vibration on x, y, z of every bag's IMU and on the baseline's ax, ay."""
    from vehicle_estimation.sim.noise import VIBRATION_BAND_HZ, band_limited_noise
    from vehicle_estimation.io.bagtools import rewrite_bag

    fs = 1.0 / float(np.median(np.diff(t)))
    vibration = band_limited_noise(np.random.default_rng(seed), t.size, fs, std)

    def shake(msg: Any, index: int) -> None:
        if index >= len(vibration):
            raise ValueError(f"{T.IMU}: more messages in the bag than imported IMU samples ({t.size})")
        a = msg.linear_acceleration
        a.x, a.y, a.z = a.x + vibration[index, 0], a.y + vibration[index, 1], a.z + vibration[index, 2]

    for speed, bag in list(bags.items()):
        shaken = bag.with_name(bag.name + "_vibration")
        if shaken.exists():
            shutil.rmtree(shaken)
        bags[speed] = rewrite_bag(bag, shaken, edit={T.IMU: shake})
        if progress:
            print(f"[vibration] {bags[speed]}: {std:g} m/s^2, {VIBRATION_BAND_HZ[0]:g} Hz up to "
                  f"{min(VIBRATION_BAND_HZ[1], 0.45 * fs):.0f} Hz, seed {seed}")
    return ax + vibration[:, 0], ay + vibration[:, 1]


def _drop_wheel_speeds(bag: Path, window: tuple[float, float], progress: bool) -> Path:
    """``bag`` with its wheel speeds NaN over ``window`` (absolute stamps) [s]: a CAN dropout."""
    from vehicle_estimation.io.bagtools import rewrite_bag

    def drop(msg: Any, index: int) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if window[0] <= stamp < window[1]:
            for i, name in enumerate(msg.name):
                if name in T.WHEEL_JOINTS:
                    msg.velocity[i] = math.nan

    dropped = rewrite_bag(bag, bag.with_name(bag.name + "_wheel_dropout"), edit={T.JOINT_STATES: drop})
    if progress:
        print(f"[wheel dropout] {dropped}: wheel speeds NaN from {window[0]:.2f} to {window[1]:.2f} s")
    return dropped


# --------------------------------------------------------------------- metrics
def _quantities(t, est: dict[str, tuple[np.ndarray, np.ndarray]], ref: dict[str, tuple[np.ndarray, np.ndarray]],
                start: float, end: float = math.inf) -> dict[str, dict]:
    """MAE/RMSE/bias per quantity of ``est`` against ``ref`` (truth interpolated at the estimate
    stamps), from ``start`` to ``end``."""
    out = {}
    for key, (te, ye) in est.items():
        tr, yr = ref[key]
        ta, ea, ra = metrics.align(te, ye, tr, yr)
        sel = (ta >= start) & (ta < end)
        out[key] = metrics.summary(ea[sel], ra[sel])
    return out


#: Bands of |ay| (raw IMU, 1 s moving average) [m/s^2]: the linear tyre range and beyond.
AY_BANDS = ((0.0, 4.0), (4.0, 8.0), (8.0, math.inf))


def _sideslip_by_band(est: dict, ref: dict, t: np.ndarray, ay_smooth: np.ndarray, start: float) -> dict[str, float]:
    """Sideslip RMSE [deg] per |ay| band (where the linear single-track model holds and beyond)."""
    if "sideslip" not in est:
        return {}
    te, ye = est["sideslip"]
    ta, ea, ra = metrics.align(te, ye, *ref["sideslip"])
    sel = ta >= start
    ta, ea, ra = ta[sel], ea[sel], ra[sel]
    a = np.abs(np.interp(ta, t, ay_smooth))
    out = {}
    for lo, hi in AY_BANDS:
        band = (a >= lo) & (a < hi)
        key = f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">{lo:g}"
        out[key] = metrics.rmse(ea[band], ra[band]) * 180.0 / math.pi if band.any() else math.nan
        out[key + " share"] = float(np.mean(band)) if band.size else math.nan
    return out


def _final_diagnostics(bag: Path) -> dict[str, str]:
    """The vehicle-state node's last /diagnostics entry (learnt R, what is missing, ...)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    last: dict[str, str] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic.endswith("/diagnostics")]
        for conn, _, raw in reader.messages(connections=conns):
            for status in reader.deserialize(raw, conn.msgtype).status:
                if status.name.endswith("vehicle_state"):
                    last = {"message": status.message, **{kv.key: kv.value for kv in status.values}}
    return last


#: The state estimates whose published variance the comparison checks against the reference.
CHECKED = ("sideslip", "vy", "yaw_rate")


def _consistency(data: dict, warmup_s: float) -> dict[str, dict[str, float]]:
    """Errors against the published sigma (share within 1/2/3 sigma, NEES, and over the samples
    flagged converged) of each :data:`CHECKED` estimate in ``data`` (:func:`_read_recording`),
    after the warm-up, as ``report`` does."""
    from vehicle_estimation.evaluation.consistency import consistency_group
    checks, _ = consistency_group(data, warmup_s)
    return {name: values for name, values in (checks or {}).items() if name in CHECKED}


def _scaled(q: dict[str, dict]) -> dict[str, dict]:
    """Metrics in report units: sideslip deg, yaw rate deg/s, speeds m/s."""
    scale = {"sideslip": 180.0 / math.pi, "yaw_rate": 180.0 / math.pi, "vy": 1.0, "vx": 1.0}
    return {k: {m: (v * scale[k] if m in ("mae", "rmse", "bias", "max_abs_error") else v) for m, v in d.items()}
            for k, d in q.items()}


# --------------------------------------------------------------------- runs
def _write_layer(path: Path, state_params: dict[str, Any]) -> Path:
    import yaml
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as handle:
        yaml.safe_dump({"vehicle_state": {"ros__parameters": state_params}}, handle, sort_keys=False)
    return path


def _read_recording(bag: Path) -> dict:
    """The recorded state estimates and the reference they are checked against, read once."""
    from vehicle_estimation.evaluation.report import read_bag
    return read_bag(bag, [T.VEHICLE_STATE, T.SIDESLIP, T.GT_VEHICLE_STATE, T.GT_SIDESLIP])


def _estimates(data: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(t, value) of each estimate in a recording (:func:`_read_recording`)."""
    out = {}
    state = data.get(T.VEHICLE_STATE)
    if state is not None:
        for key in ("vx", "vy", "yaw_rate"):
            out[key] = (state["t"], state[key])
    beta = data.get(T.SIDESLIP)
    if beta is not None:
        out["sideslip"] = (beta["t"], beta["value"])
    return out


def run(out: Path, node_group: Callable[[list[Path], Any, Path], Any], *, data_dir: str | None = None,
        filters: list[str] | None = None, speeds: list[str] | None = None, noise: str = "data",
        rows: int | None = None, warmup_s: float = DEFAULT_WARMUP_S, progress: bool = True,
        vibration_std: float = 0.0, vibration_seed: int = 0,
        wheel_dropout: tuple[float, float] | None = None, params: Sequence[str | Path] = ()) -> dict:
    """The whole comparison; returns the content of ``comparison.json``.

    ``vibration_std`` > 0 adds band-limited vibration (10-60 Hz, below 45 Hz at this log's
    100 Hz; that std per axis [m/s^2], seeded) to the accelerometer of every bag and of the baseline alike: the raw IMU of a real
    car carries several m/s^2 of it (issue "the bag a user brings").

    ``wheel_dropout`` (from, to) [s after the drive's start] makes the ``ref`` bag's wheel speeds
    NaN over that stretch; each row then has ``dropout_metrics`` over it too.

    ``params``: files (or names under params/) layered over ``estimation.yaml`` in every replay,
    below the comparison's own layer (the filter, and the noise it sets).

    ``node_group(params_files, overrides, log_dir)`` builds the node processes (see
    :func:`main`); ``params_files`` are the layers after the vehicle file.
    """
    from vehicle_estimation.paths import params_file, shared_data_dir
    from vehicle_estimation.io import import_map
    from vehicle_estimation.launcher.replay import ReplayError, print_stats, replay
    from vehicle_estimation.contract.vehicle import load_vehicle_params

    layers = [params_file(name) for name in params]

    filters = filters or list(FILTERS)
    speeds = speeds or list(SPEED_MODES)
    for name in filters:
        if name not in FILTERS:
            raise ValueError(f"unknown filter {name!r} (known: {', '.join(FILTERS)})")
    for name in speeds:
        if name not in SPEED_MODES:
            raise ValueError(f"unknown speed source {name!r} (known: {', '.join(SPEED_MODES)})")
    if not (math.isfinite(vibration_std) and vibration_std >= 0.0):
        raise ValueError(f"vibration_std must be >= 0, got {vibration_std!r}")
    if noise not in ("data", "paper"):
        raise ValueError(f"noise must be 'data' or 'paper', got {noise!r}")
    if wheel_dropout is not None and not (0.0 <= wheel_dropout[0] < wheel_dropout[1]):
        raise ValueError(f"wheel dropout must be FROM:TO with 0 <= FROM < TO [s], got {wheel_dropout!r}")
    for sub in ("bags", "runs"):
        if (out / sub).exists():
            shutil.rmtree(out / sub)
    out.mkdir(parents=True, exist_ok=True)
    vehicle = load_vehicle_params(params_file(VEHICLE))
    _, map_path = import_map.load_mapping(MAPPING)
    data_dir = data_dir or str(shared_data_dir(MAPPING))

    # ---- import (one bag per speed source) and the arrays the baseline needs
    bags: dict[str, Path] = {}
    signals = None
    for speed in speeds:
        bag = out / "bags" / f"input_{speed}"
        bag.parent.mkdir(parents=True, exist_ok=True)
        res = import_bag(bag, speed, data_dir, rows)
        if progress:
            print(f"[import] {bag}: " + ", ".join(f"{k} {v}" for k, v in sorted(res.counts.items())))
        bags[speed] = bag
        signals = signals or res.signals
    assert signals is not None
    sig = {k: v for k, v in signals.items()}
    t = sig["imu.angular_velocity.z"].t
    ax = sig["imu.linear_acceleration.x"].values
    ay = sig["imu.linear_acceleration.y"].values
    if vibration_std > 0.0:
        ax, ay = _add_vibration(bags, t, ax, ay, vibration_std, vibration_seed, progress)
    dropout = None if wheel_dropout is None else (float(t[0]) + wheel_dropout[0], float(t[0]) + wheel_dropout[1])
    if dropout is not None and "ref" in bags:
        bags["ref"] = _drop_wheel_speeds(bags["ref"], dropout, progress)
    r = sig["imu.angular_velocity.z"].values
    delta = np.interp(t, sig[import_map.STEERING_KEY].t, sig[import_map.STEERING_KEY].values) / vehicle.steering_ratio
    ref = {"vx": (sig["ground_truth.vehicle_state.vx"].t, sig["ground_truth.vehicle_state.vx"].values),
           "vy": (sig["ground_truth.vehicle_state.vy"].t, sig["ground_truth.vehicle_state.vy"].values),
           "yaw_rate": (sig["ground_truth.vehicle_state.yaw_rate"].t, sig["ground_truth.vehicle_state.yaw_rate"].values),
           "sideslip": (sig["ground_truth.sideslip"].t, sig["ground_truth.sideslip"].values)}
    t0 = float(ref["sideslip"][0][0])
    start = t0 + warmup_s
    vx_ref = np.interp(t, *ref["vx"])
    n_avg = max(1, int(round(1.0 / float(np.median(np.diff(t)))))) if t.size > 1 else 1
    ay_smooth = np.convolve(ay, np.ones(n_avg) / n_avg, mode="same")

    # ---- measurement noise as the baseline estimates it (high-passed raw signals)
    noise_std = {"ax": highpass_std(ax), "ay": highpass_std(ay), "yaw_rate": highpass_std(r)}
    r_diag = [noise_std["ax"] ** 2, noise_std["ay"] ** 2, noise_std["yaw_rate"] ** 2]

    # ---- baseline
    wall = time.monotonic()
    b_beta, b_r = baseline_linear_kf(t, ay, r, delta, vx_ref, m=vehicle.mass, lf=vehicle.lf, lr=vehicle.lr,
                                     iz=vehicle.yaw_inertia, cf=2.0 * vehicle.cornering_stiffness_front,
                                     cr=2.0 * vehicle.cornering_stiffness_rear)
    baseline_est = {"sideslip": (t, b_beta), "vy": (t, vx_ref * np.tan(b_beta)), "yaw_rate": (t, b_r),
                    "vx": (t, vx_ref)}
    rows_out: list[dict[str, Any]] = [{
        "name": "baseline linear single-track KF", "filter": "baseline", "speed": "reference vx (as the source)",
        "metrics": _scaled(_quantities(t, baseline_est, ref, start)), "wall_s": time.monotonic() - wall,
        "sideslip_rmse_by_ay_band": _sideslip_by_band(baseline_est, ref, t, ay_smooth, start)}]
    if dropout is not None:
        rows_out[0]["dropout_metrics"] = _scaled(_quantities(t, baseline_est, ref, *dropout))
    series: dict[str, dict] = {"baseline": {k: v for k, v in baseline_est.items()}}

    # ---- replays
    for speed in speeds:
        for name in filters:
            label = f"{name} / {speed}"
            run_dir = out / "runs" / f"{name}_{speed}"
            state = dict(FILTERS[name])
            # publish every sample: the node's rate limit (1e-9 s tolerance) drops about half of
            # the 100 Hz outputs at epoch stamps, whose float resolution is ~2.4e-7 s
            state["publish_rate_hz"] = 1000.0
            if noise == "data" and state["filter"] == "aoukf":
                state["aoukf"] = {"r_ay": float(r_diag[1]), "r_yaw_rate": float(r_diag[2])}
            elif noise == "data":
                state["r_diag"] = [float(v) for v in r_diag]
            if speed == "none":
                state["initial_vx"] = float(ref["vx"][1][0])     # ASSUMPTION: known initial speed
            layer = _write_layer(run_dir / "state_layer.yaml", state)
            estimates = run_dir / "estimates"
            if progress:
                print(f"[replay] {label} -> {estimates}")
            try:
                stats = replay(bags[speed], estimates,
                               lambda ov, layer=layer, run_dir=run_dir: node_group(
                                   [params_file("estimation"), *layers, layer], ov, run_dir / "logs"),
                               progress=progress)
            except ReplayError as exc:
                raise RuntimeError(f"replay {label} failed: {exc}; logs in {run_dir / 'logs'}") from exc
            if progress:
                print_stats(stats)
            recording = _read_recording(estimates)
            est = _estimates(recording)
            rows_out.append({"name": label, "filter": name, "speed": SPEED_MODES[speed][0],
                             "metrics": _scaled(_quantities(t, est, ref, start)),
                             "consistency": _consistency(recording, warmup_s),
                             "lossless": stats.lossless, "replay_wall_s": stats.wall_s,
                             "replay_speed_x": stats.bag_s / stats.wall_s if stats.wall_s > 0 else math.nan,
                             "state_params": state,
                             "sideslip_rmse_by_ay_band": _sideslip_by_band(est, ref, t, ay_smooth, start),
                             "final_diagnostics": _final_diagnostics(estimates)})
            if dropout is not None:
                rows_out[-1]["dropout_metrics"] = _scaled(_quantities(t, est, ref, *dropout))
            series[f"{name}_{speed}"] = est

    base_rmse = rows_out[0]["metrics"]["sideslip"]["rmse"]
    for row in rows_out:
        rmse = row["metrics"].get("sideslip", {}).get("rmse", math.nan)
        row["sideslip_rmse_change_percent"] = 100.0 * (rmse - base_rmse) / base_rmse
    result = {
        "data": data_dir, "mapping": str(map_path), "vehicle": VEHICLE,
        "samples": int(t.size), "duration_s": float(t[-1] - t[0]), "warmup_s": warmup_s,
        "layers": [str(path) for path in layers], "noise": noise, "noise_std_from_data": noise_std,
        "vibration_std": vibration_std,
        "wheel_dropout_s": list(wheel_dropout) if wheel_dropout is not None else None,
        "units": {"sideslip": "deg", "yaw_rate": "deg/s", "vy": "m/s", "vx": "m/s"},
        "rows": rows_out,
        "notes": [
            "baseline: linear single-track KF of MBDS/sideslip-angle-vehicle-estimation "
            "(estimators/matlab_kf), given the reference vx",
            "speed 'none': IMU + steering only; the initial vx is the reference's first sample (assumption)",
            "speed 'ref': ASSUMPTION: wheel speeds synthesised from the reference vx (the log has none)",
            "yaw-rate reference = zero-phase filtered yaw rate of the same gyro (not independent)",
        ],
    }
    result["figure"] = plot(series, ref, out / "comparison.png", t0, start)
    with open(out / "comparison.json", "w", encoding="utf-8") as handle:
        json.dump(json_safe(result), handle, indent=2)
        handle.write("\n")
    return result




# --------------------------------------------------------------------- output
def _number(value: Any) -> float:
    """``value`` as a float, NaN for None (a NaN stored in JSON reads back as null)."""
    return math.nan if value is None else float(value)


def _label(row: dict) -> str:
    return row["name"] if row["filter"] == "baseline" else f"{row['filter']} / {row['speed']}"


def format_table(result: dict) -> str:
    head = (f"{'estimator / speed source':44s} {'beta MAE':>8s} {'beta RMSE':>9s} {'vs base':>8s} "
            f"{'vy MAE':>7s} {'vy RMSE':>7s} {'r MAE':>6s} {'r RMSE':>6s} {'vx RMSE':>7s}")
    units = f"{'':44s} {'[deg]':>8s} {'[deg]':>9s} {'[%]':>8s} {'[m/s]':>7s} {'[m/s]':>7s} {'[°/s]':>6s} {'[°/s]':>6s} {'[m/s]':>7s}"
    lines = [head, units, "-" * len(head)]

    def f(row, key, metric, spec):
        value = row["metrics"].get(key, {}).get(metric)
        return format(value, spec) if value is not None and math.isfinite(value) else "n/a"

    for row in result["rows"]:
        name = _label(row)
        change = row.get("sideslip_rmse_change_percent")
        change = "—" if row["filter"] == "baseline" else (f"{change:+.1f}" if change is not None else "n/a")
        lines.append(f"{name[:44]:44s} {f(row, 'sideslip', 'mae', '.3f'):>8s} {f(row, 'sideslip', 'rmse', '.3f'):>9s} "
                     f"{change:>8s} {f(row, 'vy', 'mae', '.3f'):>7s} {f(row, 'vy', 'rmse', '.3f'):>7s} "
                     f"{f(row, 'yaw_rate', 'mae', '.2f'):>6s} {f(row, 'yaw_rate', 'rmse', '.2f'):>6s} "
                     f"{f(row, 'vx', 'rmse', '.2f'):>7s}")
    bands = [f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">{lo:g}" for lo, hi in AY_BANDS]
    shares = result["rows"][0].get("sideslip_rmse_by_ay_band", {})
    lines.append("")
    lines.append(f"{'sideslip RMSE [deg] by |ay| band [m/s^2]':44s} " + " ".join(
        f"{b + ' (' + format(100 * (shares.get(b + ' share') or 0), '.0f') + '%)':>16s}" for b in bands))
    for row in result["rows"]:
        name = _label(row)
        by = row.get("sideslip_rmse_by_ay_band", {})
        lines.append(f"{name[:44]:44s} " + " ".join(
            f"{format(by[b], '.3f') if by.get(b) is not None and math.isfinite(by[b]) else 'n/a':>16s}"
            for b in bands))
    lines.append("")
    lines.append(f"{'within 2 sigma / NEES of the published variance':44s} " + " ".join(
        f"{name:>16s}" for name in CHECKED) + f" {'sideslip flagged / beyond 3 sigma':>34s}")
    for row in result["rows"]:
        checks = row.get("consistency")
        if not checks:
            continue
        cells = []
        for name in CHECKED:
            c = checks.get(name, {})
            share, nees = c.get("within_2sigma", math.nan), c.get("nees", math.nan)
            cells.append(f"{format(100 * share, '.0f') + ' % / ' + format(nees, '.2f') if math.isfinite(share) else 'n/a':>16s}")
        sideslip = checks.get("sideslip", {})
        flagged = _number(sideslip.get("converged_share"))
        beyond = _number(sideslip.get("converged_beyond_3sigma"))
        flagged_text = (f"{100 * flagged:.0f} % / " + (f"{100 * beyond:.1f} %" if math.isfinite(beyond) else "-")
                        if math.isfinite(flagged) else "n/a")
        lines.append(f"{_label(row):44.44s} " + " ".join(cells) + f" {flagged_text:>34s}")
    lines.append("honest: 95 % within 2 sigma, NEES 1 (above 1: the variance is too small); of the "
                 "samples flagged converged, at most 1 % beyond 3 sigma")
    window = result.get("wheel_dropout_s")
    for row in result["rows"] if window else ():
        beta, vy = (row.get("dropout_metrics", {}).get(k, {}) for k in ("sideslip", "vy"))
        lines.append(f"{_label(row):44.44s} wheel dropout {window[0]:g}-{window[1]:g} s: beta RMSE "
                     f"{_number(beta.get('rmse')):.3f} deg, largest vy error {_number(vy.get('max_abs_error')):.3f} m/s")
    lines.append(f"{result['samples']} samples, {result['duration_s']:.0f} s; metrics after the first "
                 f"{result['warmup_s']:.0f} s; noise R: {result['noise']}")
    return "\n".join(lines)


def plot(series: dict[str, dict], ref: dict, path: Path, t0: float, start: float) -> str | None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    deg = 180.0 / math.pi
    fig, axes = plt.subplots(3, 1, figsize=(13, 10))
    tr, br = ref["sideslip"]
    window = (start - t0, min(start - t0 + 60.0, tr[-1] - t0))
    for ax, zoom in ((axes[0], False), (axes[1], True)):
        sel = slice(None) if not zoom else (tr - t0 >= window[0]) & (tr - t0 <= window[1])
        ax.plot(tr[sel] - t0, br[sel] * deg, "k-", lw=1.6, label="reference")
        for i, (name, est) in enumerate(series.items()):
            if "sideslip" not in est:
                continue
            te, ye = est["sideslip"]
            s = slice(None) if not zoom else (te - t0 >= window[0]) & (te - t0 <= window[1])
            style = dict(color="0.55", lw=1.0) if name == "baseline" else dict(color=f"C{i}", lw=0.9)
            ax.plot(te[s] - t0, ye[s] * deg, label=name, **style)
        ax.set_ylabel("sideslip [deg]")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=3)
    axes[0].set_title("Stanford 2014 drive: sideslip (top: whole drive; middle: 60 s)")
    tv, vv = ref["vx"]
    axes[2].plot(tv - t0, vv, "k-", lw=1.6, label="reference vx")
    for i, (name, est) in enumerate(series.items()):
        if name != "baseline" and "vx" in est:
            axes[2].plot(est["vx"][0] - t0, est["vx"][1], color=f"C{i}", lw=0.9, label=f"{name} vx")
    axes[2].set_ylabel("vx [m/s]")
    axes[2].set_xlabel("time [s]")
    axes[2].grid(True, alpha=0.3)
    axes[2].legend(loc="upper right", fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path.name


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/stanford", help="output directory (default: out/stanford)")
    p.add_argument("--data-dir", default=None, help="folder of the Stanford text files (default: ../shared/data/stanford_sideslip_2014 "
                        "beside the repository)")
    p.add_argument("--filters", default=",".join(FILTERS),
                   help=f"comma-separated state filters (default: {','.join(FILTERS)})")
    p.add_argument("--speed", default=",".join(SPEED_MODES),
                   help="comma-separated speed sources: none (as logged), ref (ASSUMED wheel speeds from the "
                        "reference vx) (default: both)")
    p.add_argument("--noise", choices=("data", "paper"), default="data",
                   help="measurement-noise R of the filters: from the data as the baseline does (default), "
                        "or paper 004's")
    p.add_argument("--rows", type=int, default=None, help="use only the first N samples (quick look)")
    p.add_argument("--vibration-std", type=float, default=0.0,
                   help="add 10-60 Hz vibration (up to 45 Hz at 100 Hz) of this std [m/s^2] to the "
                        "accelerometer, filters and baseline alike")
    p.add_argument("--vibration-seed", type=int, default=0, help="seed of the vibration")
    p.add_argument("--wheel-dropout", type=_seconds_window, default=None, metavar="FROM:TO",
                   help="ASSUMED wheel speeds (speed ref) NaN from FROM to TO s after the drive's start (a "
                        "CAN dropout; TO past the end: lost for good); the errors over it are added")
    p.add_argument("--warmup", type=float, default=DEFAULT_WARMUP_S, help="seconds skipped by the metrics")
    add_tuning_option(p, "the comparison's filter layer")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_namespace_option(p)


def _seconds_window(text: str) -> tuple[float, float]:
    try:
        start, end = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected FROM:TO in seconds, got {text!r}") from None
    return start, end


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.paths import params_file
    node_group = node_group_factory(args.namespace, [params_file(VEHICLE)])
    try:
        result = run(Path(args.out), node_group, data_dir=args.data_dir,
                     filters=[f for f in args.filters.split(",") if f],
                     speeds=[s for s in args.speed.split(",") if s], noise=args.noise, rows=args.rows,
                     warmup_s=args.warmup, progress=not args.quiet, vibration_std=args.vibration_std,
                     vibration_seed=args.vibration_seed, wheel_dropout=args.wheel_dropout,
                     params=args.params)
    except (ValueError, RuntimeError, FileNotFoundError) as exc:
        print(f"stanford comparison failed: {exc}", file=sys.stderr)
        return 1
    print(format_table(result))
    print(f"wrote {Path(args.out) / 'comparison.json'} and {Path(args.out) / 'comparison.png'}")
    return 0 if all(row.get("lossless", True) for row in result["rows"]) else 1
