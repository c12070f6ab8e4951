"""Contrast experiments: one simulated drive, two strategies, one comparison table.

``vehicle-estimation experiment paper004`` reproduces paper 004 Sec. 7.1: the D-class sedan on
a closed hilly, curvy loop (~150 s a lap) starting at 80 km/h with the time-varying
measurement noise of Eq. 34, and two strategies replayed through the same four nodes on the
same bag:

* proposed: VB-ACKF vehicle states, slope prediction + cubic observer, FFRLS mass;
* contrasted: CKF vehicle states and the classical slope model (theta' = 0), FFRLS mass.

It prints MAE and RMSE of vy, vx, sideslip, slope and mass for both, the MAE reduction next
to the paper's, and the slope lag (the time shift that best aligns estimate and truth), and
writes ``comparison.json`` and ``comparison.png`` under ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence


@dataclasses.dataclass(frozen=True)
class Quantity:
    """One compared quantity: where it sits in the report groups, and how to show it."""

    label: str
    group: str
    key: str | None          # sub-key inside the group (None: the group itself)
    unit: str
    scale: float = 1.0       # report unit -> shown unit
    paper_mae_reduction_percent: float | None = None

    def metrics(self, groups: dict) -> dict | None:
        res = groups.get(self.group, {})
        if res.get("status") != "ok":
            return None
        return res.get(self.key) if self.key else res


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    scenario: str
    description: str
    strategies: tuple[tuple[str, tuple[str, ...]], ...]   # (name, params files layered)
    quantities: tuple[Quantity, ...]


DEG = 180.0 / math.pi

EXPERIMENTS: dict[str, Experiment] = {
    "paper004": Experiment(
        name="paper004",
        scenario="paper004_loop",
        description="paper 004 Sec. 7.1: proposed (VB-ACKF + slope prediction + cubic observer + "
                    "FFRLS) vs contrasted (CKF + classical slope model + FFRLS)",
        strategies=(("proposed", ("estimation", "paper004_proposed")),
                    ("contrasted", ("estimation", "paper004_contrasted"))),
        quantities=(
            Quantity("vy", "vehicle_state", "vy", "m/s", 1.0, 80.0),
            Quantity("vx", "vehicle_state", "vx", "m/s", 1.0, 71.4),
            Quantity("sideslip", "vehicle_state", "sideslip", "deg", DEG, 79.7),
            Quantity("slope", "slope", None, "deg", DEG, 89.9),
            Quantity("mass", "mass", None, "kg", 1.0, 69.2),
        ),
    ),
}


def compare(experiment: Experiment, reports: dict[str, dict]) -> dict[str, Any]:
    """Comparison rows from the report groups of each strategy (first = proposed)."""
    first, second = (name for name, _ in experiment.strategies)
    rows = []
    for q in experiment.quantities:
        row: dict[str, Any] = {"quantity": q.label, "unit": q.unit,
                               "paper_mae_reduction_percent": q.paper_mae_reduction_percent}
        for name in (first, second):
            m = q.metrics(reports[name])
            row[name] = None if m is None else {"mae": m["mae"] * q.scale, "rmse": m["rmse"] * q.scale}
            if m is not None and "lag_s" in m:
                row[name]["lag_s"] = m["lag_s"]
        if row[first] and row[second] and row[second]["mae"] > 0.0:
            row["mae_reduction_percent"] = 100.0 * (1.0 - row[first]["mae"] / row[second]["mae"])
            row["rmse_reduction_percent"] = 100.0 * (1.0 - row[first]["rmse"] / row[second]["rmse"])
            paper = q.paper_mae_reduction_percent
            row["meets_paper"] = None if paper is None else bool(row["mae_reduction_percent"] >= paper)
        rows.append(row)
    return {"experiment": experiment.name, "description": experiment.description,
            "strategies": [name for name, _ in experiment.strategies], "rows": rows}


def format_comparison(comparison: dict) -> str:
    first, second = comparison["strategies"]
    head = (f"{'quantity':<10}{'unit':<6}{first + ' MAE':>14}{second + ' MAE':>16}{first + ' RMSE':>15}"
            f"{second + ' RMSE':>17}{'MAE red.':>10}{'paper':>8}  met")
    lines = [comparison["description"], head, "-" * len(head)]

    def fmt(value: Any, width: int, spec: str = ".4g") -> str:
        return f"{'n/a':>{width}}" if value is None else f"{value:>{width}{spec}}"

    for row in comparison["rows"]:
        a, b = row.get(first) or {}, row.get(second) or {}
        met = row.get("meets_paper")
        lines.append(
            f"{row['quantity']:<10}{row['unit']:<6}{fmt(a.get('mae'), 14)}{fmt(b.get('mae'), 16)}"
            f"{fmt(a.get('rmse'), 15)}{fmt(b.get('rmse'), 17)}"
            f"{fmt(row.get('mae_reduction_percent'), 9, '.1f')}%{fmt(row['paper_mae_reduction_percent'], 7, '.1f')}%"
            f"  {'-' if met is None else ('yes' if met else 'NO')}")
    for row in comparison["rows"]:
        a, b = row.get(first) or {}, row.get(second) or {}
        if "lag_s" in a or "lag_s" in b:
            lines.append(f"{row['quantity']} lag: {first} {fmt(a.get('lag_s'), 0, '.3f')} s, "
                         f"{second} {fmt(b.get('lag_s'), 0, '.3f')} s")
    return "\n".join(lines)


def plot_comparison(experiment: Experiment, series: dict[str, dict], out: Path) -> str | None:
    """Truth and both strategies, one panel per quantity."""
    from vehicle_estimation.evaluation.report import _plt

    plt = _plt()
    panels = []
    for q in experiment.quantities:
        per = {}
        for name, _ in experiment.strategies:
            group = series.get(name, {}).get(q.group)
            if group is None:
                continue
            d = group.get(q.key) if q.key else group
            if d is not None:
                per[name] = d
        if per:
            panels.append((q, per))
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 2.4 * len(panels)), sharex=True)
    axes = list(axes) if len(panels) > 1 else [axes]
    t0 = None
    for ax, (q, per) in zip(axes, panels):
        for i, (name, d) in enumerate(per.items()):
            t0 = d["t"][0] if t0 is None else t0
            if i == 0:
                ax.plot(d["t"] - t0, d["true"] * q.scale, "k", lw=1.2, label="truth")
            ax.plot(d["t"] - t0, d["est"] * q.scale, lw=0.9, label=name)
        ax.set_ylabel(f"{q.label} [{q.unit}]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(experiment.description, fontsize=9)
    fig.tight_layout()
    path = out / "comparison.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return str(path)


def run_experiment(experiment: Experiment, out: Path, node_group: Callable[[Sequence[str], Any, Path], Any], *,
                   duration_s: float | None = None, namespace: str = "/", progress: bool = True) -> int:
    """Simulate, replay every strategy, report, compare. Returns a process exit code."""
    from vehicle_estimation.sim import scenario_by_name, simulate, write_bag
    from vehicle_estimation.evaluation import report
    from vehicle_estimation.launcher.replay import ReplayError, print_stats, replay

    drive = out / "drive"
    if out.exists():
        for child in [drive] + [out / name for name, _ in experiment.strategies]:
            if child.exists():
                shutil.rmtree(child)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario_by_name(experiment.scenario)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    steps = 2 + len(experiment.strategies)
    print(f"[1/{steps}] simulating '{scenario.name}' ({scenario.duration_s:.0f} s) -> {drive}")
    t0 = time.process_time()
    write_bag(simulate(scenario), drive)
    print(f"      {time.process_time() - t0:.1f} CPU s")
    reports: dict[str, dict] = {}
    series: dict[str, dict] = {}
    lossless = True
    for i, (name, params) in enumerate(experiment.strategies, start=2):
        estimates, logs = out / name / "estimates", out / name / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        print(f"[{i}/{steps}] {name} ({' + '.join(params)}) -> {estimates}")
        try:
            stats = replay(drive, estimates, lambda ov, p=params, lg=logs: node_group(p, ov, lg),
                           namespace=namespace, progress=progress)
        except ReplayError as exc:
            print(f"replay failed: {exc}; node logs in {logs}", file=sys.stderr)
            return 1
        print_stats(stats)
        lossless = lossless and stats.lossless
        data = report.read_bag(estimates, report.WANTED)
        reports[name], series[name] = report.compute_groups(data)
        report.make_report(estimates, out / name / "report", print_table=False)
    comparison = compare(experiment, reports)
    comparison["scenario"] = scenario.name
    comparison["duration_s"] = scenario.duration_s
    comparison["figure"] = plot_comparison(experiment, series, out)
    print(f"[{steps}/{steps}] comparison -> {out / 'comparison.json'}")
    print(format_comparison(comparison))
    with open(out / "comparison.json", "w", encoding="utf-8") as handle:
        json.dump(report.json_safe(comparison), handle, indent=2)
        handle.write("\n")
    return 0 if lossless else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", choices=sorted(EXPERIMENTS), help="experiment")
    p.add_argument("--out", default=None, help="output directory (default: out/<name>)")
    p.add_argument("--duration", type=float, default=None, help="override the scenario duration [s]")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
