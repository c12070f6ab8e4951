"""Paper 002 Table 2: EKF, UKF, anti-outlier UKF, AO-UKF + GA-BPNN and our VB-ACKF on drives
with gross measurement errors.

Usage::

    vehicle-estimation paper002 [--out DIR] [--scenarios paper002_dlc,paper002_mixed]
                                [--duration S] [--weights FILE] [--no-plots]

(or ``python -m vehicle_estimation.experiments.paper002_aoukf_gabpnn`` with the same options)

For every scenario (default: the ISO 3888-2 double lane changes ``paper002_dlc`` and the
300 s mixed drive ``paper002_mixed``, both with the isolated spikes and speckled bursts of
Sec. 3.3 on ay and yaw rate and time-varying noise; see ``sim/scenario.py``) the simulator's
sensor arrays are run OFFLINE through each core, sample by sample, exactly as the state node
feeds them:

* ``z = [ax, ay, r]``: the simulated IMU (its noise, outliers and bias random walk) rotated
  from imu_link back to base_link by the KNOWN mounting rotation and compensated with the
  simulator's bias (what the fusion node delivers to the state node: a bias-compensated IMU in
  base_link). The outliers stay in the data.
* ``inputs``: road-wheel steer angle = measured steering-wheel angle / steering ratio, the
  measured wheel speeds (zero-order hold of the 100 Hz joint states), the TRUE road slope (the
  slope node's output in the pipeline), mass ``None`` (the vehicle file's mass).

Every filter gets the same samples. MAE and RMSE of vx, vy and r against the truth at the IMU
stamps (after ``--warmup`` s) are printed next to the paper's Table 2 (EKF and GA-BPNN
columns), together with the anti-outlier counters; ``comparison.json`` and one PNG per
scenario are written under ``--out`` (default ``out/paper002``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from vehicle_estimation.estimators.state.aoukf import AOUKFConfig, VehicleStateAOUKF
from vehicle_estimation.estimators.common.rotations import quat_from_euler, quat_to_rotmat
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs
from vehicle_estimation.evaluation import metrics
from vehicle_estimation.contract.vehicle import VehicleParams

#: Paper 002 Table 2 (Sec. 4.1): MAE / RMSE of the EKF and of the GA-BPNN (AO-UKF + GA-BPNN).
PAPER_TABLE2 = {
    "EKF": {"mae": {"vx": 0.192, "vy": 0.321, "r": 0.323}, "rmse": {"vx": 0.251, "vy": 0.354, "r": 0.422}},
    "GA-BPNN": {"mae": {"vx": 0.0465, "vy": 0.142, "r": 0.0179}, "rmse": {"vx": 0.0518, "vy": 0.139, "r": 0.0219}},
}
STATES = ("vx", "vy", "r")
UNITS = {"vx": "m/s", "vy": "m/s", "r": "rad/s"}
DEFAULT_SCENARIOS = ("paper002_dlc", "paper002_mixed")
#: Rows of the table, in order; the last one is the paper's proposed method.
FILTER_ROWS = ("EKF", "UKF", "AO-UKF", "AO-UKF + GA-BPNN", "VB-ACKF")


@dataclasses.dataclass
class Drive:
    """One simulated drive as the state node sees it, on the IMU stamps."""

    name: str
    params: VehicleParams
    t: np.ndarray              # (N,) [s]
    z: np.ndarray              # (N, 3) [ax, ay, r] bias-compensated, base_link
    steer: np.ndarray          # (N,) road-wheel angle [rad]
    wheel_speeds: np.ndarray   # (N, 4) [rad/s]
    slope: np.ndarray          # (N,) [rad]
    truth: dict[str, np.ndarray]   # vx, vy, r at t
    outlier_mask: np.ndarray   # (N,) bit 0 ay, bit 1 r

    def inputs(self, i: int) -> VehicleInputs:
        return VehicleInputs(steer_angle=float(self.steer[i]), wheel_speeds=self.wheel_speeds[i],
                             slope=float(self.slope[i]))


def drive_from_sim(sim: Any) -> Drive:
    """The node's view of a :class:`~vehicle_estimation.sim.simulate.SimResult` (module docstring)."""
    imu, js, truth = sim.sensors["imu"], sim.sensors["joint_states"], sim.truth
    C = quat_to_rotmat(quat_from_euler(*np.asarray(imu["misalignment_rpy"], dtype=float)))
    t = np.asarray(imu["t"], dtype=float)
    accel = (imu["accel"] - imu["accel_bias"]) @ C.T      # imu_link -> base_link
    gyro = (imu["gyro"] - imu["gyro_bias"]) @ C.T
    idx = np.clip(np.searchsorted(js["t"], t, side="right") - 1, 0, js["t"].size - 1)
    params = sim.scenario.vehicle
    return Drive(
        name=sim.scenario.name, params=params, t=t,
        z=np.stack([accel[:, 0], accel[:, 1], gyro[:, 2]], axis=1),
        steer=js["position"][idx, 4] / params.steering_ratio,
        wheel_speeds=np.asarray(js["velocity"][idx, :4], dtype=float),
        slope=np.interp(t, truth["t"], truth["slope"]),
        truth={"vx": np.interp(t, truth["t"], truth["vx"]), "vy": np.interp(t, truth["t"], truth["vy"]),
               "r": np.interp(t, truth["t"], truth["yaw_rate"])},
        outlier_mask=np.asarray(imu["outlier_mask"]))


