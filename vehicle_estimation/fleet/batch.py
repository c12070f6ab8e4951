"""``vehicle-estimation batch``: replay and report a fleet's bags in parallel, on Dask distributed.

Every bag is replayed through the four nodes in one worker process (``replay --in-process``:
the same nodes and the same estimates as the DDS replay, with no DDS traffic, so any number of
workers share a machine without seeing each other), then reported against its ground truth
where it has some. Per bag, under ``OUT/<bag>/``: ``estimates/`` (the recorded bag),
``report/`` (``report.json`` and plots) and ``result.json`` (status, duration, final values,
metrics, or the reason it failed). Across bags: ``summary.json``, ``summary.md`` and
``fleet_metrics.png``.

Why Dask distributed (over Ray): a bag is one coarse task of seconds to minutes that returns a
small dict, which is exactly Dask's ``Client.map`` with futures; its ``LocalCluster`` starts in
seconds from a pure-Python wheel, and ``--scheduler tcp://host:8786`` points the same command at
a cluster started with ``dask scheduler`` / ``dask worker`` on any machines that can read the
bags. Ray would bring a large binary runtime for features (actors, an object store for arrays)
that a batch of independent replays does not use.

A bag that fails (unreadable, a worker that dies) is reported with its reason and does not stop
the others. ``--resume`` skips every bag whose ``result.json`` says ``ok``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

RESULT_FILE = "result.json"
#: Estimates whose last value is written per bag (topic, what it is, unit).
FINAL_VALUES = (
    ("/estimation/mass", "mass", "kg"),
    ("/estimation/road_slope", "road_slope", "rad"),
    ("/estimation/sideslip", "sideslip", "rad"),
)
#: Metrics against ground truth in the summary: (report group, path into it, column, scale).
SUMMARY_METRICS = (
    ("mass", ("last_half_mape_percent",), "mass last-half MAPE [%]", 1.0),
    ("mass", ("last_half_max_abs_percent_error",), "mass last-half worst [%]", 1.0),
    ("slope", ("rmse_deg",), "slope RMSE [deg]", 1.0),
    ("vehicle_state", ("vx", "rmse"), "vx RMSE [m/s]", 1.0),
    ("vehicle_state", ("vy", "rmse"), "vy RMSE [m/s]", 1.0),
)


class BatchError(RuntimeError):
    pass


# ------------------------------------------------------------------------------ bags
def is_bag(path: Path) -> bool:
    """A ROS 1 ``.bag`` file, or a rosbag2 directory (``metadata.yaml`` or MCAP/sqlite3 files)."""
    if path.is_file():
        return path.suffix == ".bag"
    if path.is_dir():
        return (path / "metadata.yaml").exists() or any(path.glob("*.mcap")) or any(path.glob("*.db3"))
    return False


def find_bags(paths: Iterable[str | Path]) -> list[Path]:
    """The bags named, and the bags directly inside every directory named that is not one."""
    bags: list[Path] = []
    for item in paths:
        path = Path(item)
        if is_bag(path):
            bags.append(path)
        elif path.is_dir():
            found = sorted(p for p in path.iterdir() if is_bag(p))
            if not found:
                raise BatchError(f"{path}: neither a bag nor a directory of bags")
            bags += found
        else:
            raise BatchError(f"{path}: no such bag or directory")
    unique: dict[Path, Path] = {}
    for bag in bags:
        unique.setdefault(bag.resolve(), bag)
    return list(unique.values())


def bag_keys(bags: Sequence[Path]) -> list[str]:
    """A directory name per bag: its name, made unique with its parent's where two share one."""
    names = [b.name[:-4] if b.name.endswith(".bag") else b.name for b in bags]
    keys = []
    for bag, name in zip(bags, names):
        keys.append(name if names.count(name) == 1 else f"{bag.resolve().parent.name}_{name}")
    seen: dict[str, int] = {}
    for i, key in enumerate(keys):
        seen[key] = seen.get(key, 0) + 1
        if seen[key] > 1:
            keys[i] = f"{key}_{seen[key]}"
    return keys


# ------------------------------------------------------------------------------ one bag
@dataclass
class BagJob:
    bag: str
    key: str
    out_dir: str
    params: list[str]
    tick_s: float
    vehicle_id: str = ""


