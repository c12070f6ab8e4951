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


@dataclasses.dataclass(frozen=True)
class VehicleParams:
    """Physical description of one vehicle (all SI).

    Geometry follows paper 004 Fig. 2: ``lf``/``lr`` are the distances from the centre of
    gravity to the front/rear axle, ``track_front``/``track_rear`` the track widths
    (b_F, b_R), ``cg_height`` the CoG height h.
    """

    name: str = "vehicle"
    mass: float = 1530.0                 # true/nominal gross mass m [kg]
    curb_mass: float = 1530.0            # mass without payload [kg]
    lf: float = 1.139                    # CoG to front axle [m]
    lr: float = 1.637                    # CoG to rear axle [m]
    track_front: float = 1.55            # b_F [m]
    track_rear: float = 1.55             # b_R [m]
    cg_height: float = 0.519             # h [m]
    yaw_inertia: float = 4607.47         # I_z [kg m²]
    wheel_radius: float = 0.325          # effective rolling radius R_f / r [m]
    wheel_inertia: float = 4.0           # I_w, all four wheels incl. driveshafts [kg m²]
    engine_inertia: float = 0.2          # I_e, engine side of the gearbox [kg m²]
    frontal_area: float = 2.4            # A [m²]
    drag_coefficient: float = 0.3        # C_d [-]
    air_density: float = 1.206           # ρ_air [kg/m³]
    rolling_resistance: float = 0.013    # C_r / ζ [-]
    driveline_efficiency: float = 0.89   # η_t [-]
    final_drive: float = 4.1             # i_0 / i_d [-]
    gear_ratios: tuple[float, ...] = (3.5, 2.1, 1.4, 1.0, 0.8)  # i_t,j, first gear first
    steering_ratio: float = 19.0         # i_w, steering wheel to road wheel [-]
    driven_axle: str = "front"           # "front", "rear" or "all"
    # Engine (for the simulator's torque map and the OBD-II load of SAE J1979 PID 04)
    engine_idle_speed: float = 850.0 * math.pi / 30.0    # [rad/s]
    engine_max_speed: float = 6200.0 * math.pi / 30.0    # [rad/s]
    engine_max_torque: float = 320.0                     # [N m]
    engine_max_power: float = 142e3                      # [W]
    engine_drag_torque: float = 25.0                     # friction/pumping torque at zero load [N m]
    max_brake_torque: float = 3000.0                     # per wheel [N m]
    brake_front_share: float = 0.65                      # share of brake torque on the front axle
    # Tyres (Dugoff model, paper 004 Eqs. 5-9; per tyre)
    cornering_stiffness_front: float = 60000.0           # C_α per front tyre [N/rad]
    cornering_stiffness_rear: float = 55000.0            # C_α per rear tyre [N/rad]
    longitudinal_stiffness: float = 80000.0              # C_s per tyre [N per unit slip]
    # Load sensitivity of those two stiffnesses: C(F_z) = C (F_z / F_z0)^n with F_z0 the static
    # load of the tyre at ``mass``. 0 = constant (paper 004 Eq. 9, our simulator); 1 = proportional
    # to the load (a Magic-Formula tyre with K = p_k1 F_z, as commonroad-vehicle-models codes it);
    # real tyres lie in between (degressive).
    tyre_load_exponent: float = 0.0                      # n [-]
    road_friction: float = 0.9                           # μ [-]
    # Magic-Formula lateral tyre (paper 002 Sec. 2.2); used by the 3-DOF UKF model
    magic_b: float = 10.0
    magic_c: float = 1.3
    magic_d: float = 1.0                                 # peak factor, times μ F_z
    magic_e: float = 0.97
    # Body pitch on the suspension per longitudinal acceleration (squat/dive), positive nose up
    # when accelerating: the IMU sees it, the road does not have it.
    pitch_gain: float = 0.002                            # [rad per m/s^2]
    pitch_time_constant: float = 0.15                    # first-order lag of that pitch [s]
    gravity: float = GRAVITY

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
        positive = [
            "mass", "curb_mass", "lf", "lr", "track_front", "track_rear", "cg_height",
            "yaw_inertia", "wheel_radius", "frontal_area", "drag_coefficient", "air_density",
            "final_drive", "steering_ratio", "engine_idle_speed", "engine_max_speed",
            "engine_max_torque", "engine_max_power", "max_brake_torque",
            "cornering_stiffness_front", "cornering_stiffness_rear", "longitudinal_stiffness",
            "road_friction", "gravity",
        ]
        for key in positive:
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"vehicle.{key} must be a finite positive number, got {value!r}")
        for key in ("wheel_inertia", "engine_inertia", "rolling_resistance", "engine_drag_torque", "pitch_gain",
                    "pitch_time_constant", "tyre_load_exponent"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"vehicle.{key} must be finite and >= 0, got {value!r}")
        if not 0.0 < self.driveline_efficiency <= 1.0:
            raise ValueError(f"vehicle.driveline_efficiency must be in (0, 1], got {self.driveline_efficiency!r}")
        if not 0.0 <= self.brake_front_share <= 1.0:
            raise ValueError(f"vehicle.brake_front_share must be in [0, 1], got {self.brake_front_share!r}")
        if not self.gear_ratios or any(not (math.isfinite(g) and g > 0) for g in self.gear_ratios):
            raise ValueError(f"vehicle.gear_ratios must be a non-empty list of positive ratios, got {self.gear_ratios!r}")
        if self.driven_axle not in ("front", "rear", "all"):
            raise ValueError(f"vehicle.driven_axle must be 'front', 'rear' or 'all', got {self.driven_axle!r}")
        if self.engine_idle_speed >= self.engine_max_speed:
            raise ValueError("vehicle.engine_idle_speed must be below vehicle.engine_max_speed")

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "VehicleParams":
        """Build from a flat mapping of field name to value; unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown vehicle parameter 'vehicle.{key}'")

    def as_mapping(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["gear_ratios"] = list(self.gear_ratios)
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
