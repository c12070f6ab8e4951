"""``simulate --scenario NAME --out BAGDIR [--vehicle PARAMS_YAML] [--duration S] [--seed N] [--mass KG]``."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

from vehicle_estimation.contract.vehicle import load_vehicle_params
from vehicle_estimation.sim.scenario import SCENARIOS, params_path, scenario_by_name


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="simulate", description="Simulate a drive and write a rosbag2 (MCAP) bag.")
    p.add_argument("--scenario", default="default", choices=sorted(SCENARIOS), help="named scenario")
    p.add_argument("--out", required=True, help="output bag directory (must not exist)")
    p.add_argument("--vehicle", help="vehicle params YAML (path, or a name in params/, e.g. audi_a4)")
    p.add_argument("--duration", type=float, help="duration [s]")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--mass", type=float, help="true vehicle mass [kg]")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from vehicle_estimation.sim import simulate, write_bag

    scn = scenario_by_name(args.scenario)
    changes = {}
    if args.vehicle:
        changes["vehicle"] = load_vehicle_params(params_path(args.vehicle))
    if args.duration is not None:
        changes["duration_s"] = args.duration
    if args.seed is not None:
        changes["seed"] = args.seed
    if changes:
        scn = dataclasses.replace(scn, **changes)
    if args.mass is not None:
        scn = dataclasses.replace(scn, vehicle=scn.vehicle.with_mass(args.mass))
    t0 = time.process_time()
    try:
        result = simulate(scn)
        path = write_bag(result, args.out)
    except (FileExistsError, ValueError) as exc:
        print(f"simulate: error: {exc}", file=sys.stderr)
        return 2
    print(f"simulate: {scn.name} ({scn.vehicle.name}, {scn.duration_s:.0f} s, seed {scn.seed}) -> {path} "
          f"[{time.process_time() - t0:.1f} s CPU]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
