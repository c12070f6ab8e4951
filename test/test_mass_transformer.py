"""Tests of the paper-000 mass networks (vehicle_estimation.estimators.mass.transformer.model): shapes,
save/load without pickle, refusal of altered files, the shipped model, the estimator's network
path, and a small smoke run of the dataset, training and comparison commands."""

import argparse
import json
import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from vehicle_estimation.estimators.mass.transformer.model import (
    MassModel, ModelSpec, TransformerMassNet, build_network)
from vehicle_estimation.estimators.mass.ta_aekf import DEFAULT_MODEL_STEM, TaAekfConfig, TaAekfMassEstimator
from vehicle_estimation.estimators.mass.transformer.features import NN_FEATURES, fit_confidence_gaussian
from vehicle_estimation.contract.vehicle import load_vehicle_params

torch.set_num_threads(1)
PARAMS_DIR = Path(__file__).resolve().parents[1] / "params"
TRUCK = load_vehicle_params(PARAMS_DIR / "heavy_truck.yaml")


def tiny_model(kind="transformer", window=6, block_steps=5, seed=0):
    torch.manual_seed(seed)
    spec = ModelSpec(kind=kind, window=window, block_steps=block_steps, d_model=16, n_heads=16,
                     n_layers=1, d_ff=16, hidden=8)
    rng = np.random.default_rng(seed)
    tau_x = rng.normal(size=(200, 4)) * [5000.0, 0.3, 5.0, 0.02] + [15000.0, 0.2, 15.0, 0.0]
    mu, cov = fit_confidence_gaussian(tau_x)
    return MassModel(spec=spec, network=build_network(spec),
                     feature_mean=np.array([15000.0, 1000.0, 0.2, 0.3, 50.0]),
                     feature_std=np.array([8000.0, 500.0, 0.4, 0.3, 20.0]),
                     mass_mean=28042.0, mass_std=11000.0, tau_mean=mu, tau_cov=cov,
                     validation_rel_rmse=0.1, metadata={"note": "test"})


@pytest.mark.parametrize("kind", ["transformer", "mlp", "lstm"])
def test_network_input_output_shapes(kind):
    spec = ModelSpec(kind=kind, window=10, block_steps=10)
    net = build_network(spec).eval()
    out = net(torch.zeros(7, 10, len(NN_FEATURES)))
    assert out.shape == (7,)
    model = tiny_model(kind)
    windows = np.random.default_rng(1).normal(size=(3, 6, 5)) * model.feature_std + model.feature_mean
    pred = model.predict(windows)
    assert pred.shape == (3,) and np.all(np.isfinite(pred))
    with pytest.raises(ValueError):
        model.predict(windows[:, :4])                  # wrong window length


def test_transformer_follows_sec_2_2():
    net = TransformerMassNet(ModelSpec())
    assert len(net.encoder.layers) == 3                                    # 3 encoder layers
    assert net.encoder.layers[0].self_attn.num_heads == 16                 # 16 heads
    assert net.encoder.layers[0].dropout.p == pytest.approx(0.3)           # dropout 0.3
    assert net.position.shape == (10, 64) and net.position.requires_grad   # learnable PE
    assert net.head.in_features == 10 * 64 and net.head.out_features == 1  # flatten + linear, l = 1
    with pytest.raises(ValueError, match="n_heads"):
        ModelSpec(d_model=40).validate()


def test_save_load_round_trip_without_pickle(tmp_path, monkeypatch):
    model = tiny_model()
    stem = tmp_path / "m"
    weights, meta = model.save(stem)
    assert weights.read_bytes()[:8] != b"\x80\x04\x95"                    # not a pickle stream

    def refuse(*args, **kwargs):
        raise AssertionError("pickle must not be used")
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    loaded = MassModel.load(stem)
    windows = np.random.default_rng(2).normal(size=(4, 6, 5)) * model.feature_std + model.feature_mean
    np.testing.assert_allclose(loaded.predict(windows), model.predict(windows), rtol=1e-6)
    x = np.array([[12000.0, 0.5, 10.0, 0.01]])
    np.testing.assert_allclose(loaded.confidence(x), model.confidence(x), rtol=1e-12)
    assert loaded.validation_rel_rmse == 0.1 and loaded.metadata == {"note": "test"}


