"""``vehicle-estimation bench``: speed and memory figures (a table, never an assertion).

Sections (``--sections``, default all):

``cores``
    Per-step cost (median and p99, µs) of every estimator core on the arrays of one simulated
    drive, each core fed what its node feeds it: the fusion ES-EKF (IMU step, speed and GNSS
    updates), the three slope methods, the CKF, the VB-ACKF for N = 1..5 variational
    iterations, the anti-outlier UKF with and without the GA-BPNN correction, filterpy's UKF on
    the same 3-DOF model and data (as a ratio to ours), RLS, FFRLS and the TA-AEKF with its
    transformer inference. The fusion's steps, the CKF and the shipped VB-ACKF run twice, by the
    compiled kernels (numba, the `fast` extra) and by numpy, and their ratio is printed.
``pipeline``
    A ``--minutes`` (default 30) simulated drive (IMU 200 Hz, CAN 100 Hz, GNSS 10 Hz) replayed
    through the four nodes, each in its own process: real-time factor, CPU seconds per node,
    resident memory of each node after 1 simulated minute and at the end. Then the same bag
    through the same nodes in one process without DDS (``replay --in-process``): its real-time
    factor on one core and the ratio to the DDS replay.
``live``
    ``--live-seconds`` of the same drive published at real-time rate to the nodes in live mode
    (no replay sync): CPU share of each node, and the latency from an input's publication to
    the publication of the output it triggers (p50, p99), per output. Beside them, in the same
    run, the framework floor (:mod:`.bench_floor`): a node that only receives the same topics.
    Then the same drive to the nodes composed into one process (``run --in-process``).

The targets (issues 6 and 15) are printed beside the figures. Timings depend on the machine and on
what else runs on it: run it on an idle machine and compare like with like.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from vehicle_estimation.evaluation.bench_cores import run_cores

TARGETS = {
    "replay_rt": 20.0,          # replay >= 20x real time, four processes on 2 cores
    "in_process_rt": 50.0,      # replay --in-process >= 50x real time on one core
    "cpu_share": 0.15,          # all nodes together < 15 % of one core at real time
    "latency_p99_ms": 2.0,      # p99 input -> output latency
    "floor_ratio": 2.0,         # all nodes <= 2x four do-nothing nodes on the same topics (live)
    "fusion_imu_us": 25.0,      # median fusion IMU step (compiled)
    "state_step_us": 60.0,      # median CKF / VB-ACKF step (compiled)
    "memory_growth": 0.05,      # < 5 % growth of resident memory, minute 1 -> minute 30
    "ukf_vs_filterpy": 2.0,     # our UKF >= 2x faster per step than filterpy's
}


# ============================================================================ processes
def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return math.nan


def _params_files() -> list[Path]:
    from vehicle_estimation.launcher.options import DEFAULT_PARAMS, DEFAULT_VEHICLE
    from vehicle_estimation.paths import params_file
    return [params_file(DEFAULT_VEHICLE), params_file(DEFAULT_PARAMS)]


def _drive_bag(minutes: float, workdir: Path) -> Path:
    from vehicle_estimation.sim import default_scenario, simulate, write_bag
    bag = workdir / f"drive_{minutes:g}min"
    if not bag.exists():
        print(f"  simulating a {minutes:g}-minute drive ...", file=sys.stderr, flush=True)
        write_bag(simulate(default_scenario(duration_s=60.0 * minutes, seed=3)), bag)
    return bag


def run_pipeline(minutes: float, workdir: Path) -> dict[str, Any]:
    from vehicle_estimation.launcher.processes import NodeGroup
    from vehicle_estimation.launcher.replay import replay
    bag = _drive_bag(minutes, workdir)
    samples: dict[str, dict[str, float]] = {}
    final: dict[str, dict[str, float]] = {}
    groups: list[NodeGroup] = []

    class MeasuredGroup(NodeGroup):
        def stop(self, timeout: float = 10.0) -> None:
            for n in self.nodes:
                if n.alive():
                    final[n.spec.name] = {"cpu_s": cpu_seconds(n.process.pid), "rss_mib": rss_mib(n.process.pid)}
            super().stop(timeout)

    def factory(overrides):
        group = MeasuredGroup(_params_files(), overrides=overrides)
        groups.append(group)
        return group

    def on_tick(bag_s: float) -> None:
        if "minute_1" not in samples and bag_s >= 60.0 and groups:
            samples["minute_1"] = {n.spec.name: rss_mib(n.process.pid) for n in groups[0].nodes if n.alive()}

    print(f"  replaying {minutes:g} minutes through the four node processes ...", file=sys.stderr, flush=True)
    stats = replay(bag, None, factory, progress=sys.stderr.isatty(), tick_callback=on_tick)
    result = {"bag_s": stats.bag_s, "wall_s": stats.wall_s, "rt_factor": stats.bag_s / stats.wall_s,
              "lossless": stats.lossless, "nodes": final, "rss_minute_1": samples.get("minute_1", {})}
    print(f"  replaying {minutes:g} minutes through the same nodes in this process ...", file=sys.stderr, flush=True)
    cpu0 = time.process_time()
    stats = replay(bag, None, lambda overrides: NodeGroup(_params_files(), overrides=overrides),
                   progress=sys.stderr.isatty(), in_process=True)
    result["in_process"] = {"wall_s": stats.wall_s, "cpu_s": time.process_time() - cpu0,
                            "rt_factor": stats.bag_s / stats.wall_s, "lossless": stats.lossless}
    from vehicle_estimation.evaluation.bench_floor import handlers_switched_off
    for in_process in (True, False):
        print(f"  the {'in-process' if in_process else 'DDS'} replay with every handler switched off (its floor) ...",
              file=sys.stderr, flush=True)
        with handlers_switched_off():
            stats = replay(bag, None, lambda overrides: NodeGroup(_params_files(), overrides=overrides),
                           progress=sys.stderr.isatty(), in_process=in_process)
        floor = {"wall_s": stats.wall_s, "rt_factor": stats.bag_s / stats.wall_s}
        if in_process:
            result["in_process"]["floor"] = floor
        else:
            result["floor"] = floor
    return result


def run_live(seconds: float, workdir: Path) -> dict[str, Any]:
    """Publish ``seconds`` of a drive at real-time rate to live nodes; CPU share and latency.

    Twice: to the four node processes beside the framework floor (:mod:`.bench_floor`), then
    to the same nodes composed into one process (``run --in-process``)."""
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from vehicle_estimation.contract import topics
    from vehicle_estimation.launcher.processes import NodeGroup
    from vehicle_estimation.launcher.replay_driver import msg_class
    from vehicle_estimation.ros.runtime.spin import make_executor

    bag = _drive_bag(max(seconds / 60.0, 1.0) if seconds > 60 else 1.0, workdir)
    rclpy.init()
    node = Node("bench_live_player")
    reliable = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                          history=HistoryPolicy.KEEP_LAST, depth=1000)
    sent_wall: dict[tuple[str, int], float] = {}
    latencies: dict[str, list[float]] = {}
    # Output -> the input topic whose samples trigger it (its stamp is that input's stamp).
    triggers = {topics.ODOMETRY: topics.IMU, topics.VEHICLE_STATE: topics.IMU,
                topics.ROAD_SLOPE_STAMPED: topics.IMU, topics.MASS_STAMPED: topics.POWERTRAIN}
    lock = threading.Lock()

    def on_output(topic: str, msg: Any) -> None:
        now = time.monotonic()
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        with lock:
            t_sent = sent_wall.get((triggers[topic], round(ns / 1000)))
        if t_sent is not None:
            latencies.setdefault(topic, []).append(now - t_sent)

    for out_topic, type_name in ((topics.ODOMETRY, "nav_msgs/msg/Odometry"),
                                 (topics.VEHICLE_STATE, "geometry_msgs/msg/TwistWithCovarianceStamped"),
                                 (topics.ROAD_SLOPE_STAMPED, "geometry_msgs/msg/Vector3Stamped"),
                                 (topics.MASS_STAMPED, "geometry_msgs/msg/Vector3Stamped")):
        node.create_subscription(msg_class(type_name), out_topic,
                                 lambda m, tp=out_topic: on_output(tp, m), reliable)
    executor = make_executor()
    executor.add_node(node)
    spinner = threading.Thread(target=lambda: _spin_while(executor, rclpy), daemon=True)
    result: dict[str, Any] = {}
    typestore = get_typestore(Stores.ROS2_JAZZY)
    try:
        with AnyReader([bag], default_typestore=typestore) as reader:
            conns = [c for c in reader.connections if c.topic.lstrip("/") in topics.INPUT_TOPICS]
            pubs = {c.topic: node.create_publisher(msg_class(c.msgtype), c.topic.lstrip("/"), reliable)
                    for c in conns}
            spinner.start()

            def play(pids: dict[str, int], floor_pid: int | None) -> dict[str, Any]:
                deadline = time.monotonic() + 60.0
                while time.monotonic() < deadline and not all(
                        p.get_subscription_count() >= 1 for p in pubs.values()):
                    time.sleep(0.1)
                time.sleep(2.0)
                with lock:
                    sent_wall.clear()
                    latencies.clear()
                cpu0 = {name: cpu_seconds(pid) for name, pid in pids.items()}
                floor0 = cpu_seconds(floor_pid) if floor_pid else 0.0
                t_bag0 = None
                wall0 = time.monotonic()
                for conn, stamp_ns, data in reader.messages(connections=conns):
                    if t_bag0 is None:
                        t_bag0 = stamp_ns
                    due = wall0 + (stamp_ns - t_bag0) * 1e-9
                    if (stamp_ns - t_bag0) * 1e-9 > seconds:
                        break
                    delay = due - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    topic = conn.topic.lstrip("/")
                    with lock:
                        sent_wall[(topic, round(stamp_ns / 1000))] = time.monotonic()
                    pubs[conn.topic].publish(bytes(data))
                time.sleep(1.0)
                wall = time.monotonic() - wall0
                cpu = {name: cpu_seconds(pid) - cpu0[name] for name, pid in pids.items()}
                with lock:
                    measured = {t: list(v) for t, v in latencies.items() if v}
                out = {"seconds": wall, "cpu_share": {k: v / wall for k, v in cpu.items()},
                       "cpu_share_total": sum(cpu.values()) / wall,
                       "latency_ms": {t: {"n": len(v), "p50": 1e3 * float(np.percentile(v, 50)),
                                          "p99": 1e3 * float(np.percentile(v, 99))} for t, v in measured.items()}}
                if floor_pid:
                    out["floor_share"] = (cpu_seconds(floor_pid) - floor0) / wall
                return out

            group = NodeGroup(_params_files())
            group.start()
            # The framework floor, in the same run: rclpy's own cost of receiving the same topics.
            floor = subprocess.Popen([sys.executable, "-m", "vehicle_estimation.evaluation.bench_floor"],
                                     stdout=subprocess.PIPE, text=True)
            try:
                if floor.stdout is None or floor.stdout.readline().strip() != "ready":
                    raise RuntimeError("the framework-floor node did not start")
                result = play({n.spec.name: n.process.pid for n in group.nodes}, floor.pid)
            finally:
                _stop(floor)
                group.stop()
            composed = subprocess.Popen([sys.executable, "-m", "vehicle_estimation", "run", "--in-process",
                                         "--state-dir", ""], stderr=subprocess.PIPE, text=True)
            try:
                if composed.stderr is None or not _wait_for_line(composed.stderr, "started "):
                    raise RuntimeError("run --in-process did not start")
                result["in_process"] = play({"composed": composed.pid}, None)
            finally:
                _stop(composed)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return result


def _wait_for_line(stream: Any, prefix: str) -> bool:
    """Read ``stream`` up to a line starting with ``prefix``, then drain it in the background
    (a full pipe would block the process writing to it)."""
    for line in stream:
        if line.startswith(prefix):
            threading.Thread(target=lambda: [None for _ in stream], daemon=True).start()
            return True
    return False


def _stop(process: subprocess.Popen) -> None:
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=10.0)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def _spin_while(executor: Any, rclpy: Any) -> None:
    while rclpy.ok():
        try:
            executor.spin_once(timeout_sec=0.1)
        except Exception:   # shutdown races
            return


# ============================================================================ report
def format_report(result: dict[str, Any]) -> str:
    lines = []
    if "cores" in result:
        lines += ["## Per-step cost of the estimator cores", "",
                  "| core | steps | median [µs] | p99 [µs] | note |", "|---|---|---|---|---|"]
        for r in result["cores"]:
            lines.append(f"| {r['name']} | {r['steps']} | {r['median_us']:.1f} | {r['p99_us']:.1f} | {r['note']} |")
        lines += _compiled_ratios(result["cores"])
        closed = next((r for r in result["cores"] if "moments closed-form" in r["name"]), None)
        cubature = next((r for r in result["cores"] if "moments by cubature" in r["name"]), None)
        if closed and cubature and closed["median_us"] > 0:
            lines += ["", f"VB-ACKF step (N = 10) with closed-form IMU moments: {cubature['median_us'] / closed['median_us']:.2f}x "
                          "faster than by cubature, the same estimates to 1e-9 (test_vbackf)"]
        ratio = result.get("ukf_vs_filterpy")
        if ratio is not None:
            ok = "met" if ratio >= TARGETS["ukf_vs_filterpy"] else "missed"
            lines += ["", f"Our UKF vs filterpy's on the same model and data: {ratio:.2f}x faster per step "
                          f"(target >= {TARGETS['ukf_vs_filterpy']:g}x: {ok})"]
        lines.append("")
    if "pipeline" in result:
        p = result["pipeline"]
        ok = "met" if p["rt_factor"] >= TARGETS["replay_rt"] else "missed"
        lines += ["## Pipeline replay (four node processes)", "",
                  f"{p['bag_s']:.0f} s of bag in {p['wall_s']:.1f} s: **{p['rt_factor']:.1f}x real time** "
                  f"(target >= {TARGETS['replay_rt']:g}x: {ok}); lossless: {p['lossless']}", "",
                  "| node | CPU [s] | CPU per bag second | RSS after 1 min [MiB] | RSS at the end [MiB] | growth |",
                  "|---|---|---|---|---|---|"]
        for name, v in p["nodes"].items():
            r1 = p["rss_minute_1"].get(name, math.nan)
            growth = v["rss_mib"] / r1 - 1.0 if r1 and math.isfinite(r1) else math.nan
            lines.append(f"| {name} | {v['cpu_s']:.1f} | {v['cpu_s'] / p['bag_s']:.3f} | {r1:.1f} | "
                         f"{v['rss_mib']:.1f} | {100 * growth:+.1f} % |")
        worst = max((v["rss_mib"] / p["rss_minute_1"][n] - 1.0 for n, v in p["nodes"].items()
                     if p["rss_minute_1"].get(n)), default=math.nan)
        ok = "met" if worst < TARGETS["memory_growth"] else "missed"
        lines += ["", f"Largest memory growth from minute 1 to the end: {100 * worst:+.1f} % "
                      f"(target < {100 * TARGETS['memory_growth']:g} %: {ok})", ""]
        lines += _replay_floor_lines(p, p.get("floor"), "DDS", TARGETS["replay_rt"])
        ip = p.get("in_process")
        if ip:
            cpu_dds = sum(v["cpu_s"] for v in p["nodes"].values())
            cpu = (f"; CPU {ip['cpu_s']:.1f} s against {cpu_dds:.1f} s in the four node processes "
                   f"({ip['cpu_s'] / cpu_dds:.2f}x)" if cpu_dds > 0 else "")
            ok = "met" if ip["rt_factor"] >= TARGETS["in_process_rt"] else "missed"
            lines += ["## The same replay in one process (`replay --in-process`)", "",
                      f"{p['bag_s']:.0f} s of bag in {ip['wall_s']:.1f} s: **{ip['rt_factor']:.1f}x real time** on "
                      f"one core (target >= {TARGETS['in_process_rt']:g}x: {ok}); lossless: {ip['lossless']}; "
                      f"{ip['rt_factor'] / p['rt_factor']:.2f}x the DDS replay's factor{cpu}", ""]
            lines += _replay_floor_lines(dict(ip, bag_s=p["bag_s"]), ip.get("floor"), "in-process",
                                         TARGETS["in_process_rt"])
    if "live" in result:
        lv = result["live"]
        ok = "met" if lv["cpu_share_total"] < TARGETS["cpu_share"] else "missed"
        lines += ["## Live, at real-time rate", "",
                  f"{lv['seconds']:.0f} s; CPU share of one core: " +
                  ", ".join(f"{k} {100 * v:.1f} %" for k, v in lv["cpu_share"].items()) +
                  f"; **all nodes {100 * lv['cpu_share_total']:.1f} %** (target < {100 * TARGETS['cpu_share']:g} %: {ok})",
                  "", *_floor_line(lv), "| output (trigger) | samples | p50 [ms] | p99 [ms] |", "|---|---|---|---|"]
        worst = 0.0
        for topic, v in lv["latency_ms"].items():
            lines.append(f"| {topic} | {v['n']} | {v['p50']:.2f} | {v['p99']:.2f} |")
            worst = max(worst, v["p99"])
        ok = "met" if worst < TARGETS["latency_p99_ms"] else "missed"
        lines += ["", f"Worst p99 latency: {worst:.2f} ms (target < {TARGETS['latency_p99_ms']:g} ms: {ok})", ""]
        lines += _composed_lines(lv)
    return "\n".join(lines)


def _replay_floor_lines(run: dict[str, Any], floor: dict[str, Any] | None, kind: str, target: float) -> list[str]:
    """A replay against its floor: the same replay with every handler switched off."""
    if not floor:
        return []
    handlers = run["wall_s"] - floor["wall_s"]
    reach = "within" if floor["rt_factor"] >= target else "beyond"
    return [f"Floor of the {kind} replay, the same replay with every handler switched off (bag reading, "
            f"delivery, decoding, the input queues, the ticks): {floor['wall_s']:.1f} s, "
            f"**{floor['rt_factor']:.1f}x real time** ({target:g}x is {reach} it). The handlers (checks, "
            f"estimators, what they publish and its delivery) take the other {handlers:.1f} s, "
            f"{100 * handlers / run['wall_s']:.0f} % of the replay; {target:g}x needs the whole replay "
            f"in {run['bag_s'] / target:.1f} s.", ""]


def _composed_lines(live: dict[str, Any]) -> list[str]:
    """The nodes composed into one process (``run --in-process``) against the four processes."""
    composed = live.get("in_process")
    if not composed:
        return []
    share = composed["cpu_share_total"]
    ok = "met" if share < TARGETS["cpu_share"] else "missed"
    worst = max((v["p99"] for v in composed["latency_ms"].values()), default=math.nan)
    ok_latency = "met" if worst < TARGETS["latency_p99_ms"] else "missed"
    floor = live.get("floor_share")
    against_floor = (f"; **{share / floor:.1f}x** one framework floor (it receives each topic once)"
                     if floor else "")
    return ["## Live, the nodes composed into one process (`run --in-process`), same run", "",
            f"{composed['seconds']:.0f} s; **{100 * share:.1f} % of one core** (target < "
            f"{100 * TARGETS['cpu_share']:g} %: {ok}), {share / live['cpu_share_total']:.2f}x the four node "
            f"processes'{against_floor}; worst p99 latency {worst:.2f} ms (target < "
            f"{TARGETS['latency_p99_ms']:g} ms: {ok_latency})", ""]


def _floor_line(live: dict[str, Any]) -> list[str]:
    """The nodes' CPU against the framework floor (four do-nothing nodes), same run."""
    floor = live.get("floor_share")
    if not floor:
        return []
    ratio = live["cpu_share_total"] / (4.0 * floor)
    ok = "met" if ratio <= TARGETS["floor_ratio"] else "missed"
    return [f"Framework floor, same run: a node that only receives the same sensor topics (raw, sensor-data "
            f"QoS, the same executor) takes {100 * floor:.1f} % of one core; the four nodes take "
            f"**{ratio:.1f}x** four of it (target <= {TARGETS['floor_ratio']:g}x: {ok})", ""]


