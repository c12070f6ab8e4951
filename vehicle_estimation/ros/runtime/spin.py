"""The node executables' main loop: executor choice, clean shutdown, optional profiling."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any, Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

from vehicle_estimation.ros.runtime.parameters import ParameterError


def make_executor() -> Any:
    """The C++ events executor of rclpy (Jazzy: ``rclpy.experimental``) when present.

    It dispatches callbacks without rebuilding a wait set in Python for every message, which
    roughly doubles replay speed; the plain single-threaded executor is the fallback.
    ``VEHICLE_ESTIMATION_EXECUTOR=single_threaded`` forces the fallback.
    """
    if os.environ.get("VEHICLE_ESTIMATION_EXECUTOR", "events") == "events":
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def run_node(node_factory: Callable[[], Node], args: list[str] | None = None) -> int:
    """Entry point shared by the node executables: a bad parameter exits 2 with its name."""
    rclpy.init(args=args if args is not None else sys.argv)
    try:
        node = node_factory()
        check = getattr(node, "check_parameter_overrides", None)
        if check is not None:
            check()
    except ParameterError as exc:
        print(f"[vehicle_estimation] invalid parameter: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        spin([node], node.get_name())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass                # a stop that came between start-up and spin
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def spin(nodes: list[Node], profile_name: str) -> None:
    """Spin ``nodes`` on one executor until the context shuts down (Ctrl-C, SIGTERM: rclpy's
    signal handlers); the profile is ``<profile_name>.prof`` (see :func:`_start_profiler`)."""
    executor, profiler = None, None
    try:
        # A Ctrl-C may come as soon as the node is up, before the executor spins: it is a stop.
        executor = make_executor()
        for node in nodes:
            executor.add_node(node)
        never = Future()
        profiler = _start_profiler()
        # spin_until_future_complete in slices rather than spin(): the events executor's
        # spin() busy-waits in rclpy 7 (Jazzy), and slices let us notice a shutdown.
        while rclpy.ok():
            executor.spin_until_future_complete(never, timeout_sec=0.5)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # rclpy's RCLError: a signal shut the context down between ok() and the wait, or while
        # a callback was publishing. That is the stop it asked for, not a failure.
        if rclpy.ok():
            raise
    finally:
        if profiler is not None:
            _dump_profile(profiler, profile_name)
        if executor is not None:
            executor.shutdown()


def _start_profiler() -> Any:
    """cProfile of the whole spin when ``VEHICLE_ESTIMATION_PROFILE_DIR`` is set (development:
    ``python -m pstats DIR/<node>.prof`` shows where a node's time goes)."""
    if not os.environ.get("VEHICLE_ESTIMATION_PROFILE_DIR"):
        return None
    import cProfile
    import time
    profiler = cProfile.Profile(time.process_time)   # CPU time: idle waiting is not a cost
    profiler.enable()
    return profiler


def _dump_profile(profiler: Any, name: str) -> None:
    profiler.disable()
    out = Path(os.environ["VEHICLE_ESTIMATION_PROFILE_DIR"])
    out.mkdir(parents=True, exist_ok=True)
    profiler.dump_stats(str(out / f"{name}.prof"))