def test_altered_files_are_refused(tmp_path):
    from safetensors.torch import load_file, save_file

    model = tiny_model()
    stem = tmp_path / "m"
    weights, meta = model.save(stem)
    good_blob, good_doc = weights.read_bytes(), json.loads(meta.read_text())

    def rehash(doc):
        import hashlib
        doc = dict(doc, weights_sha256=hashlib.sha256(weights.read_bytes()).hexdigest())
        meta.write_text(json.dumps(doc))

    # one flipped byte
    blob = bytearray(good_blob)
    blob[len(blob) // 2] ^= 0xFF
    weights.write_bytes(bytes(blob))
    with pytest.raises(ValueError, match="SHA-256"):
        MassModel.load(stem)
    # a consistent hash but a non-finite weight
    tensors = load_file(str(tmp_path / "m.safetensors")) if False else None
    weights.write_bytes(good_blob)
    tensors = load_file(str(weights))
    name = next(k for k in tensors if k.startswith("net."))
    tensors[name] = tensors[name].clone()
    tensors[name].view(-1)[0] = float("nan")
    save_file(tensors, str(weights))
    rehash(good_doc)
    with pytest.raises(ValueError, match="non-finite"):
        MassModel.load(stem)
    # a wrong shape (weights of another window length under this spec)
    other = tiny_model(window=8)
    save_file(other.tensors(), str(weights))
    rehash(good_doc)
    with pytest.raises(ValueError, match="expected"):
        MassModel.load(stem)
    # a missing tensor
    tensors = load_file(str(weights))
    tensors.pop("tau.cov")
    save_file(tensors, str(weights))
    rehash(good_doc)
    with pytest.raises(ValueError, match="names differ"):
        MassModel.load(stem)
    # not a safetensors file at all (a pickle), hash made consistent
    weights.write_bytes(pickle.dumps({"a": 1}))
    rehash(good_doc)
    with pytest.raises(ValueError, match="safetensors"):
        MassModel.load(stem)
    # a broken JSON, a wrong format tag, a missing file
    weights.write_bytes(good_blob)
    meta.write_text("{")
    with pytest.raises(ValueError, match="cannot read"):
        MassModel.load(stem)
    meta.write_text(json.dumps(dict(good_doc, format="other")))
    with pytest.raises(ValueError, match="format"):
        MassModel.load(stem)
    with pytest.raises(ValueError, match="cannot read"):
        MassModel.load(tmp_path / "absent")


def test_shipped_model_loads_and_is_plausible():
    model = MassModel.load(DEFAULT_MODEL_STEM)
    assert model.spec.kind == "transformer" and model.spec.n_heads == 16 and model.spec.n_layers == 3
    assert 0.0 < model.validation_rel_rmse < 0.5
    lo, hi = model.metadata["train_mass_range_kg"]
    assert lo == pytest.approx(10042.0) and hi == pytest.approx(46042.0)
    # tau at the training mean is 1, far from it (a car's forces) almost 0
    assert float(model.confidence(model.tau_mean)) == pytest.approx(1.0)
    assert float(model.confidence(np.array([1500.0, 2.5, 35.0, -0.1]))) < 1e-3


def test_estimator_runs_the_network_every_block_on_the_feature_windows(monkeypatch):
    """The estimator's windows are those of training/truck_data.feature_blocks (train = use)."""
    from vehicle_estimation.training import truck_data as td
    from vehicle_estimation.experiments.paper000_ta_aekf import run_filter

    model = tiny_model(window=6, block_steps=5)
    n = 400
    t = np.arange(n) * 0.01
    rng = np.random.default_rng(5)
    sig = {"t": t, "vx": 12.0 + 0.5 * t, "ax": 0.5 + rng.normal(0, 0.05, n),
           "slope": 0.01 * np.sin(t), "drive_force": 20000.0 + 1000.0 * np.sin(3 * t),
           "engine_torque": np.full(n, np.nan), "engine_speed": np.full(n, np.nan),
           "gear": np.full(n, np.nan), "brake_torque": np.zeros(n)}
    sig["vx"][200] = 0.3                           # a creeping sample restarts the window
    # the core derives a_x from vx (accel_from_speed): the dataset's definition
    sig["ax"] = td.causal_slope(t, sig["vx"], td.ACCEL_FIT_S)
    seen = []
    original = model.predict

    def spy(windows):
        seen.append(np.array(windows[0]))
        return original(windows)
    monkeypatch.setattr(model, "predict", spy)
    res = run_filter(TRUCK, sig, TaAekfConfig(inference_period_steps=5, initial_mass=6042.0), model)
    blocks, _, segment, _ = td.feature_blocks(sig, TRUCK, 5)
    expected, _ = td.windows_of(blocks, segment, 6)
    assert len(seen) == expected.shape[0] > 0
    np.testing.assert_allclose(np.stack(seen), expected, rtol=1e-9, atol=1e-9)
    assert np.all(np.isfinite(res["mass"]))
    assert np.isfinite(res["tau"]).sum() > 0
    with pytest.raises(ValueError, match="inference_period_steps"):
        TaAekfMassEstimator(TRUCK, TaAekfConfig(inference_period_steps=10), model=model)


def test_commands_smoke(tmp_path, capsys):
    """Dataset -> training of the three networks -> comparison, all tiny."""
    from vehicle_estimation.experiments import paper000_ta_aekf as paper000
    from vehicle_estimation.training import truck_data
    from vehicle_estimation.training.train_mass_transformer import train_one

    data = truck_data.generate(block_steps=10, payloads=(4000.0, 36000.0), duration_s=6.0, progress=False)
    assert set(np.unique(data["drive_split"])) == {0, 1, 2}
    path = truck_data.save_dataset(data, tmp_path / "dataset.npz")
    data = truck_data.load_dataset(path)
    small = {"transformer": {"d_model": 16, "n_layers": 1, "d_ff": 16}, "mlp": {"hidden": 8}, "lstm": {"hidden": 8}}
    for kind, overrides in small.items():
        model, history = train_one(kind, data, window=10, epochs=1, seed=0, progress=False,
                                   max_train=200, spec_overrides=overrides)
        assert len(history["val_loss"]) == 1 and math.isfinite(history["val_loss"][0])
        model.save(tmp_path / f"mass_{kind}")
    parser = argparse.ArgumentParser()
    paper000.add_arguments(parser)
    args = parser.parse_args(["--out", str(tmp_path / "out"), "--models", str(tmp_path), "--duration", "6",
                              "--no-clean", "--quiet"])
    assert paper000.main(args) == 0
    doc = json.loads((tmp_path / "out" / "comparison.json").read_text())
    assert set(doc["main"]["average"]) >= {"EKF", "MLP", "LSTM", "Transformer", "TA-AEKF", "TA-AEKF (Alg. 1)", "tau = 1"}
    assert set(doc["ood"]) == {"truck 28.5 t (in range)", "truck 48 t", "truck 60 t", "sedan (paper 004)"}
    assert (tmp_path / "out" / "test1.png").is_file() and (tmp_path / "out" / "ood.png").is_file()
    assert "Table 4" in capsys.readouterr().out


def test_bad_input_with_the_network_never_raises():
    model = tiny_model(window=6, block_steps=5)
    est = TaAekfMassEstimator(TRUCK, TaAekfConfig(inference_period_steps=5, initial_mass=20000.0), model=model)
    rng = np.random.default_rng(9)
    t = 0.0
    for k in range(1500):
        t += 0.01
        vx, force, slope = 15.0 + math.sin(0.01 * k), 20000.0 + 3000.0 * math.sin(0.03 * k), 0.01
        if k % 37 == 0:
            vx = [math.nan, math.inf, -1e9, 0.2][k % 4]
        if k % 53 == 0:
            force = [math.nan, 1e12, -math.inf][k % 3]
        if k % 71 == 0:
            slope = [math.nan, 3.0][k % 2]
        if k % 97 == 0:
            t -= 0.5                                   # time jumps back
        if k % 301 == 0:
            t += 3.0                                   # a gap
        est.step(t, vx, rng.normal(), slope, drive_force=force, brake_torque=[0.0, math.nan, -5.0][k % 3])
        assert np.all(np.isfinite(est.ekf.x)) and np.all(np.isfinite(est.ekf.P))
        assert math.isfinite(est.mass) and math.isfinite(est.variance)
    assert est.network_updates + est.network_gated > 0
    assert sum(est.rejected.values()) > 0
