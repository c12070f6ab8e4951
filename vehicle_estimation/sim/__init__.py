"""Vehicle + sensor simulator writing rosbag2 (MCAP) bags of the topic contract.

Public API::

    from vehicle_estimation.sim import (Scenario, SensorConfig, SpeedProfile, RoadSpec,
        simulate, write_bag, default_scenario, scenario_by_name, SCENARIOS, params_path)
"""

from vehicle_estimation.sim.profiles import SpeedProfile, load_cycle
from vehicle_estimation.sim.road import RoadSpec
from vehicle_estimation.sim.scenario import SCENARIOS, Scenario, SensorConfig, default_scenario, load_vehicle, params_path, scenario_by_name
from vehicle_estimation.sim.simulate import SimResult, simulate


def write_bag(result, path):
    """Write ``result`` as a rosbag2 MCAP directory at ``path`` (must not exist); returns path."""
    from vehicle_estimation.sim.bag import write_bag as _write_bag
    return _write_bag(result, path)


__all__ = [
    "Scenario", "SensorConfig", "SpeedProfile", "RoadSpec", "SimResult", "simulate", "write_bag",
    "default_scenario", "scenario_by_name", "SCENARIOS", "params_path", "load_vehicle", "load_cycle",
]
