"""Accuracy report of a recorded drive: estimates against ground truth from a rosbag2.

Usage::

    report BAG [--out DIR] [--warmup SECONDS]

Reads a rosbag2 (MCAP or sqlite3) with ``rosbags`` (no ROS installation needed), pairs each
estimate topic with its ground-truth topic, prints a table, and writes ``report.json`` and
one PNG per group (``mass.png``, ``slope.png``, ``vehicle_state.png``, ``fusion.png``) into
the output directory. Groups whose topics are missing are reported as ``"no data"``.

Time stamps: ``header.stamp`` where the message has one, else the bag's log time. Each
pair's times are shown relative to the earliest sample of that pair. The truth is
interpolated linearly at the estimate stamps within the overlap (mass: zero-order hold, the
last truth value held to the end). Metrics other than the mass convergence rate and the
"last half" figures skip the first ``warmup_s`` seconds of each pair.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vehicle_estimation.contract import topics
from vehicle_estimation.estimators.common.rotations import euler_from_quat
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.evaluation.consistency import (
    POSE_AND_BIAS_TOPICS,
    consistency_group,
    format_consistency,
    plot_consistency,
    truth_in_odom,
)

DEFAULT_WARMUP_S = 5.0
CV_WINDOW_S = 5.0          # length of the trailing c_v window of the mass CR (Eq. 40 of paper 000)
MAX_LAG_S = 2.0

Series = dict[str, np.ndarray]   # "t" plus named value arrays


# --------------------------------------------------------------------- bag reading
def _stamp(msg: Any, log_ns: int) -> float:
    header = getattr(msg, "header", None)
    if header is not None:
        stamp = header.stamp
        ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
        if ns > 0:
            return ns * 1e-9
    return log_ns * 1e-9


def _extract(msgtype: str, msg: Any) -> dict[str, float] | None:
    if msgtype == "std_msgs/msg/Float64":
        return {"value": float(msg.data)}
    if msgtype == "geometry_msgs/msg/Vector3Stamped":  # stamped companion: value, variance, converged
        return {"value": float(msg.vector.x), "variance": float(msg.vector.y), "converged": float(msg.vector.z)}
    if msgtype in ("geometry_msgs/msg/TwistWithCovarianceStamped",):
        tw, cov = msg.twist.twist, msg.twist.covariance
        return {"vx": tw.linear.x, "vy": tw.linear.y, "yaw_rate": tw.angular.z,
                "var_vx": float(cov[0]), "var_vy": float(cov[7]), "var_yaw_rate": float(cov[35])}
    if msgtype == "nav_msgs/msg/Odometry":
        tw = msg.twist.twist
        pos = msg.pose.pose.position
        q = msg.pose.pose.orientation
        roll, pitch, yaw = euler_from_quat(np.array([q.x, q.y, q.z, q.w]))
        var_roll, var_pitch = _tilt_variances(msg.pose.covariance, float(yaw))
        return {"x": pos.x, "y": pos.y, "vx": tw.linear.x, "vy": tw.linear.y,
                "speed": math.hypot(tw.linear.x, tw.linear.y),
                "roll": float(roll), "pitch": float(pitch), "yaw": float(yaw), "yaw_rate": tw.angular.z,
                # REP-103 6x6 row-major: twist (vx, ...) and pose (x, y, z, then rotations)
                "var_vx": float(msg.twist.covariance[0]), "var_yaw_rate": float(msg.twist.covariance[35]),
                "var_roll": var_roll, "var_pitch": var_pitch, "var_x": float(msg.pose.covariance[0]),
                "var_y": float(msg.pose.covariance[7]), "var_yaw": float(msg.pose.covariance[35])}
    if msgtype == "sensor_msgs/msg/NavSatFix":
        return {"lat": float(msg.latitude), "lon": float(msg.longitude), "alt": float(msg.altitude)}
    if msgtype == "sensor_msgs/msg/Imu":        # estimation/imu_bias and its truth: biases, variances
        a, g = msg.linear_acceleration, msg.angular_velocity
        ca, cg = msg.linear_acceleration_covariance, msg.angular_velocity_covariance
        return {"ax": a.x, "ay": a.y, "az": a.z, "gx": g.x, "gy": g.y, "gz": g.z,
                "var_ax": float(ca[0]), "var_ay": float(ca[4]), "var_az": float(ca[8]),
                "var_gx": float(cg[0]), "var_gy": float(cg[4]), "var_gz": float(cg[8])}
    return None


def _tilt_variances(pose_covariance, yaw: float) -> tuple[float, float]:
    """The variances of the roll and the pitch from an Odometry pose covariance whose rotation
    block is about the fixed axes (REP-103; about ENU for ``estimation/odometry``). Near level
    (ZYX Euler angles) a roll error is the rotation about the heading, (cos yaw, sin yaw, 0),
    and a pitch error the rotation about the heading's left, (-sin yaw, cos yaw, 0)."""
    rotation = np.asarray(pose_covariance, dtype=float).reshape(6, 6)[3:, 3:]
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    return float(forward @ rotation @ forward), float(left @ rotation @ left)


