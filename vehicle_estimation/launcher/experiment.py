"""``vehicle-estimation experiment NAME``: a contrast experiment of paper 004
(:mod:`vehicle_estimation.experiments.paper004_joint_soft_sensing`) through the node processes."""

from __future__ import annotations

import argparse
from pathlib import Path

from vehicle_estimation.launcher.options import add_namespace_option, add_vehicle_option, node_group_factory
from vehicle_estimation.paths import params_file


def add_arguments(p: argparse.ArgumentParser) -> None:
    from vehicle_estimation.experiments.paper004_joint_soft_sensing import add_arguments as experiment_arguments
    experiment_arguments(p)
    add_vehicle_option(p)
    add_namespace_option(p)


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.experiments import paper004_joint_soft_sensing as experiment

    build = node_group_factory(args.namespace, [params_file(args.vehicle)])

    def node_group(params, overrides, log_dir):
        return build([params_file(name) for name in params], overrides, log_dir)

    out = Path(args.out or f"out/{args.name}")
    return experiment.run_experiment(experiment.EXPERIMENTS[args.name], out, node_group,
                                     duration_s=args.duration, namespace=args.namespace,
                                     progress=not args.quiet)
