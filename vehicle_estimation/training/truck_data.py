"""Training data for the paper-000 mass networks (Zhang et al. 2023, Sec. 3 and Sec. 4).

Usage::

    python -m vehicle_estimation.training.truck_data [--out out/truck_data] [--repeats 1] [--slope-noise-deg 0.3,0]

The heavy truck of Table 1 (``params/heavy_truck.yaml``: curb 6042 kg, 6.8 m^2, eta 0.99) with
payloads 4000-40,000 kg in 4000 kg steps (10 gross masses, 10,042-46,042 kg), on each of the
five training slope profiles of :data:`TRAIN_SLOPES` (Fig. 5a), all on the HWFET speed
profile (Fig. 5b), 100 s each at 0.01 s (Table 1): 50 drives. Split 6:2:2 (Sec. 4) *by drive*
(windows of one drive overlap, so a split by window would leak): per payload, three slope
profiles train, one validates and one tests, rotated over the payloads, so every mass is in
every split. Each drive is written once per slope error of ``--slope-noise-deg`` (default 0.3 deg
and 0, the paper's error-free setting; the same simulation and sensor noise), 100 drives in all.
Writes ``dataset.npz`` (no pickle) with the block features of every drive.

Choices the paper leaves open (ASSUMPTIONS):

* Speed profile: the 100 s of HWFET from second :data:`HWFET_OFFSET_S` on, the truck already
  rolling at the cycle's speed (the first seconds of HWFET are standstill, where Eq. 14 says
  nothing about the mass). Same segment for training and test drives, as in the paper.
* Slope profiles: :data:`TRAIN_SLOPES` / :data:`TEST_SLOPES`, built from the simulator's
  ``straight`` road (constant grade plus smooth hills); the test profiles have hills of other
  lengths and phases than any training profile, test 2 changing more often (Sec. 4.2).
* Sensor noise, what a truck would see (our simulator's sensors, default ``SensorConfig``):
  speed v_x = mean undriven (front) wheel speed x r from ``joint_states`` (0.02 rad/s
  noise per wheel); a_x = least-squares slope of that speed over the last 0.2 s (causal);
  drive force, engine torque/speed and gear from ``powertrain`` (CAN, 2 N m torque noise);
  brake torque from ``joint_states``; slope = true slope + first-order Gauss-Markov error of
  0.3 deg RMS with a 2 s correlation time, like the slope observer's error (and the same drive
  with an exact slope).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from vehicle_estimation.estimators.mass.ta_aekf import TaAekfConfig
from vehicle_estimation.estimators.mass.ta_aekf_filter import drive_force_input
from vehicle_estimation.estimators.mass.transformer.features import NN_FEATURES, TAU_FEATURES, FeatureBlocks, eq15_features
from vehicle_estimation.contract.vehicle import VehicleParams

CURB_MASS = 6042.0                                            # Table 1 [kg]
PAYLOADS = tuple(float(p) for p in range(4000, 40001, 4000))  # Table 1 [kg]
TEST_GROSS_MASS = 28542.0                                     # Sec. 3 [kg]
DURATION_S = 100.0                                            # Sec. 3
HWFET_OFFSET_S = 5
SLOPE_NOISE_DEG = 0.3
#: The slope errors [deg RMS] of the dataset: each drive once per level (the same simulation and
#: sensor noise). 0.3 deg is what the slope node's estimate carries; 0 is the paper's setting.
SLOPE_NOISE_LEVELS = (SLOPE_NOISE_DEG, 0.0)
SLOPE_NOISE_TAU_S = 2.0
ACCEL_FIT_S = 0.2
MIN_SPEED = 1.0


@dataclasses.dataclass(frozen=True)
class SlopeProfile:
    """A road for :func:`make_scenario`: ``straight`` with ``constant_grade`` plus hills of
    ``grade_max`` and ``wavelengths`` [m]; ``seed`` fixes the hills' phases (and the sim's
    sensor noise) so every payload drives the same road."""

    name: str
    constant_grade: float
    grade_max: float
    wavelengths: tuple[float, ...]
    seed: int

    def road(self) -> Any:
        from vehicle_estimation.sim import RoadSpec
        return RoadSpec(kind="straight", constant_grade=self.constant_grade, grade_max=self.grade_max,
                        hill_wavelengths=self.wavelengths or (1000.0,))


TRAIN_SLOPES = (
    SlopeProfile("level", 0.0, 0.0, (), 101),
    SlopeProfile("uphill_2pct", 0.02, 0.0, (), 102),
    SlopeProfile("downhill_1pct", -0.01, 0.0, (), 103),
    SlopeProfile("rolling_3pct", 0.0, 0.03, (600.0, 300.0), 104),
    SlopeProfile("long_hills_4pct", 0.005, 0.04, (1800.0, 900.0), 105),
)
TEST_SLOPES = (
    SlopeProfile("test1", 0.005, 0.025, (1100.0, 450.0), 201),
    SlopeProfile("test2", 0.0, 0.035, (380.0, 170.0), 202),
)


def hwfet_points(offset_s: int = HWFET_OFFSET_S, duration_s: float = DURATION_S) -> tuple[tuple[float, float], ...]:
    """HWFET (1 Hz) from ``offset_s`` on as (t, v [m/s]) points."""
    from vehicle_estimation.sim import load_cycle
    v = load_cycle("hwfet")
    n = int(math.ceil(duration_s)) + 1
    return tuple((float(i), float(v[offset_s + i])) for i in range(n))


def make_scenario(gross_mass: float, slope: SlopeProfile, vehicle: str | VehicleParams = "heavy_truck",
                  duration_s: float = DURATION_S) -> Any:
    from vehicle_estimation.sim import Scenario, SpeedProfile, load_vehicle
    params = load_vehicle(vehicle) if isinstance(vehicle, str) else vehicle
    points = hwfet_points(duration_s=duration_s)
    return Scenario(name=f"{params.name}_{slope.name}_{gross_mass:.0f}kg",
                    vehicle=params.with_mass(gross_mass), duration_s=duration_s,
                    speed_profile=SpeedProfile(kind="points", points=points),
                    road=slope.road(), seed=slope.seed, initial_speed=points[0][1], standstill_s=0.0)


def gauss_markov(rng: np.random.Generator, n: int, dt: float, std: float, tau_s: float) -> np.ndarray:
    """First-order Gauss-Markov sequence with stationary ``std`` and correlation time ``tau_s``."""
    phi = math.exp(-dt / tau_s)
    e = np.empty(n)
    e[0] = rng.normal(0.0, std)
    w = rng.normal(0.0, std * math.sqrt(1.0 - phi * phi), n)
    for k in range(1, n):
        e[k] = phi * e[k - 1] + w[k]
    return e


def causal_slope(t: np.ndarray, y: np.ndarray, span_s: float) -> np.ndarray:
    """Least-squares slope of y over the trailing ``span_s`` at every sample (NaN until full)."""
    dt = float(np.median(np.diff(t)))
    n = max(int(round(span_s / dt)), 2)
    out = np.full(y.size, np.nan)
    if y.size < n:
        return out
    tw = (np.arange(n) - (n - 1) / 2.0) * dt
    weights = tw / np.sum(tw * tw)
    out[n - 1:] = np.convolve(y, weights[::-1], mode="valid")
    return out


def drive_signals(result: Any, seed: int, *, slope_noise_deg: float = SLOPE_NOISE_DEG,
                  slope_noise_tau_s: float = SLOPE_NOISE_TAU_S) -> dict[str, np.ndarray]:
    """The estimator's inputs at the powertrain stamps (100 Hz) from the simulated sensors
    (see the module docstring) plus the truths ``mass``, ``vx_true``, ``slope_true``."""
    params: VehicleParams = result.scenario.vehicle
    pt, js = result.sensors["powertrain"], result.sensors["joint_states"]
    t = np.asarray(pt["t"], dtype=float)
    if not np.array_equal(t, np.asarray(js["t"], dtype=float)):
        raise ValueError("powertrain and joint_states stamps differ")
    undriven = list(params.undriven_wheels)
    vx = np.mean(np.asarray(js["velocity"])[:, undriven], axis=1) * params.wheel_radius
    ax = causal_slope(t, vx, ACCEL_FIT_S)
    truth = result.truth
    slope_true = np.interp(t, truth["t"], truth["slope"])
    rng = np.random.default_rng(seed)
    slope = slope_true + gauss_markov(rng, t.size, float(np.median(np.diff(t))),
                                      math.radians(slope_noise_deg), slope_noise_tau_s)
    return {"t": t, "vx": vx, "ax": ax, "slope": slope,
            "drive_force": np.asarray(pt["drive_force"], float),
            "engine_torque": np.asarray(pt["engine_torque"], float),
            "engine_speed": np.asarray(pt["engine_speed"], float),
            "gear": np.asarray(pt["gear"], float),
            "brake_torque": np.sum(np.asarray(js["effort"])[:, :4], axis=1),
            "mass": np.full(t.size, params.mass),
            "vx_true": np.interp(t, truth["t"], truth["vx"]), "slope_true": slope_true}


def feature_blocks(signals: dict[str, np.ndarray], params: VehicleParams, block_steps: int,
                   min_speed: float = MIN_SPEED, max_step_s: float = 0.5,
                   max_abs_accel: float = TaAekfConfig.max_abs_accel) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Block means of the Eq. (15) and Eq. (16) features, gated as
    :meth:`TaAekfMassEstimator.step` gates them. Returns (nn (K, 5), tau (K, 4), segment (K,),
    end_index (K,)): blocks of one segment are consecutive (a gap, standstill or missing
    force starts a new segment); end_index is the sample that completed the block."""
    delta = 1.0 + params.wheel_inertia / params.wheel_radius ** 2 / params.curb_mass
    blocks = FeatureBlocks(block_steps, 1)
    nn_out: list[np.ndarray] = []
    tau_out: list[np.ndarray] = []
    seg_out: list[int] = []
    end_out: list[int] = []
    segment = 0
    t_last = -math.inf
    s = signals
    for k in range(s["t"].size):
        t, vx, ax, slope = s["t"][k], s["vx"][k], s["ax"][k], s["slope"][k]
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(slope)) or not t > t_last:
            continue
        gap = t - t_last > max_step_s
        t_last = t
        drive = drive_force_input(params, vx, s["drive_force"][k], s["engine_torque"][k],
                                  s["engine_speed"][k], s["gear"][k], s["brake_torque"][k], min_speed)
        if gap or vx < min_speed or drive is None or not abs(ax) <= max_abs_accel:
            blocks.clear()
            segment += 1
            continue
        force = drive[0]
        if blocks.add(eq15_features(force, vx, ax, slope, params, delta), (force, ax, vx, slope)):
            nn_out.append(blocks.blocks[-1])
            tau_out.append(blocks.last_tau_features)
            seg_out.append(segment)
            end_out.append(k)
    nf, nt = len(NN_FEATURES), len(TAU_FEATURES)
    return (np.array(nn_out).reshape(-1, nf), np.array(tau_out).reshape(-1, nt),
            np.array(seg_out, dtype=np.int64), np.array(end_out, dtype=np.int64))