def _match_topic(available: Sequence[str], relative: str) -> str | None:
    """The bag topic for a relative name: '/name' or 'name' first, else a unique '/ns/.../name'."""
    exact = "/" + relative.lstrip("/")
    if exact in available:
        return exact
    if exact[1:] in available:          # rosbags writes a topic as it is given: ours unrooted
        return exact[1:]
    suffix = [name for name in sorted(available) if name.endswith(exact)]
    return suffix[0] if len(suffix) == 1 else None


STAMPED_COMPANIONS = {
    topics.MASS: topics.MASS_STAMPED,
    topics.ROAD_SLOPE: topics.ROAD_SLOPE_STAMPED,
    topics.SIDESLIP: topics.SIDESLIP_STAMPED,
}


def read_bag(bag_path: str | Path, wanted: Sequence[str]) -> dict[str, Series]:
    """Series of the ``wanted`` relative topic names present in the bag (others absent)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    out: dict[str, Series] = {}
    with AnyReader([Path(bag_path)], default_typestore=typestore) as reader:
        by_name: dict[str, list] = {}
        for conn in reader.connections:
            by_name.setdefault(conn.topic, []).append(conn)
        chosen = {}
        for rel in wanted:
            # A scalar estimate's stamped companion carries the estimate's own stamp; the
            # std_msgs/Float64 twin only has the recorder's receive time.
            name = _match_topic(list(by_name), STAMPED_COMPANIONS.get(rel, rel)) \
                or _match_topic(list(by_name), rel)
            if name is not None:
                chosen[rel] = by_name[name]
        for rel, conns in chosen.items():
            rows: list[tuple[float, dict[str, float]]] = []
            for conn, log_ns, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                values = _extract(conn.msgtype, msg)
                if values is not None:
                    rows.append((_stamp(msg, log_ns), values))
            if not rows:
                continue
            rows.sort(key=lambda r: r[0])
            series: Series = {"t": np.array([r[0] for r in rows], dtype=float)}
            for key in rows[0][1]:
                series[key] = np.array([r[1][key] for r in rows], dtype=float)
            out[rel] = series
    return out


# --------------------------------------------------------------------- helpers
def json_safe(value: Any) -> Any:
    """JSON-safe: NaN/inf -> None, NumPy scalars -> Python, tuples and sets -> lists."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic) and not isinstance(value, np.floating):
        return value.item()
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


def _pair(data: dict[str, Series], est_topic: str, true_topic: str, est_key: str, true_key: str,
          *, mode: str = "linear", hold_last: bool = False):
    """(t_rel, est, truth, t0) on the estimate stamps, or None when either topic is missing."""
    est = data.get(est_topic)
    true = data.get(true_topic)
    if est is None or true is None:
        return None
    t0 = float(min(est["t"][0], true["t"][0]))
    t, e, tr = metrics.align(est["t"] - t0, est[est_key], true["t"] - t0, true[true_key],
                             mode=mode, hold_last=hold_last)
    if t.size == 0:
        return None
    return t, e, tr, t0


