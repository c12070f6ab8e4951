"""What the drives of other simulators share (:mod:`.fastsim_drive`, :mod:`.wltp_drive`).

A car on a straight hilly road with no lateral motion and no suspension (the body follows the
road): a speed trace of knots joined by smoothsteps, a road grade of sines of the distance, the
kinematic truth of such a drive, and the IMU, CAN speed, wheel and GNSS samples of our topic
contract made from it (noise and constant biases drawn from one ``numpy`` generator, in the order
the callers draw them), the bag writer with its variants (with or without ``gnss/fix`` and
``vehicle/joint_states``), and the vehicle file written from another simulator's data, each
value with its origin (:func:`format_vehicle_yaml`, CommonRoad's too).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from vehicle_estimation.contract import topics as T
from vehicle_estimation.estimators.common.geodesy import LocalTangentPlane
from vehicle_estimation.estimators.common.rotations import rotmat_from_euler
from vehicle_estimation.sim import bag as simbag

#: Truth keys a bag's ground-truth topics are written from.
TRUTH_KEYS = ("t", "vx", "vy", "yaw_rate", "sideslip", "roll", "pitch", "yaw", "x", "y", "z", "wx", "wy", "wz",
              "slope", "mass", "ax")


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def knot_trace(t, points) -> np.ndarray:
    """The trace through the ``(time, value)`` knots ``points`` at times ``t``, consecutive knots
    joined by smoothsteps (flat before the first and after the last)."""
    t = np.asarray(t, dtype=float)
    knots = np.asarray(points, dtype=float)
    v = np.full(t.shape, knots[0, 1])
    for (t0, v0), (t1, v1) in itertools.pairwise(knots):
        v = v + (v1 - v0) * smoothstep((t - t0) / (t1 - t0))
    return v


def sine_grade(s, terms, level_start: float) -> np.ndarray:
    """Road grade (rise over run) at the distance ``s`` [m]: the sum of the ``(amplitude [-],
    wavelength [m], phase [rad])`` sines ``terms``, faded in over the first ``level_start`` m."""
    s = np.asarray(s, dtype=float)
    g = sum(a * np.sin(2.0 * np.pi * s / wl + ph) for a, wl, ph in terms)
    return g * smoothstep(s / level_start)


def road_cycle(duration: float, rate_hz: int, speed_points, grade_terms, level_start: float) -> dict[str, np.ndarray]:
    """A simulator's cycle: time at ``rate_hz`` over ``duration`` [s], the speed through the
    ``speed_points`` knots (:func:`knot_trace`) and the grade of :func:`sine_grade` looked up
    at the cycle's distance (trapezoid)."""
    n = round(float(duration) * rate_hz) + 1
    t = np.arange(n) / rate_hz
    v = knot_trace(t, speed_points)
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate_hz)])
    return {"t": t, "speed": v, "grade": sine_grade(dist, grade_terms, level_start), "dist": dist}


def every(t: np.ndarray, rate: float) -> np.ndarray:
    """Indices of the samples of the uniform time base ``t`` at ``rate`` [Hz]."""
    step = round(1.0 / (rate * (t[1] - t[0])))
    return np.arange(0, t.size, step)


def road_truth(t: np.ndarray, v: np.ndarray, slope: np.ndarray, *, mass: float, gravity: float,
               heading_deg: float) -> dict[str, np.ndarray]:
    """Truth of a car following a straight road (ENU yaw ``heading_deg``) from the odom origin at
    speed ``v`` [m/s] over the road slope ``slope`` [rad, + uphill], on the uniform time base
    ``t``: pitch = -slope (REP-103, no suspension), dv/dt and d(slope)/dt central differences,
    the specific force (dv/dt + g sin(slope), 0, g cos(slope) + v d(slope)/dt) and the position
    (trapezoid of v cos(slope) and v sin(slope))."""
    dt = float(t[1] - t[0])
    slope_rate = np.gradient(slope, dt)
    accel = np.gradient(v, dt)
    dist_h = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] * np.cos(slope[1:]) + v[:-1] * np.cos(slope[:-1])) * dt)])
    up = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] * np.sin(slope[1:]) + v[:-1] * np.sin(slope[:-1])) * dt)])
    psi = math.radians(heading_deg)
    zero = np.zeros_like(t)
    return {
        "t": t, "vx": v, "vy": zero, "yaw_rate": zero, "sideslip": zero, "roll": zero,
        "pitch": -slope, "yaw": np.full_like(t, psi), "slope": slope,
        "x": dist_h * math.cos(psi), "y": dist_h * math.sin(psi), "z": up,
        "wx": zero, "wy": -slope_rate, "wz": zero, "ax": accel,
        "accel": np.column_stack([accel + gravity * np.sin(slope), zero,
                                  gravity * np.cos(slope) + v * slope_rate]),
        "mass": np.full_like(t, mass),
    }


