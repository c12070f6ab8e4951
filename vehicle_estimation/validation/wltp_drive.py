"""A hilly drive of the EU JRC WLTP gear-shift tool, as OBD-II-only bags in our topic contract.

The powertrain truth comes from an implementation that is *not* ours: ``wltp`` 0.1.2a0 (PyPI,
the European Commission JRC's gear-shift calculator of the WLTP type-approval test, Annex 2 of
UN GTR 15; pure Python). For a forced speed profile (its ``cycle_run`` column ``v_target``
[km/h], one row per second) and a road slope (column ``slope`` [rad]) its
``wltp.experiment.Experiment.run`` computes per second i, with ``A[i] = (V[i+1] - V[i]) / 3.6``
(the forward difference, 0 for the last row):

* the power required at the wheels (``calcPower_required``, column ``p_required`` [kW]):
  ``P_REQ = (f0 V cos(slope) + f1 V^2 + f2 V^3 + f_inertial m A V + m g sin(slope) V) / 3600``
  with V in km/h, the road-load coefficients f0 [N], f1 [N/(km/h)], f2 [N/(km/h)^2], the test
  mass m and its g = 9.81 m/s^2;
* the gear its own shift rules choose (``run_cycle`` and ``applyDriveabilityRules``: the
  highest gear whose engine speed lies between n_min and n_max and whose available power
  ``f_safety_margin x P_wot(n)`` covers P_REQ, then the driveability rules a-g of Annex 2-4;
  gear 0 at standstill and when it declutches to stop), column ``gears``;
* the engine speed ``n = V x gear ratio`` (its gear ratios are engine rpm per km/h; at least
  n_idle), column ``rpm``, and the available power (column ``p_available``) from its own
  normalised full-load curve ``model.default_load_curve()`` (the petrol curve of the "Heinz
  database": ``P_wot(n) = p_rated x p_norm((n - n_idle) / (n_rated - n_idle))``) times the
  safety margin 0.9.

It has no engine torque or load signal, no brakes and no rotating inertia of its own (that is
``f_inertial``). ``wltp`` was written for numpy 1: its ``np2bytes`` and ``rule_a`` call
``ndarray.tostring()`` (removed in numpy 2) and ``bytes2np`` ``np.fromstring``; :func:`_wltp`
replaces these three in the module's namespace by the same functions with ``tobytes()`` /
``np.frombuffer`` (nothing else changes). Its ``model.get_class_parts_index`` uses ``np.int``
too, but only for the WLTC class cycles, which a forced-speed run never reads.

The car (``VEHICLE_NAME``, a mid-size petrol car with a 6-speed manual gearbox): test mass
``TEST_MASS`` 1500 kg (+ ``payload``), p_rated 100 kW at n_rated 6000 rpm, n_idle 800 rpm,
transmission ratios ``TRANSMISSION_RATIOS`` with final drive ``FINAL_DRIVE`` 3.94 and rolling
radius ``WHEEL_RADIUS`` 0.316 m (the tool's gear ratios ``i_t i_d / r x 30/pi / 3.6``, 119.7 to
23.2 rpm per km/h). Road load: the tool's own regression of the coefficients on the test mass
(``params.resistance_coeffs_regression_curves``, ``calc_default_resistance_coeffs``) at
``TEST_MASS``: f0 = 210.8 N (C_r = f0 / (m g) = 0.0143), f1 = 0.0084 N/(km/h), f2 = 0.03695
N/(km/h)^2 (1/2 rho C_d A = 0.479 kg/m); with a payload f0 grows in proportion to the mass
(rolling resistance) while f1 and f2 stay (the air does not see the payload).
``f_inertial = 1 + ROTATING_MASS / m``: the rotating parts (wheels, driveline, engine) count as
``ROTATING_MASS`` = 45 kg more (0.03 of the test mass, the k_r = 1.03 of the WLTP regulation; the
tool's default 1.1 is older), which does not grow with the payload. The engine delivers
``P_REQ / DRIVELINE_EFFICIENCY`` (0.90) when P_REQ > 0 and nothing otherwise (the tool has no
engine braking: a negative P_REQ is all brakes). With the safety margin 0.9 the tool's gear
choice keeps that power below ``P_wot`` wherever its driveability rules leave the chosen gear.

The drive (``FULL_DURATION`` 605 s, 10.9 km; ``duration`` cuts it short; the first 120 s, 2.2 km,
have a start, accelerations through gears 2-6, cruises at 48, 90, 62 and 84 km/h and hills of
-6 to +4 %): ``SPEED_POINTS`` [km/h] joined by smoothsteps (peak accelerations 0.8-1.6 m/s^2,
decelerations up to 2.1 m/s^2, two stops besides the start and the end, up to 110 km/h), the
road grade a function of the distance (:func:`grade_of_distance`: three sines of 370-1900 m
wavelength, within +-6 %, level for the first ~60 m; ``road`` "a" or "b" picks their phases, so
that a second drive climbs other hills at other speeds). The tool runs at 1 Hz on the trace's
speed at whole seconds; the slope it is given for second i is the grade in the middle of its
step (t = i + 0.5), where its forward-difference acceleration A[i] (the step's mean) is centred.
Its shift rules use 1st gear only below ~10 km/h (2nd from 0.9 n_idle), so a calibration sees
gears 2-6.

From its 1 Hz outputs to our rates (a ``SIM_RATE_HZ`` = 200 Hz base; stamps start at 0 s):

* speed: the smoothstep trace itself (the tool's V at whole seconds), acceleration its central
  difference; the grade at the trace's distance (``ground_truth/road_slope`` = atan(grade)).
* the tractive force at the wheels: the tool's ``F_i = P_REQ[i] / V[i]`` (at V[i] = 0 its
  ``calcPower_required`` at a vanishing speed, so the launch step has its force too), split into
  its inertial part ``f_inertial m A[i]``, which becomes ``f_inertial m dv/dt`` of the trace (A[i]
  is the step's mean of dv/dt exactly), and the rest (road load and grade), placed at t = i + 0.5
  and interpolated linearly; so the force averages to the tool's over each step (within the
  interpolation of the rest, a few N) and agrees with the acceleration written.
  ``P_wheel(t) = F(t) v(t)``.
* gear: the tool's ``gears[i]`` on [i, i + 1); engine speed ``v(t) x ratio`` (at least n_idle;
  n_idle in gear 0), so it is the tool's ``rpm`` at whole seconds.
* OBD-II calculated load (SAE J1979 PID 04, joint ``engine_load`` position, 0-1): ``P_engine /
  P_wot(n)`` at that engine speed, ``P_engine = max(P_wheel, 0) / DRIVELINE_EFFICIENCY`` and
  ``P_wot`` the tool's full-load curve (its ``calcPower_available`` with margin 1), clipped to
  [0, 1] (full load: ~0.5 % of the samples, just after upshifts, where the tool checked the new
  gear at the step's start with the step's mean acceleration) and quantised to 1/255 as PID 04
  is; engine speed quantised to 0.25 rpm (PID 0C). The engine torque ``P_engine / omega_e`` is
  the truth (``Drive.engine_torque``), not a topic.

Which topic carries what (an OBD-II-only car: ``vehicle/powertrain`` has engine speed and load
only):

* ``vehicle/powertrain`` 100 Hz: joint ``engine`` velocity [rad/s], joint ``engine_load``
  position. Engine torque, gear and drive force: NaN (OBD-II reports none of them).
* ``vehicle/speed`` 100 Hz: the speed quantised to 1 km/h.
* ``imu/data`` 200 Hz, ``gnss/fix`` 10 Hz, and the ground truth topics as
  :mod:`.fastsim_drive` writes them (:mod:`.road_drive`: specific force dv/dt + g sin(slope),
  the IMU's noise and constant biases, a straight road heading ``HEADING_DEG`` from ``ORIGIN``).
  ``ground_truth/mass`` is the tool's test mass.
* ``vehicle/joint_states`` (only in a ``wheels`` variant; an OBD-II-only car has none): wheel
  speeds v / r plus noise, efforts the braking torque ``-min(F, 0) r`` split
  ``BRAKE_FRONT_SHARE`` front / rear.

:func:`generate` writes two drives, ``wltp_train`` (the test mass, road "a", ``seed``) and
``wltp_loaded`` (``LOADED_PAYLOAD`` 300 kg more, road "b", ``seed + 1``), each with GNSS and as
``*_no_gnss``, all without wheel speeds, plus the vehicle file ``wltp_midsize_petrol.yaml``
(what a user knows of the car, for ``calibrate --vehicle``): calibrate on the one, replay the
other with the calibrated file.

CLI: ``python -m vehicle_estimation.validation.wltp_drive --out DIR [--duration S] [--seed N]``.
Needs ``pip install wltp==0.1.2a0`` (in the ``test`` and ``validation`` extras).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import types
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from vehicle_estimation.validation import road_drive as rd

WLTP_VERSION = "0.1.2a0"
VEHICLE_NAME = "wltp_midsize_petrol"
TEST_MASS = 1500.0               # [kg]
LOADED_PAYLOAD = 300.0           # [kg] of the second drive (+20 %)
ROTATING_MASS = 45.0             # [kg] equivalent mass of the rotating parts (f_inertial)
P_RATED, N_RATED, N_IDLE = 100.0, 6000.0, 800.0   # [kW], [rpm], [rpm]
TRANSMISSION_RATIOS = (3.62, 2.08, 1.36, 1.03, 0.84, 0.70)
FINAL_DRIVE = 3.94
WHEEL_RADIUS = 0.316             # [m] (205/55 R16)
DRIVELINE_EFFICIENCY = 0.90      # wheel power / engine power
G_MODEL = 9.81                   # the tool's gravity [m/s^2] (calcPower_required)
SIM_RATE_HZ = 200
FULL_DURATION = 605.0            # [s]
ORIGIN = (45.8030, 8.6270, 220.0)   # JRC Ispra, lat/lon [deg], alt [m]
HEADING_DEG = -20.0              # ENU yaw of the straight road [deg]
IMU_RATE_HZ, CAN_RATE_HZ, GNSS_RATE_HZ, TRUTH_RATE_HZ = 200, 100, 10, 100
ACCEL_NOISE, GYRO_NOISE = 0.05, 0.003            # white-noise std [m/s^2], [rad/s] (as fastsim_drive)
ACCEL_BIAS, GYRO_BIAS = 0.05, 0.002              # constant bias magnitude [m/s^2], [rad/s]
GNSS_NOISE_H, GNSS_NOISE_V = 0.5, 1.0            # [m]
WHEEL_SPEED_NOISE = 0.02                         # [rad/s]
BRAKE_FRONT_SHARE = 0.65                         # a guess: the tool has no brakes
LOAD_STEP = 1.0 / 255.0                          # OBD-II PID 04 resolution
RPM_STEP = 0.25                                  # OBD-II PID 0C resolution [rpm]
#: (time [s], speed [km/h]) knots of the speed trace, joined by smoothsteps.
SPEED_POINTS = (
    (0, 0), (3, 0), (16, 48), (30, 48), (44, 90), (66, 90), (76, 62), (90, 62), (102, 84), (118, 84),
    (132, 34), (142, 34), (156, 72), (174, 72), (188, 0), (194, 0),
    (208, 55), (232, 55), (248, 100), (280, 100), (292, 70), (310, 70), (324, 40), (334, 40), (350, 80),
    (372, 80), (388, 0), (394, 0),
    (406, 45), (420, 45), (436, 95), (470, 95), (484, 58), (500, 58), (516, 110), (546, 110), (562, 64),
    (578, 64), (598, 0), (605, 0),
)
#: (amplitude [-], wavelength [m]) of the grade sines and their phases [rad] per road.
GRADE_SINES = ((0.0315, 1900.0), (0.0198, 830.0), (0.0108, 370.0))
ROAD_PHASES = {"a": (0.0, 1.3, 0.4), "b": (2.6, 4.4, 1.9)}
LEVEL_START_M = 60.0


def _shim_numpy2(ex) -> None:
    """wltp 0.1.2a0 under numpy 2: ``ndarray.tostring()`` and ``np.fromstring`` are gone. Its
    ``np2bytes``, ``bytes2np`` and ``rule_a`` are replaced by the same code with ``tobytes()`` /
    ``np.frombuffer`` (idempotent)."""
    if getattr(ex, "_vehicle_estimation_numpy2", False):
        return

    def np2bytes(NUMS):   # noqa: N803 - the tool's names
        if (NUMS < 0).any() or (NUMS >= (256 - ex._escape_char)).any():
            raise AssertionError(f"Outside byte-range: {NUMS[(NUMS < 0) | (NUMS >= (256 - ex._escape_char))]}")
        return (NUMS + ex._escape_char).astype("uint8").tobytes()

    def bytes2np(bytesarr):
        assert isinstance(bytesarr, bytes), f"Not bytes: {bytesarr!r}"
        return np.frombuffer(bytesarr, dtype="uint8") - ex._escape_char

    def rule_a(bV, GEARS, CLUTCH, driveability_issues, re_zeros):   # noqa: N803
        for m in re_zeros.finditer(bV):
            t_accel = m.end()
            if t_accel == len(bV):
                break
            GEARS[t_accel - 1:t_accel] = 1
            CLUTCH[t_accel - 1:t_accel - 2] = True
            ex.addDriveabilityMessage(t_accel - 1, "(a: X-->0)", driveability_issues)
        ex.assert_regexp_unmatched(b"\x00[^\x00\x01]", GEARS.astype("uint8").tobytes(), "Jumped gears from standstill")

    ex.np2bytes, ex.bytes2np, ex.rule_a = np2bytes, bytes2np, rule_a
    ex._vehicle_estimation_numpy2 = True


def _wltp():
    """``(wltp.model, wltp.experiment)``, the experiment module made to run under numpy 2."""
    try:
        from wltp import experiment, model
    except ImportError as exc:   # pragma: no cover - depends on the environment
        raise ImportError("vehicle_estimation.validation.wltp_drive needs the JRC WLTP gear-shift tool: "
                          f"pip install wltp=={WLTP_VERSION} (or pip install -e '.[validation]')") from exc
    _shim_numpy2(experiment)
    return model, experiment


# --------------------------------------------------------------------------- the car and road
def tool_gear_ratios() -> list[float]:
    """The tool's gear ratios: engine rpm per km/h, ``i_t i_d / r x 30/pi / 3.6``."""
    return [i * FINAL_DRIVE / WHEEL_RADIUS * 30.0 / math.pi / 3.6 for i in TRANSMISSION_RATIOS]