def _after(t: np.ndarray, *arrays: np.ndarray, start: float) -> list[np.ndarray]:
    sel = t >= start
    return [t[sel]] + [a[sel] for a in arrays]


def _lag(data, est_topic, true_topic, est_key, true_key) -> float:
    est, true = data[est_topic], data[true_topic]
    return metrics.estimate_lag(est["t"], est[est_key], true["t"], true[true_key], max_lag=MAX_LAG_S)


def _quantity(t, e, tr, warmup_s, *, unit: str, scale: float = 1.0, scaled_unit: str | None = None) -> dict:
    t_w, e_w, tr_w = _after(t, e, tr, start=t[0] + warmup_s)
    out = {"unit": unit, **metrics.summary(e_w, tr_w)}
    if scaled_unit:
        for key in ("mae", "rmse", "bias", "max_abs_error"):
            out[f"{key}_{scaled_unit}"] = out[key] * scale
    return out


# --------------------------------------------------------------------- groups
def _mass_group(data, warmup_s):
    pair = _pair(data, "estimation/mass", topics.GT_MASS, "value", "value", mode="previous", hold_last=True)
    if pair is None:
        return None, None
    t, e, tr, _ = pair
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    window = int(max(10, round(CV_WINDOW_S / dt))) if dt > 0 else 10
    window = min(window, t.size)
    cr = metrics.convergence_rate(e, tr, window=window)
    t_w, e_w, tr_w = _after(t, e, tr, start=t[0] + warmup_s)
    half = t >= t[0] + 0.5 * (t[-1] - t[0])
    pe_half = metrics.percent_errors(e[half], tr[half])
    res = {
        "unit": "kg",
        "n": int(e_w.size),
        "mape_percent": metrics.mape(e_w, tr_w),
        "mae": metrics.mae(e_w, tr_w),
        "rmse": metrics.rmse(e_w, tr_w),
        "bias": metrics.bias(e_w, tr_w),
        "convergence_rate_steps": cr,
        "convergence_time_s": metrics.convergence_time(t, e, tr, window=window),
        "cv_window_samples": window,
        "last_half_max_abs_percent_error": float(np.max(np.abs(pe_half))) if pe_half.size else math.nan,
        "last_half_mape_percent": metrics.mape(e[half], tr[half]),
        "share_within_3_percent": metrics.share_within(e_w, tr_w, 3.0),
        "share_within_5_percent": metrics.share_within(e_w, tr_w, 5.0),
        "final_estimate": float(e[-1]),
        "final_truth": float(tr[-1]),
    }
    return res, {"t": t, "est": e, "true": tr}


def _slope_group(data, warmup_s):
    pair = _pair(data, "estimation/road_slope", topics.GT_ROAD_SLOPE, "value", "value")
    if pair is None:
        return None, None
    t, e, tr, _ = pair
    res = _quantity(t, e, tr, warmup_s, unit="rad", scale=180.0 / math.pi, scaled_unit="deg")
    res["lag_s"] = _lag(data, "estimation/road_slope", topics.GT_ROAD_SLOPE, "value", "value")
    return res, {"t": t, "est": e, "true": tr}


