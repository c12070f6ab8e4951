"""A hilly drive of NREL FASTSim 3, as bags in our topic contract.

The longitudinal truth comes from an implementation that is *not* ours: FASTSim 3.1.0 (PyPI
``fastsim``, NREL's Future Automotive Systems Technology Simulator, Rust core with Python
bindings) with its shipped resource vehicle ``2012_Ford_Fusion.yaml`` (``VEHICLE_RESOURCE``): a
conventional (``pt_type: Conv``) front-wheel-drive sedan, 130.5 kW fuel converter, constant
transmission efficiency 0.875, test mass 1644.27 kg (the EPA test weight; it includes the
136 kg ``cargo_mass``), C_d 0.393, frontal area 2.12 m^2, C_rr 0.007, four wheels of
0.82 kg m^2 and radius 0.326 m. FASTSim is a backward-facing power model: for a cycle of
time, speed and road grade it computes, per time step i (``t[i-1]`` to ``t[i]``, speed linear
in between, ``v_avg = (v[i-1] + v[i]) / 2``), the powers of inertia ``m (v[i]^2 -
v[i-1]^2) / (2 dt)``, wheel inertia, ascent ``m g sin(atan(grade)) v_avg``, rolling resistance
``m g C_rr cos(atan(grade)) v_avg`` and aerodynamic drag ``k v_avg^3``; their sum is the tractive
power at the wheels, which its fuel converter and transmission deliver when positive (limited
by the fuel converter's power and its ramp rate, in which case the achieved speed falls short of
the cycle) and its friction brakes absorb when negative. It has no engine speed, torque or gear
(the conventional model is power-based), no lateral dynamics and no suspension.

Read off FASTSim 3.1.0's own history (checked by ``test/test_validation_fastsim.py``): its
gravity is 9.8 m/s^2 (``G_MODEL``: ``pwr_rr / (m C_rr v_avg)`` on a level road); its drag
power is ``k v_avg^3`` with ``k = 0.4886 W s^3/m^3`` whatever ``SimParams.f2_const_air_density``
and the cycle's elevation or temperature say, i.e. ``0.5 rho C_d A`` with ``rho = 1.1728`` at its
C_d and A, although its state reports an air density of 1.2: :func:`drag_power_coefficient`
measures ``k`` on a short level drive and :func:`params_yaml` writes the implied density; its
``pwr_brake`` history column reads ``-max(pwr_tractive, 0)`` (not the braking power), so the
braking power here is ``min(pwr_tractive, 0)``.

The drive (``FULL_DURATION`` 605 s, 11.7 km; ``duration`` cuts it short, the first 120 s, 2.0 km,
have a start, cruise, braking and hills of -6 to +5 %): a speed trace of ``SPEED_POINTS`` joined
by smoothsteps (peak accelerations 1.0-1.9 m/s^2, decelerations 1.1-2.7 m/s^2, three stops
besides the start, speeds up to 30 m/s) and a road
grade that is a function of the distance along the road (``GRADE_TERMS`` by
:func:`.road_drive.sine_grade`: three sines of 370-1900 m wavelength, level for the first ~60 m, within +-6 %). FASTSim's ``Cycle``
takes the time, the speed and, per time step, the grade at the cycle's distance. It is walked
(``SimDrive.walk()``) at ``SIM_RATE_HZ`` = 200 Hz (5 ms steps).

Which FASTSim quantity becomes which topic (all from ``SimDrive.to_dict(flatten=True)`` after
the walk; ``veh.history.*`` unless said otherwise; stamps start at 0 s):

* ``ground_truth/vehicle_state`` vx, ``ground_truth/odometry`` twist vx: ``speed_ach`` (the
  achieved speed, equal to the cycle's where ``cyc_met``). vy, yaw rate, sideslip, roll: 0.
* ``ground_truth/road_slope`` [rad, + uphill, as the simulator's ``truth["slope"]``]:
  ``atan(grade_curr)``. ``ground_truth/odometry`` pitch = -slope (REP-103: + nose down; no
  suspension), pitch rate = d(pitch)/dt.
* ``ground_truth/mass``: ``mass_kilograms`` (the mass FASTSim's inertia, ascent and rolling
  powers use).
* ``vehicle/powertrain`` 100 Hz, ``drive`` effort (the force the driveline delivers to the
  driven wheels, as the contract asks): ``veh.pt_type.Conv.transmission.history.pwr_out_watts``
  (= ``max(pwr_tractive, 0)``) / ``v_avg`` (0 at rest), the mean of the two steps around the
  stamp, plus ``DRIVE_FORCE_NOISE`` white noise while it is non-zero. It includes FASTSim's
  wheel-inertia power, as the contract's "wheel" drive force does. Engine speed and torque,
  engine load and gear: NaN (FASTSim's conventional model has none; its fuel-converter power
  ``pwr_prop`` is not an engine torque without a speed).
* ``vehicle/joint_states`` 100 Hz: wheel speeds ``speed_ach / wheel_radius_meters`` (all four
  wheels, no slip: FASTSim has no tyre model) plus ``WHEEL_SPEED_NOISE`` (exactly 0 at rest),
  efforts = braking torque ``-min(pwr_tractive, 0) / v_avg x r`` split ``BRAKE_FRONT_SHARE``
  front / rear, half per wheel (0 at rest: FASTSim has no holding force); steering wheel 0;
  wheel positions NaN.
* ``vehicle/speed`` 100 Hz: ``speed_ach`` quantised to 1 km/h (covariance[0] = (1/3.6)^2/12).
* ``imu/data`` 200 Hz (one sample per FASTSim step), ``imu_link`` = ``base_link``, the body
  following the road: specific force x = dv/dt + g sin(slope) (dv/dt the central difference of
  ``speed_ach``), z = g cos(slope) + v d(slope)/dt (the centripetal part over crests and dips),
  y = 0; gyro = (0, d(pitch)/dt, 0). White noise ``ACCEL_NOISE`` / ``GYRO_NOISE`` and a
  constant bias per axis of +-``ACCEL_BIAS`` / +-``GYRO_BIAS`` (signs from the seed).
* ``gnss/fix`` 10 Hz: a straight road heading ``HEADING_DEG`` (ENU yaw) from ``ORIGIN``; the
  horizontal distance integrates ``speed_ach cos(slope)``, the altitude ``speed_ach
  sin(slope)`` (trapezoid); 0.5 m white noise east/north, 1.0 m up; WGS84 by
  :class:`vehicle_estimation.estimators.common.geodesy.LocalTangentPlane`.

Variants (:func:`write_drive`): ``gnss=False`` drops ``gnss/fix``, ``wheels=False`` drops
``vehicle/joint_states`` (wheel speeds and brake torques); the same realisation otherwise.
:func:`generate` writes ``fastsim_hills``, ``fastsim_hills_no_gnss`` and
``fastsim_hills_no_gnss_no_wheels`` plus the vehicle file ``fastsim_2012_ford_fusion.yaml``.

CLI: ``python -m vehicle_estimation.validation.fastsim_drive --out DIR [--duration S] [--seed N]``.
Needs ``pip install fastsim==3.1.0`` (in the ``test`` and ``validation`` extras).
"""