def imu_samples(rng: np.random.Generator, truth: dict, idx: np.ndarray, *, accel_noise: float, gyro_noise: float,
                accel_bias: float, gyro_bias: float, mounting_rpy_deg=(0.0, 0.0, 0.0)) -> dict:
    """``imu/data`` at the truth samples ``idx`` in ``imu_link``, which sits in ``base_link`` at
    roll, pitch, yaw ``mounting_rpy_deg`` (REP-103 angles; zero: the same axes), with white noise
    and a constant bias per axis of +-``accel_bias`` / +-``gyro_bias`` (signs from ``rng``)."""
    a_bias = accel_bias * rng.choice([-1.0, 1.0], 3)
    g_bias = gyro_bias * rng.choice([-1.0, 1.0], 3)
    # rows are vectors: v_imu = C^T v_base is v_base @ C, C imu_link -> base_link
    C = rotmat_from_euler(*(math.radians(float(a)) for a in mounting_rpy_deg))
    gyro = np.column_stack([truth["wx"], truth["wy"], truth["wz"]])
    accel = truth["accel"][idx] @ C + a_bias + accel_noise * rng.standard_normal((idx.size, 3))
    gyro = gyro[idx] @ C + g_bias + gyro_noise * rng.standard_normal((idx.size, 3))
    return {"t": truth["t"][idx], "accel": accel, "gyro": gyro, "gyro_cov": np.full(3, gyro_noise ** 2),
            "accel_cov": np.full(3, accel_noise ** 2), "bias_accel": a_bias, "bias_gyro": g_bias}


def can_speed(t: np.ndarray, v: np.ndarray) -> dict:
    """``vehicle/speed``: ``v`` quantised to 1 km/h (variance of the rounding, (1/3.6)^2/12)."""
    return {"t": t, "v": np.round(v * 3.6) / 3.6, "var": np.full(t.size, (1.0 / 3.6) ** 2 / 12.0)}


def wheel_joints(rng: np.random.Generator, t: np.ndarray, v: np.ndarray, brake: np.ndarray, *, radius: float,
                 front_share: float, noise: float) -> dict:
    """``vehicle/joint_states``: four wheel speeds v / r plus white noise ``noise`` [rad/s]
    (exactly 0 at rest, no slip), efforts the total braking torque ``brake`` [N m] split
    ``front_share`` front / rear, half per wheel; steering wheel 0; wheel positions NaN."""
    shares = np.array([front_share, front_share, 1.0 - front_share, 1.0 - front_share]) / 2.0
    wheel = np.where(v[:, None] > 0.0, v[:, None] / radius + noise * rng.standard_normal((t.size, 4)), 0.0)
    position = np.full((t.size, 5), np.nan)
    position[:, 4] = 0.0
    velocity = np.full((t.size, 5), np.nan)
    velocity[:, :4] = wheel
    effort = np.full((t.size, 5), np.nan)
    effort[:, :4] = brake[:, None] * shares
    return {"t": t, "position": position, "velocity": velocity, "effort": effort}


def gnss_samples(rng: np.random.Generator, truth: dict, idx: np.ndarray, *, origin: tuple[float, float, float],
                 noise_h: float, noise_v: float) -> dict:
    """``gnss/fix`` at the truth samples ``idx``: the ENU position plus white noise ``noise_h``
    east/north and ``noise_v`` up [m], WGS84 about ``origin`` (lat, lon [deg], alt [m])."""
    enu = np.column_stack([truth["x"][idx], truth["y"][idx], truth["z"][idx]])
    enu = enu + rng.standard_normal((idx.size, 3)) * np.array([noise_h, noise_h, noise_v])
    lat, lon, alt = LocalTangentPlane(*origin).to_geodetic(enu)
    return {"t": truth["t"][idx], "lat": np.asarray(lat), "lon": np.asarray(lon), "alt": np.asarray(alt),
            "status": np.zeros(idx.size, dtype=np.int64),
            "cov": np.array([noise_h ** 2, noise_h ** 2, noise_v ** 2]), "origin": tuple(origin)}