def road_load(mass: float) -> tuple[float, float, float]:
    """(f0 [N], f1 [N/(km/h)], f2 [N/(km/h)^2]) at ``mass``: the tool's regression at the test
    mass, f0 in proportion to the mass."""
    model, experiment = _wltp()
    curves = model._get_model_base()["params"]["resistance_coeffs_regression_curves"]
    f0, f1, f2 = experiment.calc_default_resistance_coeffs(TEST_MASS, curves)
    return f0 * mass / TEST_MASS, f1, f2


def speed_trace(t) -> np.ndarray:
    """The drive's speed [m/s] at times ``t`` [s] (``SPEED_POINTS`` joined by smoothsteps)."""
    return rd.knot_trace(t, SPEED_POINTS) / 3.6


def grade_of_distance(s, road: str = "a") -> np.ndarray:
    """Road grade (rise over run) of road ``road`` at the distance ``s`` [m]."""
    terms = [(a, wl, ph) for (a, wl), ph in zip(GRADE_SINES, ROAD_PHASES[road])]
    return rd.sine_grade(s, terms, LEVEL_START_M)


def tool_model(v_kmh: np.ndarray, slope: np.ndarray, mass: float) -> dict:
    """The tool's input model: the car at ``mass`` and the forced cycle (1 Hz rows)."""
    import pandas as pd

    model, _ = _wltp()
    mdl = model._get_model_base()
    mdl["vehicle"].update({
        "test_mass": float(mass), "unladen_mass": float(mass) - mdl["params"]["driver_mass"],
        "p_rated": P_RATED, "n_rated": N_RATED, "n_idle": N_IDLE, "n_min": None, "v_max": None,
        "gear_ratios": tool_gear_ratios(), "resistance_coeffs": list(road_load(mass)),
        "full_load_curve": model.default_load_curve(),
    })
    mdl["params"]["f_inertial"] = 1.0 + ROTATING_MASS / float(mass)
    mdl["cycle_run"] = pd.DataFrame({"v_target": np.asarray(v_kmh, float), "slope": np.asarray(slope, float)})
    return mdl


