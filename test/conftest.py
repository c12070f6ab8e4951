"""Test-session set-up: a private ROS domain on localhost, so parallel runs never cross-talk.

The domain id is claimed with an exclusive file lock among ids 1..100, held for the whole
session; child processes (node executables, the launcher) inherit the environment.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

_DOMAIN_CLAIM = None


def _claim_domain_id() -> int:
    global _DOMAIN_CLAIM
    from vehicle_estimation.launcher.processes import claim_domain_id
    _DOMAIN_CLAIM = claim_domain_id(range(1, 101))
    return _DOMAIN_CLAIM.domain


if "VEHICLE_ESTIMATION_TEST_DOMAIN" not in os.environ:
    os.environ["ROS_DOMAIN_ID"] = str(_claim_domain_id())
    os.environ["VEHICLE_ESTIMATION_TEST_DOMAIN"] = os.environ["ROS_DOMAIN_ID"]
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