def run_estimator(drive: Drive, estimator: Any) -> np.ndarray:
    """Step ``estimator`` (VehicleStateAOUKF / VehicleStateCKF API) through ``drive``;
    returns its ``[vx, vy, r]`` after every sample, ``(N, 3)`` (NaN before it starts)."""
    out = np.full((drive.t.size, 3), np.nan)
    for i in range(drive.t.size):
        estimator.step(float(drive.t[i]), drive.inputs(i), drive.z[i])
        if estimator.initialised:
            out[i] = estimator.x[:3]
    return out


def score(drive: Drive, est: np.ndarray, warmup_s: float) -> dict[str, Any]:
    keep = drive.t >= drive.t[0] + warmup_s
    res: dict[str, Any] = {"mae": {}, "rmse": {}, "max": {}}
    for j, key in enumerate(STATES):
        res["mae"][key] = metrics.mae(est[keep, j], drive.truth[key][keep])
        res["rmse"][key] = metrics.rmse(est[keep, j], drive.truth[key][keep])
        res["max"][key] = metrics.max_abs_error(est[keep, j], drive.truth[key][keep])
    return res


def make_estimators(params: VehicleParams, correction: Any = None,
                    config: Optional[AOUKFConfig] = None) -> dict[str, Callable[[], Any]]:
    """Factories of the compared estimators (all on the same vehicle parameters)."""
    from vehicle_estimation.estimators.state.ckf import VehicleStateConfig
    from vehicle_estimation.estimators.state.vbackf import VehicleStateVBACKF

    # the paper's tyre (its D), as the GA-BPNN weights were trained on (train_gabpnn)
    cfg = AOUKFConfig(mf_peak_from_road_friction=False) if config is None else config
    rows: dict[str, Callable[[], Any]] = {
        "EKF": lambda: VehicleStateAOUKF(params, dataclasses.replace(cfg, filter="ekf")),
        "UKF": lambda: VehicleStateAOUKF(params, dataclasses.replace(cfg, filter="ukf")),
        "AO-UKF": lambda: VehicleStateAOUKF(params, dataclasses.replace(cfg, filter="aoukf")),
    }
    if correction is not None:
        rows["AO-UKF + GA-BPNN"] = lambda: VehicleStateAOUKF(params, dataclasses.replace(cfg, filter="aoukf"),
                                                             correction=correction.fresh())
    rows["VB-ACKF"] = lambda: VehicleStateVBACKF(params, VehicleStateConfig(init_vx_from_wheel_speeds=True))
    return rows


NO_WHEELS_ROWS = ("EKF", "UKF", "AO-UKF")