# --------------------------------------------------------------------------- the drive
def full_load_power(rpm, load_curve) -> np.ndarray:
    """The tool's ``P_wot`` [W] at the engine speeds ``rpm``: its ``calcPower_available`` with a
    safety margin of 1 on its full-load curve ``load_curve``."""
    _, experiment = _wltp()
    n = np.atleast_2d(np.asarray(rpm, dtype=float))
    p, _ = experiment.calcPower_available(n, N_IDLE, N_RATED, P_RATED, load_curve, [1.0] * n.shape[0])
    return 1e3 * np.reshape(p, np.shape(rpm))


@dataclasses.dataclass
class Drive:
    """A drive of the tool: its 1 Hz run and the ``SIM_RATE_HZ`` signals made from it."""

    mass: float
    road: str
    tool: object = dataclasses.field(repr=False)   # the tool's ``cycle_run`` DataFrame (1 Hz rows)
    model: dict = dataclasses.field(repr=False)    # the tool's model after the run
    step_force: np.ndarray = dataclasses.field(repr=False)    # the tool's P_REQ / V per 1 Hz step [N]
    t: np.ndarray = dataclasses.field(repr=False)
    speed: np.ndarray = dataclasses.field(repr=False)         # [m/s]
    slope: np.ndarray = dataclasses.field(repr=False)         # [rad]
    force: np.ndarray = dataclasses.field(repr=False)         # tractive force at the wheels [N]
    gear: np.ndarray = dataclasses.field(repr=False)          # the tool's gear (0: none)
    engine_speed: np.ndarray = dataclasses.field(repr=False)  # [rad/s]
    engine_power: np.ndarray = dataclasses.field(repr=False)  # [W]
    full_load_power: np.ndarray = dataclasses.field(repr=False)  # P_wot at the engine speed [W]
    load: np.ndarray = dataclasses.field(repr=False)          # OBD-II calculated load, 0-1 (not quantised)

    @property
    def engine_torque(self) -> np.ndarray:
        """P_engine / omega_e [N m] (what OBD-II does not report)."""
        return self.engine_power / self.engine_speed


