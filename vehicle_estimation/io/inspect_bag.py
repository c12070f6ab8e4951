"""``vehicle-estimation inspect BAG``: what a bag holds and what the nodes will make of it.

For a user who just brought their own bag (MCAP or sqlite3 rosbag2, or a ROS 1 ``.bag``)::

    vehicle-estimation inspect BAG [--vehicle V] [--params P ...] [--remap FROM:=TO ...] [--json]

1. Per contract input topic (:data:`vehicle_estimation.contract.topics.INPUT_TOPICS`): present or
   missing, message type (warned when it is not the contract's), count, mean rate, first and
   last header stamp and log time, out-of-order and duplicated header stamps, frame_id(s);
   for the JointState topics which joints report which entries (NaN = not reported), for
   ``gnss/fix`` the share without a fix. Every other topic is listed as ignored (ground truth
   as used by ``report``).
2. Per node, the method and the fallbacks that will run with the layered parameters.
3. Which outputs will stay empty (or that every output will be published).

The bag is read by :mod:`vehicle_estimation.io.bag_survey` (one pass, content sampled), the
nodes' plan comes from :mod:`vehicle_estimation.launcher.node_plan`; this module puts them together
and prints them. ``replay`` prints the same summary (:func:`summarize`, :func:`format_summary`)
before it starts.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from vehicle_estimation.contract import topics
from vehicle_estimation.io.bag_survey import CONTRACT_JOINTS, InspectError, read_bag, topic_summary
from vehicle_estimation.launcher.node_plan import NODES, layered_params, plan_nodes
from vehicle_estimation.evaluation.report import json_safe

__all__ = ["InspectError", "format_summary", "summarize"]


# ------------------------------------------------------------------------------ public API
def _ground_truth(topic: str) -> bool:
    """A simulator's truth topic (every one of ``topics.GROUND_TRUTH_TOPICS`` is under
    ``ground_truth/``, and so are any a bag adds): read by ``report``, never by a node."""
    return topics.relative(topic).startswith("ground_truth/")


def summarize(bag: Path, params_files: list[Path], remaps: dict[str, str]) -> dict:
    """Everything ``inspect`` prints, as plain JSON-able data (see :func:`format_summary`)."""
    try:
        remaps = topics.bag_to_contract((remaps or {}).items(), topics.INPUT_TOPICS)
    except ValueError as exc:
        raise InspectError(f"--remap: {exc}") from None
    params = layered_params([Path(p) for p in params_files])
    data = read_bag(Path(bag), remaps)
    contract = data["contract"]
    inputs = {t: topic_summary(contract[t]) for t in topics.INPUT_TOPICS}
    others = []
    missing = [t for t in topics.INPUT_TOPICS if not inputs[t]["present"]]
    for topic, entry in sorted(data["others"].items()):
        gt = _ground_truth(topic)
        hint = None
        if not gt:
            # a missing input under a namespace (/car1/imu/data), or the only topic of its type
            # that is not ground truth (ground_truth/imu_bias is an Imu too)
            hint = next((t for t in missing if topics.relative(topic).endswith("/" + t)), None)
            by_type = [t for t in missing if {topics.INPUT_TYPES[t]} == entry["types"]]
            same = [o for o, e in data["others"].items() if e["types"] == entry["types"] and not _ground_truth(o)]
            if hint is None and len(by_type) == 1 and len(same) == 1:
                hint = by_type[0]
        others.append({"topic": topic, "types": sorted(entry["types"]), "count": entry["count"],
                       "role": "ground truth, used by report" if gt else "ignored",
                       "remap_hint": f"{hint}:={topic}" if hint else None})
    plan = plan_nodes(inputs, params, contract[topics.IMU], contract[topics.SPEED],
                      contract[topics.JOINT_STATES])
    shown = ("method", "filter", "speed_fallback", "accel_source", "speed_source", "require_slope",
             "mass.torque_regression", "vehicle.name", "vehicle.driven_axle", "vehicle.gear_ratios")
    return {
        "bag": str(bag),
        "storage": data["storage"],
        "log_time": {"start": data["start"], "end": data["end"], "duration_s": data["end"] - data["start"]},
        "params_files": [str(p) for p in params_files],
        "remaps": remaps,
        "inputs": inputs,
        "other_topics": others,
        "params": {node: {k: json_safe(v) for k, v in params[node].items() if k in shown} for node in NODES},
        **plan,
    }


def _pct(x: float) -> str:
    return f"{100.0 * x:.0f} %"


def _format_topic(info: dict[str, Any]) -> list[str]:
    name = info["topic"]
    if not info["present"]:
        return [f"  {name}: MISSING (expected {info['expected_type']})"]
    shown = ", ".join(t for t in info["bag_topics"] if topics.relative(t) != name)
    head = f"  {name}" + (f" (from {shown})" if shown else "") + f": {info['count']} messages, "
    head += ", ".join(info["types"])
    lines = [head]
    if not info["type_ok"]:
        lines.append(f"    WARNING: the contract's type is {info['expected_type']}; the nodes will not read it")
    if info.get("first_stamp") is None:
        lines.append("    no readable header stamps")
    else:
        rate = f"{info['rate_hz']:.1f} Hz" if info.get("rate_hz") else "rate unknown"
        lines.append(f"    {rate} mean; header stamps {info['first_stamp']:.3f} .. {info['last_stamp']:.3f} s, "
                     f"log time {info['first_log']:.3f} .. {info['last_log']:.3f} s")
        if abs(info["stamp_minus_log_s"]) > 1.0:
            lines.append(f"    note: header stamps are {info['stamp_minus_log_s']:+.3f} s off the log time")
        order = f"{info['out_of_order']} out of order, {info['duplicates']} duplicated stamps"
        frames = ", ".join(f"'{f}' ({n})" if len(info["frame_ids"]) > 1 else f"'{f}'"
                           for f, n in info["frame_ids"].items())
        lines.append(f"    {order}; frame_id {frames}")
    if info.get("unreadable"):
        lines.append(f"    {info['unreadable']} messages without a readable header")
    if "joints" in info:
        wanted = CONTRACT_JOINTS[name]
        lines.append(f"    joints (in {info['sampled']} sampled messages): "
                     + (", ".join(info["joints"]) if info["joints"] else "none"))
        for joint, fields in wanted.items():
            seen = info["joints"].get(joint)
            if seen is None:
                lines.append(f"      {joint}: not in the messages ({', '.join(fields.values())} not reported)")
                continue
            parts = []
            for field, meaning in fields.items():
                share = seen.get(field, 0.0)
                state = "finite" if share >= 0.999 else (f"finite in {_pct(share)}" if share > 0 else "NaN (not reported)")
                parts.append(f"{field} ({meaning}) {state}")
            lines.append(f"      {joint}: " + ", ".join(parts))
        extra = sorted(set(info["joints"]) - set(wanted))
        if extra:
            lines.append(f"      not in the contract, ignored: {', '.join(extra)}")
        if info.get("malformed"):
            lines.append(f"      {info['malformed']} sampled messages with arrays that do not match the names")
    if info.get("no_fix_share") is not None:
        lines.append(f"    no fix (status < 0) in {_pct(info['no_fix_share'])} of {info['sampled']} sampled messages")
    return lines


def format_summary(summary: dict) -> str:
    """The summary in plain words, one topic or node aspect per line."""
    lt = summary["log_time"]
    out = [(f"bag {summary['bag']}: {summary['storage']}, log time {lt['start']:.3f} .. {lt['end']:.3f} s "
            f"({lt['duration_s']:.1f} s)")]
    if summary["params_files"]:
        out.append("params: " + " < ".join(Path(p).name for p in summary["params_files"])
                   + " (a later file overrides)")
    if summary["remaps"]:
        out.append("remaps: " + ", ".join(f"{v}:={k}" for k, v in summary["remaps"].items()))
    out.append("")
    out.append("inputs:")
    for topic in topics.INPUT_TOPICS:
        out += _format_topic(summary["inputs"][topic])
    if summary["other_topics"]:
        out.append("other topics:")
        for entry in summary["other_topics"]:
            line = f"  {entry['topic']}: {entry['count']} messages, {', '.join(entry['types'])}: {entry['role']}"
            if entry.get("remap_hint"):
                line += f" (a contract input? --remap {entry['remap_hint']})"
            out.append(line)
    out.append("")
    out.append("nodes:")
    for node in NODES:
        info = summary["nodes"][node]
        out.append(f"  {node} (needs {info['needs']}):")
        out += [f"    - {line}" for line in info["lines"]]
    out.append("")
    if summary["prior_outputs"]:
        out.append("will stay at the prior: " + ", ".join(summary["prior_outputs"]))
    if summary["empty_outputs"]:
        out.append("will stay empty: " + ", ".join(summary["empty_outputs"]))
    else:
        out.append("every output will be published")
    return "\n".join(out)


# ------------------------------------------------------------------------------ command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from vehicle_estimation.launcher.options import add_params_options, add_remap_option
    parser.add_argument("bag", help="rosbag2 directory (MCAP or sqlite3) or ROS 1 .bag")
    add_params_options(parser)
    add_remap_option(parser, "read a bag topic as a contract topic, CONTRACT:=BAG_TOPIC as for replay")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.launcher.options import params_files
    try:
        summary = summarize(Path(args.bag), params_files(args), dict(args.remap))
    except (InspectError, FileNotFoundError) as exc:
        print(f"inspect: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(json_safe(summary), indent=2, allow_nan=False))
    else:
        print(format_summary(summary))
    return 0
