"""Scenario and sensor configuration, the named scenarios, and ``params_path``."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path
from typing import Any, Callable, Optional

from vehicle_estimation.contract.vehicle import VehicleParams, load_vehicle_params
from vehicle_estimation.sim.profiles import SpeedProfile
from vehicle_estimation.sim.road import RoadSpec


def params_path(name: str) -> Path:
    """Path of ``params/<name>.yaml`` (``name`` with or without ``.yaml``).

    Looks in ``<sys.prefix>/share/vehicle_estimation/params/`` (installed package) and then in
    ``<repo>/params/`` (source checkout). An existing path is returned unchanged.
    """
    p = Path(name)
    if p.suffix in (".yaml", ".yml") and p.is_file():
        return p
    fname = name if name.endswith((".yaml", ".yml")) else f"{name}.yaml"
    candidates = [
        Path(sys.prefix) / "share" / "vehicle_estimation" / "params" / fname,
        Path(__file__).resolve().parents[2] / "params" / fname,
    ]
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(f"params file {fname!r} not found in " + ", ".join(str(c.parent) for c in candidates))


def load_vehicle(name: str) -> VehicleParams:
    return load_vehicle_params(params_path(name))


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """Rates [Hz], noise (1-sigma, SI), biases and faults of the simulated sensors."""

    # IMU (body frame imu_link, specific force incl. gravity, angular rate)
    imu_rate: float = 200.0
    accel_noise: float = 0.05                 # white noise per sample [m/s²]
    gyro_noise: float = 0.002                 # white noise per sample [rad/s]
    accel_bias_rw: float = 2e-4               # bias random walk [m/s²/√s]
    gyro_bias_rw: float = 2e-5                # bias random walk [rad/s/√s]
    accel_bias: Optional[tuple[float, float, float]] = None   # turn-on bias; None: drawn (seeded)
    gyro_bias: Optional[tuple[float, float, float]] = None
    accel_bias_std: float = 0.05              # std of the drawn turn-on bias [m/s²]
    gyro_bias_std: float = 0.002              # [rad/s]
    imu_misalignment_deg: tuple[float, float, float] = (0.4, -0.5, 0.3)  # roll, pitch, yaw of imu_link in base_link
    # GNSS (antenna at base_link)
    gnss_rate: float = 10.0
    gnss_noise: tuple[float, float, float] = (1.5, 1.5, 3.0)  # E, N, U [m]
    gnss_noise_tau: float = 0.0               # >0: first-order Gauss-Markov correlation time [s]
    gnss_outages: tuple[tuple[float, float], ...] = ()        # (start, end) [s since sim start]
    gnss_outage_mode: str = "nofix"           # "nofix": status -1 and NaN position; "drop": no messages
    # CAN / OBD-II
    speed_rate: float = 100.0                 # vehicle/speed
    joint_states_rate: float = 100.0          # vehicle/joint_states
    powertrain_rate: float = 100.0            # vehicle/powertrain
    speed_noise: float = 0.0                  # before quantisation [m/s]
    speed_quantum_kmh: float = 1.0            # OBD-II PID 0D resolution
    wheel_speed_noise: float = 0.02           # [rad/s]
    steering_noise: float = 0.002             # steering-wheel angle [rad]
    engine_speed_noise: float = 0.0           # [rad/s]
    engine_torque_noise: float = 2.0          # [N m] (also on the drive force, scaled)
    brake_torque_noise: float = 0.0           # [N m]
    # What the car puts on vehicle/powertrain; the rest is NaN ("not reported"). An OBD-II-only
    # car: ("engine_speed", "engine_load").
    powertrain_reports: tuple[str, ...] = ("engine_speed", "engine_torque", "engine_load", "gear", "drive_force")
    # paper 004 Eq. 34: variance multipliers 9, 1, 4, 0.25 over 40 s segments on IMU ax, ay, r
    eq34_noise: bool = False
    eq34_multipliers: tuple[float, ...] = (9.0, 1.0, 4.0, 0.25)
    eq34_segment_s: float = 40.0
    # paper 002 outliers on IMU ay and yaw rate
    outliers: bool = False
    outlier_isolated_rate: float = 0.005      # probability per sample
    outlier_burst_rate: float = 0.02          # bursts per second
    outlier_burst_len: tuple[int, int] = (3, 12)   # samples
    outlier_magnitude_ay: float = 3.0         # [m/s²], random sign, times U(0.7, 1.5)
    outlier_magnitude_r: float = 0.15         # [rad/s]
    # vehicle body motion seen by the IMU
    suspension_roll_gain: float = 0.0         # roll [rad] per m/s² of lateral acceleration


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Everything that defines one simulated drive. Vary it with ``dataclasses.replace``."""

    name: str = "custom"
    vehicle: VehicleParams = dataclasses.field(default_factory=VehicleParams)
    duration_s: float = 60.0
    speed_profile: SpeedProfile = dataclasses.field(default_factory=SpeedProfile)
    road: RoadSpec = dataclasses.field(default_factory=RoadSpec)
    wind_enu: tuple[float, float, float] = (0.0, 0.0, 0.0)   # air velocity [m/s] (E, N, U)
    seed: int = 0
    sensors: SensorConfig = dataclasses.field(default_factory=SensorConfig)
    initial_speed: float = 0.0          # [m/s]; > 0 starts moving (no standstill)
    standstill_s: float = 10.0          # standstill at the start [s] (when initial_speed == 0)
    origin_lat: float = 55.78
    origin_lon: float = 12.52
    origin_alt: float = 50.0
    physics_rate: float = 500.0         # fixed-step integration rate [Hz]