def simulate(duration: float | None = None, *, payload: float = 0.0, road: str = "a",
             rate_hz: int = SIM_RATE_HZ) -> Drive:
    """Run the tool through the hilly drive (``duration`` [s], default the full drive) with
    ``payload`` [kg] on road ``road`` and take its outputs to ``rate_hz``."""
    _, experiment = _wltp()
    duration = FULL_DURATION if duration is None else float(duration)
    if road not in ROAD_PHASES:
        raise ValueError(f"road must be one of {sorted(ROAD_PHASES)}, got {road!r}")
    mass = TEST_MASS + float(payload)
    # the fine time base and the road along the trace
    n = round(duration * rate_hz) + 1
    t = np.arange(n) / rate_hz
    v = speed_trace(t)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate_hz)])
    slope = np.arctan(grade_of_distance(dist, road))
    # the tool's 1 Hz rows: the speed at whole seconds, the slope in the middle of each step
    sec = np.arange(int(math.floor(duration + 1e-9)) + 1, dtype=float)
    v_kmh = speed_trace(sec) * 3.6
    slope_mid = np.arctan(grade_of_distance(np.interp(sec + 0.5, t, dist), road))
    mdl = experiment.Experiment(tool_model(v_kmh, slope_mid, mass)).run()
    run = mdl["cycle_run"]
    V = run["v_target"].to_numpy(dtype=float)
    A = np.append(np.diff(V), 0.0) / 3.6                                 # the tool's A (as run() has it)
    f0, f1, f2 = mdl["vehicle"]["resistance_coeffs"]
    V_eval = np.where(V > 0.0, V, 1e-6)     # a vanishing speed where it stands: the launch step's force
    p_eval = experiment.calcPower_required(V_eval, A, slope_mid, mass, f0, f1, f2, mdl["params"]["f_inertial"])
    p_req = run["p_required"].to_numpy(dtype=float)
    step_force = np.where(V > 0.0, p_req, p_eval) * 3600.0 / V_eval  # [kW] / [km/h] -> [N]
    # to the fine time base. The tool's inertial force f_inertial m A[i] is the step's mean of
    # f_inertial m dv/dt of the trace exactly (A[i] is the step's speed change); the rest of its
    # force (road load and grade) is placed in the middle of the step and interpolated.
    m_inertial = mdl["params"]["f_inertial"] * mass
    resistance = step_force - m_inertial * A
    force = m_inertial * np.gradient(v, t) + np.interp(t, sec + 0.5, resistance)
    gears = run["gears"].to_numpy(dtype=np.int64)
    gear = gears[np.minimum(np.floor(t + 1e-9).astype(np.int64), sec.size - 1)]
    ratio = np.concatenate([[0.0], tool_gear_ratios()])[gear]           # rpm per km/h (0 in gear 0)
    rpm = np.maximum(v * 3.6 * ratio, N_IDLE)
    p_wot = full_load_power(rpm, mdl["vehicle"]["full_load_curve"])
    p_engine = np.maximum(force * v, 0.0) / DRIVELINE_EFFICIENCY
    return Drive(mass=mass, road=road, tool=run, model=mdl, step_force=step_force, t=t, speed=v, slope=slope,
                 force=force, gear=gear, engine_speed=rpm * math.pi / 30.0, engine_power=p_engine,
                 full_load_power=p_wot, load=np.clip(p_engine / p_wot, 0.0, 1.0))