def _compiled_ratios(cores: list[dict[str, Any]]) -> list[str]:
    """Compiled kernels against the same maths in numpy, measured side by side in this run."""
    rows = {r["name"]: r for r in cores}
    lines = []
    for label, target in (("fusion ES-EKF: IMU step (18 states, incl. vehicle constraints)", "fusion_imu_us"),
                          ("fusion ES-EKF: CAN speed update", None), ("fusion ES-EKF: GNSS update", None),
                          ("vehicle state: CKF (paper 004, 5 states, 4-wheel Dugoff)", "state_step_us"),
                          ("vehicle state: VB-ACKF, N = 10 (shipped)", "state_step_us")):
        fast, slow = rows.get(f"{label}, compiled"), rows.get(f"{label}, numpy")
        if not (fast and slow and fast["median_us"] > 0):
            continue
        goal = ""
        if target:
            ok = "met" if fast["median_us"] <= TARGETS[target] else "missed"
            goal = f"; target <= {TARGETS[target]:g} µs: {ok}"
        lines.append(f"- {label}: compiled {fast['median_us']:.1f} µs against numpy {slow['median_us']:.1f} µs, "
                     f"**{slow['median_us'] / fast['median_us']:.1f}x**{goal}")
    if lines:
        lines = ["", "Compiled kernels (numba) against the same maths in numpy, median per step, this run "
                     "(the same estimates to 1e-9: test_model_kernels):", ""] + lines
    return lines


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sections", default="cores,pipeline,live",
                   help="comma-separated: cores, pipeline, live (default: all)")
    p.add_argument("--minutes", type=float, default=30.0, help="pipeline drive length [min] (default 30)")
    p.add_argument("--core-seconds", type=float, default=120.0,
                   help="simulated drive the cores are timed on [s] (default 120)")
    p.add_argument("--live-seconds", type=float, default=60.0, help="live run length [s] (default 60)")
    p.add_argument("--out", default=None, help="also write bench.json and bench.md here")
    p.add_argument("--workdir", default=None, help="where simulated bags are kept (default: a temporary dir)")


def main(args: argparse.Namespace) -> int:
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = set(sections) - {"cores", "pipeline", "live"}
    if unknown:
        print(f"bench: unknown section(s) {sorted(unknown)}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="vehicle_estimation_bench_") as tmp:
        workdir = Path(args.workdir) if args.workdir else Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        result: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0]}}
        if "cores" in sections:
            rows = run_cores(args.core_seconds)
            result["cores"] = [dataclasses.asdict(r) for r in rows]
            ours = next((r for r in rows if r.name.startswith("UKF, ours")), None)
            theirs = next((r for r in rows if r.name.startswith("filterpy")), None)
            if ours and theirs and ours.median_us > 0:
                result["ukf_vs_filterpy"] = theirs.median_us / ours.median_us
        if "pipeline" in sections:
            result["pipeline"] = run_pipeline(args.minutes, workdir)
        if "live" in sections:
            result["live"] = run_live(args.live_seconds, workdir)
    report = format_report(result)
    print(report)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "bench.json").write_text(json.dumps(result, indent=2))
        (out / "bench.md").write_text(report + "\n")
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    raise SystemExit(run_as_script(sys.modules[__name__]))