def run_scenario(scenario: Any, correction: Any, warmup_s: float, *, paper_observations: bool = True,
                 log: Callable[[str], None] = print) -> tuple[dict[str, Any], dict[str, Any]]:
    """All rows on one scenario: ``(results, series)``; results per row: metrics, counters, CPU s."""
    from vehicle_estimation.sim import simulate

    drive = drive_from_sim(simulate(scenario))
    mask = drive.outlier_mask
    results: dict[str, Any] = {
        "scenario": scenario.name, "duration_s": float(drive.t[-1] - drive.t[0]), "samples": int(drive.t.size),
        "injected_outliers": {"ay": int(np.count_nonzero(mask & 1)), "r": int(np.count_nonzero(mask & 2))},
        "rows": {}, "rows_no_wheel_speeds": {}}
    series: dict[str, Any] = {"t": drive.t - drive.t[0], "truth": drive.truth, "z": drive.z, "mask": mask,
                              "rows": {}, "rows_no_wheel_speeds": {}}
    groups = [("rows", make_estimators(drive.params, correction))]
    if paper_observations:
        cfg = AOUKFConfig(wheel_speed_update=False, mf_peak_from_road_friction=False)
        groups.append(("rows_no_wheel_speeds",
                       {k: v for k, v in make_estimators(drive.params, None, cfg).items() if k in NO_WHEELS_ROWS}))
    for group, factories in groups:
        for name, factory in factories.items():
            est = factory()
            t0 = time.process_time()
            x = run_estimator(drive, est)
            cpu = time.process_time() - t0
            res = score(drive, x, warmup_s)
            counters = getattr(est, "counters", None)
            res["counters"] = dict(counters) if counters is not None else {
                "rejected_" + k: v for k, v in getattr(est, "rejected", {}).items()}
            res["cpu_s"] = cpu
            results[group][name] = res
            series[group][name] = x
            log(f"  {scenario.name} {name}{' (no wheel speeds)' if group != 'rows' else ''}: "
                f"MAE vx {res['mae']['vx']:.4f} vy {res['mae']['vy']:.4f} r {res['mae']['r']:.4f}  ({cpu:.1f} CPU s)")
    return results, series


def format_table(results: dict[str, Any]) -> str:
    """Markdown table of one scenario next to the paper's Table 2."""
    head = ("| filter | MAE vx [m/s] | MAE vy [m/s] | MAE r [rad/s] | RMSE vx | RMSE vy | RMSE r | max vx | max vy "
            "| max r | outliers down-weighted / zero gain / replaced |")
    lines = [f"**{results['scenario']}** ({results['duration_s']:.0f} s, {results['samples']} IMU samples; injected "
             f"outlier samples: ay {results['injected_outliers']['ay']}, r {results['injected_outliers']['r']})", "",
             head, "|" + "---|" * (head.count("|") - 1)]

    def row(name: str, res: dict[str, Any]) -> str:
        c = res.get("counters", {})
        out = (f"{c.get('isolated_downweighted', 0)} / {c.get('isolated_zero_gain', 0)} / "
               f"{c.get('speckled_replaced', 0)}") if "isolated_downweighted" in c else "-"
        return (f"| {name} | " + " | ".join(f"{res[m][k]:.4f}" for m in ("mae", "rmse", "max") for k in STATES)
                + f" | {out} |")

    for name, res in results["rows"].items():
        lines.append(row(name, res))
    for name, res in results.get("rows_no_wheel_speeds", {}).items():
        lines.append(row(f"{name}, no wheel speeds (paper's observations)", res))
    for name, ref in PAPER_TABLE2.items():
        lines.append(f"| paper Table 2: {name} | " + " | ".join(f"{ref[m][k]:.4g}" for m in ("mae", "rmse") for k in STATES)
                     + " | | | | |")
    best = results["rows"].get("AO-UKF + GA-BPNN")
    if best is not None:
        verdict = ", ".join(f"{k} {best['mae'][k]:.4f} {'<=' if best['mae'][k] <= PAPER_TABLE2['GA-BPNN']['mae'][k] else '>'} "
                            f"{PAPER_TABLE2['GA-BPNN']['mae'][k]}" for k in STATES)
        lines += ["", f"AO-UKF + GA-BPNN MAE vs the paper's GA-BPNN: {verdict}"]
    return "\n".join(lines)


