"""Command-line options shared by the commands that start the nodes (``run``, ``replay``,
``demo``, ``experiment``, ``inspect``, ``stanford``, ``validate``), and the node groups they
build from them.

A command's params are layered: ``--vehicle`` first, then every ``--params`` (default
``estimation``), a later file overriding an earlier one (:func:`params_files`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Callable, Sequence

from vehicle_estimation.paths import params_file

DEFAULT_VEHICLE = "sedan_d_class"
DEFAULT_PARAMS = "estimation"

#: ``node_group(params_files, overrides, log_dir)``: the node processes of one replay.
NodeGroupFactory = Callable[[Sequence[Path], Any, "Path | None"], Any]


def add_vehicle_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default=DEFAULT_VEHICLE,
                   help=f"vehicle params file or name in params/ (default: {DEFAULT_VEHICLE})")


def add_params_options(p: argparse.ArgumentParser) -> None:
    """``--vehicle`` and ``--params``: the layered params files (:func:`params_files`)."""
    add_vehicle_option(p)
    p.add_argument("--params", action="append", default=None,
                   help=f"node params file or name in params/ (default: {DEFAULT_PARAMS}); repeat to "
                        "layer files, a later file overriding an earlier one")


def add_tuning_option(p: argparse.ArgumentParser, below: str) -> None:
    """``--params`` of a comparison (``validate``, ``stanford``): files layered over
    ``estimation.yaml`` in every replay, below the comparison's own layer (``below``)."""
    p.add_argument("--params", action="append", default=[], metavar="FILE",
                   help=f"params file or name in params/ layered over estimation.yaml in every replay, below {below}; "
                        "repeat to layer files: a tuning scored beside the same baselines")


def add_namespace_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--namespace", default="/", help="ROS namespace of every node (default: /)")


def add_node_options(p: argparse.ArgumentParser) -> None:
    """``--vehicle``, ``--params`` and ``--namespace``."""
    add_params_options(p)
    add_namespace_option(p)


def _remap_arg(text: str) -> tuple[str, str]:
    """argparse type of ``--remap FROM:=TO``: a malformed one is a usage error that says why."""
    from vehicle_estimation.contract.topics import parse_remap
    try:
        return parse_remap(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_remap_option(p: argparse.ArgumentParser, help_text: str) -> None:
    """``--remap FROM:=TO``, repeatable; ``args.remap`` is a list of ``(FROM, TO)`` pairs."""
    p.add_argument("--remap", action="append", type=_remap_arg, default=[], metavar="FROM:=TO",
                   help=help_text + "; repeat for more topics")


def params_files(args: argparse.Namespace) -> list[Path]:
    """``--vehicle`` then every ``--params`` (default ``estimation``): a later file wins."""
    return [params_file(args.vehicle)] + [params_file(name) for name in (args.params or [DEFAULT_PARAMS])]


def node_group(args: argparse.Namespace, overrides=None, log_dir: Path | None = None, remaps=()):
    """The four nodes with the params files, namespace (and remappings) of ``args``."""
    from vehicle_estimation.launcher.processes import NodeGroup
    return NodeGroup(params_files(args), namespace=args.namespace, overrides=overrides or {}, log_dir=log_dir,
                     remaps=list(remaps))


def node_group_factory(namespace: str, leading: Sequence[Path] = ()) -> NodeGroupFactory:
    """``node_group(params_files, overrides, log_dir)`` for commands that choose the params files
    per replay: the nodes in ``namespace`` with ``leading`` (e.g. the vehicle file) before them."""
    def build(params: Sequence[Path], overrides: Any, log_dir: Path | None):
        from vehicle_estimation.launcher.processes import NodeGroup
        return NodeGroup(list(leading) + list(params), namespace=namespace, overrides=overrides or {},
                         log_dir=log_dir)
    return build


def persisted_state_overrides(state_dir: Path, namespace: str) -> dict[str, dict[str, str]]:
    """The nodes' state files under ``state_dir`` (``persist.path``): the mass node's estimate,
    the fusion's learnt speed scale. One pair per namespace: two vehicles on one computer never
    share an estimate."""
    ns = namespace.strip("/").replace("/", "_") or "root"
    return {"mass": {"persist.path": str(Path(state_dir) / f"mass_{ns}.json")},
            "fusion": {"persist.path": str(Path(state_dir) / f"fusion_{ns}.json")}}