def _state_group(data, warmup_s):
    res: dict[str, Any] = {}
    plots: dict[str, Any] = {}
    spec = [("vx", "m/s", 1.0, None), ("vy", "m/s", 1.0, None), ("yaw_rate", "rad/s", 180 / math.pi, "deg_s")]
    for key, unit, scale, su in spec:
        pair = _pair(data, "estimation/vehicle_state", topics.GT_VEHICLE_STATE, key, key)
        if pair is None:
            continue
        t, e, tr, _ = pair
        res[key] = _quantity(t, e, tr, warmup_s, unit=unit, scale=scale, scaled_unit=su)
        plots[key] = {"t": t, "est": e, "true": tr, "unit": unit}
    pair = _pair(data, "estimation/sideslip", topics.GT_SIDESLIP, "value", "value")
    if pair is not None:
        t, e, tr, _ = pair
        res["sideslip"] = _quantity(t, e, tr, warmup_s, unit="rad", scale=180 / math.pi, scaled_unit="deg")
        res["sideslip"]["lag_s"] = _lag(data, "estimation/sideslip", topics.GT_SIDESLIP, "value", "value")
        plots["sideslip"] = {"t": t, "est": e, "true": tr, "unit": "rad"}
    return (res or None), (plots or None)


def _fusion_group(data, warmup_s):
    res: dict[str, Any] = {}
    plots: dict[str, Any] = {}
    pair = _pair(data, "estimation/odometry", topics.GT_ODOMETRY, "speed", "speed")
    if pair is None:
        return None, None
    t, e, tr, t0 = pair
    res["speed"] = _quantity(t, e, tr, warmup_s, unit="m/s")
    plots["speed"] = {"t": t, "est": e, "true": tr}
    aligned = truth_in_odom(data)
    if aligned is not None and np.isfinite(aligned["x"]).all():
        est, i = data["estimation/odometry"], aligned["index"]
        t = aligned["t"] - t0
        ex, ey, tx, ty = est["x"][i], est["y"][i], aligned["x"], aligned["y"]
        dist = np.hypot(ex - tx, ey - ty)
        t_w, d_w = _after(t, dist, start=t[0] + warmup_s)
        res["position"] = {
            "unit": "m",
            "n": int(d_w.size),
            "horizontal_rmse": float(np.sqrt(np.mean(d_w ** 2))) if d_w.size else math.nan,
            "horizontal_max": float(np.max(d_w)) if d_w.size else math.nan,
            "final_horizontal_error": float(dist[-1]),
            "frame": aligned["frame"],
        }
        plots["position"] = {"t": t, "ex": ex, "ey": ey, "tx": tx, "ty": ty, "err": dist}
    pp = _pair(data, "estimation/odometry", topics.GT_ODOMETRY, "pitch", "pitch")
    if pp is not None:
        t, e, tr, _ = pp
        if np.any(e != 0.0) or np.any(tr != 0.0):
            res["pitch"] = _quantity(t, e, tr, warmup_s, unit="rad", scale=180 / math.pi, scaled_unit="deg")
            plots["pitch"] = {"t": t, "est": e, "true": tr}
    return res, plots


# --------------------------------------------------------------------- plots
def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _plot_pair(ax_val, ax_err, d, label, unit, scale=1.0, err_label=None, err_scale=None):
    ax_val.plot(d["t"], d["true"] * scale, "k-", lw=1.0, label="truth")
    ax_val.plot(d["t"], d["est"] * scale, "C0-", lw=1.0, label="estimate")
    ax_val.set_ylabel(f"{label} [{unit}]")
    ax_val.legend(loc="best", fontsize=8)
    ax_val.grid(True, alpha=0.3)
    if err_scale is None:
        ax_err.plot(d["t"], (d["est"] - d["true"]) * scale, "C3-", lw=1.0)
        ax_err.set_ylabel(f"error [{unit}]")
    else:
        ax_err.plot(d["t"], err_scale(d), "C3-", lw=1.0)
        ax_err.set_ylabel(err_label)
    ax_err.grid(True, alpha=0.3)


def _save(fig, path: Path) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    _plt().close(fig)
    return path.name


def _plot_mass(d, out: Path) -> str:
    plt = _plt()
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    _plot_pair(a, b, d, "mass", "kg", err_label="error [%]",
               err_scale=lambda d: 100.0 * (d["est"] - d["true"]) / np.abs(d["true"]))
    for lim in (-5, 5):
        b.axhline(lim, color="0.5", ls="--", lw=0.8)
    b.set_xlabel("time [s]")
    fig.suptitle("Mass estimate vs ground truth")
    return _save(fig, out / "mass.png")


