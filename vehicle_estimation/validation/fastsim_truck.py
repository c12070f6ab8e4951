"""A 36 t truck cruising a long-haul road in NREL FASTSim 3: the low-excitation mass case.

A heavy truck at near-constant highway speed is the hardest case for an online mass estimate:
the regressor of the longitudinal dynamics, ``a + g (sin(slope) + C_r)``, barely varies (here
its standard deviation is about 0.1 m/s^2), so a slope error of a few tenths of a degree
(0.05 m/s^2) is the size of the excitation itself, and least squares with noise in its
regressor is biased towards zero (errors-in-variables). This drive makes that case with a
vehicle model that is not ours.

The vehicle is FASTSim's conventional powertrain (the ``2012_Ford_Fusion.yaml`` resource of
:mod:`.fastsim_drive`, FASTSim's only conventional vehicle) re-parametrised as a class-8
tractor-trailer at 36 t gross (:data:`TRUCK`; typical values, each said in the vehicle file):
C_d 0.6, frontal area 9.7 m^2, C_rr 0.0055, 18 wheels of 0.5 m, a 380 kW engine and a 0.93
efficient transmission. FASTSim's physics are unchanged (backward-facing power balance,
:mod:`.fastsim_drive` describes it); with ``allow_trace_miss`` the truck, short of power on
the climbs, falls behind the cycle's speed as a real one does, and its achieved speed is the
truth.

The drive (``FULL_DURATION`` 1800 s, about 38 km): a start from rest to 80 km/h in two minutes,
30 minutes of cruise between 78 and 84 km/h (knots a few minutes apart, as a driver and a cruise
control leave it), a stop at the end; a rolling long-haul road whose grade is three sines of
the distance (1.6-6 km wavelengths, within +-1.5 %). The sensors, their noise and every topic
are those of :mod:`.fastsim_drive` (:func:`.fastsim_drive.sensor_result`).

CLI: ``python -m vehicle_estimation.validation.fastsim_truck --out DIR [--duration S] [--seed N]``
writes ``fastsim_truck`` and ``fastsim_truck_no_gnss`` and the vehicle file
``fastsim_class8_truck.yaml``.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vehicle_estimation.validation import fastsim_drive as fd
from vehicle_estimation.validation import road_drive as rd

VEHICLE_NAME = "fastsim_class8_truck"
FULL_DURATION = 1800.0           # [s]
SIM_RATE_HZ = fd.SIM_RATE_HZ
#: (time [s], speed [m/s]) knots: away from rest, then a cruise around 80 km/h.
SPEED_POINTS = (
    (0, 0), (5, 0), (45, 10), (85, 17), (125, 22.2), (300, 22.2), (420, 23.2), (600, 22.5), (760, 21.7),
    (900, 22.4), (1080, 23.3), (1260, 22.6), (1420, 21.9), (1600, 22.8), (1760, 22.2), (1790, 0), (1800, 0),
)
#: (amplitude [-], wavelength [m], phase [rad]) of the grade sines: a rolling long-haul road.
GRADE_TERMS = ((0.009, 6000.0, 0.0), (0.0045, 2900.0, 0.9), (0.0025, 1600.0, 2.1))
LEVEL_START_M = 200.0
#: FASTSim fields (dotted paths in its vehicle dict) changed from the Ford Fusion resource.
TRUCK = {
    "name": "class-8 tractor-trailer (FASTSim Conv re-parametrised)",
    "mass_kilograms": 36000.0,
    "pwr_aux_base_watts": 2000.0,
    "chassis.drag_coef": 0.6,
    "chassis.frontal_area_square_meters": 9.7,
    "chassis.wheel_rr_coef": 0.0055,
    "chassis.wheel_inertia_kilogram_square_meters": 20.0,
    "chassis.num_wheels": 18,
    "chassis.wheel_radius_meters": 0.5,
    "chassis.cg_height_meters": 1.6,
    "chassis.drive_type": "RWD",
    "chassis.drive_axle_weight_frac": 0.35,
    "chassis.wheel_base_meters": 5.9,
    "chassis.glider_mass_kilograms": 14000.0,
    "chassis.cargo_mass_kilograms": 22000.0,
    "pt_type.Conv.fc.pwr_out_max_watts": 380000.0,
    "pt_type.Conv.fc.pwr_out_max_init_watts": 60000.0,
    "pt_type.Conv.transmission.eff_interp": 0.93,
}


def load_vehicle():
    """FASTSim's conventional vehicle with the :data:`TRUCK` fields."""
    fsim = fd._fastsim()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        data = fsim.Vehicle.from_resource(fd.VEHICLE_RESOURCE).to_dict()
        for path, value in TRUCK.items():
            *parents, leaf = path.split(".")
            node = data
            for key in parents:
                node = node[key]
            node[leaf] = value
        return fsim.Vehicle.from_dict(data)