from __future__ import annotations

import sys
import types
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vehicle_estimation.validation import road_drive as rd

FASTSIM_VERSION = "3.1.0"
VEHICLE_RESOURCE = "2012_Ford_Fusion.yaml"
VEHICLE_NAME = "fastsim_2012_ford_fusion"
G_MODEL = 9.8                    # FASTSim 3.1.0's gravity [m/s^2] (see the module docstring)
SIM_RATE_HZ = 200                # FASTSim time step 5 ms
FULL_DURATION = 605.0            # [s]
ORIGIN = (39.7402, -105.1686, 1730.0)   # NREL, Golden (Colorado), lat/lon [deg], alt [m]
HEADING_DEG = 30.0               # ENU yaw of the straight road [deg]
IMU_RATE_HZ, CAN_RATE_HZ, GNSS_RATE_HZ, TRUTH_RATE_HZ = 200, 100, 10, 100
ACCEL_NOISE, GYRO_NOISE = 0.05, 0.003            # white-noise std [m/s^2], [rad/s]
ACCEL_BIAS, GYRO_BIAS = 0.05, 0.002              # constant bias magnitude [m/s^2], [rad/s]
GNSS_NOISE_H, GNSS_NOISE_V = 0.5, 1.0            # [m]
WHEEL_SPEED_NOISE = 0.02                         # [rad/s]
DRIVE_FORCE_NOISE = 20.0                         # [N]
BRAKE_FRONT_SHARE = 0.65                         # a guess: FASTSim has one friction brake
#: (time [s], speed [m/s]) knots of the speed trace, joined by smoothsteps.
SPEED_POINTS = (
    (0, 0), (4, 0), (16, 14), (40, 14), (52, 24), (78, 24), (90, 12), (98, 12), (110, 22),
    (132, 22), (146, 0), (152, 0), (166, 16), (196, 16), (208, 27), (246, 27), (258, 18),
    (276, 18), (286, 26), (318, 26), (332, 10), (342, 10), (356, 25), (392, 25), (406, 0),
    (412, 0), (426, 18), (456, 18), (468, 28), (506, 28), (516, 20), (540, 20), (555, 30),
    (578, 30), (598, 0), (605, 0),
)
#: (amplitude [-], wavelength [m], phase [rad]) of the grade sines.
GRADE_TERMS = ((0.0315, 1900.0, 0.0), (0.0198, 830.0, 1.3), (0.0108, 370.0, 0.4))
LEVEL_START_M = 60.0             # the grade fades in over the first metres [m]


