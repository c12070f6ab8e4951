"""Neural mass pre-estimators of Zhang et al. 2023 (paper 000): the transformer of Sec. 2.2
(Eqs. 1-5, input features of Eq. 15) and the MLP and LSTM baselines of its Tables 2-4.

No ROS; torch on CPU (``torch.set_num_threads(1)`` is enough for inference).

Transformer (Fig. 2): the window of w past feature vectors (w x 5, Eq. 15, normalised) is
projected to n = ``d_model`` dimensions, a learnable positional embedding is added (z_t), and
an encoder of ``n_layers`` = 3 layers with ``n_heads`` = 16 heads (Eqs. 1-2) and dropout 0.3
on every linear layer follows; its output E is flattened (Eq. 3) and a linear layer maps it to
l = 1 output (Eq. 4), the normalised total mass. Loss: the quadratic loss of Eq. (5).

Beside the paper (``ModelSpec.window_features``, ``slope_error_input``; the shipped transformer has
both, the MLP and LSTM baselines neither): every block of a window also carries the window's
own Eq. (14) estimates of 1/m (``features.window_features``: an integral that needs no
differentiated speed) and the slope input's stated RMS error, so that one network serves an
exact slope (the paper's setting) and a slope estimate; it trains on both (``training.truck_data``).
Measured on paper 000's test drives (``vehicle-estimation paper000``): the paper's 5 inputs over
1 s windows, trained on the 0.3 deg slope error only, are 10.0 % off with an exact slope and 15.0 %
with the error; least squares on Eq. (14) within such a window is itself 10 % off with an exact
slope, from the noise of a_x (a wheel-speed derivative): 4 % with the true a_x.

A :class:`MassModel` carries, with the weights, everything needed to use them: the feature
normalisation, the mass scaling, the Gaussian of the confidence level tau (Eqs. 16-19, fitted
to x' = [F_t, a_x, v_x, alpha] of the training set) and the relative RMSE on the validation
set (the sqrt(R_nn) of Algorithm 1). Files: ``<stem>.safetensors`` (tensors only, never
pickle) and ``<stem>.json`` (hyper-parameters, metadata and the SHA-256 of the tensor file);
:meth:`MassModel.load` refuses a file whose hash, tensor names, shapes or values do not fit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.estimators.mass.transformer.features import (NN_FEATURES, SLOPE_ERROR_FEATURE, TAU_FEATURES,
                                                                 WINDOW_FEATURES, confidence_level,
                                                                 window_features)

KINDS = ("transformer", "mlp", "lstm")
FORMAT_VERSION = 1


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Architecture and input layout of a mass network.

    ``window``: blocks per input window (w); ``block_steps``: samples averaged into one block
    (see :class:`vehicle_estimation.estimators.mass.ta_aekf.FeatureBlocks`). Transformer: ``d_model``
    (n), ``n_heads`` (h of Eq. 2; paper 16), ``n_layers`` (paper 3), ``d_ff`` (feed-forward
    width of each encoder layer), ``dropout`` (paper 0.3). MLP and LSTM: ``hidden`` width and
    ``n_layers``."""

    kind: str = setting("transformer", "Network kind", choices=KINDS)
    window: int = setting(10, "Blocks per input window w", low=1)
    block_steps: int = setting(10, "Samples averaged into one block", low=1)
    n_features: int = setting(len(NN_FEATURES), "Input features per block (Eq. 15)",
                              low=len(NN_FEATURES), high=len(NN_FEATURES))
    d_model: int = setting(64, "Transformer width n", low=1)
    n_heads: int = setting(16, "Attention heads h of Eq. 2 (paper 16)", low=1)
    n_layers: int = setting(3, "Encoder (or MLP/LSTM) layers (paper 3)", low=1)
    d_ff: int = setting(128, "Feed-forward width of each encoder layer", low=1)
    dropout: float = setting(0.3, "Dropout (paper 0.3)", low=0.0, high=1.0, high_open=True)
    hidden: int = setting(64, "MLP and LSTM hidden width", low=1)
    window_features: bool = setting(False, "Append the window's Eq. (14) inverse-mass estimates "
                                           "(features.WINDOW_FEATURES) to every block; not in the paper")
    slope_error_input: bool = setting(False, "Append the slope input's stated RMS error [deg] to every block "
                                             "(trained on several slope errors); not in the paper")
    sample_period_s: float = setting(0.01, "Sample period of the training data [s] (the block spacing is "
                                           "block_steps x this)", low=0.0, low_open=True)

    @property
    def input_names(self) -> tuple[str, ...]:
        """The network's inputs per block: Eq. (15), then the optional window and slope-error inputs."""
        return (NN_FEATURES + (WINDOW_FEATURES if self.window_features else ())
                + ((SLOPE_ERROR_FEATURE,) if self.slope_error_input else ()))

    @property
    def input_width(self) -> int:
        return len(self.input_names)

    @property
    def block_s(self) -> float:
        return self.block_steps * self.sample_period_s

    def validate(self) -> None:
        check_settings(self)
        if self.kind == "transformer" and self.d_model % self.n_heads:
            raise ValueError(f"d_model ({self.d_model}) must be a multiple of n_heads ({self.n_heads})")