def cycle_arrays(duration: float | None = None, rate_hz: int = SIM_RATE_HZ) -> dict[str, np.ndarray]:
    """Time, speed and grade of the cycle (the grade at the cycle's distance)."""
    return rd.road_cycle(FULL_DURATION if duration is None else duration, rate_hz, SPEED_POINTS, GRADE_TERMS,
                         LEVEL_START_M)


def simulate(duration: float | None = None) -> fd.Drive:
    """The truck walked through the cycle; it may fall behind the cycle's speed on climbs."""
    return fd.simulate(cycle=cycle_arrays(duration), vehicle=load_vehicle(), allow_trace_miss=True)


def params_yaml(*, drag_k: float | None = None) -> str:
    """The text of the truck's vehicle file (FASTSim's values; the rest from our heavy truck)."""
    vehicle = load_vehicle()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        flat = vehicle.to_dict(flatten=True)
    d = {k: v for k, v in flat.items() if ".history." not in k and not k.startswith("state.")}
    drag_k = fd.drag_power_coefficient(vehicle=vehicle) if drag_k is None else drag_k
    values = fd.vehicle_params_mapping(d, drag_k=drag_k)
    values.update({
        "name": VEHICLE_NAME, "track_front": 2.05, "track_rear": 1.85, "yaw_inertia": 250000.0,
        "engine_inertia": 0.0, "final_drive": 3.4,
        "gear_ratios": [14.94, 11.73, 9.04, 7.09, 5.54, 4.35, 3.44, 2.70, 2.08, 1.63, 1.27, 1.00],
        "steering_ratio": 20.0, "engine_idle_speed": 62.83, "engine_max_speed": 230.38,
        "engine_max_torque": 2500.0, "engine_drag_torque": 120.0, "max_brake_torque": 60000.0,
        "cornering_stiffness_front": 250000.0, "cornering_stiffness_rear": 600000.0,
        "longitudinal_stiffness": 800000.0,
    })
    notes = {
        "mass": "FASTSim mass_kilograms (36 t gross, set for this drive)",
        "curb_mass": "derived: mass_kilograms - cargo_mass_kilograms",
        "air_density": f"derived: 2 k / (C_d A), k = {drag_k:.6f} W s^3/m^3 of FASTSim's drag power k v^3",
        "rolling_resistance": "FASTSim wheel_rr_coef", "frontal_area": "FASTSim frontal_area_square_meters",
        "drag_coefficient": "FASTSim drag_coef", "wheel_radius": "FASTSim wheel_radius_meters",
        "wheel_inertia": "FASTSim num_wheels x wheel_inertia_kilogram_square_meters",
        "driveline_efficiency": "FASTSim transmission eff_interp",
        "engine_max_power": "FASTSim fc pwr_out_max_watts", "gravity": "FASTSim's g",
        "pitch_gain": "FASTSim has no suspension: the body pitch is the road's",
    }
    for key in ("track_front", "track_rear", "yaw_inertia", "final_drive", "gear_ratios", "steering_ratio",
                "engine_idle_speed", "engine_max_speed", "engine_max_torque", "engine_drag_torque",
                "max_brake_torque", "cornering_stiffness_front", "cornering_stiffness_rear",
                "longitudinal_stiffness", "lf", "lr", "cg_height", "brake_front_share", "road_friction"):
        notes.setdefault(key, "guess (typical class-8 value; FASTSim has no gearbox, tyres or lateral model)")
    header = [
        f"# A 36 t class-8 truck in NREL FASTSim {fd.FASTSIM_VERSION}: its conventional powertrain",
        "# re-parametrised (vehicle_estimation.validation.fastsim_truck.TRUCK), the vehicle of the",
        "# low-excitation mass drive. Written by vehicle_estimation.validation.fastsim_truck.params_yaml().",
    ]
    return rd.format_vehicle_yaml(header, values, notes)


VARIANTS = {"fastsim_truck": (True, True), "fastsim_truck_no_gnss": (False, True)}


def generate(out_dir: Path, *, seed: int = 0, duration: float | None = None,
             imu_rpy_deg=(0.0, 0.0, 0.0)) -> list[Path]:
    """``fastsim_truck`` and ``fastsim_truck_no_gnss`` in ``out_dir`` plus the vehicle file
    ``fastsim_class8_truck.yaml``; returns the bag paths. ``imu_rpy_deg``: the IMU's roll, pitch, yaw in
    ``base_link`` [deg] (:func:`~.road_drive.imu_samples`)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{VEHICLE_NAME}.yaml").write_text(rd.with_imu_mounting(params_yaml(), imu_rpy_deg), encoding="utf-8")
    result = fd.sensor_result(simulate(duration), seed=seed, imu_rpy_deg=imu_rpy_deg)
    return [fd.write_drive(result, out_dir / name, gnss=gnss, wheels=wheels)
            for name, (gnss, wheels) in VARIANTS.items()]


def main(argv: Sequence[str] | None = None) -> int:
    return rd.generator_main(argv, sys.modules[__name__], out_help="output folder (one bag per variant)")


if __name__ == "__main__":
    raise SystemExit(main())