def _plot_slope(d, out: Path) -> str:
    plt = _plt()
    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    _plot_pair(a, b, d, "road slope", "deg", scale=180.0 / math.pi)
    b.set_xlabel("time [s]")
    fig.suptitle("Road slope estimate vs ground truth")
    return _save(fig, out / "slope.png")


def _plot_state(plots, out: Path) -> str:
    plt = _plt()
    rows = [k for k in ("vx", "vy", "yaw_rate", "sideslip") if k in plots]
    fig, axes = plt.subplots(len(rows), 2, figsize=(12, 2.6 * len(rows)), squeeze=False)
    labels = {"vx": ("v_x", "m/s", 1.0), "vy": ("v_y", "m/s", 1.0),
              "yaw_rate": ("yaw rate", "deg/s", 180 / math.pi), "sideslip": ("sideslip", "deg", 180 / math.pi)}
    for i, key in enumerate(rows):
        label, unit, scale = labels[key]
        _plot_pair(axes[i, 0], axes[i, 1], plots[key], label, unit, scale=scale)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    fig.suptitle("Vehicle state estimate vs ground truth (left) and error (right)")
    return _save(fig, out / "vehicle_state.png")


def _plot_fusion(plots, out: Path) -> str:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    _plot_pair(axes[0, 0], axes[0, 1], plots["speed"], "speed", "m/s")
    axes[0, 0].set_xlabel("time [s]")
    axes[0, 1].set_xlabel("time [s]")
    pos = plots.get("position")
    if pos is not None:
        axes[1, 0].plot(pos["tx"], pos["ty"], "k-", lw=1.0, label="truth")
        axes[1, 0].plot(pos["ex"], pos["ey"], "C0-", lw=1.0, label="estimate")
        axes[1, 0].set_xlabel("x [m]")
        axes[1, 0].set_ylabel("y [m]")
        axes[1, 0].set_aspect("equal", adjustable="datalim")
        axes[1, 0].legend(loc="best", fontsize=8)
        axes[1, 0].grid(True, alpha=0.3)
        axes[1, 1].plot(pos["t"], pos["err"], "C3-", lw=1.0)
        axes[1, 1].set_xlabel("time [s]")
        axes[1, 1].set_ylabel("horizontal position error [m]")
        axes[1, 1].grid(True, alpha=0.3)
    else:
        for ax in axes[1]:
            ax.text(0.5, 0.5, "no position data", ha="center", va="center", transform=ax.transAxes)
    fig.suptitle("Fused odometry vs ground truth")
    return _save(fig, out / "fusion.png")


def _plot_consistency(series, out: Path) -> str:
    return _save(plot_consistency(series, out, _plt()), out / "consistency.png")


# --------------------------------------------------------------------- report
WANTED = ("estimation/mass", topics.GT_MASS, "estimation/road_slope", topics.GT_ROAD_SLOPE,
          "estimation/vehicle_state", topics.GT_VEHICLE_STATE, "estimation/sideslip",
          topics.GT_SIDESLIP, "estimation/odometry", topics.GT_ODOMETRY) + POSE_AND_BIAS_TOPICS


GROUP_BUILDERS: dict[str, Callable] = {
    "mass": _mass_group, "slope": _slope_group, "vehicle_state": _state_group, "fusion": _fusion_group,
    "consistency": consistency_group}
PLOTTERS: dict[str, Callable] = {
    "mass": _plot_mass, "slope": _plot_slope, "vehicle_state": _plot_state, "fusion": _plot_fusion,
    "consistency": _plot_consistency}