def windows_of(nn_blocks: np.ndarray, segment: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """All windows of ``window`` consecutive blocks within one segment: (windows (M, w, 5),
    index of each window's last block (M,))."""
    if nn_blocks.shape[0] < window:
        return np.zeros((0, window, nn_blocks.shape[1])), np.zeros(0, dtype=np.int64)
    ends = np.arange(window - 1, nn_blocks.shape[0])
    ok = segment[ends] == segment[ends - window + 1]
    ends = ends[ok]
    idx = ends[:, None] + np.arange(-window + 1, 1)[None, :]
    return nn_blocks[idx], ends


def split_of(payload_index: int, slope_index: int, n_slopes: int = len(TRAIN_SLOPES)) -> str:
    """6:2:2 by drive: for payload i the slope (i + 3) mod 5 validates, (i + 4) mod 5 tests."""
    r = (slope_index - payload_index) % n_slopes
    return "train" if r < 3 else ("val" if r == 3 else "test")


def generate(block_steps: int = 10, repeats: int = 1, payloads: tuple[float, ...] = PAYLOADS,
             slopes: tuple[SlopeProfile, ...] = TRAIN_SLOPES, duration_s: float = DURATION_S,
             progress: bool = True, slope_noise_deg: tuple[float, ...] = SLOPE_NOISE_LEVELS) -> dict[str, np.ndarray]:
    """Simulate every (payload, slope profile, repeat) drive and return the block features,
    once per slope error of ``slope_noise_deg`` (the same simulation and sensor noise).

    Arrays: ``nn`` (K, 5), ``tau`` (K, 4), ``segment`` (K,) globally unique, ``drive`` (K,)
    drive index; per drive: ``drive_mass``, ``drive_split`` (0 train, 1 val, 2 test),
    ``drive_payload_index``, ``drive_slope_index``, ``drive_repeat``, ``drive_slope_noise_deg``."""
    from vehicle_estimation.sim import load_vehicle, simulate

    truck = load_vehicle("heavy_truck")
    nn_all, tau_all, seg_all, drive_all = [], [], [], []
    meta: dict[str, list[Any]] = {"drive_mass": [], "drive_split": [], "drive_payload_index": [],
                                  "drive_slope_index": [], "drive_repeat": [], "drive_slope_noise_deg": []}
    seg_offset = 0
    total = len(payloads) * len(slopes) * repeats
    # Drawn on a terminal only (disable=None): a log gets no frames.
    bar = tqdm(total=total, desc="drives", unit="drive", disable=None if progress else True)
    d = 0
    for rep in range(repeats):
        for i, payload in enumerate(payloads):
            for j, slope in enumerate(slopes):
                mass = CURB_MASS + payload
                profile = dataclasses.replace(slope, seed=slope.seed + 1000 * rep)
                result = simulate(make_scenario(mass, profile, truck, duration_s))
                for noise in slope_noise_deg:
                    sig = drive_signals(result, seed=10_000 * rep + 100 * i + j, slope_noise_deg=noise)
                    nn, tau, seg, _ = feature_blocks(sig, result.scenario.vehicle, block_steps)
                    nn_all.append(nn)
                    tau_all.append(tau)
                    seg_all.append(seg + seg_offset)
                    seg_offset += int(seg.max(initial=0)) + 1
                    drive_all.append(np.full(nn.shape[0], d, dtype=np.int64))
                    meta["drive_mass"].append(mass)
                    meta["drive_split"].append(("train", "val", "test").index(split_of(i, j, len(slopes))))
                    meta["drive_payload_index"].append(i)
                    meta["drive_slope_index"].append(j)
                    meta["drive_repeat"].append(rep)
                    meta["drive_slope_noise_deg"].append(float(noise))
                    d += 1
                bar.set_postfix_str(f"{slope.name} {mass:.0f} kg, {nn.shape[0]} blocks", refresh=False)
                bar.update()
    bar.close()
    out = {"nn": np.concatenate(nn_all), "tau": np.concatenate(tau_all),
           "segment": np.concatenate(seg_all), "drive": np.concatenate(drive_all),
           "block_steps": np.array(block_steps)}
    out.update({k: np.asarray(v) for k, v in meta.items()})
    return out


def save_dataset(data: dict[str, np.ndarray], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)  # type: ignore[arg-type]
    return path


def load_dataset(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as f:
        data = {k: f[k] for k in f.files}
    if "drive_slope_noise_deg" not in data:     # a dataset from before the slope-error levels
        data["drive_slope_noise_deg"] = np.full(data["drive_mass"].shape, SLOPE_NOISE_DEG)
    return data


def parse_levels(text: str) -> tuple[float, ...]:
    """``"0.3,0"`` -> (0.3, 0.0): slope errors [deg RMS], each finite and >= 0."""
    try:
        levels = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ValueError(f"--slope-noise-deg: not a comma-separated list of numbers: {text!r}") from None
    if not levels or not all(math.isfinite(v) and v >= 0.0 for v in levels):
        raise ValueError(f"--slope-noise-deg: give one or more finite values >= 0, got {text!r}")
    return levels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/truck_data", help="output directory (dataset.npz)")
    p.add_argument("--repeats", type=int, default=1,
                   help="realisations per (payload, slope) drive; >1 adds drives with other hill phases and noise")
    p.add_argument("--block-steps", type=int, default=10, help="samples per feature block")
    p.add_argument("--duration", type=float, default=DURATION_S, help="drive length [s]")
    p.add_argument("--payloads", type=int, default=len(PAYLOADS),
                   help="use only the first N payloads (quick runs)")
    p.add_argument("--slope-noise-deg", default=",".join(f"{v:g}" for v in SLOPE_NOISE_LEVELS),
                   help="slope errors [deg RMS]: every drive once per value")
    p.add_argument("--quiet", action="store_true")


def main(args: argparse.Namespace) -> int:
    t0 = time.monotonic()
    data = generate(args.block_steps, args.repeats, PAYLOADS[:args.payloads], duration_s=args.duration,
                    progress=not args.quiet, slope_noise_deg=parse_levels(args.slope_noise_deg))
    path = save_dataset(data, Path(args.out) / "dataset.npz")
    split = data["drive_split"]
    print(f"{len(split)} drives (train {int(np.sum(split == 0))}, val {int(np.sum(split == 1))}, "
          f"test {int(np.sum(split == 2))}), {data['nn'].shape[0]} blocks -> {path} "
          f"({time.monotonic() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    sys.exit(run_as_script(sys.modules[__name__]))
