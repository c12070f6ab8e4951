"""``vehicle-estimation``: the launcher (a plain Python script, not ``ros2 launch``).

Subcommands::

    vehicle-estimation demo [--out DIR]                 simulate a drive, replay it, report
    vehicle-estimation simulate --scenario NAME --out BAG
    vehicle-estimation run [--vehicle FILE] [--params FILE ...] [--namespace NS] [--remap FROM:=TO ...]
    vehicle-estimation replay BAG --record OUT [--vehicle FILE] [--params FILE] [--remap FROM:=TO ...]
                                                        BAG: MCAP/sqlite3 rosbag2 or ROS 1 .bag
    vehicle-estimation report BAG [--out DIR]
    vehicle-estimation inspect BAG [--vehicle V] [--params P ...] [--remap FROM:=TO ...] [--json]
                                                        topics of a bag and what each node will do
    vehicle-estimation experiment paper004 [--out DIR]   contrast experiment of paper 004
    vehicle-estimation import MAPPING --out BAG [--data-dir DIR] [--rows N]
                                                        column logs (CSV/text) -> contract bag
    vehicle-estimation stanford [--out DIR]             real Stanford drive: state filters vs
                                                        the linear single-track KF baseline
    vehicle-estimation validate [--out DIR] [--cases commonroad,fastsim,sim] [--quick]
                                                        every estimator vs a textbook baseline,
                                                        on drives our simulator did not make
    vehicle-estimation params [--write|--check README.md] the parameter reference of every node
    vehicle-estimation bench [--sections cores,pipeline,live] [--minutes 30]
                                                        speed and memory figures (a table)
    vehicle-estimation paper000 [--out DIR]             paper 000 Tables 2-4, 6: TA-AEKF vs EKF,
                                                        MLP, LSTM, transformer; tau; OOD masses
    vehicle-estimation paper002 [--out DIR]             paper 002 Table 2: EKF, UKF, AO-UKF,
                                                        AO-UKF + GA-BPNN, VB-ACKF with outliers
    vehicle-estimation calibrate BAG --mass KG --out calibrated.yaml
                                                        paper 003 training phase from one drive
    vehicle-estimation campaign [--out DIR]             calibration + paper 003's 18 drives + wind
    vehicle-estimation truck-data | train-mass-transformer | train-gabpnn
                                                        data and training of the shipped models

``run`` and ``replay`` start every node as its own OS process. Ctrl-C or SIGTERM stops them
all; the children also die with the launcher if it is killed (no orphans).
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import signal
import sys
import time
from pathlib import Path

from vehicle_estimation.paths import params_file


def _params_files(args: argparse.Namespace) -> list[Path]:
    """``--vehicle`` then every ``--params`` (default ``estimation``): a later file wins."""
    return [params_file(args.vehicle)] + [params_file(name) for name in (args.params or ["estimation"])]


def _node_group(args: argparse.Namespace, overrides=None, log_dir: Path | None = None, remaps=()):
    from vehicle_estimation.launcher.processes import NodeGroup
    return NodeGroup(_params_files(args), namespace=args.namespace, overrides=overrides or {}, log_dir=log_dir,
                     remaps=list(remaps))


def _remap_arg(text: str) -> tuple[str, str]:
    """argparse type of ``--remap FROM:=TO``: a malformed one is a usage error that says why."""
    from vehicle_estimation.contract.topics import parse_remap
    try:
        return parse_remap(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_remap_option(p: argparse.ArgumentParser, help_text: str) -> None:
    p.add_argument("--remap", action="append", type=_remap_arg, default=[], metavar="FROM:=TO",
                   help=help_text + "; repeat for more topics")


def _add_node_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default="sedan_d_class",
                   help="vehicle params file or name in params/ (default: sedan_d_class)")
    p.add_argument("--params", action="append", default=None,
                   help="node params file or name in params/ (default: estimation); repeat to "
                        "layer files, a later file overriding an earlier one")
    p.add_argument("--namespace", default="/", help="ROS namespace of every node (default: /)")


def _default_state_dir() -> str:
    import os
    return str(Path(os.environ.get("ROS_HOME") or Path.home() / ".ros") / "vehicle_estimation")


def cmd_run(args: argparse.Namespace) -> int:
    overrides = {}
    if args.state_dir:
        # One state file per namespace: two vehicles on one computer never share an estimate.
        ns = args.namespace.strip("/").replace("/", "_") or "root"
        overrides["mass"] = {"persist.path": str(Path(args.state_dir) / f"mass_{ns}.json")}
    group = _node_group(args, overrides, remaps=args.remap)
    stopping = {"flag": False}

    def on_signal(signum, frame):  # noqa: ARG001
        stopping["flag"] = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    group.start()
    names = ", ".join(n.spec.name for n in group.nodes)
    print(f"started {names} in namespace {args.namespace}; Ctrl-C stops them", file=sys.stderr)
    try:
        while not stopping["flag"]:
            for node in group.check():
                code = node.process.returncode
                if code == 2:  # bad parameters: respawning would only repeat the error
                    print(f"{node.spec.name} refused its parameters (exit 2); stopping", file=sys.stderr)
                    stopping["flag"] = True
                    break
                node.restarts += 1
                print(f"{node.spec.name} exited with {code}; respawning (restart {node.restarts})",
                      file=sys.stderr)
                group.restart(node)
            time.sleep(0.2)
    finally:
        group.stop()
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from vehicle_estimation.io.inspect_bag import InspectError, format_summary, summarize
    from vehicle_estimation.launcher.replay import ReplayError, print_stats, replay
    # What `inspect` says of this bag with these params: the sources and fallbacks each node
    # will use, and what will stay empty, before minutes of replay.
    try:
        print(format_summary(summarize(Path(args.bag), _params_files(args), dict(args.remap))), file=sys.stderr)
    except (InspectError, OSError, ValueError) as exc:
        print(f"replay: cannot inspect {args.bag} ({exc}); replaying anyway", file=sys.stderr)
    record = Path(args.record) if args.record else None
    log_dir = Path(args.log_dir) if args.log_dir else None
    if log_dir:
        log_dir.mkdir(parents=True, exist_ok=True)
    try:
        stats = replay(Path(args.bag), record, lambda ov: _node_group(args, ov, log_dir),
                       namespace=args.namespace, tick_s=args.tick, progress=not args.quiet,
                       remap=dict(args.remap))
    except ReplayError as exc:
        print(f"replay failed: {exc}", file=sys.stderr)
        return 1
    print_stats(stats)
    return 0 if stats.lossless else 1


def cmd_report(args: argparse.Namespace) -> int:
    from vehicle_estimation.evaluation import report
    argv = [args.bag] + (["--out", args.out] if args.out else [])
    return report.main(argv)


def cmd_simulate(args: argparse.Namespace, rest: list[str]) -> int:
    from vehicle_estimation.sim import cli as sim_cli
    return sim_cli.main(rest)


def cmd_demo(args: argparse.Namespace) -> int:
    from vehicle_estimation.sim import default_scenario, scenario_by_name, simulate, write_bag
    from vehicle_estimation.evaluation import report
    from vehicle_estimation.launcher.replay import ReplayError, print_stats, replay

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
        stats = replay(drive, estimates, lambda ov: _node_group(args, ov, out / "logs"),
                       namespace=args.namespace, progress=True)
    except ReplayError as exc:
        print(f"replay failed: {exc}; node logs in {out / 'logs'}", file=sys.stderr)
        return 1
    print_stats(stats)
    print(f"[3/3] report -> {report_dir}")
    code = report.main([str(estimates), "--out", str(report_dir)])
    return code if stats.lossless else 1


def cmd_experiment(args: argparse.Namespace) -> int:
    from vehicle_estimation.experiments import paper004_joint_soft_sensing as experiment
    from vehicle_estimation.launcher.processes import NodeGroup

    def node_group(params, overrides, log_dir):
        files = [params_file(args.vehicle)] + [params_file(name) for name in params]
        return NodeGroup(files, namespace=args.namespace, overrides=overrides or {}, log_dir=log_dir)

    out = Path(args.out or f"out/{args.name}")
    return experiment.run_experiment(experiment.EXPERIMENTS[args.name], out, node_group,
                                     duration_s=args.duration, namespace=args.namespace,
                                     progress=not args.quiet)


def cmd_bench(args: argparse.Namespace) -> int:
    from vehicle_estimation.evaluation import bench
    return bench.main(args)


def cmd_stanford(args: argparse.Namespace) -> int:
    from vehicle_estimation.validation import stanford
    from vehicle_estimation.launcher.processes import NodeGroup

    def node_group(params, overrides, log_dir):
        files = [params_file(stanford.VEHICLE)] + list(params)
        return NodeGroup(files, namespace=args.namespace, overrides=overrides or {}, log_dir=log_dir)

    return stanford.main(args, node_group)


#: Subcommands that are one tool module each (``add_arguments(parser)`` and ``main(args)``).
def cmd_validate(args: argparse.Namespace) -> int:
    from vehicle_estimation.launcher.processes import NodeGroup
    from vehicle_estimation.validation import validate

    def node_group(params, overrides, log_dir):
        return NodeGroup(list(params), namespace=args.namespace, overrides=overrides or {}, log_dir=log_dir)

    return validate.main(args, node_group)


TOOL_COMMANDS = {
    "paper000": ("experiments.paper000_ta_aekf", "paper 000: TA-AEKF vs EKF, MLP, LSTM and transformer (Tables 2-4, 6)"),
    "paper002": ("experiments.paper002_aoukf_gabpnn", "paper 002: EKF, UKF, anti-outlier UKF (+ GA-BPNN) on outliers (Table 2)"),
    "inspect": ("io.inspect_bag", "what a bag holds and what each node will make of it (before a replay)"),
    "calibrate": ("training.calibrate", "learn gear ratios, torque map, CdA, Cr, inertias from one drive of known mass"),
    "campaign": ("experiments.paper003_obd_campaign", "calibration plus paper 003's drive campaign (loads, tyres, windows, wind)"),
    "truck-data": ("training.truck_data", "simulate the paper-000 truck drives the mass networks train on"),
    "train-mass-transformer": ("training.train_mass_transformer", "train the paper-000 mass networks (safetensors)"),
    "train-gabpnn": ("training.train_gabpnn", "train the paper-002 GA-BPNN correction (npz, no pickle)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vehicle-estimation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulate a drive, replay it through all nodes, report")
    p.add_argument("--out", default="out/demo", help="output directory (default: out/demo)")
    p.add_argument("--scenario", default=None, help="simulator scenario (default: the default drive)")
    _add_node_options(p)

    sub.add_parser("simulate", help="simulate a drive into a bag (see: simulate --help)", add_help=False)
    sub.add_parser("params", help="the parameter reference of every node (see: params --help)", add_help=False)

    p = sub.add_parser("run", help="start every node (live)")
    _add_node_options(p)
    p.add_argument("--state-dir", default=_default_state_dir(),
                   help="where the mass node persists its estimate, so that a restart resumes it "
                        "(default: $ROS_HOME/vehicle_estimation, else ~/.ros/vehicle_estimation); "
                        "'' turns persistence off")
    _add_remap_option(p, "ROS remapping given to every node as -r FROM:=TO (e.g. imu/data:=/sensors/imu)")

    p = sub.add_parser("replay", help="play a bag through every node and record the estimates")
    p.add_argument("bag", help="rosbag2 directory (MCAP or sqlite3) or ROS 1 .bag file; stamps may start at 0 s")
    p.add_argument("--record", required=True, help="output bag directory (MCAP)")
    p.add_argument("--tick", type=float, default=0.1, help="replay tick of bag time [s]")
    p.add_argument("--log-dir", default=None, help="write each node's log here")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_remap_option(p, "play a bag topic as a contract topic, ROS-style CONTRACT:=BAG_TOPIC (e.g. "
                      "imu/data:=/sensors/imu; the reverse order is taken too)")
    _add_node_options(p)

    p = sub.add_parser("experiment", help="contrast experiment of a paper: one drive, two strategies")
    from vehicle_estimation.experiments.paper004_joint_soft_sensing import add_arguments
    add_arguments(p)
    p.add_argument("--vehicle", default="sedan_d_class",
                   help="vehicle params file or name in params/ (default: sedan_d_class)")
    p.add_argument("--namespace", default="/", help="ROS namespace of every node (default: /)")

    p = sub.add_parser("report", help="metrics and plots of estimates against ground truth")
    p.add_argument("bag")
    p.add_argument("--out", default=None)

    sub.add_parser("import", help="import CSV/text column logs into a contract bag (see: import --help)",
                   add_help=False)

    p = sub.add_parser("stanford", help="real Stanford drive: state filters vs the linear single-track KF")
    from vehicle_estimation.validation.stanford import add_arguments as stanford_arguments
    stanford_arguments(p)
    p.add_argument("--namespace", default="/", help="ROS namespace of every node (default: /)")

    p = sub.add_parser("validate", help="every estimator vs a textbook baseline, through the nodes, on "
                                        "drives our simulator did not make (a table of ratios)")
    from vehicle_estimation.validation.validate import add_arguments as validate_arguments
    validate_arguments(p)
    p.add_argument("--namespace", default="/", help="ROS namespace of every node (default: /)")

    p = sub.add_parser("bench", help="speed and memory figures: cores, pipeline replay, live (a table)")
    from vehicle_estimation.evaluation.bench import add_arguments as bench_arguments
    bench_arguments(p)

    for command, (module, help_text) in TOOL_COMMANDS.items():
        p = sub.add_parser(command, help=help_text)
        importlib.import_module(f"vehicle_estimation.{module}").add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "simulate":
        return cmd_simulate(argparse.Namespace(), argv[1:])
    if argv and argv[0] == "import":
        from vehicle_estimation.io import importer
        return importer.main(argv[1:])
    if argv and argv[0] == "params":
        from vehicle_estimation.ros import paramdoc
        return paramdoc.main(argv[1:])
    args = build_parser().parse_args(argv)
    commands = {"demo": cmd_demo, "run": cmd_run, "replay": cmd_replay, "report": cmd_report,
                "experiment": cmd_experiment, "stanford": cmd_stanford, "bench": cmd_bench,
                "validate": cmd_validate}
    if args.command in TOOL_COMMANDS:
        return importlib.import_module(f"vehicle_estimation.{TOOL_COMMANDS[args.command][0]}").main(args)
    return commands[args.command](args)


if __name__ == "__main__":
    raise SystemExit(main())