def truth_samples(truth: dict, idx: np.ndarray) -> dict:
    """The :data:`TRUTH_KEYS` of ``truth`` at the samples ``idx`` (the ground-truth topics)."""
    return {key: np.asarray(truth[key])[idx] for key in TRUTH_KEYS}


def write_drive(result, path: Path, *, gnss: bool = True, wheels: bool = True) -> Path:
    """Write a ``sensor_result`` (``sensors``, ``truth``) as an MCAP bag at ``path`` (stamps from
    0 s); without ``gnss/fix`` unless ``gnss``, without ``vehicle/joint_states`` unless ``wheels``."""
    simbag.check_new_bag_path(path)
    drop = set()
    if not gnss:
        drop.add(T.GNSS)
    if not wheels:
        drop.add(T.JOINT_STATES)
    streams = [s for s in simbag.build_streams(result, t0_ns=0) if s[0] not in drop]
    return simbag.write_streams(streams, path)


def generator_main(argv, module, *, out_help: str) -> int:
    """The command line the road-drive generators share: ``python -m <module> --out DIR
    [--duration S] [--seed N] [--imu-rpy-deg R P Y] [--write-params FILE]``; prints each bag
    written. ``module`` has ``generate(out, seed=, duration=, imu_rpy_deg=)``, ``params_yaml()``
    and ``FULL_DURATION``; its docstring's first line is the description."""
    import argparse

    ap = argparse.ArgumentParser(prog=f"python -m {module.__spec__.name}",
                                 description=module.__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help=out_help)
    ap.add_argument("--duration", type=float, default=None, help=f"drive length [s] (default {module.FULL_DURATION:g})")
    ap.add_argument("--seed", type=int, default=0)
    add_imu_mounting_option(ap)
    ap.add_argument("--write-params", type=Path, default=None, help="also write the vehicle params file here")
    args = ap.parse_args(argv)
    if args.write_params is not None:
        args.write_params.parent.mkdir(parents=True, exist_ok=True)   # often the --out folder, made below
        args.write_params.write_text(with_imu_mounting(module.params_yaml(), args.imu_rpy_deg), encoding="utf-8")
    for path in module.generate(args.out, seed=args.seed, duration=args.duration, imu_rpy_deg=tuple(args.imu_rpy_deg)):
        print(path)
    return 0


def add_imu_mounting_option(ap) -> None:
    """``--imu-rpy-deg R P Y`` of the generators (``args.imu_rpy_deg``)."""
    ap.add_argument("--imu-rpy-deg", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("R", "P", "Y"),
                    help="the IMU's roll, pitch, yaw in base_link [deg]: imu/data is in that imu_link, "
                         "and the vehicle files say so (vehicle.imu_mounting_rpy)")


def format_vehicle_yaml(header: list[str], values: dict, notes: dict[str, str]) -> str:
    """``/**: ros__parameters: vehicle:`` with ``values``, each line commented by ``notes[key]``.

    ``header``: comment lines (with their ``#``) that say where the data come from. A value
    that is a string is written as it is.
    """
    lines = [*header, "/**:", "  ros__parameters:", "    vehicle:"]
    for key, value in values.items():
        if isinstance(value, str):
            text = value
        elif isinstance(value, list):
            text = _float_list(value)
        else:
            text = repr(round(float(value), 6))
        note = notes.get(key, "")
        lines.append(f"      {key}: {text}" + (f"   # {note}" if note else ""))
    return "\n".join(lines) + "\n"


def with_imu_mounting(vehicle_yaml: str, imu_rpy_deg) -> str:
    """A vehicle file of :func:`format_vehicle_yaml` (its ``vehicle:`` section last) that also
    gives the IMU's mounting ``imu_rpy_deg`` [deg], as ``vehicle.imu_mounting_rpy`` [rad];
    unchanged for a level IMU."""
    if not any(imu_rpy_deg):
        return vehicle_yaml
    text = _float_list([math.radians(float(a)) for a in imu_rpy_deg])
    degrees = ", ".join(f"{float(a):g}" for a in imu_rpy_deg)
    return vehicle_yaml + f"      imu_mounting_rpy: {text}   # the drive's imu_link, roll, pitch, yaw {degrees} deg\n"


def _float_list(values) -> str:
    """A YAML flow list of floats; repr keeps "1.0" a float: a ROS params file refuses an array
    of mixed types."""
    return "[" + ", ".join(repr(float(x)) for x in values) + "]"
