"""Vehicle + sensor simulator writing rosbag2 (MCAP) bags of the topic contract.

Public API::

    from vehicle_estimation.sim import (Scenario, SensorConfig, SpeedProfile, RoadSpec,
        simulate, write_bag, default_scenario, scenario_by_name, SCENARIOS, params_path)
"""

from .profiles import SpeedProfile, load_cycle
from .road import RoadSpec
from .scenario import SCENARIOS, Scenario, SensorConfig, default_scenario, load_vehicle, params_path, scenario_by_name
from .simulate import SimResult, simulate


def write_bag(result, path):
    """Write ``result`` as a rosbag2 MCAP directory at ``path`` (must not exist); returns path."""
    from .bag import write_bag as _write_bag
    return _write_bag(result, path)


__all__ = [
    "Scenario", "SensorConfig", "SpeedProfile", "RoadSpec", "SimResult", "simulate", "write_bag",
    "default_scenario", "scenario_by_name", "SCENARIOS", "params_path", "load_vehicle", "load_cycle",
]