def _scenario(name: str, duration_s: float, speed_profile: SpeedProfile, road: RoadSpec, seed: int,
              vehicle: str = "sedan_d_class", **fields: Any) -> Scenario:
    """A named scenario of a shipped vehicle (the sedan of paper 004 unless said otherwise)."""
    return Scenario(name=name, vehicle=load_vehicle(vehicle), duration_s=duration_s,
                    speed_profile=speed_profile, road=road, seed=seed, **fields)


def default_scenario(**overrides) -> Scenario:
    """Sedan (paper 004), 620 s: 10 s standstill, then urban/country/highway/country/urban
    on a hilly (|grade| <= 6 %), curvy road, ending at standstill."""
    scn = _scenario("default", 620.0, SpeedProfile(kind="route"), RoadSpec(kind="random", grade_max=0.06), seed=1)
    return dataclasses.replace(scn, **overrides)


def _short() -> Scenario:
    points = ((0, 0), (10, 16.7), (30, 16.7), (36, 12.0), (40, 12.0), (47, 0.0), (50, 0.0))
    return _scenario("short", 60.0, SpeedProfile(kind="points", points=points),
                     RoadSpec(kind="random", grade_max=0.05, hill_wavelengths=(600.0, 300.0)), seed=2)


def _paper004_loop() -> Scenario:
    # Eq. 34 scales the paper's R = diag[4e-2, 4e-2, 6e-5] (Sec. 7.1): the base noise of the
    # measured ax, ay (0.2 m/s^2) and yaw rate (0.0077 rad/s) is the paper's.
    return _scenario("paper004_loop", 320.0, SpeedProfile(kind="distance"), RoadSpec(kind="loop004", grade_max=0.05),
                     seed=4, initial_speed=80.0 / 3.6, standstill_s=0.0,
                     sensors=SensorConfig(eq34_noise=True, accel_noise=0.2, gyro_noise=math.sqrt(6e-5)))


def _truck_hwfet() -> Scenario:
    return _scenario("truck_hwfet", 790.0, SpeedProfile(kind="cycle", cycle="hwfet"),
                     RoadSpec(kind="random", grade_max=0.03, lat_acc=1.5), seed=5, vehicle="heavy_truck")


def _cycle(cycle: str, duration: float, vehicle: str = "sedan_d_class", seed: int = 6) -> Callable[[], Scenario]:
    def make() -> Scenario:
        return _scenario(f"{vehicle.split('_')[0]}_{cycle}", duration, SpeedProfile(kind="cycle", cycle=cycle),
                         RoadSpec(kind="random", grade_max=0.05), seed=seed, vehicle=vehicle)
    return make


def paper002_sensors(segment_s: float, burst_rate: float) -> SensorConfig:
    """Paper-002 measurement conditions: the isolated spikes and speckled bursts of Sec. 3.3 on
    the IMU ay and yaw rate, and time-varying noise (the Eq.-34 variance schedule 9, 1, 4, 0.25
    of paper 004 over ``segment_s`` segments around 0.1 m/s^2 and 0.004 rad/s); IMU at 100 Hz."""
    return SensorConfig(imu_rate=100.0, accel_noise=0.1, gyro_noise=0.004, eq34_noise=True,
                        eq34_segment_s=segment_s, outliers=True, outlier_isolated_rate=0.005,
                        outlier_burst_rate=burst_rate)


def _paper002_dlc() -> Scenario:
    """ISO 3888-2 double lane changes at 80 km/h (one every 200 m, 30 s), flat road."""
    return _scenario("paper002_dlc", 30.0, SpeedProfile(kind="constant", speed_mps=80.0 / 3.6),
                     RoadSpec(kind="dlc3888", grade_max=0.0, dlc_lead_in=80.0, dlc_repeat_m=200.0), seed=21,
                     initial_speed=80.0 / 3.6, standstill_s=0.0, sensors=paper002_sensors(segment_s=5.0, burst_rate=0.2))


def _paper002_mixed() -> Scenario:
    """300 s urban/country/highway drive on a curvy, hilly road with the paper-002 outliers."""
    return _scenario("paper002_mixed", 300.0, SpeedProfile(kind="route", route_mix=("urban", "country", "highway")),
                     RoadSpec(kind="random", grade_max=0.05, lat_acc=3.0), seed=22, standstill_s=5.0,
                     sensors=paper002_sensors(segment_s=40.0, burst_rate=0.05))


SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "default": default_scenario,
    "short": _short,
    "paper004_loop": _paper004_loop,
    "truck_hwfet": _truck_hwfet,
    "sedan_wltc3": _cycle("wltc3", 1815.0),
    "sedan_hwfet": _cycle("hwfet", 780.0),
    "sedan_udds": _cycle("udds", 1385.0),
    "sedan_us06": _cycle("us06", 615.0),
    "audi_wltc3": _cycle("wltc3", 1815.0, "audi_a4", 7),
    "paper002_dlc": _paper002_dlc,
    "paper002_mixed": _paper002_mixed,
}


def scenario_by_name(name: str) -> Scenario:
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None
    return factory()