def _fastsim():
    try:
        import fastsim
    except ImportError as exc:   # pragma: no cover - depends on the environment
        raise ImportError("vehicle_estimation.validation.fastsim_drive needs NREL FASTSim 3: "
                          f"pip install fastsim=={FASTSIM_VERSION} (or pip install -e '.[validation]')") from exc
    return fastsim


# --------------------------------------------------------------------------- the drive
_smoothstep = rd.smoothstep


def cycle_arrays(duration: float | None = None, rate_hz: int = SIM_RATE_HZ) -> dict[str, np.ndarray]:
    """Time, speed and grade of the FASTSim cycle (the grade looked up at the cycle's distance)."""
    return rd.road_cycle(FULL_DURATION if duration is None else duration, rate_hz, SPEED_POINTS, GRADE_TERMS,
                         LEVEL_START_M)


def load_vehicle():
    """The FASTSim resource vehicle (``VEHICLE_RESOURCE``)."""
    return _fastsim().Vehicle.from_resource(VEHICLE_RESOURCE)


def _walk(cycle: dict[str, np.ndarray], init_elev: float = ORIGIN[2], *, vehicle=None,
          allow_trace_miss: bool = False) -> dict:
    """Walk ``vehicle`` (default :func:`load_vehicle`) through ``cycle``; with
    ``allow_trace_miss`` a vehicle short of power falls behind the cycle's speed (its achieved
    speed is the truth) instead of FASTSim stopping with an error."""
    fsim = _fastsim()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        cyc = fsim.Cycle.from_dict({"time_seconds": cycle["t"].tolist(),
                                    "speed_meters_per_second": cycle["speed"].tolist(),
                                    "grade": cycle["grade"].tolist(), "init_elev_meters": float(init_elev)})
        params = fsim.SimParams.default().to_dict()
        if allow_trace_miss:
            params["trace_miss_opts"] = "Allow"
        sd = fsim.SimDrive(load_vehicle() if vehicle is None else vehicle, cyc, fsim.SimParams.from_dict(params))
        sd.walk()
        return sd.to_dict(flatten=True)


HISTORY = {   # our name: FASTSim flattened key
    "t": "veh.history.time_seconds",
    "speed": "veh.history.speed_ach_meters_per_second",
    "grade": "veh.history.grade_curr",
    "mass": "veh.history.mass_kilograms",
    "cyc_met": "veh.history.cyc_met",
    "pwr_tractive": "veh.history.pwr_tractive_watts",
    "pwr_accel": "veh.history.pwr_accel_watts",
    "pwr_ascent": "veh.history.pwr_ascent_watts",
    "pwr_rr": "veh.history.pwr_rr_watts",
    "pwr_drag": "veh.history.pwr_drag_watts",
    "pwr_whl_inertia": "veh.history.pwr_whl_inertia_watts",
    "pwr_brake": "veh.history.pwr_brake_watts",
    "elev": "veh.history.elev_curr_meters",
    "pwr_trans_out": "veh.pt_type.Conv.transmission.history.pwr_out_watts",
    "pwr_fc_prop": "veh.pt_type.Conv.fc.history.pwr_prop_watts",
}


@dataclass
class Drive:
    """A walked FASTSim drive: its cycle, the history arrays and the vehicle's data."""

    cycle: dict[str, np.ndarray]
    history: dict[str, np.ndarray]
    vehicle: dict = field(repr=False)      # FASTSim's flattened vehicle fields ("veh.*", no history)

    @property
    def t(self) -> np.ndarray:
        return self.cycle["t"]

    @property
    def mass(self) -> float:
        return float(self.history["mass"][1])   # index 0 is the unset initial state (NaN)


