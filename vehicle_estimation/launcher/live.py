"""``vehicle-estimation run``: start every node as its own OS process, live, and keep them up.

A node that exits is respawned (the mass node resumes from its persisted estimate), except
one that refused its parameters (exit 2): that stops them all. Ctrl-C or SIGTERM stops them
all; the children also die with the launcher if it is killed (no orphans).

``run --in-process`` composes the same nodes into this one process instead (as a ROS 2
component container does), on one executor and a :class:`~vehicle_estimation.ros.runtime.
in_process.LiveBus`: each sensor message is received and decoded once for all nodes, and the
estimates pass between nodes without DDS (they are still published for everyone else). It
costs less CPU and uses one core; the separate processes keep a node's crash to itself.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from vehicle_estimation.launcher.options import add_node_options, add_remap_option, node_group, persisted_state_overrides


def default_state_dir() -> str:
    return str(Path(os.environ.get("ROS_HOME") or Path.home() / ".ros") / "vehicle_estimation")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_node_options(p)
    p.add_argument("--state-dir", default=default_state_dir(),
                   help="where the mass node persists its estimate (a restart resumes it) and the "
                        "fusion the speed scale it learnt (the next drive starts from it) "
                        "(default: $ROS_HOME/vehicle_estimation, else ~/.ros/vehicle_estimation); "
                        "'' turns persistence off")
    add_remap_option(p, "ROS remapping given to every node as -r FROM:=TO (e.g. imu/data:=/sensors/imu)")
    p.add_argument("--in-process", action="store_true",
                   help="compose the nodes into this process on one executor: each sensor message is "
                        "received once for all nodes, estimates pass between them without DDS (less CPU)")


def main(args: argparse.Namespace) -> int:
    overrides = {}
    if args.state_dir:
        overrides.update(persisted_state_overrides(Path(args.state_dir), args.namespace))
    group = node_group(args, overrides, remaps=args.remap)
    if args.in_process:
        return run_in_process(group)
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


def run_in_process(group: Any) -> int:
    """The group's nodes composed into this process until Ctrl-C or SIGTERM (rclpy's signal
    handlers shut the context down); exit 2 when a node refuses its parameters."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node

    from vehicle_estimation.ros.runtime.in_process import LiveBus
    from vehicle_estimation.ros.runtime.parameters import ParameterError
    from vehicle_estimation.ros.runtime.spin import spin

    rclpy.init()
    # The host of the shared subscriptions, publishers and timers; topics are resolved by the
    # nodes (namespace, remaps), so its own namespace only names it.
    host = Node("vehicle_estimation", namespace=group.namespace)
    nodes: list[Any] = []
    try:
        bus = LiveBus(host)
        try:
            group.make_in_process(nodes, transport=bus)
        except ParameterError as exc:
            print(f"[vehicle_estimation] {exc}", file=sys.stderr)
            return 2
        bus.connect()
        names = ", ".join(node.get_name() for node in nodes)
        print(f"started {names} in this process, namespace {group.namespace}; Ctrl-C stops them", file=sys.stderr)
        spin([host, *nodes], "composed")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass                # a stop that came before the executor spun (spin catches the rest)
    finally:
        for node in [*nodes, host]:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