# --------------------------------------------------------------------------- sensors
def sensor_result(drive: Drive, *, seed: int = 0, imu_rpy_deg=(0.0, 0.0, 0.0)):
    """A :class:`~vehicle_estimation.sim.simulate.SimResult`-like object (``sensors``, ``truth``)
    that :func:`vehicle_estimation.sim.bag.build_streams` accepts."""
    rng = np.random.default_rng(seed)
    t = drive.t
    tru = rd.road_truth(t, drive.speed, drive.slope, mass=drive.mass, gravity=G_MODEL, heading_deg=HEADING_DEG)

    imu = rd.imu_samples(rng, tru, rd.every(t, IMU_RATE_HZ), accel_noise=ACCEL_NOISE, gyro_noise=GYRO_NOISE,
                         accel_bias=ACCEL_BIAS, gyro_bias=GYRO_BIAS, mounting_rpy_deg=imu_rpy_deg)

    j = rd.every(t, CAN_RATE_HZ)
    v = tru["vx"][j]
    speed = rd.can_speed(t[j], v)
    brake = np.maximum(-drive.force[j], 0.0) * WHEEL_RADIUS * (v > 0.0)   # total [N m]; the tool has no holding force
    joints = rd.wheel_joints(rng, t[j], v, brake, radius=WHEEL_RADIUS, front_share=BRAKE_FRONT_SHARE,
                             noise=WHEEL_SPEED_NOISE)

    # powertrain: what OBD-II reports, engine speed (PID 0C) and calculated load (PID 04)
    rpm = np.round(drive.engine_speed[j] * 30.0 / math.pi / RPM_STEP) * RPM_STEP
    nan = np.full(j.size, np.nan)
    powertrain = {"t": t[j], "engine_speed": rpm * math.pi / 30.0, "engine_torque": nan,
                  "load": np.round(drive.load[j] / LOAD_STEP) * LOAD_STEP, "gear": nan, "drive_force": nan}

    gnss = rd.gnss_samples(rng, tru, rd.every(t, GNSS_RATE_HZ), origin=ORIGIN, noise_h=GNSS_NOISE_H,
                           noise_v=GNSS_NOISE_V)

    m = rd.every(t, TRUTH_RATE_HZ)
    truth = rd.truth_samples(tru, m)
    truth.update({"drive_force": np.maximum(drive.force[m], 0.0), "tractive_force": drive.force[m],
                  "gear": drive.gear[m], "engine_speed": drive.engine_speed[m], "load": drive.load[m],
                  "engine_torque": drive.engine_torque[m]})
    return types.SimpleNamespace(
        sensors={"imu": imu, "gnss": gnss, "speed": speed, "joint_states": joints, "powertrain": powertrain},
        truth=truth)


