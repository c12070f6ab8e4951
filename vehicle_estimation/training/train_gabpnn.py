"""Train the GA-BPNN output correction of paper 002 (Secs. 3.1-3.2) on simulated drives.

Usage::

    python -m vehicle_estimation.training.train_gabpnn [--vehicle sedan_d_class] [--out FILE]
                                                    [--seed 2023] [--epochs 300] [--generations 100]
                                                    [--population 40] [--quick]

1. Simulates the TRAINING drives (never the seeds of ``experiments/paper002_aoukf_gabpnn.py``'s evaluation
   scenarios 21/22 nor the validation seed): ISO 3888-2 double lane changes at 60, 70, 80 and
   90 km/h (``paper002_dlc`` with seeds 100-103) and three 150 s mixed drives
   (``paper002_mixed`` with seeds 200-202), with the paper-002 outliers and time-varying noise.
2. Runs the anti-outlier UKF (default :class:`~vehicle_estimation.estimators.state.aoukf.AOUKFConfig`) on
   each, as ``experiments/paper002_aoukf_gabpnn.py`` does, and collects per sample the network inputs (the
   low-passed state-correction rates of :class:`~vehicle_estimation.estimators.state.gabpnn.BPCorrection`)
   and the target ``X_true - X_k|k`` (Sec. 3.2 Steps 1-3); the first 2 s of a drive are skipped.
3. Per state (vx, vy, r): the GA searches the 2-5-1 network's initial weights and thresholds
   (improved roulette, Sec. 3.1), then BP trains it; the same BP from random initial weights is
   reported beside it (the paper's reason for the GA).
4. Writes ``vehicle_estimation/models/gabpnn_<vehicle>.npz`` (plain arrays, no pickle) and
   prints the MAE of the AO-UKF with and without the correction on a held-out validation drive
   (``paper002_mixed`` seed 300, 120 s, and ``paper002_dlc`` seed 301).

Deterministic for a given ``--seed``; about a minute on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from vehicle_estimation.estimators.state import gabpnn
from vehicle_estimation.estimators.state.aoukf import AOUKFConfig, VehicleStateAOUKF

WARMUP_S = 2.0


def training_scenarios(vehicle: str, quick: bool = False) -> list[Any]:
    from vehicle_estimation.sim.scenario import load_vehicle, scenario_by_name

    vp = load_vehicle(vehicle)
    dlc, mix = scenario_by_name("paper002_dlc"), scenario_by_name("paper002_mixed")
    out = []
    for i, kmh in enumerate((60.0, 70.0, 80.0, 90.0)):
        v = kmh / 3.6
        out.append(dataclasses.replace(dlc, name=f"train_dlc_{kmh:.0f}", vehicle=vp, seed=100 + i, initial_speed=v,
                                       speed_profile=dataclasses.replace(dlc.speed_profile, speed_mps=v)))
    for i in range(1 if quick else 3):
        out.append(dataclasses.replace(mix, name=f"train_mixed_{i}", vehicle=vp, seed=200 + i,
                                       duration_s=60.0 if quick else 150.0))
    return out


def validation_scenarios(vehicle: str) -> list[Any]:
    from vehicle_estimation.sim.scenario import load_vehicle, scenario_by_name

    vp = load_vehicle(vehicle)
    return [dataclasses.replace(scenario_by_name("paper002_mixed"), name="validation_mixed", vehicle=vp,
                                seed=300, duration_s=120.0),
            dataclasses.replace(scenario_by_name("paper002_dlc"), name="validation_dlc", vehicle=vp, seed=301)]


def collect(scenario: Any, config: AOUKFConfig, feature_tau_s=(0.1, 1.0)) -> dict[str, np.ndarray]:
    """Simulate ``scenario``, run the AO-UKF; per sample: features (N, 3, 2), error (N, 3),
    estimate (N, 3), truth (N, 3), t (N,)."""
    from vehicle_estimation.sim import simulate
    from vehicle_estimation.experiments.paper002_aoukf_gabpnn import drive_from_sim

    drive = drive_from_sim(simulate(scenario))
    est = VehicleStateAOUKF(drive.params, config)
    feature = gabpnn.BPCorrection({k: gabpnn.BPNetwork.from_vector(np.zeros(gabpnn.N_GENES)) for k in gabpnn.STATES},
                                  np.zeros((3, 2)), np.ones((3, 2)), np.ones(3), np.zeros(3), feature_tau_s)
    n = drive.t.size
    feats = np.zeros((n, 3, 2))
    xs = np.full((n, 3), np.nan)
    for i in range(n):
        est.step(float(drive.t[i]), drive.inputs(i), drive.z[i])
        f = est.filter
        feature.update_features(float(drive.t[i]), f.x - f.x_prior)
        feats[i] = feature.features
        xs[i] = f.x
    truth = np.stack([drive.truth[k] for k in gabpnn.STATES], axis=1)
    return {"t": drive.t, "features": feats, "estimate": xs, "truth": truth, "error": truth - xs}


def _usable(run: dict[str, np.ndarray]) -> np.ndarray:
    keep = run["t"] >= run["t"][0] + WARMUP_S
    return keep & np.all(np.isfinite(run["error"]), axis=1) & np.all(np.isfinite(run["features"]), axis=(1, 2))


def _prefixed(log: Callable[[str], Any], prefix: str) -> Callable[[str], None]:
    return lambda msg: log(prefix + msg)


def fit(runs: list[dict[str, np.ndarray]], seed: int, *, epochs: int, generations: int, population: int,
        feature_tau_s=(0.1, 1.0), log=print) -> tuple[gabpnn.BPCorrection, dict[str, Any]]:
    """GA + BP per state on the collected runs; returns the correction and a training report."""
    # every 2nd sample: neighbouring 100 Hz samples carry almost the same information
    F = np.concatenate([r["features"][_usable(r)] for r in runs])[::2]
    E = np.concatenate([r["error"][_usable(r)] for r in runs])[::2]
    mean, std = F.mean(axis=0), F.std(axis=0)
    std = np.where(std > 0.0, std, 1.0)
    out_scale = np.maximum(E.std(axis=0), 1e-9)
    clip = np.quantile(np.abs(E), 0.999, axis=0)
    nets: dict[str, gabpnn.BPNetwork] = {}
    report: dict[str, Any] = {"samples": int(F.shape[0]), "states": {}}
    for j, key in enumerate(gabpnn.STATES):
        u = (F[:, j] - mean[j]) / std[j]
        target = E[:, j] / out_scale[j]
        t0 = time.process_time()
        ga = gabpnn.train_gabp(u, target, np.random.default_rng([seed, j]), epochs=epochs, generations=generations,
                               population=population, progress=_prefixed(log, f"  [{key}] "))
        plain = gabpnn.train_gabp(u, target, np.random.default_rng([seed, j, 1]), epochs=epochs, use_ga=False)
        nets[key] = ga.network
        early = min(50, epochs)
        report["states"][key] = {
            "ga_initial_mse": ga.bp_history[0], f"ga_mse_epoch_{early}": ga.bp_history[early],
            "ga_final_mse": ga.bp_history[-1], "random_initial_mse": plain.bp_history[0],
            f"random_mse_epoch_{early}": plain.bp_history[early], "random_final_mse": plain.bp_history[-1],
            "ga_best_E": ga.ga_history[-1] if ga.ga_history else None, "cpu_s": time.process_time() - t0}
        log(f"  [{key}] BP loss (normalised MSE) at epochs 0 / {early} / {epochs}: GA init "
            f"{ga.bp_history[0]:.4f} / {ga.bp_history[early]:.4f} / {ga.bp_history[-1]:.4f}; random init "
            f"{plain.bp_history[0]:.4f} / {plain.bp_history[early]:.4f} / {plain.bp_history[-1]:.4f}")
    corr = gabpnn.BPCorrection(nets, mean, std, out_scale, clip, feature_tau_s)
    return corr, report


def evaluate(correction: gabpnn.BPCorrection, run: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """MAE of the AO-UKF with and without Eq. 5 on a collected run (features as the node sees them)."""
    keep = _usable(run)
    corrected = run["estimate"] + correction.predict(run["features"])
    res: dict[str, dict[str, float]] = {}
    for j, key in enumerate(gabpnn.STATES):
        res[key] = {"aoukf": float(np.mean(np.abs(run["error"][keep, j]))),
                    "aoukf_gabpnn": float(np.mean(np.abs(run["truth"][keep, j] - corrected[keep, j])))}
    return res


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default="sedan_d_class", help="params/<vehicle>.yaml (default sedan_d_class)")
    p.add_argument("--out", default=None, help="weights file (default vehicle_estimation/models/gabpnn_<vehicle>.npz)")
    p.add_argument("--seed", type=int, default=2023, help="GA / BP random seed (default 2023)")
    p.add_argument("--epochs", type=int, default=300, help="BP epochs per state (default 300)")
    p.add_argument("--generations", type=int, default=100, help="GA generations (default 100)")
    p.add_argument("--population", type=int, default=40, help="GA population, even (default 40)")
    p.add_argument("--quick", action="store_true", help="fewer, shorter training drives (smoke test)")


def main(args: argparse.Namespace) -> int:
    try:
        import torch   # noqa: F401  (not used; keep BLAS/OpenMP threads of any import to one)
        torch.set_num_threads(1)
    except Exception:
        pass
    out = Path(args.out) if args.out else gabpnn.default_weights_path(args.vehicle)
    # the paper's tyre: the correction learns the residuals of paper 002's own model
    config = AOUKFConfig(mf_peak_from_road_friction=False)
    t0 = time.process_time()
    runs = []
    scenarios = training_scenarios(args.vehicle, quick=args.quick)
    print(f"[1/3] {len(scenarios)} training drives (AO-UKF, the paper's tyre)")
    for scn in scenarios:
        runs.append(collect(scn, config))
        print(f"  {scn.name}: {scn.duration_s:.0f} s, seed {scn.seed}, AO-UKF MAE "
              + ", ".join(f"{k} {np.mean(np.abs(runs[-1]['error'][_usable(runs[-1]), j])):.4f}"
                          for j, k in enumerate(gabpnn.STATES)))
    print(f"[2/3] GA ({args.population} x {args.generations} generations) + BP ({args.epochs} epochs), seed {args.seed}")
    correction, report = fit(runs, args.seed, epochs=args.epochs, generations=args.generations,
                             population=args.population)
    out.parent.mkdir(parents=True, exist_ok=True)
    gabpnn.save_correction(correction, out, vehicle=args.vehicle, seed=str(args.seed),
                           command="python -m vehicle_estimation.training.train_gabpnn "
                                   + " ".join(sys.argv[1:]).strip())
    print(f"[3/3] wrote {out} ({report['samples']} training samples)")
    loaded = gabpnn.load_correction(out)
    for scn in validation_scenarios(args.vehicle):
        res = evaluate(loaded, collect(scn, config))
        print(f"  held-out {scn.name} (seed {scn.seed}) MAE AO-UKF -> AO-UKF + GA-BPNN: "
              + ", ".join(f"{k} {v['aoukf']:.4f} -> {v['aoukf_gabpnn']:.4f}" for k, v in res.items()))
    print(f"  {time.process_time() - t0:.1f} CPU s")
    return 0


if __name__ == "__main__":
    from vehicle_estimation.cli import run_as_script
    sys.exit(run_as_script(sys.modules[__name__]))
