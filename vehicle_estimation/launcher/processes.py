"""Start the estimator nodes as OS processes and stop them cleanly.

Each node runs as ``python -m vehicle_estimation.ros.<node> --ros-args ...`` in its own
process. Children get ``PR_SET_PDEATHSIG`` so that they die with the launcher even if the
launcher itself is killed with SIGKILL: no orphan keeps publishing into a vehicle stack.

A replay started without ``ROS_DOMAIN_ID`` runs its nodes in a ROS domain of its own
(:func:`claim_domain_id`): a DDS replay owns ``/clock`` and the sync topics of its domain, so two
replays in one domain stall each other, and a replay in a vehicle stack's domain would drive its
clock. The first free id of :data:`REPLAY_DOMAINS` is locked exclusively with a lock file (held
until the replay ends, released by the OS if it dies); the test suite claims its domain the same
way, so tests and replays never share one either.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Sequence

from vehicle_estimation.ros import PIPELINE, NodeSpec

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


@dataclass
class NodeProcess:
    spec: NodeSpec
    argv: list[str]
    process: subprocess.Popen | None = None
    restarts: int = 0
    log_path: Path | None = None

    def start(self, env: dict[str, str]) -> None:
        stdout = None
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            stdout = open(self.log_path, "ab")  # noqa: SIM115 (closed below; the child keeps its copy)
        try:
            self.process = subprocess.Popen(
                self.argv, env=env, stdout=stdout, stderr=subprocess.STDOUT if stdout else None,
                preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)
        finally:
            if stdout is not None:
                stdout.close()

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def last_words(self, max_chars: int = 400) -> str:
        """The last non-empty line of the node's log ("" without one): where a node's output
        goes to a file, the reason it stopped (a refused parameter names itself there)."""
        if self.log_path is None:
            return ""
        try:
            with open(self.log_path, "rb") as log:
                log.seek(max(0, log.seek(0, os.SEEK_END) - 4 * max_chars))
                lines = log.read().decode("utf-8", errors="replace").splitlines()
        except OSError:
            return ""
        last = next((line.strip() for line in reversed(lines) if line.strip()), "")
        return last[-max_chars:]


@dataclass
class NodeGroup:
    """The four nodes, with their params files, namespace, extra ``-p`` overrides and remappings.

    ``remaps`` are ``(FROM, TO)`` pairs given to every node as ``-r FROM:=TO``, so a vehicle
    stack's own topic names can be used without a relay.
    """

    params_files: Sequence[Path]
    namespace: str = "/"
    overrides: dict[str, dict[str, str]] = field(default_factory=dict)
    log_dir: Path | None = None
    remaps: Sequence[tuple[str, str]] = ()
    nodes: list[NodeProcess] = field(default_factory=list)

    def __post_init__(self) -> None:
        for spec in PIPELINE:
            argv = [sys.executable, "-m", spec.module, "--ros-args", "-r", f"__ns:={self.namespace}"]
            for source, target in self.remaps:
                argv += ["-r", f"{source}:={target}"]
            for params in self.params_files:
                argv += ["--params-file", str(params)]
            for key, value in self.overrides.get(spec.name, {}).items():
                argv += ["-p", f"{key}:={value}"]
            log = self.log_dir / f"{spec.name}.log" if self.log_dir else None
            self.nodes.append(NodeProcess(spec, argv, log_path=log))

    def start(self) -> None:
        for node in self.nodes:
            node.start(self._env())

    def make_in_process(self, made: list, **node_kwargs: Any) -> None:
        """The group's nodes made in this process instead (``--in-process``): each node class
        with the arguments its process would get and ``node_kwargs`` (``transport``,
        ``context``, ...), appended to ``made`` as it is made, so that a caller can destroy
        those made before a failure. A refused parameter raises ``ParameterError`` naming the
        node."""
        import importlib

        from vehicle_estimation.ros.runtime.parameters import ParameterError
        for proc in self.nodes:
            node_class = getattr(importlib.import_module(proc.spec.module), proc.spec.node_class)
            try:
                made.append(node_class(cli_args=proc.argv[proc.argv.index("--ros-args"):],
                                       use_global_arguments=False, **node_kwargs))
                made[-1].check_parameter_overrides()
            except ParameterError as exc:
                raise ParameterError(f"{proc.spec.name}: invalid parameter: {exc}") from None

    def restart(self, node: NodeProcess) -> None:
        """Start ``node`` again (after it exited) with the same command line."""
        node.start(self._env())

    @staticmethod
    def _env() -> dict[str, str]:
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        return env

    def check(self) -> list[NodeProcess]:
        """Nodes that have exited."""
        return [n for n in self.nodes if not n.alive()]

    def stop(self, timeout: float = 10.0) -> None:
        """SIGINT, wait, then SIGTERM, then SIGKILL: every child is reaped."""
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            running = [n for n in self.nodes if n.alive()]
            if not running:
                return
            for n in running:
                try:
                    n.process.send_signal(sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            for n in running:
                try:
                    n.process.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass


#: Linux leaves domains 0..101 outside the ephemeral port range (ROS 2 "The ROS_DOMAIN_ID"). The
#: low ids are the ones people pick for their stacks; replays take the upper half.
REPLAY_DOMAINS = range(51, 102)


class DomainClaim:
    """An exclusively locked domain id; :meth:`release` (or process exit) frees it."""

    def __init__(self, domain: int, handle: IO[str]) -> None:
        self.domain, self._handle = domain, handle

    def release(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None


def claim_domain_id(candidates: range = REPLAY_DOMAINS, start: int | None = None) -> DomainClaim:
    """Lock the first free id of ``candidates``, trying from ``start`` (default: by process id,
    so that concurrent claims seldom try the same id first)."""
    lock_dir = Path(tempfile.gettempdir())
    n = len(candidates)
    first = (os.getpid() if start is None else start) % n
    for offset in range(n):
        domain = candidates[(first + offset) % n]
        handle = open(lock_dir / f"vehicle_estimation_ros_domain_{domain}.lock", "w")  # noqa: SIM115
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        return DomainClaim(domain, handle)
    raise RuntimeError(f"no free ROS domain id in {candidates.start}..{candidates.stop - 1}: "
                       "set ROS_DOMAIN_ID for this replay")