#: Write a :func:`sensor_result` as a bag, with or without GNSS and wheels (shared: road_drive).
write_drive = rd.write_drive


# --------------------------------------------------------------------------- vehicle file
USER_GEAR_RATIOS = [3.5, 2.1, 1.4, 1.0, 0.8, 0.65]   # a guess: only the number of gears is known


def vehicle_params_mapping() -> dict:
    """Our ``vehicle.*`` section for the car, as its user knows it (see :func:`params_yaml`)."""
    return {
        "name": VEHICLE_NAME, "mass": 1400.0, "curb_mass": 1400.0,
        "lf": 1.05, "lr": 1.58, "track_front": 1.54, "track_rear": 1.52, "cg_height": 0.55,
        "yaw_inertia": 2500.0, "wheel_radius": WHEEL_RADIUS, "wheel_inertia": 4.0, "engine_inertia": 0.2,
        "frontal_area": 2.2, "drag_coefficient": 0.3, "air_density": 1.2, "rolling_resistance": 0.010,
        "driveline_efficiency": DRIVELINE_EFFICIENCY, "final_drive": FINAL_DRIVE, "gear_ratios": USER_GEAR_RATIOS,
        "steering_ratio": 15.5, "driven_axle": "front",
        "engine_idle_speed": N_IDLE * math.pi / 30.0, "engine_max_speed": 6500.0 * math.pi / 30.0,
        "engine_max_torque": 170.0, "engine_max_power": P_RATED * 1e3, "engine_drag_torque": 20.0,
        "max_brake_torque": 2500.0, "brake_front_share": BRAKE_FRONT_SHARE,
        "cornering_stiffness_front": 60000.0, "cornering_stiffness_rear": 55000.0,
        "longitudinal_stiffness": 80000.0, "road_friction": 0.9,
        "pitch_gain": 0.0, "pitch_time_constant": 0.15, "gravity": G_MODEL,
    }


