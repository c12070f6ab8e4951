"""``vehicle-estimation run``: start every node as its own OS process, live, and keep them up.

A node that exits is respawned (the mass node resumes from its persisted estimate), except
one that refused its parameters (exit 2): that stops them all. Ctrl-C or SIGTERM stops them
all; the children also die with the launcher if it is killed (no orphans).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

from vehicle_estimation.launcher.options import add_node_options, add_remap_option, node_group


def default_state_dir() -> str:
    return str(Path(os.environ.get("ROS_HOME") or Path.home() / ".ros") / "vehicle_estimation")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_node_options(p)
    p.add_argument("--state-dir", default=default_state_dir(),
                   help="where the mass node persists its estimate, so that a restart resumes it "
                        "(default: $ROS_HOME/vehicle_estimation, else ~/.ros/vehicle_estimation); "
                        "'' turns persistence off")
    add_remap_option(p, "ROS remapping given to every node as -r FROM:=TO (e.g. imu/data:=/sensors/imu)")


def main(args: argparse.Namespace) -> int:
    overrides = {}
    if args.state_dir:
        # One state file per namespace: two vehicles on one computer never share an estimate.
        ns = args.namespace.strip("/").replace("/", "_") or "root"
        overrides["mass"] = {"persist.path": str(Path(args.state_dir) / f"mass_{ns}.json")}
    group = node_group(args, overrides, remaps=args.remap)
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