class TransformerMassNet(nn.Module):
    """Eqs. (1)-(4): projection, learnable positional embedding, encoder, flatten, linear."""

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        self.project = nn.Linear(spec.input_width, spec.d_model)               # w -> n dims
        self.position = nn.Parameter(torch.zeros(spec.window, spec.d_model))   # learnable PE
        nn.init.normal_(self.position, std=0.02)
        self.dropout = nn.Dropout(spec.dropout)
        layer = nn.TransformerEncoderLayer(spec.d_model, spec.n_heads, spec.d_ff, spec.dropout,
                                           batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, spec.n_layers, enable_nested_tensor=False)
        self.head = nn.Linear(spec.window * spec.d_model, 1)                   # Eq. (4), l = 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.dropout(self.project(x) + self.position)                      # z_t
        e = self.encoder(z)                                                    # Eqs. (1)-(2)
        return self.head(self.dropout(e.flatten(1)))[:, 0]                     # Eqs. (3)-(4)


class MLPMassNet(nn.Module):
    """Baseline MLP on the flattened window (paper 000 Tables 2-4, 'MLP')."""

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = spec.window * spec.input_width
        for _ in range(spec.n_layers):
            layers += [nn.Linear(width, spec.hidden), nn.ReLU(), nn.Dropout(spec.dropout)]
            width = spec.hidden
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.flatten(1))[:, 0]