def final_values(estimates: Path) -> dict[str, float]:
    """The last value of each of :data:`FINAL_VALUES` in a recorded replay (absent: not there)."""
    from rosbags.highlevel import AnyReader

    from vehicle_estimation.io.msgconvert import jazzy_typestore

    wanted = {topic: name for topic, name, _ in FINAL_VALUES}
    last: dict[str, float] = {}
    with AnyReader([estimates], default_typestore=jazzy_typestore()) as reader:
        connections = [c for c in reader.connections if c.topic in wanted]
        for conn, _, data in reader.messages(connections=connections):
            last[wanted[conn.topic]] = float(reader.deserialize(data, conn.msgtype).data)
    return last


def _write_json(path: Path, value: Any) -> None:
    from vehicle_estimation.evaluation.report import json_safe
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(json_safe(value), indent=2, sort_keys=True) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def run_bag(job: BagJob) -> dict[str, Any]:
    """Replay one bag in this process (in-process nodes), report it, write its ``result.json``.

    Never raises for a bad bag: the failure and its reason are the result.
    """
    from vehicle_estimation.evaluation.report import make_report
    from vehicle_estimation.launcher.processes import NodeGroup
    from vehicle_estimation.launcher.replay import replay

    out = Path(job.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    estimates = out / "estimates"
    shutil.rmtree(estimates, ignore_errors=True)     # what a failed earlier attempt left
    result: dict[str, Any] = {"bag": job.bag, "key": job.key, "vehicle_id": job.vehicle_id,
                              "params": job.params, "status": "failed", "reason": ""}
    wall0 = time.monotonic()
    try:
        stats = replay(Path(job.bag), estimates, lambda ov: NodeGroup([Path(p) for p in job.params], overrides=ov),
                       tick_s=job.tick_s, progress=False, in_process=True)
        result.update(duration_s=stats.bag_s, replay_wall_s=stats.wall_s,
                      rt_factor=stats.bag_s / stats.wall_s if stats.wall_s > 0 else math.nan,
                      lossless=stats.lossless, messages=sum(stats.read.values()))
        result["final"] = final_values(estimates)
        report = make_report(estimates, out / "report", print_table=False)
        result["metrics"] = report["groups"]
        result["status"] = "ok" if stats.lossless else "failed"
        if not stats.lossless:
            result["reason"] = "replay was not lossless"
    except Exception as exc:   # a bad bag is a row of the summary, not the end of the batch
        result["reason"] = f"{type(exc).__name__}: {exc}"
    result["wall_s"] = time.monotonic() - wall0
    _write_json(out / RESULT_FILE, result)
    return result


def load_result(out_dir: Path) -> dict[str, Any] | None:
    try:
        return json.loads((out_dir / RESULT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


# ------------------------------------------------------------------------------ the fleet
@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """A Dask client on ``scheduler``, or on a local cluster of ``workers`` processes (default:
    one per core) that ends with the block."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise BatchError("batch needs Dask distributed: pip install -e '.[fleet]'") from None
    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    n = workers or os.cpu_count() or 1
    # One single-threaded worker process per core: a replay is CPU-bound Python (one core),
    # and rclpy contexts are per process.
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        yield client


def run_jobs(jobs: Sequence[BagJob], client: Any, *, progress: bool = True) -> list[dict[str, Any]]:
    """Run :func:`run_bag` for every job on the cluster; results in the jobs' order."""
    if not jobs:
        return []
    from distributed import as_completed
    from tqdm import tqdm

    results: dict[str, dict[str, Any]] = {}
    # pure=False: a rerun of the same job is a new replay, never a cached result.
    futures = {client.submit(run_bag, job, pure=False, key=f"bag-{job.key}-{time.time_ns()}"): job
               for job in jobs}
    bar = tqdm(total=len(jobs), desc="batch", unit="bag", file=sys.stderr, disable=None if progress else True)
    for future in as_completed(futures):
        job = futures[future]
        try:
            results[job.key] = future.result()
        except Exception as exc:   # the worker died (a crash, out of memory)
            results[job.key] = {"bag": job.bag, "key": job.key, "vehicle_id": job.vehicle_id,
                                "status": "failed", "reason": f"worker lost: {type(exc).__name__}: {exc}"}
            _write_json(Path(job.out_dir) / RESULT_FILE, results[job.key])
        bar.update(1)
    bar.close()
    return [results[job.key] for job in jobs]


def _dig(d: Any, path: Sequence[str]) -> float:
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return math.nan
        d = d[key]
    return float(d) if isinstance(d, (int, float)) else math.nan


def summarize(results: Sequence[dict[str, Any]], out: Path, *, wall_s: float, workers: int | None) -> dict[str, Any]:
    """Write ``summary.json``, ``summary.md`` and ``fleet_metrics.png``; returns the summary."""
    rows = []
    for r in results:
        metrics = r.get("metrics", {}) or {}
        rows.append({
            "bag": r["key"], "vehicle_id": r.get("vehicle_id", ""), "status": r["status"],
            "reason": r.get("reason", ""), "duration_s": r.get("duration_s", math.nan),
            "rt_factor": r.get("rt_factor", math.nan), "skipped": bool(r.get("skipped", False)),
            "final": r.get("final", {}),
            "metrics": {column: _dig(metrics.get(group, {}), path) * scale
                        for group, path, column, scale in SUMMARY_METRICS},
        })
    ran = [r for r in rows if r["status"] == "ok" and not r["skipped"]]
    bag_s = sum(r["duration_s"] for r in ran)
    summary = {
        "bags": len(rows), "ok": sum(r["status"] == "ok" for r in rows),
        "failed": sum(r["status"] != "ok" for r in rows), "skipped": sum(r["skipped"] for r in rows),
        "wall_s": wall_s, "workers": workers,
        "bags_per_hour": 3600.0 * len(ran) / wall_s if wall_s > 0 and ran else math.nan,
        "bag_seconds_per_wall_second": bag_s / wall_s if wall_s > 0 and ran else math.nan,
        "rows": rows,
    }
    _write_json(out / "summary.json", summary)
    (out / "summary.md").write_text(format_summary(summary) + "\n", encoding="utf-8")
    plot_fleet(rows, out / "fleet_metrics.png")
    return summary


def _cell(x: Any, digits: int = 3) -> str:
    if isinstance(x, (int, float)) and math.isfinite(x):
        return f"{x:.{digits}g}"
    return "–"


def format_summary(summary: dict[str, Any]) -> str:
    columns = [c for _, _, c, _ in SUMMARY_METRICS]
    finals = [(name, unit) for _, name, unit in FINAL_VALUES]
    where = f"{summary['workers']} local workers" if summary["workers"] else "the cluster's workers"
    lines = [f"# Batch: {summary['bags']} bags, {summary['ok']} ok, {summary['failed']} failed"
             f" ({summary['skipped']} done before, skipped)", "",
             f"{summary['wall_s']:.1f} s wall on {where}: "
             f"{_cell(summary['bags_per_hour'])} bags per hour, "
             f"{_cell(summary['bag_seconds_per_wall_second'])} s of bag per second (bags run now only)", "",
             "| bag | vehicle | status | duration [s] | " + " | ".join(f"final {n} [{u}]" for n, u in finals)
             + " | " + " | ".join(columns) + " | reason |",
             "|" + "---|" * (5 + len(finals) + len(columns))]
    for r in summary["rows"]:
        status = r["status"] + (" (skipped)" if r["skipped"] else "")
        lines.append(f"| {r['bag']} | {r['vehicle_id'] or '–'} | {status} | {_cell(r['duration_s'], 4)} | "
                     + " | ".join(_cell(r["final"].get(n, math.nan), 5) for n, _ in finals) + " | "
                     + " | ".join(_cell(r["metrics"].get(c, math.nan)) for c in columns) + " | "
                     + (r["reason"].replace("|", "/").replace("\n", " ")[:200] or "") + " |")
    return "\n".join(lines)


def plot_fleet(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """One panel per summary metric: its value per bag (bags without ground truth are gaps)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = [c for _, _, c, _ in SUMMARY_METRICS]
    names = [r["bag"] for r in rows]
    fig, axes = plt.subplots(len(columns), 1, figsize=(max(6.0, 0.5 * len(names) + 2.0), 2.2 * len(columns)),
                             sharex=True, squeeze=False)
    for ax, column in zip(axes[:, 0], columns):
        values = [r["metrics"].get(column, math.nan) if r["status"] == "ok" else math.nan for r in rows]
        ax.bar(range(len(names)), [v if math.isfinite(v) else 0.0 for v in values],
               color=["C0" if math.isfinite(v) else "0.8" for v in values])
        ax.set_ylabel(column, fontsize=8)
        ax.grid(axis="y", alpha=0.3)
    axes[-1, 0].set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=7)
    fig.suptitle("Metrics per bag against ground truth (grey: none, or failed)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------ calibration
def read_vehicle_table(path: Path, bags: Sequence[Path]) -> dict[Path, tuple[str, float]]:
    """``--mass-from FILE.csv``: columns ``bag``, ``vehicle`` and ``mass_kg`` (empty where the
    mass is not known). A bag of the batch is named by its path or its file name; a row naming
    another bag (a path, relative to the CSV's directory or absolute) with a mass is a
    calibration drive that is not replayed. Returns bag -> (vehicle id, mass or NaN)."""
    import csv

    by_name: dict[str, Path] = {}
    for bag in bags:
        for name in (str(bag), bag.name, str(bag.resolve())):
            by_name[name] = bag
    table: dict[Path, tuple[str, float]] = {}
    with open(path, newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        missing = {"bag", "vehicle", "mass_kg"} - set(reader.fieldnames or ())
        if missing:
            raise BatchError(f"{path}: missing column(s) {', '.join(sorted(missing))} (want bag,vehicle,mass_kg)")
        for line, row in enumerate(reader, start=2):
            name = (row["bag"] or "").strip()
            text = (row["mass_kg"] or "").strip()
            try:
                mass = float(text) if text else math.nan
            except ValueError:
                raise BatchError(f"{path}:{line}: mass_kg {text!r} is not a number") from None
            if text and not (math.isfinite(mass) and mass > 0.0):
                raise BatchError(f"{path}:{line}: mass_kg must be a positive mass, got {text!r}")
            bag = by_name.get(name)
            if bag is None:
                other = path.parent / name
                if not (math.isfinite(mass) and is_bag(other)):
                    raise BatchError(f"{path}:{line}: {name!r} is not a bag of this batch, nor a calibration "
                                     "drive (a bag path with its mass)")
                bag = other
            table[bag] = ((row["vehicle"] or "").strip() or "unknown", mass)
    return table


def calibrate_vehicle(vehicle_id: str, bag: str, mass: float, base_vehicle: str, out_path: str) -> dict[str, Any]:
    """Paper 003's training phase (``calibrate``) on one drive of known mass; writes the
    vehicle's params file. Never raises: a failed calibration is reported."""
    from vehicle_estimation.contract.vehicle import load_vehicle_params
    from vehicle_estimation.training.calibrate import (
        calibrate_signals,
        params_document,
        read_drive,
        write_params,
    )

    result: dict[str, Any] = {"vehicle_id": vehicle_id, "bag": bag, "mass_kg": mass, "params": out_path}
    try:
        base = load_vehicle_params(base_vehicle)
        fitted = calibrate_signals(read_drive(Path(bag), None, base.imu_mounting_rpy), mass, base)
        header = (f"Calibrated by `batch --calibrate` for vehicle {vehicle_id} from {Path(bag).name} at {mass:g} kg\n"
                  f"(paper 003 Sec. 6, Eqs. 48-50). Torque fit R^2 = {fitted.fit.r2:.4f}.")
        write_params(out_path, params_document(fitted, base, mass), header)
        result.update(status="ok", r2=fitted.fit.r2)
    except Exception as exc:
        result.update(status="failed", reason=f"{type(exc).__name__}: {exc}")
    return result


def run_calibrations(table: dict[Path, tuple[str, float]], base_vehicle: Path, out: Path,
                     client: Any) -> dict[str, dict[str, Any]]:
    """One calibration per vehicle id, on its longest bag of known mass, on the cluster."""
    from rosbags.highlevel import AnyReader

    candidates: dict[str, list[tuple[float, Path, float]]] = {}
    for bag, (vehicle_id, mass) in table.items():
        if math.isfinite(mass):
            try:
                with AnyReader([bag]) as reader:
                    duration = (reader.end_time - reader.start_time) * 1e-9
            except Exception:
                duration = 0.0
            candidates.setdefault(vehicle_id, []).append((duration, bag, mass))
    jobs = []
    for vehicle_id, items in sorted(candidates.items()):
        _, bag, mass = max(items, key=lambda item: (item[0], str(item[1])))
        jobs.append((vehicle_id, str(bag), mass, str(base_vehicle),
                     str(out / "calibration" / f"{_safe(vehicle_id)}.yaml")))
    if not jobs:
        return {}
    futures = [client.submit(calibrate_vehicle, *job, pure=False) for job in jobs]
    results = client.gather(futures, errors="skip")
    done = {r["vehicle_id"]: r for r in results}
    for job in jobs:
        done.setdefault(job[0], {"vehicle_id": job[0], "bag": job[1], "status": "failed", "reason": "worker lost"})
    return done


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name) or "vehicle"


# ------------------------------------------------------------------------------ command
def add_arguments(p: argparse.ArgumentParser) -> None:
    from vehicle_estimation.launcher.options import add_params_options
    p.add_argument("bags", nargs="+", metavar="BAG_OR_DIR",
                   help="bags (rosbag2 directories, ROS 1 .bag files) or directories holding bags")
    p.add_argument("--out", required=True, help="output directory: one folder per bag, and the summary")
    add_params_options(p)
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--scheduler", default=None,
                   help="address of a running Dask scheduler (tcp://host:8786) instead of a local cluster")
    p.add_argument("--resume", action="store_true", help="skip the bags whose result.json says ok")
    p.add_argument("--tick", type=float, default=0.1, help="replay tick of bag time [s]")
    p.add_argument("--calibrate", action="store_true",
                   help="first run paper 003's training phase per vehicle (needs --mass-from) and replay "
                        "each vehicle's bags with its calibrated params file")
    p.add_argument("--mass-from", default=None, metavar="FILE.csv",
                   help="CSV with columns bag,vehicle,mass_kg: the vehicle id of each bag and, where known, "
                        "its mass (the calibration drives)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def main(args: argparse.Namespace) -> int:
    from vehicle_estimation.launcher.options import params_files
    from vehicle_estimation.paths import params_file

    if args.workers is not None and args.workers < 1:
        print("batch: --workers must be at least 1", file=sys.stderr)
        return 2
    if args.calibrate and not args.mass_from:
        print("batch: --calibrate needs --mass-from FILE.csv (which bags are which vehicle, and their mass)",
              file=sys.stderr)
        return 2
    try:
        bags = find_bags(args.bags)
        files = [str(p) for p in params_files(args)]
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        table = read_vehicle_table(Path(args.mass_from), bags) if args.mass_from else {}
        wall0 = time.monotonic()
        keys = bag_keys(bags)
        results: dict[str, dict[str, Any]] = {}
        pending = []
        for bag, key in zip(bags, keys):
            previous = load_result(out / key) if args.resume else None
            if previous is not None and previous.get("status") == "ok":
                results[key] = {**previous, "skipped": True}
            else:
                pending.append((bag, key))
        print(f"batch: {len(bags)} bags, {len(pending)} to replay, {len(results)} done before", file=sys.stderr)
        calibrations: dict[str, dict[str, Any]] = {}
        if args.calibrate or pending:
            with dask_client(args.workers, args.scheduler) as client:
                if args.calibrate:
                    calibrations = run_calibrations(table, params_file(args.vehicle), out, client)
                    for vehicle_id, c in calibrations.items():
                        line = f"R^2 {c['r2']:.3f} -> {c['params']}" if c["status"] == "ok" else c["reason"]
                        print(f"calibration of {vehicle_id} on {Path(c['bag']).name}: {c['status']}, {line}",
                              file=sys.stderr)
                jobs = []
                for bag, key in pending:
                    vehicle_id = table.get(bag, ("", math.nan))[0]
                    params = list(files)
                    calibration = calibrations.get(vehicle_id)
                    if calibration is not None and calibration["status"] == "ok":
                        params[0] = calibration["params"]     # the calibrated file in place of --vehicle
                    jobs.append(BagJob(str(bag), key, str(out / key), params, args.tick, vehicle_id))
                for r in run_jobs(jobs, client, progress=not args.quiet):
                    results[r["key"]] = r
        ordered = [results[key] for key in keys]
        summary = summarize(ordered, out, wall_s=time.monotonic() - wall0,
                            workers=None if args.scheduler else (args.workers or os.cpu_count()))
        if calibrations:
            _write_json(out / "calibration" / "calibrations.json", calibrations)
    except BatchError as exc:
        print(f"batch: {exc}", file=sys.stderr)
        return 2
    print(format_summary(summary))
    return 0 if summary["failed"] == 0 else 1
