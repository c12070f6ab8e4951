"""Test-session set-up: a private ROS domain on localhost, so parallel runs never cross-talk.

The domain id is claimed with an exclusive file lock among ids 1..100, held for the whole
session; child processes (node executables, the launcher) inherit the environment.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

_DOMAIN_CLAIM = None


def _claim_domain_id() -> int:
    global _DOMAIN_CLAIM
    from vehicle_estimation.launcher.processes import claim_domain_id
    _DOMAIN_CLAIM = claim_domain_id(range(1, 101))
    return _DOMAIN_CLAIM.domain


# Each pytest-xdist worker claims its own: a node that outlives its test (a crash) cannot then
# talk to the other worker's next one.
_CLAIMANT = os.environ.get("PYTEST_XDIST_WORKER", "main")
if os.environ.get("VEHICLE_ESTIMATION_TEST_DOMAIN_OWNER") != _CLAIMANT:
    os.environ["ROS_DOMAIN_ID"] = str(_claim_domain_id())
    os.environ["VEHICLE_ESTIMATION_TEST_DOMAIN_OWNER"] = _CLAIMANT
# Localhost-only discovery, over UDP on the loopback interface (the profile says why not over
# rmw_fastrtps's LOCALHOST range, which adds shared memory). SYSTEM_DEFAULT makes the rmw take the
# transports from the profile instead of configuring its own.
_LOOPBACK_PROFILE = Path(__file__).parent / "data" / "fastdds_loopback_udp.xml"
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(_LOOPBACK_PROFILE)
os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(_LOOPBACK_PROFILE)
os.environ.pop("RMW_FASTRTPS_USE_QOS_FROM_XML", None)
os.environ.pop("ROS_STATIC_PEERS", None)
os.environ.setdefault("MPLBACKEND", "Agg")
# Node logs and the launcher's persisted estimator state go to ROS_HOME: keep them out of ~/.ros.
os.environ["ROS_HOME"] = tempfile.mkdtemp(prefix="vehicle_estimation_test_ros_home_")

# Tests that start a live ROS graph run alone, the others side by side on every core
# (test/dds_serial.py says why and how).
pytest_plugins = ["dds_serial"]


@pytest.hookimpl(tryfirst=True)
def pytest_cmdline_main(config):
    """Spread the tests over the cores when pytest-xdist is installed and the command line
    did not say otherwise (``-n 0`` runs them in one process)."""
    from dds_serial import workers_wanted
    if config.pluginmanager.hasplugin("xdist") and config.option.numprocesses is None \
            and not hasattr(config, "workerinput"):
        config.option.numprocesses = workers_wanted()
        if config.option.dist == "no" and config.option.numprocesses:
            config.option.dist = "loadscope"
