"""Is each published variance honest? Errors against their own sigma, for ``report`` and ``validate``.

Every estimate that carries a variance and has a truth in the bag is checked: the scalar
estimates of :data:`CONSISTENCY_SPEC`, the fusion's horizontal position and heading (in the
frame the estimate is published in, :func:`truth_in_odom`), and the IMU biases
(``estimation/imu_bias`` against ``ground_truth/imu_bias``). Position and biases are pooled
over their axes, each axis with its own variance.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.rotations import wrap_angle
from vehicle_estimation.evaluation import metrics

#: Estimates whose variance is checked against the truth: (name, estimate topic, key, variance
#: key, flag key or None, truth topic, truth key, truth interpolation, unit, display scale).
CONSISTENCY_SPEC = (
    ("mass", "estimation/mass", "value", "variance", "converged", topics.GT_MASS, "value", "previous", "kg", 1.0),
    ("slope", "estimation/road_slope", "value", "variance", "converged", topics.GT_ROAD_SLOPE, "value",
     "linear", "deg", 180.0 / math.pi),
    ("sideslip", "estimation/sideslip", "value", "variance", "converged", topics.GT_SIDESLIP, "value",
     "linear", "deg", 180.0 / math.pi),
    ("vx", "estimation/vehicle_state", "vx", "var_vx", None, topics.GT_VEHICLE_STATE, "vx", "linear", "m/s", 1.0),
    ("vy", "estimation/vehicle_state", "vy", "var_vy", None, topics.GT_VEHICLE_STATE, "vy", "linear", "m/s", 1.0),
    ("yaw_rate", "estimation/vehicle_state", "yaw_rate", "var_yaw_rate", None, topics.GT_VEHICLE_STATE,
     "yaw_rate", "linear", "deg/s", 180.0 / math.pi),
    ("fusion_vx", "estimation/odometry", "vx", "var_vx", None, topics.GT_ODOMETRY, "vx", "linear", "m/s", 1.0),
    ("fusion_pitch", "estimation/odometry", "pitch", "var_pitch", None, topics.GT_ODOMETRY, "pitch", "linear",
     "deg", 180.0 / math.pi),
    ("fusion_roll", "estimation/odometry", "roll", "var_roll", None, topics.GT_ODOMETRY, "roll", "linear",
     "deg", 180.0 / math.pi),
    ("fusion_yaw_rate", "estimation/odometry", "yaw_rate", "var_yaw_rate", None, topics.GT_ODOMETRY, "yaw_rate",
     "linear", "deg/s", 180.0 / math.pi),
)

#: The IMU's biases, each over its three axes: (name, key prefix, unit, display scale).
BIAS_SPEC = (("accel_bias", "a", "m/s²", 1.0), ("gyro_bias", "g", "deg/s", 180.0 / math.pi))

#: What :func:`consistency_series` reads besides :data:`CONSISTENCY_SPEC`'s topics.
POSE_AND_BIAS_TOPICS = (topics.DATUM, topics.GT_DATUM, topics.IMU_BIAS, topics.GT_IMU_BIAS)

Series = dict[str, np.ndarray]


def truth_in_odom(data: dict[str, Series]) -> dict[str, Any] | None:
    """The truth's horizontal pose in the frame ``estimation/odometry`` is published in, on the
    estimate's stamps: ``{"t", "x", "y", "yaw", "frame"}``, or None without both topics.

    With ``estimation/datum`` (odom is ENU about that WGS84 point from the datum's stamp on)
    and ``ground_truth/datum`` (the truth's own origin) the truth is moved by the difference of
    the origins, and only samples from the datum's stamp on are kept: odom's origin is the
    first fix, whose own error would otherwise read as the estimate's. Without
    ``estimation/datum`` (no GNSS) odom is the pose at alignment with a free heading: the truth
    is turned and moved onto the first estimate. An estimate datum without a truth datum
    leaves the heading only (the position's frames cannot be related)."""
    est, true = data.get(topics.ODOMETRY), data.get(topics.GT_ODOMETRY)
    if est is None or true is None or not all(k in d for d in (est, true) for k in ("x", "y", "yaw")):
        return None
    order = np.argsort(true["t"], kind="stable")
    tt = true["t"][order]
    t = est["t"]
    inside = (t >= tt[0]) & (t <= tt[-1])
    datum, gt_datum = data.get(topics.DATUM), data.get(topics.GT_DATUM)
    if datum is not None:
        inside &= t >= datum["t"][0]
    if not np.any(inside):
        return None
    idx = np.nonzero(inside)[0]
    t = t[idx]
    x = np.interp(t, tt, true["x"][order])
    y = np.interp(t, tt, true["y"][order])
    yaw = np.interp(t, tt, np.unwrap(true["yaw"][order]))
    if datum is not None:
        if gt_datum is None:
            x = y = np.full(t.size, math.nan)
            frame = "ENU about estimation/datum (no ground_truth/datum: heading only)"
        else:
            from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
            origin = LocalTangentPlane(gt_datum["lat"][0], gt_datum["lon"][0], gt_datum["alt"][0])
            east, north, _ = origin.to_enu(datum["lat"][0], datum["lon"][0], datum["alt"][0])
            x, y = x - float(east), y - float(north)
            frame = "ENU about estimation/datum"
    else:
        turn = wrap_angle(float(est["yaw"][idx[0]] - yaw[0]))
        c, s = math.cos(turn), math.sin(turn)
        dx, dy = x - x[0], y - y[0]
        x = est["x"][idx[0]] + c * dx - s * dy
        y = est["y"][idx[0]] + s * dx + c * dy
        yaw = yaw + turn
        frame = "free: the first odometry sample's pose (no estimation/datum)"
    return {"index": idx, "t": t, "x": x, "y": y, "yaw": yaw, "frame": frame}


def _pose_series(data: dict[str, Series], start: float) -> dict[str, dict[str, Any]]:
    aligned = truth_in_odom(data)
    if aligned is None:
        return {}
    est, i = data[topics.ODOMETRY], aligned["index"]
    if "var_x" not in est:
        return {}
    sel = aligned["t"] >= start
    out: dict[str, dict[str, Any]] = {}
    if np.isfinite(aligned["x"]).any():
        error = np.column_stack([est["x"][i] - aligned["x"], est["y"][i] - aligned["y"]])
        variance = np.column_stack([est["var_x"][i], est["var_y"][i]])
        out["fusion_xy"] = {"t": aligned["t"][sel], "error": error[sel], "variance": variance[sel],
                            "converged": None, "unit": "m", "scale": 1.0}
    yaw_error = wrap_angle(est["yaw"][i] - aligned["yaw"])   # elementwise on arrays
    out["fusion_yaw"] = {"t": aligned["t"][sel], "error": yaw_error[sel], "variance": est["var_yaw"][i][sel],
                         "converged": None, "unit": "deg", "scale": 180.0 / math.pi}
    return out


def _bias_series(data: dict[str, Series], start: float) -> dict[str, dict[str, Any]]:
    est, true = data.get(topics.IMU_BIAS), data.get(topics.GT_IMU_BIAS)
    if est is None or true is None:
        return {}
    out: dict[str, dict[str, Any]] = {}
    order = np.argsort(true["t"], kind="stable")
    for name, prefix, unit, scale in BIAS_SPEC:
        # align() on the sample index once; the three axes share the truth's stamps
        t, idx, _ = metrics.align(est["t"], np.arange(est["t"].size, dtype=float), true["t"],
                                  true[prefix + "x"], mode="linear", hold_last=True)
        if t.size == 0:
            continue
        i = idx.astype(int)
        error = np.column_stack([est[prefix + axis][i] - np.interp(t, true["t"][order], true[prefix + axis][order])
                                 for axis in "xyz"])
        variance = np.column_stack([est[f"var_{prefix}{axis}"][i] for axis in "xyz"])
        sel = t >= start
        out[name] = {"t": t[sel], "error": error[sel], "variance": variance[sel], "converged": None,
                     "unit": unit, "scale": scale}
    return out


def consistency_series(data: dict[str, Series], warmup_s: float) -> dict[str, dict[str, Any]]:
    """Per checked estimate: stamps, error, variance and flag on the estimate stamps after the
    warm-up (the mass over the last half, as every mass figure); the pooled ones have one
    column per axis."""
    out: dict[str, dict[str, Any]] = {}
    for name, topic, key, var_key, flag_key, truth_topic, truth_key, mode, unit, scale in CONSISTENCY_SPEC:
        est, true = data.get(topic), data.get(truth_topic)
        if est is None or true is None or var_key not in est:
            continue
        if not np.any(np.isfinite(est[var_key]) & (est[var_key] > 0.0)):
            continue            # no variance published (a zero covariance): nothing to check
        # align() on the sample index keeps each estimate's own variance and flag with it
        t, idx, truth = metrics.align(est["t"], np.arange(est["t"].size, dtype=float), true["t"], true[truth_key],
                                      mode=mode, hold_last=mode == "previous")
        if t.size == 0:
            continue
        i = idx.astype(int)
        start = t[0] + (0.5 * (t[-1] - t[0]) if name == "mass" else warmup_s)
        sel = t >= start
        out[name] = {"t": t[sel], "error": (est[key][i] - truth)[sel], "variance": est[var_key][i][sel],
                     "converged": est[flag_key][i][sel] if flag_key and flag_key in est else None,
                     "unit": unit, "scale": scale}
    pooled: dict[str, dict[str, Any]] = {}
    odometry = data.get(topics.ODOMETRY)
    if odometry is not None and odometry["t"].size:
        pooled.update(_pose_series(data, float(odometry["t"][0]) + warmup_s))
    bias = data.get(topics.IMU_BIAS)
    if bias is not None and bias["t"].size:
        pooled.update(_bias_series(data, float(bias["t"][0]) + warmup_s))
    out.update({name: s for name, s in pooled.items()
                if np.any(np.isfinite(s["variance"]) & (np.asarray(s["variance"]) > 0.0))})
    return out


def consistency_group(data, warmup_s):
    """metrics.consistency of each checked estimate (``{name: metrics}`` or None) and the series."""
    series = consistency_series(data, warmup_s)
    res = {name: metrics.consistency(np.ravel(s["error"]), np.ravel(s["variance"]),
                                     None if s["converged"] is None else np.ravel(s["converged"]))
           for name, s in series.items()}
    return (res or None), (series or None)


def plot_consistency(series, out: Path, plt) -> Any:
    """One panel per checked estimate: its error against the published ±2σ (pooled estimates:
    one line and band per axis). Returns the figure."""
    fig, axes = plt.subplots(len(series), 1, figsize=(10, 2.2 * len(series)), sharex=True, squeeze=False)
    for ax, (name, s) in zip(axes[:, 0], series.items()):
        k = s["scale"]
        error, variance = np.asarray(s["error"]), np.asarray(s["variance"])
        if error.ndim == 1:
            error, variance = error[:, None], variance[:, None]
        for j in range(error.shape[1]):
            sigma2 = 2.0 * np.sqrt(np.maximum(variance[:, j], 0.0)) * k
            axis = "" if error.shape[1] == 1 else f" {'xyz'[j]}"
            ax.fill_between(s["t"], -sigma2, sigma2, color=f"C{j}", alpha=0.15, label=f"±2σ published{axis}")
            ax.plot(s["t"], error[:, j] * k, color=f"C{j}" if error.shape[1] > 1 else "tab:red", lw=0.8,
                    label=f"error{axis}")
        if s["converged"] is not None:
            flagged = s["converged"] > 0.5
            ax.plot(s["t"][~flagged], np.zeros(int((~flagged).sum())), ".", color="grey", ms=1,
                    label="not converged")
        ax.set_ylabel(f"{name} [{s['unit']}]")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=2)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Error against the published ±2σ")
    return fig


def format_share(x: Any) -> str:
    """A share 0-1 as a whole percentage; n/a for None or NaN."""
    return "n/a" if x is None or not math.isfinite(x) else f"{100.0 * x:.0f} %"


def format_consistency(rows: dict[str, dict]) -> list[str]:
    """Shares of the errors within 1/2/3 sigma of the published variance (Gaussian: 68/95/99.7 %)
    and NEES (honest: 1), over every sample and over those flagged converged."""
    head = (f"{'consistency':<16}{'n':>7}{'1σ':>7}{'2σ':>7}{'3σ':>7}{'NEES':>9}"
            f"{'conv.':>8}{'conv. 2σ':>10}{'conv. >3σ':>11}{'conv. NEES':>12}")
    lines = [head, "-" * len(head)]
    for name, c in rows.items():
        def num(key, spec=".3g"):
            v = c.get(key)
            return "n/a" if v is None or not math.isfinite(v) else format(v, spec)
        share = {key: format_share(c.get(key)) for key in (
            "within_1sigma", "within_2sigma", "within_3sigma", "converged_share", "converged_within_2sigma",
            "converged_beyond_3sigma")}
        lines.append(f"{name:<16}{c.get('n', 0):>7}{share['within_1sigma']:>7}{share['within_2sigma']:>7}"
                     f"{share['within_3sigma']:>7}{num('nees'):>9}{share['converged_share']:>8}"
                     f"{share['converged_within_2sigma']:>10}{share['converged_beyond_3sigma']:>11}"
                     f"{num('converged_nees'):>12}")
    lines.append("honest: 68 / 95 / 99.7 % within 1/2/3σ, NEES 1; NEES above 1: the variance is too small; "
                 "fusion_xy, accel_bias and gyro_bias pool their axes")
    return lines