def simulate(duration: float | None = None, *, rate_hz: int = SIM_RATE_HZ, cycle: dict | None = None,
             vehicle=None, allow_trace_miss: bool = False) -> Drive:
    """Walk the FASTSim vehicle through the hilly cycle (``duration`` [s], default the full drive),
    or ``vehicle`` through ``cycle`` (see :func:`_walk`)."""
    cycle = cycle_arrays(duration, rate_hz) if cycle is None else cycle
    flat = _walk(cycle, vehicle=vehicle, allow_trace_miss=allow_trace_miss)
    hist = {name: np.asarray(flat[key], dtype=float) for name, key in HISTORY.items()}
    if hist["t"].size != cycle["t"].size or not np.allclose(hist["t"], cycle["t"], atol=1e-9):
        raise RuntimeError("FASTSim history does not match the cycle's time steps")
    vehicle = {k: v for k, v in flat.items() if k.startswith("veh.") and ".history." not in k}
    return Drive(cycle, hist, vehicle)


def forces(drive: Drive) -> dict[str, np.ndarray]:
    """Per step (ending at ``t[i]``): ``v_avg`` and the tractive, propulsion (transmission
    output) and braking forces at the wheels [N], FASTSim's powers over ``v_avg`` (0 at rest)."""
    h = drive.history
    v = h["speed"]
    v_avg = np.concatenate([[0.0], 0.5 * (v[1:] + v[:-1])])
    moving = v_avg > 1e-9
    safe = np.where(moving, v_avg, 1.0)

    def per_speed(p):
        return np.where(moving, p / safe, 0.0)

    return {"v_avg": v_avg, "tractive": per_speed(h["pwr_tractive"]),
            "propulsion": per_speed(h["pwr_trans_out"]),
            "braking": per_speed(np.maximum(-h["pwr_tractive"], 0.0))}


def drag_power_coefficient(probe_speed: float = 20.0, vehicle=None) -> float:
    """FASTSim's ``k`` in ``pwr_drag = k v_avg^3`` [W s^3/m^3], measured on a short level drive."""
    t = np.arange(0.0, 20.0 + 1e-9, 0.1)
    v = probe_speed * _smoothstep(t / 10.0)
    flat = _walk({"t": t, "speed": v, "grade": np.zeros_like(t)}, vehicle=vehicle, allow_trace_miss=True)
    va = np.asarray(flat[HISTORY["speed"]], dtype=float)
    v_avg = 0.5 * (va[1:] + va[:-1])
    p = np.asarray(flat[HISTORY["pwr_drag"]], dtype=float)[1:]
    sel = v_avg > 5.0
    return float(np.median(p[sel] / v_avg[sel] ** 3))


# --------------------------------------------------------------------------- sensors
def truth_signals(drive: Drive) -> dict[str, np.ndarray]:
    """Truth at every FASTSim step (base_link / ENU odom at the start)."""
    h = drive.history
    return rd.road_truth(drive.t, h["speed"], np.arctan(h["grade"]), mass=drive.mass, gravity=G_MODEL,
                         heading_deg=HEADING_DEG)


_every = rd.every


def sensor_result(drive: Drive, *, seed: int = 0, imu_rpy_deg=(0.0, 0.0, 0.0)):
    """A :class:`~vehicle_estimation.sim.simulate.SimResult`-like object (``sensors``, ``truth``)
    that :func:`vehicle_estimation.sim.bag.build_streams` accepts."""
    rng = np.random.default_rng(seed)
    tru = truth_signals(drive)
    frc = forces(drive)
    t = drive.t
    radius = float(drive.vehicle["veh.chassis.wheel_radius_meters"])

    # IMU
    imu = rd.imu_samples(rng, tru, _every(t, IMU_RATE_HZ), accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE,
                         accel_bias=ACCEL_BIAS, gyro_bias=GYRO_BIAS, mounting_rpy_deg=imu_rpy_deg)

    # CAN speed, wheel speeds and brake torques
    j = _every(t, CAN_RATE_HZ)
    v = tru["vx"][j]
    speed = rd.can_speed(t[j], v)
    # a step's force placed at its stamp: the mean of the steps ending at and after it
    nxt = np.minimum(j + 1, t.size - 1)
    brake = 0.5 * (frc["braking"][j] + frc["braking"][nxt]) * radius          # total [N m]
    joints = rd.wheel_joints(rng, t[j], v, brake, radius=radius, front_share=BRAKE_FRONT_SHARE,
                             noise=WHEEL_SPEED_NOISE)

    # powertrain: the drive force only
    drive_force = 0.5 * (frc["propulsion"][j] + frc["propulsion"][nxt])
    drive_force = np.where(drive_force != 0.0, drive_force + DRIVE_FORCE_NOISE * rng.standard_normal(j.size), 0.0)
    nan = np.full(j.size, np.nan)
    powertrain = {"t": t[j], "engine_speed": nan, "engine_torque": nan, "load": nan, "gear": nan,
                  "drive_force": drive_force}

    # GNSS
    gnss = rd.gnss_samples(rng, tru, _every(t, GNSS_RATE_HZ), origin=ORIGIN, noise_h=GNSS_NOISE_H,
                           noise_v=GNSS_NOISE_V)

    m = _every(t, TRUTH_RATE_HZ)
    truth = rd.truth_samples(tru, m)
    truth["drive_force"] = 0.5 * (frc["propulsion"][m] + frc["propulsion"][np.minimum(m + 1, t.size - 1)])
    return types.SimpleNamespace(
        sensors={"imu": imu, "gnss": gnss, "speed": speed, "joint_states": joints, "powertrain": powertrain},
        truth=truth)