def params_yaml() -> str:
    """The text of ``wltp_midsize_petrol.yaml`` (what :func:`generate` writes)."""
    known = "known (the car's data sheet)"
    fitted = "guess; calibrate fits it"
    notes = {
        "mass": "a prior (data-sheet kerb mass + driver), not the drives' mass; calibrate --mass replaces it",
        "curb_mass": "data sheet (a guess)",
        "lf": "guess (the tool is longitudinal only)", "lr": "guess", "track_front": "guess",
        "track_rear": "guess", "cg_height": "guess", "yaw_inertia": "guess",
        "wheel_radius": f"{known}: 205/55 R16 rolling radius (the tool's gear ratios use it)",
        "wheel_inertia": fitted, "engine_inertia": fitted,
        "frontal_area": f"{known}; calibrate fits C_d A and splits it by this",
        "drag_coefficient": fitted, "air_density": "the tool's road load has none; C_d A is fitted at this density",
        "rolling_resistance": fitted,
        "driveline_efficiency": "guess (the torque map absorbs it: the mass node takes eta = 1 with it)",
        "final_drive": known, "gear_ratios": f"guess (6-speed manual: {known} is the number of gears); calibrate fits them",
        "steering_ratio": "guess", "driven_axle": known,
        "engine_idle_speed": f"{known}: 800 rpm", "engine_max_speed": "guess (6500 rpm)",
        "engine_max_torque": "guess", "engine_max_power": f"{known}: 100 kW", "engine_drag_torque": "guess",
        "max_brake_torque": "guess", "brake_front_share": "guess",
        "cornering_stiffness_front": "guess", "cornering_stiffness_rear": "guess",
        "longitudinal_stiffness": "guess", "road_friction": "guess",
        "pitch_gain": "the tool has no suspension: the body pitch is the road's",
        "pitch_time_constant": "unused at pitch_gain 0", "gravity": "the tool's g (calcPower_required)",
    }
    header = [
        "# A mid-size petrol car with a 6-speed manual gearbox, the car of the JRC WLTP gear-shift tool",
        f"# drives (wltp {WLTP_VERSION}; vehicle_estimation.validation.wltp_drive), as its user knows it: tyre",
        "# radius, final drive, frontal area, idle speed, rated power and the number of gears; the rest",
        "# are guesses, for `vehicle-estimation calibrate BAG --mass KG --vehicle THIS_FILE` to fit.",
        "# Written by vehicle_estimation.validation.wltp_drive.params_yaml().",
    ]
    return rd.format_vehicle_yaml(header, vehicle_params_mapping(), notes)