def plot_scenario(results: dict[str, Any], series: dict[str, Any], path: Path) -> Optional[str]:
    """Measured and estimated yaw rate, then the error of every filter in vx, vy, r."""
    from vehicle_estimation.evaluation.report import _plt

    plt = _plt()
    t = series["t"]
    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True)
    ax0 = axes[0]
    flagged = (series["mask"] & 2) > 0
    ax0.plot(t, series["z"][:, 2], ".", ms=1.5, color="0.7", label="measured r (with outliers)")
    ax0.plot(t[flagged], series["z"][flagged, 2], "x", ms=3, color="r", label="injected outliers")
    ax0.plot(t, series["truth"]["r"], "k", lw=1.2, label="truth")
    for name in ("EKF", "AO-UKF + GA-BPNN"):
        if name in series["rows"]:
            ax0.plot(t, series["rows"][name][:, 2], lw=0.9, label=name)
    ax0.set_ylabel("r [rad/s]")
    ax0.legend(loc="upper right", fontsize=7, ncol=3)
    for j, key in enumerate(STATES):
        ax = axes[j + 1]
        # VB-ACKF (a different model, no outlier handling) first and faint: it would hide the rest
        for name in sorted(series["rows"], key=lambda n: n != "VB-ACKF"):
            x = series["rows"][name]
            ax.plot(t, x[:, j] - series["truth"][key], lw=0.8, label=name, alpha=0.4 if name == "VB-ACKF" else 1.0)
        ax.set_ylabel(f"{key} error [{UNITS[key]}]")
        ax.grid(alpha=0.3)
    axes[1].legend(loc="upper right", fontsize=7, ncol=5)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(f"paper 002 comparison, {results['scenario']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return str(path)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/paper002", help="output directory (default out/paper002)")
    p.add_argument("--scenarios", default=",".join(DEFAULT_SCENARIOS),
                   help=f"comma-separated scenario names (default {','.join(DEFAULT_SCENARIOS)})")
    p.add_argument("--duration", type=float, default=None, help="override every scenario's duration [s]")
    p.add_argument("--weights", default=None,
                   help="GA-BPNN weights (.npz; default the shipped vehicle_estimation/models/gabpnn_<vehicle>.npz)")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds skipped by the metrics (default 1)")
    p.add_argument("--no-paper-observations", action="store_true",
                   help="skip the rows without wheel speeds (the paper's observation set)")
    p.add_argument("--no-plots", action="store_true", help="do not write PNGs")


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.estimators.state.gabpnn import load_correction
    from vehicle_estimation.sim.scenario import scenario_by_name
    from vehicle_estimation.evaluation.report import json_safe
    from vehicle_estimation.estimators.state.gabpnn import default_weights_path

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    try:
        scenarios = [scenario_by_name(n) for n in names]
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 2
    comparison: dict[str, Any] = {"paper_table2": PAPER_TABLE2, "scenarios": {}, "imu": (
        "simulated IMU rotated to base_link by the known mounting, bias-compensated with the simulator's bias; "
        "noise, time-varying noise and outliers kept"), "warmup_s": args.warmup}
    tables = []
    for scn in scenarios:
        if args.duration is not None:
            scn = dataclasses.replace(scn, duration_s=args.duration)
        weights = Path(args.weights) if args.weights else default_weights_path(scn.vehicle.name)
        try:
            correction = load_correction(weights)
        except (ValueError, FileNotFoundError) as exc:
            print(f"no GA-BPNN correction for {scn.vehicle.name}: {exc}", file=sys.stderr)
            correction = None
        print(f"{scn.name}: {scn.duration_s:.0f} s, vehicle {scn.vehicle.name}, weights "
              f"{weights if correction is not None else 'none'}")
        results, series = run_scenario(scn, correction, args.warmup,
                                       paper_observations=not args.no_paper_observations)
        results["weights"] = str(weights) if correction is not None else None
        if not args.no_plots:
            results["figure"] = plot_scenario(results, series, out / f"{scn.name}.png")
        comparison["scenarios"][scn.name] = results
        tables.append(format_table(results))
    text = "\n\n".join(tables)
    print()
    print(text)
    with open(out / "comparison.json", "w", encoding="utf-8") as handle:
        json.dump(json_safe(comparison), handle, indent=2)
        handle.write("\n")
    (out / "comparison.md").write_text(text + "\n", encoding="utf-8")
    print(f"\nwrote {out / 'comparison.json'}" + ("" if args.no_plots else " and the PNGs"))
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    sys.exit(run_as_script(sys.modules[__name__]))