#: Write a :func:`sensor_result` as a bag, with or without GNSS and wheels (shared: road_drive).
write_drive = rd.write_drive


# --------------------------------------------------------------------------- vehicle file
def vehicle_data() -> dict:
    """FASTSim's flattened fields of the resource vehicle (``veh.`` prefix dropped)."""
    flat = load_vehicle().to_dict(flatten=True)
    return {k: v for k, v in flat.items() if ".history." not in k and not k.startswith("state.")}


def vehicle_params_mapping(data: dict | None = None, *, drag_k: float | None = None) -> dict:
    """Our ``vehicle.*`` section for the FASTSim car (see :func:`params_yaml` for sources)."""
    d = vehicle_data() if data is None else data
    drag_k = drag_power_coefficient() if drag_k is None else drag_k
    ch = "chassis."
    cd, area = d[ch + "drag_coef"], d[ch + "frontal_area_square_meters"]
    wheelbase, front = d[ch + "wheel_base_meters"], d[ch + "drive_axle_weight_frac"]
    mass = d["mass_kilograms"]
    return {
        "name": VEHICLE_NAME, "mass": mass, "curb_mass": mass - d[ch + "cargo_mass_kilograms"],
        "lf": wheelbase * (1.0 - front), "lr": wheelbase * front,
        "track_front": 1.58, "track_rear": 1.58, "cg_height": d[ch + "cg_height_meters"],
        "yaw_inertia": 2800.0, "wheel_radius": d[ch + "wheel_radius_meters"],
        "wheel_inertia": d[ch + "num_wheels"] * d[ch + "wheel_inertia_kilogram_square_meters"],
        "engine_inertia": 0.0,
        "frontal_area": area, "drag_coefficient": cd, "air_density": 2.0 * drag_k / (cd * area),
        "rolling_resistance": d[ch + "wheel_rr_coef"],
        "driveline_efficiency": d["pt_type.Conv.transmission.eff_interp"],
        "final_drive": 3.77, "gear_ratios": [4.58, 2.96, 1.91, 1.45, 1.0, 0.75],
        "steering_ratio": 15.0, "driven_axle": {"FWD": "front", "RWD": "rear"}.get(d[ch + "drive_type"], "all"),
        "engine_idle_speed": 78.5, "engine_max_speed": 680.7, "engine_max_torque": 235.0,
        "engine_max_power": d["pt_type.Conv.fc.pwr_out_max_watts"], "engine_drag_torque": 20.0,
        "max_brake_torque": 2500.0, "brake_front_share": BRAKE_FRONT_SHARE,
        "cornering_stiffness_front": 60000.0, "cornering_stiffness_rear": 55000.0,
        "longitudinal_stiffness": 80000.0, "road_friction": d[ch + "wheel_fric_coef"],
        "pitch_gain": 0.0, "pitch_time_constant": 0.15, "gravity": G_MODEL,
    }