# --------------------------------------------------------------------------- output
DRIVES = {   # bag name: (payload [kg], road, seed offset)
    "wltp_train": (0.0, "a", 0),
    "wltp_loaded": (LOADED_PAYLOAD, "b", 1),
}
VARIANTS = {   # suffix: (gnss, wheels)
    "": (True, False),
    "_no_gnss": (False, False),
}


def generate(out_dir: Path, *, seed: int = 0, duration: float | None = None,
             imu_rpy_deg=(0.0, 0.0, 0.0)) -> list[Path]:
    """The drives of :data:`DRIVES` in every variant of :data:`VARIANTS` in ``out_dir`` plus the
    vehicle file ``wltp_midsize_petrol.yaml``; returns the bag paths. ``imu_rpy_deg``: the IMU's roll, pitch, yaw in
    ``base_link`` [deg] (:func:`~.road_drive.imu_samples`)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{VEHICLE_NAME}.yaml").write_text(rd.with_imu_mounting(params_yaml(), imu_rpy_deg), encoding="utf-8")
    paths = []
    for name, (payload, road, offset) in DRIVES.items():
        result = sensor_result(simulate(duration, payload=payload, road=road), seed=seed + offset,
                               imu_rpy_deg=imu_rpy_deg)
        paths += [write_drive(result, out_dir / f"{name}{suffix}", gnss=gnss, wheels=wheels)
                  for suffix, (gnss, wheels) in VARIANTS.items()]
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    return rd.generator_main(argv, sys.modules[__name__], out_help="output folder (one bag per drive and variant)")


if __name__ == "__main__":
    raise SystemExit(main())