def compute_groups(data: dict[str, Series], warmup_s: float = DEFAULT_WARMUP_S) -> tuple[dict, dict]:
    """Metrics per group (``{"status": "ok", ...}`` or ``{"status": "no data"}``) and the
    paired time series behind them (``{"t", "est", "true"}`` per quantity) for plots."""
    groups: dict[str, Any] = {}
    series: dict[str, Any] = {}
    for name, build in GROUP_BUILDERS.items():
        res, plots = build(data, warmup_s)
        if res is None:
            groups[name] = {"status": "no data"}
            continue
        groups[name] = {"status": "ok", **res}
        series[name] = plots
    return groups, series


def make_report(bag_path: str | Path, out_dir: str | Path, *, warmup_s: float = DEFAULT_WARMUP_S,
                print_table: bool = True) -> dict:
    """Compute the metrics of one bag, write ``report.json`` and PNGs to ``out_dir``.

    Returns the report dict (the content of ``report.json``, NaN written as null).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = read_bag(bag_path, WANTED)
    groups, series = compute_groups(data, warmup_s)
    figures = [PLOTTERS[name](series[name], out) for name in groups if name in series]
    report = json_safe({
        "bag": Path(bag_path).name,
        "warmup_s": float(warmup_s),
        "topics_found": sorted(data),
        "groups": groups,
        "figures": figures,
    })
    with open(out / "report.json", "w", encoding="utf-8") as handle:
        json.dump(report, handle, indent=2, sort_keys=True)
        handle.write("\n")
    if print_table:
        print(format_table(report))
    return report


def _fmt(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def format_table(report: dict) -> str:
    """A readable text table of a report dict."""
    lines = [f"Report of {report['bag']} (warm-up {report['warmup_s']:g} s)",
             f"{'group':<14}{'quantity':<12}{'metric':<34}{'value':>12}"]
    lines.append("-" * len(lines[-1]))
    for group, res in report["groups"].items():
        if group == "consistency":
            continue
        if res.get("status") != "ok":
            lines.append(f"{group:<14}{'-':<12}{'no data':<34}{'':>12}")
            continue
        scalars = {k: v for k, v in res.items() if k not in ("status", "unit") and not isinstance(v, dict)}
        for key, value in scalars.items():
            lines.append(f"{group:<14}{'':<12}{key + ' [' + res.get('unit', '') + ']':<34}{_fmt(value):>12}"
                         if key in ("mae", "rmse", "bias", "max_abs_error") else
                         f"{group:<14}{'':<12}{key:<34}{_fmt(value):>12}")
        for qty, sub in res.items():
            if not isinstance(sub, dict):
                continue
            for key, value in sub.items():
                if key == "unit":
                    continue
                label = f"{key} [{sub.get('unit', '')}]" if key in ("mae", "rmse", "bias", "max_abs_error") else key
                lines.append(f"{group:<14}{qty:<12}{label:<34}{_fmt(value):>12}")
    consistency = report["groups"].get("consistency", {})
    if consistency.get("status") == "ok":
        lines.append("")
        lines.extend(format_consistency({k: v for k, v in consistency.items() if isinstance(v, dict)}))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="report", description="Estimation accuracy report of a rosbag2.")
    parser.add_argument("bag", help="rosbag2 directory or file (MCAP or sqlite3)")
    parser.add_argument("--out", default=None, help="output directory (default: <bag>_report)")
    parser.add_argument("--warmup", type=float, default=DEFAULT_WARMUP_S,
                        help=f"seconds skipped at the start of each pair (default {DEFAULT_WARMUP_S})")
    args = parser.parse_args(argv)
    bag = Path(args.bag)
    if not bag.exists():
        print(f"report: no such bag: {bag}", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else bag.parent / (bag.stem + "_report")
    try:
        make_report(bag, out, warmup_s=args.warmup)
    except Exception as exc:  # noqa: BLE001 - a CLI should fail with a message, not a trace
        print(f"report: cannot read {bag}: {exc}", file=sys.stderr)
        return 1
    print(f"report written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