class LSTMMassNet(nn.Module):
    """Baseline LSTM over the window, linear head on the last hidden state ('LSTM')."""

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        self.lstm = nn.LSTM(spec.input_width, spec.hidden, spec.n_layers, batch_first=True,
                            dropout=spec.dropout if spec.n_layers > 1 else 0.0)
        self.head = nn.Linear(spec.hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out, _ = self.lstm(x)
        return self.head(out[:, -1])[:, 0]


def build_network(spec: ModelSpec) -> nn.Module:
    spec.validate()
    if spec.kind == "transformer":
        return TransformerMassNet(spec)
    if spec.kind == "mlp":
        return MLPMassNet(spec)
    return LSTMMassNet(spec)


def network_inputs(spec: ModelSpec, windows: np.ndarray, slope_error_deg: float | np.ndarray = 0.0) -> np.ndarray:
    """Raw Eq. (15) windows (B, w, 5) with the optional inputs of ``spec`` appended to every
    block: (B, w, ``spec.input_width``), not normalised. Training and use both call this."""
    w = np.asarray(windows, dtype=float)
    extra = []
    if spec.window_features:
        extra.append(window_features(w, spec.block_s))
    if spec.slope_error_input:
        extra.append(np.broadcast_to(np.asarray(slope_error_deg, dtype=float).reshape(-1, 1), (w.shape[0], 1)))
    if not extra:
        return w
    per_window = np.concatenate(extra, axis=1)
    return np.concatenate([w, np.repeat(per_window[:, None, :], w.shape[1], axis=1)], axis=2)


# --------------------------------------------------------------------- the model with its data
#: Tensors stored beside the network's own (name -> shape, given the spec).
def _extra_shapes(spec: ModelSpec) -> dict[str, tuple[int, ...]]:
    nf, nt = spec.input_width, len(TAU_FEATURES)
    return {"norm.feature_mean": (nf,), "norm.feature_std": (nf,), "norm.mass_mean_std": (2,),
            "tau.mean": (nt,), "tau.cov": (nt, nt)}


@dataclasses.dataclass
class MassModel:
    """A trained network and its data: normalisation, the tau Gaussian and validation error.

    ``predict(windows)`` takes raw (unnormalised) Eq. (15) windows (B, w, 5) and returns the
    total mass [kg] per window; ``confidence(x')`` is tau of Eq. (19). The feature normalisation
    covers every network input (``spec.input_names``)."""

    spec: ModelSpec
    network: nn.Module
    feature_mean: np.ndarray
    feature_std: np.ndarray
    mass_mean: float
    mass_std: float
    tau_mean: np.ndarray
    tau_cov: np.ndarray
    validation_rel_rmse: float = 0.05
    metadata: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        self.network.eval()

    @property
    def training_mean_mass(self) -> float:
        return float(self.mass_mean)

    def normalise(self, inputs: np.ndarray) -> np.ndarray:
        return (np.asarray(inputs, dtype=float) - self.feature_mean) / self.feature_std

    def _normalised_inputs(self, windows: np.ndarray, slope_error_deg: float | np.ndarray) -> np.ndarray:
        w = np.asarray(windows, dtype=float)
        if w.ndim != 3 or w.shape[1:] != (self.spec.window, self.spec.n_features):
            raise ValueError(f"windows must be (B, {self.spec.window}, {self.spec.n_features}), got {w.shape}")
        return self.normalise(network_inputs(self.spec, w, slope_error_deg))

    def predict(self, windows: np.ndarray, slope_error_deg: float | np.ndarray = 0.0) -> np.ndarray:
        """Mass [kg] for raw windows (B, window, 5); ``slope_error_deg``: the slope input's RMS
        error (scalar or per window), for a model with ``slope_error_input`` (else unused)."""
        return self._network_mass(self._normalised_inputs(windows, slope_error_deg))

    def predict_with_input_distance(self, windows: np.ndarray,
                                    slope_error_deg: float | np.ndarray = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` and, from the same inputs, the largest |input - training mean| /
        training std over each window's per-window inputs (the window features and the slope
        error; 0 for a model without them): how far outside its training data the network
        extrapolates (B,)."""
        x = self._normalised_inputs(windows, slope_error_deg)
        per_window = x[:, 0, self.spec.n_features:]
        distance = np.abs(per_window).max(axis=1) if per_window.shape[1] else np.zeros(x.shape[0])
        return self._network_mass(x), distance

    def _network_mass(self, x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            out = self.network(torch.as_tensor(x, dtype=torch.float32)).double().numpy()
        return out * self.mass_std + self.mass_mean

    def confidence(self, tau_features: np.ndarray) -> np.ndarray:
        """tau of Eq. (19) for x' = [F_t, a_x, v_x, alpha] (..., 4)."""
        return confidence_level(tau_features, self.tau_mean, self.tau_cov)

    # ------------------------------------------------------------------ files
    def tensors(self) -> dict[str, torch.Tensor]:
        out = {f"net.{k}": v.detach().clone().contiguous() for k, v in self.network.state_dict().items()}
        out["norm.feature_mean"] = torch.as_tensor(self.feature_mean, dtype=torch.float64)
        out["norm.feature_std"] = torch.as_tensor(self.feature_std, dtype=torch.float64)
        out["norm.mass_mean_std"] = torch.tensor([self.mass_mean, self.mass_std], dtype=torch.float64)
        out["tau.mean"] = torch.as_tensor(self.tau_mean, dtype=torch.float64)
        out["tau.cov"] = torch.as_tensor(self.tau_cov, dtype=torch.float64)
        return out

    def save(self, stem: str | Path) -> tuple[Path, Path]:
        """Write ``<stem>.safetensors`` and ``<stem>.json``; returns both paths."""
        from safetensors.torch import save_file

        stem = Path(stem)
        stem.parent.mkdir(parents=True, exist_ok=True)
        weights, meta = stem.with_suffix(".safetensors"), stem.with_suffix(".json")
        save_file(self.tensors(), str(weights))
        weights.chmod(0o644)          # package data: readable by every user, like the JSON
        doc = {"format": "vehicle_estimation.mass_model", "version": FORMAT_VERSION,
               "spec": dataclasses.asdict(self.spec), "nn_features": list(NN_FEATURES),
               "network_inputs": list(self.spec.input_names),
               "tau_features": list(TAU_FEATURES),
               "validation_rel_rmse": float(self.validation_rel_rmse),
               "weights_sha256": hashlib.sha256(weights.read_bytes()).hexdigest(),
               "metadata": self.metadata}
        meta.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        return weights, meta

    @classmethod
    def load(cls, stem: str | Path) -> MassModel:
        """Load ``<stem>.safetensors`` + ``<stem>.json`` without unpickling anything.

        ``ValueError`` (naming the problem) for a missing or malformed JSON, a tensor file
        whose SHA-256 differs from the JSON's, a missing/unexpected tensor, a wrong shape or
        dtype, or a non-finite value, or a tau covariance that is not positive definite."""
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        stem = Path(stem)
        if stem.suffix in (".json", ".safetensors"):
            stem = stem.with_suffix("")
        weights, meta = stem.with_suffix(".safetensors"), stem.with_suffix(".json")
        try:
            doc = json.loads(meta.read_text(encoding="utf-8"))
            blob = weights.read_bytes()
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ValueError(f"cannot read mass model {stem}: {exc}") from None
        if not isinstance(doc, dict) or doc.get("format") != "vehicle_estimation.mass_model" \
                or doc.get("version") != FORMAT_VERSION:
            raise ValueError(f"{meta}: not a vehicle_estimation mass model (format/version)")
        if doc.get("nn_features") != list(NN_FEATURES) or doc.get("tau_features") != list(TAU_FEATURES):
            raise ValueError(f"{meta}: feature layout differs from this code's Eq. (15)/(16) features")
        if hashlib.sha256(blob).hexdigest() != doc.get("weights_sha256"):
            raise ValueError(f"{weights}: SHA-256 differs from the one in {meta.name} (file altered?)")
        try:
            spec_doc = doc["spec"]
            # a field newer than the file (an optional input) takes its default: the file's layout
            spec = ModelSpec(**{f.name: spec_doc[f.name] for f in dataclasses.fields(ModelSpec)
                                if f.name in spec_doc or f.default is dataclasses.MISSING})
            spec.validate()
            rel = float(doc["validation_rel_rmse"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{meta}: bad model spec: {exc}") from None
        if not (math.isfinite(rel) and rel > 0.0):
            raise ValueError(f"{meta}: validation_rel_rmse must be finite and > 0, got {rel!r}")
        if doc.get("network_inputs", list(spec.input_names)) != list(spec.input_names):
            raise ValueError(f"{meta}: network inputs {doc['network_inputs']} differ from this code's "
                             f"{list(spec.input_names)} for that spec")
        try:
            tensors = load_file(str(weights))
        except (SafetensorError, OSError, ValueError) as exc:
            raise ValueError(f"{weights}: not a readable safetensors file: {exc}") from None
        network = build_network(spec)
        expected = {f"net.{k}": (tuple(v.shape), v.dtype) for k, v in network.state_dict().items()}
        expected.update({k: (s, torch.float64) for k, s in _extra_shapes(spec).items()})
        missing, unexpected = set(expected) - set(tensors), set(tensors) - set(expected)
        if missing or unexpected:
            raise ValueError(f"{weights}: tensor names differ (missing {sorted(missing)[:5]}, "
                             f"unexpected {sorted(unexpected)[:5]})")
        for name, (shape, dtype) in expected.items():
            value = tensors[name]
            if tuple(value.shape) != shape or value.dtype != dtype:
                raise ValueError(f"{weights}: tensor {name} is {tuple(value.shape)} {value.dtype}, "
                                 f"expected {shape} {dtype}")
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise ValueError(f"{weights}: tensor {name} has non-finite values")
        network.load_state_dict({k[4:]: v for k, v in tensors.items() if k.startswith("net.")}, strict=True)
        std = tensors["norm.feature_std"].numpy()
        mass_mean, mass_std = (float(v) for v in tensors["norm.mass_mean_std"].numpy())
        if not (np.all(std > 0.0) and mass_std > 0.0 and mass_mean > 0.0):
            raise ValueError(f"{weights}: normalisation scales must be > 0")
        cov = tensors["tau.cov"].numpy()
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise ValueError(f"{weights}: tau covariance is not positive definite") from None
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
            raise ValueError(f"{weights}: tau covariance is not symmetric")
        return cls(spec=spec, network=network, feature_mean=tensors["norm.feature_mean"].numpy(),
                   feature_std=std, mass_mean=mass_mean, mass_std=mass_std,
                   tau_mean=tensors["tau.mean"].numpy(), tau_cov=cov, validation_rel_rmse=rel,
                   metadata=dict(doc.get("metadata") or {}))
