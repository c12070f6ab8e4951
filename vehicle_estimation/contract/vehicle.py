"""Vehicle parameters shared by the simulator and every estimator.

A vehicle is described once, in the ``vehicle.*`` section of a ROS 2 parameters file
(``params/<vehicle>.yaml``), and read here into a frozen :class:`VehicleParams`.
All quantities are SI (REP-103): kg, m, s, rad, N, N·m, rad/s.

Sources of the defaults shipped in ``params/``:

* ``sedan_d_class.yaml``: the D-class sedan of Chen et al. 2021 (paper 004), Table 1.
* ``audi_a4.yaml``: the 2018 Audi A4 of Jensen et al. 2022 (paper 003), Table 1.
* ``heavy_truck.yaml``: the heavy truck of Zhang et al. 2023 (paper 000), Table 1.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Mapping

import yaml

from vehicle_estimation.contract.settings import check_settings, setting

GRAVITY = 9.80665  # m/s², standard gravity


def dataclass_from_mapping(cls: Any, values: Mapping[str, Any], unknown: str) -> Any:
    """``cls(**values)`` from a flat mapping (ROS parameters, YAML), each value coerced to the
    type of its field's default: float, int, str, a bool only as a bool, a tuple or list of
    floats (a list may be None for empty). An unknown key raises ``ValueError(unknown)``,
    formatted with ``key``; the instance is validated before it is returned."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        field = fields.get(key)
        if field is None:
            raise ValueError(unknown.format(key=key))
        default: Any = None
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{key} must be a bool, got {value!r}")
        elif isinstance(default, int):
            value = int(value)
        elif isinstance(default, str):
            value = str(value)
        elif isinstance(default, tuple):
            value = tuple(float(v) for v in value)
        elif isinstance(default, list):
            value = [float(v) for v in (value or [])]
        else:
            value = float(value)
        kwargs[key] = value
    instance = cls(**kwargs)
    instance.validate()
    return instance


DRIVEN_AXLES = ("front", "rear", "all")
#: Wheel indices, in the contract's order fl, fr, rl, rr, of the undriven axle.
UNDRIVEN_WHEELS = {"front": (2, 3), "rear": (0, 1), "all": (0, 1, 2, 3)}
#: Wheel indices (same order) that the drive torque reaches.
DRIVEN_WHEELS = {"front": (0, 1), "rear": (2, 3), "all": (0, 1, 2, 3)}


