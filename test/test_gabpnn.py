"""GA-BPNN of paper 002: improved roulette, GA vs random initial weights, weight files without
pickle, and the Eq.-5 correction beating the uncorrected filter on a held-out drive."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vehicle_estimation.estimators.state import gabpnn
from vehicle_estimation.estimators.state.gabpnn import (BPCorrection, BPNetwork, improved_roulette, load_correction,
                                            save_correction, train_bp, train_gabp)
from vehicle_estimation.estimators.state.gabpnn import default_weights_path


def test_improved_roulette_draws_distinct_individuals_by_fitness():
    rng = np.random.default_rng(0)
    fitness = np.array([100.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    picks = improved_roulette(fitness, 3, rng)
    assert len(set(picks.tolist())) == 3          # a drawn individual leaves the pool
    firsts = [improved_roulette(fitness, 1, np.random.default_rng(s))[0] for s in range(200)]
    assert np.mean(np.asarray(firsts) == 0) > 0.9  # roulette: the fit one is drawn first
    with pytest.raises(ValueError):
        improved_roulette(fitness, 7, rng)


def _problem():
    rng = np.random.default_rng(7)
    u = rng.normal(size=(400, 2))
    y = 0.8 * np.sin(2.0 * u[:, 0]) + 0.5 * np.tanh(3.0 * u[:, 1]) + 0.05 * rng.normal(size=400)
    return u, y


def test_backprop_gradient_and_training_reduce_the_loss():
    u, y = _problem()
    net = BPNetwork.from_vector(np.random.default_rng(1).uniform(-1, 1, gabpnn.N_GENES))
    history = train_bp(net, u, y, epochs=200)
    assert history[-1] < 0.5 * history[0]
    assert all(b <= a + 1e-12 for a, b in zip(history, history[1:]))       # accepted steps only
    assert np.mean((net.forward(u) - y) ** 2) == pytest.approx(history[-1])


def test_ga_improves_the_bp_training_loss_over_random_initial_weights():
    u, y = _problem()
    ga = train_gabp(u, y, np.random.default_rng(2023), epochs=100, generations=60, population=40)
    rand = train_gabp(u, y, np.random.default_rng(2023), epochs=100, use_ga=False)
    assert ga.ga_history[-1] < ga.ga_history[0]                 # the GA itself made progress (Eq. 4)
    assert ga.bp_history[0] < rand.bp_history[0]
    assert ga.bp_history[-1] < rand.bp_history[-1]


def _correction(seed: int = 0) -> BPCorrection:
    rng = np.random.default_rng(seed)
    nets = {k: BPNetwork.from_vector(rng.normal(size=gabpnn.N_GENES)) for k in gabpnn.STATES}
    return BPCorrection(nets, rng.normal(size=(3, 2)), np.ones((3, 2)), [0.1, 0.05, 0.01], [0.3, 0.2, 0.05])


def test_weights_round_trip_without_pickle(tmp_path):
    corr = _correction()
    path = tmp_path / "w.npz"
    save_correction(corr, path, vehicle="test")
    loaded = load_correction(path)
    f = np.random.default_rng(3).normal(size=(10, 3, 2))
    np.testing.assert_allclose(loaded.predict(f), corr.predict(f))
    assert np.all(np.abs(loaded.predict(100 * f)) <= corr.output_clip + 1e-12)


@pytest.mark.parametrize("tamper, message", [
    (lambda a: a.pop("vy_w1"), "missing"),
    (lambda a: a.__setitem__("r_w1", np.zeros((4, 2))), "shape"),
    (lambda a: a.__setitem__("vx_b1", np.full(5, np.nan)), "non-finite"),
    (lambda a: a.__setitem__("input_std", np.zeros((3, 2))), "positive"),
    (lambda a: a.__setitem__("format", np.array("something else")), "format"),
    (lambda a: a.__setitem__("extra", np.zeros(1)), "unexpected"),
    (lambda a: a.__setitem__("vx_w2", np.array([object()] * 5, dtype=object)), "plain-array|numeric"),
])
def test_tampered_weight_files_raise_a_clear_value_error(tmp_path, tamper, message):
    path = tmp_path / "w.npz"
    save_correction(_correction(), path)
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    tamper(arrays)
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)
    with pytest.raises(ValueError, match=message):
        load_correction(path)


def test_not_an_npz_raises_value_error(tmp_path):
    path = tmp_path / "w.npz"
    path.write_bytes(b"not a zip file")
    with pytest.raises(ValueError):
        load_correction(path)


def test_features_are_rate_based_and_warm_up():
    corr = _correction()
    corr.warmup_s = 0.5
    out = [corr.step(0.01 * k, np.array([0.001, 0.0, 0.0])) for k in range(800)]
    assert np.all(out[10] == 0.0) and np.any(out[-1] != 0.0)
    np.testing.assert_allclose(corr.features[0], [0.1, 0.1], rtol=0.02)   # 0.001 per 0.01 s = 0.1 /s


def test_shipped_weights_load_and_correct_the_aoukf_on_a_held_out_drive():
    """The shipped correction (trained on seeds 100-103, 200-202) beats the uncorrected AO-UKF,
    and the plain UKF, on a drive it never saw (seed 77)."""
    from vehicle_estimation.estimators.state.aoukf import AOUKFConfig, VehicleStateAOUKF
    from vehicle_estimation.sim import simulate
    from vehicle_estimation.sim.scenario import scenario_by_name
    from vehicle_estimation.experiments.paper002_aoukf_gabpnn import drive_from_sim, run_estimator, score

    correction = load_correction(default_weights_path("sedan_d_class"))
    scn = dataclasses.replace(scenario_by_name("paper002_mixed"), duration_s=60.0, seed=77)
    drive = drive_from_sim(simulate(scn))
    res = {}
    paper = AOUKFConfig(mf_peak_from_road_friction=False)      # the tyre the weights learnt
    for name, est in (("ukf", VehicleStateAOUKF(drive.params, dataclasses.replace(paper, filter="ukf"))),
                      ("aoukf", VehicleStateAOUKF(drive.params, paper)),
                      ("corrected", VehicleStateAOUKF(drive.params, paper, correction=correction.fresh()))):
        res[name] = score(drive, run_estimator(drive, est), 2.0)
    for key in ("vy", "r"):
        assert res["corrected"]["mae"][key] < 0.8 * res["aoukf"]["mae"][key]
        assert res["corrected"]["rmse"][key] < res["ukf"]["rmse"][key]
    assert res["corrected"]["mae"]["vx"] < 1.1 * res["aoukf"]["mae"]["vx"]


def test_the_node_runs_the_correction_on_the_tyre_it_learnt():
    """A GA-BPNN correction learnt the residuals of the paper's tyre: the registry runs that
    tyre with it, and the road-friction tyre (the default) without it."""
    from vehicle_estimation.estimators.registry import build_state_filter
    from vehicle_estimation.contract.vehicle import load_vehicle_params
    from vehicle_estimation.paths import params_file

    sedan = load_vehicle_params(params_file("sedan_d_class"))
    correction = load_correction(default_weights_path("sedan_d_class"))
    plain = build_state_filter("aoukf", sedan)
    corrected = build_state_filter("aoukf", sedan, correction=correction.fresh())
    fz_front = 0.5 * sedan.mass * sedan.gravity * sedan.lr / sedan.wheelbase
    assert plain.model.D_front == pytest.approx(sedan.road_friction * fz_front)
    assert corrected.model.D_front == pytest.approx(3610.5 * fz_front / (1522.0 * 9.81 / 4.0))