def params_yaml(data: dict | None = None, *, drag_k: float | None = None) -> str:
    """The text of ``params/fastsim_2012_ford_fusion.yaml``."""
    d = vehicle_data() if data is None else data
    drag_k = drag_power_coefficient() if drag_k is None else drag_k
    v = vehicle_params_mapping(d, drag_k=drag_k)
    lib = "FASTSim"
    ch = "chassis."
    notes = {
        "mass": f"{lib} mass_kilograms (test mass, incl. cargo_mass {d[ch + 'cargo_mass_kilograms']:g} kg)",
        "curb_mass": f"derived: {lib} mass_kilograms - cargo_mass_kilograms",
        "lf": f"derived: {lib} wheel_base x (1 - drive_axle_weight_frac) (FWD: the front share)",
        "lr": f"derived: {lib} wheel_base x drive_axle_weight_frac",
        "track_front": "guess (FASTSim has no lateral model)", "track_rear": "guess",
        "cg_height": f"{lib} cg_height_meters", "yaw_inertia": "guess (FASTSim has no lateral model)",
        "wheel_radius": f"{lib} wheel_radius_meters (no tyre slip in the model)",
        "wheel_inertia": f"{lib} num_wheels x wheel_inertia_kilogram_square_meters",
        "engine_inertia": f"{lib} has no engine inertia",
        "frontal_area": f"{lib} frontal_area_square_meters", "drag_coefficient": f"{lib} drag_coef",
        "air_density": f"derived: 2 k / (C_d A), k = {drag_k:.6f} W s^3/m^3 of {lib}'s drag power k v^3 "
                       "(its state says 1.2, its drag power implies this)",
        "rolling_resistance": f"{lib} wheel_rr_coef",
        "driveline_efficiency": f"{lib} transmission eff_interp (constant)",
        "final_drive": "guess (FASTSim has no gearbox)", "gear_ratios": "guess (6-speed automatic)",
        "steering_ratio": "guess", "driven_axle": f"{lib} drive_type {d[ch + 'drive_type']}",
        "engine_idle_speed": "guess (750 rpm; FASTSim has no engine speed)", "engine_max_speed": "guess",
        "engine_max_torque": "guess (2.5 l I4)", "engine_max_power": f"{lib} fc pwr_out_max_watts",
        "engine_drag_torque": "guess", "max_brake_torque": "guess",
        "brake_front_share": "guess; the bag's brake efforts split the braking torque so",
        "cornering_stiffness_front": "guess", "cornering_stiffness_rear": "guess",
        "longitudinal_stiffness": "guess", "road_friction": f"{lib} wheel_fric_coef",
        "pitch_gain": f"{lib} has no suspension: the body pitch is the road's",
        "pitch_time_constant": "unused at pitch_gain 0", "gravity": f"{lib}'s g (its rolling-resistance power)",
    }
    header = [
        f"# 2012 Ford Fusion of NREL FASTSim {FASTSIM_VERSION} (resource {VEHICLE_RESOURCE}), the car of",
        "# the hilly validation drives (vehicle_estimation.validation.fastsim_drive).",
        "# Written by vehicle_estimation.validation.fastsim_drive.params_yaml(); each value says whether",
        "# it comes from FASTSim, is derived from it, or is a guess (FASTSim is a longitudinal,",
        "# power-based model: no engine speed, gearbox, tyres, suspension or lateral dynamics).",
    ]
    return rd.format_vehicle_yaml(header, v, notes)


# --------------------------------------------------------------------------- output
VARIANTS = {   # bag name: (gnss, wheels)
    "fastsim_hills": (True, True),
    "fastsim_hills_no_gnss": (False, True),
    "fastsim_hills_no_gnss_no_wheels": (False, False),
}


def generate(out_dir: Path, *, seed: int = 0, duration: float | None = None,
             imu_rpy_deg=(0.0, 0.0, 0.0)) -> list[Path]:
    """The drive as ``fastsim_hills``, ``fastsim_hills_no_gnss`` and
    ``fastsim_hills_no_gnss_no_wheels`` in ``out_dir`` plus the vehicle file
    ``fastsim_2012_ford_fusion.yaml``; returns the bag paths. ``imu_rpy_deg``: the IMU's roll, pitch, yaw in
    ``base_link`` [deg] (:func:`~.road_drive.imu_samples`)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{VEHICLE_NAME}.yaml").write_text(rd.with_imu_mounting(params_yaml(), imu_rpy_deg), encoding="utf-8")
    result = sensor_result(simulate(duration), seed=seed, imu_rpy_deg=imu_rpy_deg)
    return [write_drive(result, out_dir / name, gnss=gnss, wheels=wheels)
            for name, (gnss, wheels) in VARIANTS.items()]


def main(argv: Sequence[str] | None = None) -> int:
    return rd.generator_main(argv, sys.modules[__name__], out_help="output folder (one bag per variant)")


if __name__ == "__main__":
    raise SystemExit(main())