@dataclasses.dataclass(frozen=True)
class VehicleParams:
    """Physical description of one vehicle (all SI).

    Geometry follows paper 004 Fig. 2: ``lf``/``lr`` are the distances from the centre of
    gravity to the front/rear axle, ``track_front``/``track_rear`` the track widths
    (b_F, b_R), ``cg_height`` the CoG height h.
    """

    name: str = setting("vehicle", "Vehicle name (persisted estimates and shipped models are per vehicle)")
    mass: float = setting(1530.0, "Nominal gross mass [kg]; estimators use it only as a prior", low=100.0, high=100000.0)
    curb_mass: float = setting(1530.0, "Mass without payload [kg]", low=100.0, high=100000.0)
    lf: float = setting(1.139, "CoG to front axle [m]", low=0.2, high=10.0)
    lr: float = setting(1.637, "CoG to rear axle [m]", low=0.2, high=10.0)
    track_front: float = setting(1.55, "Front track width b_F [m]", low=0.5, high=4.0)
    track_rear: float = setting(1.55, "Rear track width b_R [m]", low=0.5, high=4.0)
    cg_height: float = setting(0.519, "CoG height h [m]", low=0.1, high=4.0)
    roll_lever: float = setting(
        0.0, "Height of the IMU (on the sprung body) above the roll axis [m]: the body's roll "
        "acceleration then adds -roll_lever x roll acceleration to the measured ay, which the state "
        "node takes back out with the gyro's roll rate (0: not modelled)", low=0.0, high=4.0)
    imu_mounting_rpy: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), "Roll, pitch, yaw of imu_link in base_link [rad], as a static transform would "
        "give them (REP-145: imu/data is in imu_link): every node turns the IMU into base_link by it, "
        "and the fusion refines its pitch and yaw from there", low=-math.pi, high=math.pi, each=True)
    yaw_inertia: float = setting(4607.47, "Yaw moment of inertia I_z [kg m^2]", low=100.0, high=2000000.0)
    wheel_radius: float = setting(0.325, "Effective rolling radius [m]", low=0.1, high=1.5)
    wheel_inertia: float = setting(4.0, "Rotational inertia of all wheels and driveshafts I_w [kg m^2]", low=0.0, high=1000.0)
    engine_inertia: float = setting(0.2, "Engine-side rotational inertia I_e [kg m^2]", low=0.0, high=50.0)
    frontal_area: float = setting(2.4, "Frontal area A [m^2]", low=0.5, high=20.0)
    drag_coefficient: float = setting(0.3, "Aerodynamic drag coefficient C_d", low=0.05, high=2.0)
    air_density: float = setting(1.206, "Air density [kg/m^3]", low=0.5, high=2.0)
    rolling_resistance: float = setting(0.013, "Rolling resistance coefficient C_r", low=0.0, high=0.1)
    driveline_efficiency: float = setting(0.89, "Driveline efficiency eta", low=0.3, high=1.0)
    final_drive: float = setting(4.1, "Final drive ratio i_d", low=0.5, high=20.0)
    gear_ratios: tuple[float, ...] = setting((3.5, 2.1, 1.4, 1.0, 0.8), "Transmission ratios i_t,j, first gear first",
                                             low=0.0, low_open=True, each=True)
    steering_ratio: float = setting(19.0, "Steering-wheel to road-wheel ratio", low=1.0, high=40.0)
    driven_axle: str = setting("front", "Driven axle", choices=DRIVEN_AXLES)
    # Engine (for the simulator's torque map and the OBD-II load of SAE J1979 PID 04)
    engine_idle_speed: float = setting(850.0 * math.pi / 30.0, "Engine idle speed [rad/s]", low=10.0, high=300.0)
    engine_max_speed: float = setting(6200.0 * math.pi / 30.0, "Engine maximum speed [rad/s]", low=50.0, high=2000.0)
    engine_max_torque: float = setting(320.0, "Engine maximum torque [N m]", low=10.0, high=10000.0)
    engine_max_power: float = setting(142e3, "Engine maximum power [W]", low=1000.0, high=2000000.0)
    engine_drag_torque: float = setting(25.0, "Engine drag torque at zero load [N m]", low=0.0, high=1000.0)
    max_brake_torque: float = setting(3000.0, "Maximum brake torque per wheel [N m]", low=100.0, high=100000.0)
    brake_front_share: float = setting(0.65, "Share of brake torque on the front axle", low=0.0, high=1.0)
    # Tyres (Dugoff model, paper 004 Eqs. 5-9; per tyre)
    cornering_stiffness_front: float = setting(60000.0, "Cornering stiffness per front tyre [N/rad]", low=1000.0, high=2000000.0)
    cornering_stiffness_rear: float = setting(55000.0, "Cornering stiffness per rear tyre [N/rad]", low=1000.0, high=2000000.0)
    longitudinal_stiffness: float = setting(80000.0, "Longitudinal slip stiffness per tyre [N]", low=1000.0, high=5000000.0)
    # Load sensitivity of those two stiffnesses: C(F_z) = C (F_z / F_z0)^n with F_z0 the static
    # load of the tyre at ``mass``. 0 = constant (paper 004 Eq. 9, our simulator); 1 = proportional
    # to the load (a Magic-Formula tyre with K = p_k1 F_z, as commonroad-vehicle-models codes it);
    # real tyres lie in between (degressive).
    tyre_load_exponent: float = setting(0.0, "Load sensitivity n of the tyre stiffnesses, C (F_z/F_z0)^n (0 = constant, paper 004)", low=0.0, high=2.0)
    road_friction: float = setting(0.9, "Tyre-road friction coefficient mu", low=0.05, high=1.5)
    # Magic-Formula lateral tyre (paper 002 Sec. 2.2); used by the 3-DOF UKF model
    magic_b: float = setting(10.0, "Magic Formula stiffness factor B", low=0.1, high=50.0)
    magic_c: float = setting(1.3, "Magic Formula shape factor C", low=0.1, high=5.0)
    magic_d: float = setting(1.0, "Magic Formula peak factor D (times mu F_z)", low=0.1, high=5.0)
    magic_e: float = setting(0.97, "Magic Formula curvature factor E", low=-10.0, high=1.0)
    # Body pitch on the suspension per longitudinal acceleration (squat/dive), positive nose up
    # when accelerating: the IMU sees it, the road does not have it.
    pitch_gain: float = setting(0.002, "Body pitch per longitudinal acceleration, nose up when accelerating [rad per m/s^2]", low=0.0, high=0.05)
    pitch_time_constant: float = setting(0.15, "Time constant of the suspension pitch response [s]", low=0.0, high=5.0)
    gravity: float = setting(GRAVITY, "Gravitational acceleration [m/s^2]", low=9.7, high=9.9)


    @property
    def wheelbase(self) -> float:
        return self.lf + self.lr

    @property
    def drag_area(self) -> float:
        """C_d·A_0, the product the mass filters use (paper 003 Eq. 1, C_a)."""
        return self.drag_coefficient * self.frontal_area

    def effective_gearing(self, gear: int) -> float:
        """G = i_t,j·i_d / r of paper 003 Eq. 1 for gear ``gear`` (1-based) [1/m]."""
        if not 1 <= gear <= len(self.gear_ratios):
            raise ValueError(f"gear {gear} outside 1..{len(self.gear_ratios)}")
        return self.gear_ratios[gear - 1] * self.final_drive / self.wheel_radius

    def with_mass(self, mass: float) -> "VehicleParams":
        return dataclasses.replace(self, mass=float(mass))

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first parameter that is not physical."""
        check_settings(self, prefix="vehicle.")
        if not self.gear_ratios:
            raise ValueError("vehicle.gear_ratios must list at least one ratio")
        if len(self.imu_mounting_rpy) != 3:
            raise ValueError(f"vehicle.imu_mounting_rpy must be 3 angles, got {self.imu_mounting_rpy!r}")
        if self.engine_idle_speed >= self.engine_max_speed:
            raise ValueError("vehicle.engine_idle_speed must be below vehicle.engine_max_speed")

    @property
    def undriven_wheels(self) -> tuple[int, ...]:
        """Indices (fl, fr, rl, rr order) of the wheels no drive torque reaches: their speed is
        the vehicle's without drive slip. An all-wheel drive has none; all four are returned,
        since they slip alike."""
        return UNDRIVEN_WHEELS[self.driven_axle]

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "VehicleParams":
        """Build from a flat mapping of field name to value; unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown vehicle parameter 'vehicle.{key}'")

    def as_mapping(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["gear_ratios"] = list(self.gear_ratios)
        out["imu_mounting_rpy"] = list(self.imu_mounting_rpy)
        return out


def read_ros_params_file(path: str | Path) -> dict[str, Any]:
    """Return the merged ``ros__parameters`` of a ROS 2 params file, nested as written.

    Sections for ``/**`` come first and node-specific sections are merged over them, the
    same precedence rcl applies. Node names are ignored here: the simulator and the tools
    only need the shared ``vehicle`` section.
    """
    with open(path, "r", encoding="utf-8") as handle:
        document = yaml.safe_load(handle) or {}
    return merge_ros_parameters(document)


def merge_ros_parameters(document: Mapping[str, Any], node: str | None = None) -> dict[str, Any]:
    """The ``ros__parameters`` of a parsed params file that apply to ``node``, nested as written.

    ``/**`` first, then the node's own section (a key whose last name is ``node``: ``mass``,
    ``/car1/mass``) over it, as rcl does; ``node=None`` merges every section.
    """
    merged: dict[str, Any] = {}
    keys = sorted(document, key=lambda k: 0 if k in ("/**", "**") else 1)
    for key in keys:
        shared = key in ("/**", "**")
        if not (shared or node is None or str(key).strip("/").split("/")[-1] == node):
            continue
        section = document[key]
        if isinstance(section, dict) and "ros__parameters" in section:
            _deep_merge(merged, section["ros__parameters"] or {})
    return merged


def _deep_merge(into: dict[str, Any], update: Mapping[str, Any]) -> None:
    for key, value in update.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _deep_merge(into[key], value)
        elif isinstance(value, Mapping):
            into[key] = {}
            _deep_merge(into[key], value)
        else:
            into[key] = value


def load_vehicle_params(path: str | Path) -> VehicleParams:
    """Load the ``vehicle`` section of a ROS 2 params file."""
    section = read_ros_params_file(path).get("vehicle")
    if not isinstance(section, Mapping):
        raise ValueError(f"{path}: no 'vehicle' section under ros__parameters")
    return VehicleParams.from_mapping(section)
