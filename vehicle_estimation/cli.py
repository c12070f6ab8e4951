"""``vehicle-estimation``: the launcher (a plain Python script, not ``ros2 launch``).

Subcommands::

    vehicle-estimation demo [--out DIR]                 simulate a drive, replay it, report
    vehicle-estimation simulate --scenario NAME --out BAG
    vehicle-estimation run [--vehicle FILE] [--params FILE ...] [--namespace NS] [--remap FROM:=TO ...]
    vehicle-estimation replay BAG --record OUT [--vehicle FILE] [--params FILE] [--remap FROM:=TO ...]
                          [--in-process]                BAG: MCAP/sqlite3 rosbag2 or ROS 1 .bag
    vehicle-estimation batch BAG_OR_DIR... --out DIR [--workers N] [--scheduler ADDRESS] [--resume]
                          [--calibrate --mass-from FILE.csv]
                                                        replay and report many bags on Dask
    vehicle-estimation report BAG [--out DIR]
    vehicle-estimation inspect BAG [--vehicle V] [--params P ...] [--remap FROM:=TO ...] [--json]
                                                        topics of a bag and what each node will do
    vehicle-estimation experiment paper004 [--out DIR]   contrast experiment of paper 004
    vehicle-estimation import MAPPING --out BAG [--data-dir DIR] [--rows N]
                                                        column logs (CSV/text) -> contract bag
    vehicle-estimation stanford [--out DIR]             real Stanford drive: state filters vs
                                                        the linear single-track KF baseline
    vehicle-estimation validate [--out DIR] [--cases commonroad,fastsim,truck,sim] [--quick]
                          [--params FILE ...]
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

``run`` and ``replay`` start every node as its own OS process (``replay --in-process`` and
``batch`` run the same nodes in one process per bag, without DDS). Ctrl-C or SIGTERM stops them
all; the children also die with the launcher if it is killed (no orphans).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from types import ModuleType


@dataclass(frozen=True)
class Command:
    """A subcommand: a module of :mod:`vehicle_estimation` with ``add_arguments(parser)`` and
    ``main(args)``, or, with ``own_argv``, ``main(argv)`` that parses the rest of the line itself."""

    module: str
    help: str
    own_argv: bool = False

    def load(self) -> ModuleType:
        return importlib.import_module(f"vehicle_estimation.{self.module}")


#: Subcommand -> its module, in the order ``--help`` lists them.
COMMANDS: dict[str, Command] = {
    "demo": Command("launcher.demo", "simulate a drive, replay it through all nodes, report"),
    "simulate": Command("sim.cli", "simulate a drive into a bag (see: simulate --help)", own_argv=True),
    "params": Command("ros.paramdoc", "the parameter reference of every node (see: params --help)", own_argv=True),
    "run": Command("launcher.live", "start every node (live)"),
    "replay": Command("launcher.replay", "play a bag through every node and record the estimates"),
    "batch": Command("fleet.batch", "replay and report many bags in parallel on Dask distributed "
                                    "(pip install -e '.[fleet]')"),
    "experiment": Command("launcher.experiment", "contrast experiment of a paper: one drive, two strategies"),
    "report": Command("evaluation.report", "metrics and plots of estimates against ground truth "
                                           "(see: report --help)", own_argv=True),
    "import": Command("io.importer", "import CSV/text column logs into a contract bag (see: import --help)",
                      own_argv=True),
    "stanford": Command("validation.stanford", "real Stanford drive: state filters vs the linear single-track KF"),
    "validate": Command("validation.validate", "every estimator vs a textbook baseline, through the nodes, on "
                                               "drives our simulator did not make (a table of ratios)"),
    "bench": Command("evaluation.bench", "speed and memory figures: cores, pipeline replay, live (a table)"),
    "paper000": Command("experiments.paper000_ta_aekf",
                        "paper 000: TA-AEKF vs EKF, MLP, LSTM and transformer (Tables 2-4, 6)"),
    "paper002": Command("experiments.paper002_aoukf_gabpnn",
                        "paper 002: EKF, UKF, anti-outlier UKF (+ GA-BPNN) on outliers (Table 2)"),
    "inspect": Command("io.inspect_bag", "what a bag holds and what each node will make of it (before a replay)"),
    "calibrate": Command("training.calibrate",
                         "learn gear ratios, torque map, CdA, Cr, inertias from one drive of known mass"),
    "campaign": Command("experiments.paper003_obd_campaign",
                        "calibration plus paper 003's drive campaign (loads, tyres, windows, wind)"),
    "truck-data": Command("training.truck_data", "simulate the paper-000 truck drives the mass networks train on"),
    "train-mass-transformer": Command("training.train_mass_transformer",
                                      "train the paper-000 mass networks (safetensors)"),
    "train-gabpnn": Command("training.train_gabpnn", "train the paper-002 GA-BPNN correction (npz, no pickle)"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every subcommand, or, given ``command``, with only that one's options
    loaded: the others are listed by name and help, and their modules (scipy, torch, ...)
    are not imported, which keeps a command's start-up to what it needs."""
    parser = argparse.ArgumentParser(prog="vehicle-estimation", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    for name, entry in COMMANDS.items():
        if entry.own_argv or (command is not None and name != command):
            # listed here; an own_argv command's main() gets the rest of the line
            sub.add_parser(name, help=entry.help, add_help=False)
        else:
            entry.load().add_arguments(sub.add_parser(name, help=entry.help, description=entry.help))
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = COMMANDS.get(argv[0]) if argv else None
    if command is not None and command.own_argv:
        return command.load().main(argv[1:])
    args = build_parser(argv[0] if command is not None else None).parse_args(argv)
    return COMMANDS[args.command].load().main(args)


def run_as_script(module: ModuleType) -> int:
    """``python -m <module>`` of a subcommand's module: its options, under the module's name."""
    name = module.__spec__.name if module.__spec__ is not None else module.__name__
    parser = argparse.ArgumentParser(prog=f"python -m {name}", description=(module.__doc__ or "").split("\n\n")[0])
    module.add_arguments(parser)
    return module.main(parser.parse_args())


if __name__ == "__main__":
    raise SystemExit(main())
