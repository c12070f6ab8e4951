"""``vehicle-estimation demo``: simulate a drive, replay it through every node, report."""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

from vehicle_estimation.launcher.options import add_node_options, node_group


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/demo", help="output directory (default: out/demo)")
    p.add_argument("--scenario", default=None, help="simulator scenario (default: the default drive)")
    add_node_options(p)


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.evaluation import report
    from vehicle_estimation.launcher.replay import ReplayError, print_stats, replay
    from vehicle_estimation.sim import default_scenario, scenario_by_name, simulate, write_bag

    out = Path(args.out)
    drive, estimates, report_dir = out / "drive", out / "estimates", out / "report"
    for path in (drive, estimates, report_dir):
        if path.exists():
            shutil.rmtree(path)
    out.mkdir(parents=True, exist_ok=True)
    scenario = scenario_by_name(args.scenario) if args.scenario else default_scenario()
    print(f"[1/3] simulating '{args.scenario or 'default'}' ({scenario.duration_s:.0f} s) -> {drive}")
    t0 = time.process_time()
    write_bag(simulate(scenario), drive)
    print(f"      {time.process_time() - t0:.1f} CPU s")
    print(f"[2/3] replaying through fusion, road_slope, vehicle_state, mass -> {estimates}")
    try:
        stats = replay(drive, estimates, lambda ov: node_group(args, ov, out / "logs"),
                       namespace=args.namespace, progress=True)
    except ReplayError as exc:
        print(f"replay failed: {exc}; node logs in {out / 'logs'}", file=sys.stderr)
        return 1
    print_stats(stats)
    print(f"[3/3] report -> {report_dir}")
    code = report.main([str(estimates), "--out", str(report_dir)])
    return code if stats.lossless else 1
