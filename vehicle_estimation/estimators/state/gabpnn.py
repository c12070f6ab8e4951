"""GA-optimised BP network that corrects the UKF output (paper 002 Secs. 3.1-3.2, Eq. 5).

Liu, Cui, Peng 2023 (J. Vibroengineering, doi 10.21595/jve.2023.23441):

* :class:`BPNetwork`: the 2-5-1 back-propagation network of Sec. 4.1 ("2 nodes in the input
  layer, 5 in the hidden layer and 1 in the output layer"), tanh hidden layer and linear output
  (MATLAB's ``tansig``/``purelin``), weights and thresholds (biases), trained by
  :func:`train_bp`: full-batch gradient descent with momentum and an adaptive learning rate.
* :func:`genetic_initialisation`: the genetic algorithm of Sec. 3.1 that searches the initial
  weights and thresholds. Fitness is Eq. 4, ``E = sum (T_i - Y_i)^2`` of the network with those
  weights (smaller is better; the roulette uses ``1 / E``). Selection is the IMPROVED roulette
  (Steps 1-4): a drawn individual leaves the pool, so ``N/2`` distinct parents are drawn
  (:func:`improved_roulette`); arithmetic crossover and Gaussian mutation refill the population;
  the best individual is kept.
* :class:`BPCorrection`: one network per corrected state (``vx``, ``vy``, ``r``: the network has
  one output, the paper corrects all three). Input (Sec. 3.2 Steps 1-3): the UKF's state
  correction ``X_k|k - X_k|k-1`` of that state, per unit time; the network's two inputs are
  that rate low-passed with two time constants (``feature_tau_s``: 0.1 s, and the paper's
  running interval of 1 s) so that the mapping does not depend on the IMU rate and is not
  swamped by per-sample noise. Output: ``B_perr``, the UKF error ``X_true - X_k|k`` (Step 2),
  added to the UKF output by Eq. 5, clipped to the range seen in training.
* :func:`save_correction` / :func:`load_correction`: ``.npz`` without pickle
  (``allow_pickle=False``); loading checks every name, shape and value and raises a
  ``ValueError`` that says what is wrong.
"""

from __future__ import annotations

import dataclasses
import math
import zipfile
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
from vehicle_estimation.paths import MODELS_DIR

__all__ = [
    "BPNetwork", "BPCorrection", "TrainResult", "FORMAT", "N_HIDDEN", "N_INPUT", "STATES",
    "default_weights_path", "genetic_initialisation", "improved_roulette", "load_correction", "save_correction", "train_bp",
    "train_gabp",
]

N_INPUT, N_HIDDEN = 2, 5
STATES = ("vx", "vy", "r")
FORMAT = "vehicle_estimation.gabpnn.v1"
#: Shipped weights live in the package (``vehicle_estimation/models``), one file per vehicle.
N_GENES = N_HIDDEN * N_INPUT + N_HIDDEN + N_HIDDEN + 1   # 21 weights and thresholds


@dataclasses.dataclass
class BPNetwork:
    """2-5-1 network ``y = w2 . tanh(W1 u + b1) + b2`` (weights ``W1``, ``w2``; thresholds
    ``b1``, ``b2``)."""

    w1: np.ndarray   # (5, 2)
    b1: np.ndarray   # (5,)
    w2: np.ndarray   # (5,)
    b2: float

    @classmethod
    def from_vector(cls, genes: np.ndarray) -> "BPNetwork":
        g = np.asarray(genes, dtype=float).reshape(N_GENES)
        i = N_HIDDEN * N_INPUT
        return cls(g[:i].reshape(N_HIDDEN, N_INPUT).copy(), g[i:i + N_HIDDEN].copy(),
                   g[i + N_HIDDEN:i + 2 * N_HIDDEN].copy(), float(g[-1]))

    def to_vector(self) -> np.ndarray:
        return np.concatenate([self.w1.ravel(), self.b1, self.w2, [self.b2]])

    def forward(self, u: np.ndarray) -> np.ndarray:
        """Outputs for inputs ``u`` of shape ``(N, 2)`` (or ``(2,)``)."""
        u = np.asarray(u, dtype=float)
        return np.tanh(u @ self.w1.T + self.b1) @ self.w2 + self.b2

    def copy(self) -> "BPNetwork":
        return BPNetwork.from_vector(self.to_vector())


def _batch_forward(genes: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Outputs of a population ``genes (P, 21)`` on ``u (N, 2)``: ``(P, N)``."""
    i = N_HIDDEN * N_INPUT
    w1 = genes[:, :i].reshape(-1, N_HIDDEN, N_INPUT)
    b1 = genes[:, i:i + N_HIDDEN]
    w2 = genes[:, i + N_HIDDEN:i + 2 * N_HIDDEN]
    b2 = genes[:, -1]
    hidden = np.tanh(np.einsum("pkj,nj->pnk", w1, u) + b1[:, None, :])
    return np.einsum("pnk,pk->pn", hidden, w2) + b2[:, None]


def sum_squared_error(genes: np.ndarray, u: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Eq. 4, ``E = sum_i (T_i - Y_i)^2``, for each individual of ``genes (P, 21)``."""
    return np.sum((_batch_forward(np.atleast_2d(genes), u) - target[None, :]) ** 2, axis=1)


def improved_roulette(fitness: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Sec. 3.1 Steps 1-4: ``count`` distinct indices drawn by roulette on ``fitness`` (larger
    is better); each drawn individual is removed from the pool before the next draw."""
    fitness = np.asarray(fitness, dtype=float)
    if count > fitness.size:
        raise ValueError(f"cannot draw {count} distinct parents from {fitness.size} individuals")
    pool = list(range(fitness.size))
    chosen: list[int] = []
    for _ in range(count):
        w = np.maximum(fitness[pool], 0.0)
        S = float(w.sum())                                  # Step 1
        if not S > 0.0 or not math.isfinite(S):
            pick = int(rng.integers(len(pool)))
        else:
            M = rng.uniform(0.0, S)                         # Step 2
            pick = int(np.searchsorted(np.cumsum(w), M, side="right"))   # Step 3
            pick = min(pick, len(pool) - 1)
        chosen.append(pool.pop(pick))                       # Step 4
    return np.asarray(chosen, dtype=int)


def genetic_initialisation(u: np.ndarray, target: np.ndarray, rng: np.random.Generator, *,
                           population: int = 40, generations: int = 30, crossover_rate: float = 0.8,
                           mutation_rate: float = 0.1, mutation_scale: float = 0.3, init_scale: float = 1.0,
                           progress: Optional[Callable[[int, float], None]] = None) -> tuple[np.ndarray, list[float]]:
    """GA over the 21 initial weights and thresholds (Sec. 3.1). Returns the best chromosome
    and the best Eq.-4 error of every generation."""
    if population < 4 or population % 2:
        raise ValueError(f"population must be an even number >= 4, got {population}")
    pop = rng.uniform(-init_scale, init_scale, (population, N_GENES))
    err = sum_squared_error(pop, u, target)
    history = [float(err.min())]
    best, best_err = pop[int(np.argmin(err))].copy(), float(err.min())
    for gen in range(generations):
        parents = pop[improved_roulette(1.0 / np.maximum(err, 1e-300), population // 2, rng)]
        order = rng.permutation(parents.shape[0])
        children: list[np.ndarray] = []
        for a, b in zip(order[0::2], order[1::2]):
            p1, p2 = parents[a], parents[b]
            if rng.random() < crossover_rate:
                lam = rng.random()
                c1, c2 = lam * p1 + (1.0 - lam) * p2, (1.0 - lam) * p1 + lam * p2
            else:
                c1, c2 = p1.copy(), p2.copy()
            children.extend((c1, c2))
        kids = np.asarray(children)
        if kids.shape[0] < population - parents.shape[0]:   # odd parent count: clone to fill
            kids = np.concatenate([kids, parents[: population - parents.shape[0] - kids.shape[0]]])
        mutate = rng.random(kids.shape) < mutation_rate
        kids = kids + mutate * rng.normal(0.0, mutation_scale, kids.shape)
        pop = np.concatenate([parents, kids])
        err = sum_squared_error(pop, u, target)
        worst = int(np.argmax(err))
        pop[worst], err[worst] = best, best_err            # elitism: the best survives
        i_best = int(np.argmin(err))
        if err[i_best] < best_err:
            best, best_err = pop[i_best].copy(), float(err[i_best])
        history.append(best_err)
        if progress is not None:
            progress(gen + 1, best_err)
    return best, history


def train_bp(net: BPNetwork, u: np.ndarray, target: np.ndarray, *, epochs: int = 300, lr: float = 0.05,
             momentum: float = 0.9, lr_up: float = 1.05, lr_down: float = 0.5, max_increase: float = 1.0) -> list[float]:
    """Back-propagation (full batch, momentum, adaptive learning rate like MATLAB ``traingdx``)
    on the mean squared error; trains ``net`` in place and returns the loss per epoch."""
    n = u.shape[0]
    theta = net.to_vector()
    velocity = np.zeros_like(theta)

    def loss_grad(th: np.ndarray) -> tuple[float, np.ndarray]:
        k = N_HIDDEN * N_INPUT
        w1 = th[:k].reshape(N_HIDDEN, N_INPUT)
        b1, w2, b2 = th[k:k + N_HIDDEN], th[k + N_HIDDEN:k + 2 * N_HIDDEN], th[-1]
        hidden = np.tanh(u @ w1.T + b1)
        resid = hidden @ w2 + b2 - target
        g_out = 2.0 * resid / n
        g_hidden = np.outer(g_out, w2) * (1.0 - hidden * hidden)
        grad = np.concatenate([(g_hidden.T @ u).ravel(), g_hidden.sum(axis=0), hidden.T @ g_out, [g_out.sum()]])
        return float(np.mean(resid * resid)), grad

    loss, grad = loss_grad(theta)
    history = [loss]
    for _ in range(epochs):
        step = momentum * velocity - lr * grad
        trial = theta + step
        trial_loss, trial_grad = loss_grad(trial)
        if trial_loss > loss * max_increase or not math.isfinite(trial_loss):
            lr *= lr_down
            velocity = np.zeros_like(theta)
        else:
            theta, loss, grad, velocity = trial, trial_loss, trial_grad, step
            if trial_loss < history[-1]:
                lr *= lr_up
        history.append(loss)
    trained = BPNetwork.from_vector(theta)
    net.w1, net.b1, net.w2, net.b2 = trained.w1, trained.b1, trained.w2, trained.b2
    return history


@dataclasses.dataclass
class TrainResult:
    network: BPNetwork
    ga_history: list[float]
    bp_history: list[float]


def train_gabp(u: np.ndarray, target: np.ndarray, rng: np.random.Generator, *, ga_samples: int = 4000,
               epochs: int = 300, use_ga: bool = True, progress: Optional[Callable[[str], None]] = None,
               **ga_kwargs) -> TrainResult:
    """GA initialisation (on at most ``ga_samples`` samples) then BP training on all of ``u``
    (``use_ga=False``: the same BP from random initial weights, the paper's contrast)."""
    u = np.asarray(u, dtype=float)
    target = np.asarray(target, dtype=float)
    if use_ga:
        sub = rng.choice(u.shape[0], size=min(ga_samples, u.shape[0]), replace=False)

        def report(gen: int, e: float) -> None:
            if progress is not None and (gen % 10 == 0):
                progress(f"GA generation {gen}: E = {e:.4g} (mean sq. {e / sub.size:.4g})")

        genes, ga_history = genetic_initialisation(u[sub], target[sub], rng, progress=report, **ga_kwargs)
    else:
        genes = rng.uniform(-ga_kwargs.get("init_scale", 1.0), ga_kwargs.get("init_scale", 1.0), N_GENES)
        ga_history = []
    net = BPNetwork.from_vector(genes)
    bp_history = train_bp(net, u, target, epochs=epochs)
    return TrainResult(net, ga_history, bp_history)


# ========================================================================================
class BPCorrection:
    """Eq. 5 output correction: ``X' = X_k|k + B_perr`` with one :class:`BPNetwork` per state.

    :meth:`step` takes the UKF state correction ``X_k|k - X_k|k-1`` of every sample, updates
    the two low-passed correction rates per state (time constants ``feature_tau_s``) and
    returns ``B_perr`` (3,), zeros until ``warmup_s`` of features have been seen.

    Args:
        networks: one network per name of :data:`STATES`.
        input_mean, input_std: ``(3, 2)`` normalisation of the network inputs.
        output_scale: ``(3,)`` network output -> error [state units].
        output_clip: ``(3,)`` largest ``|B_perr|`` (the range of the training errors).
        feature_tau_s: ``(2,)`` time constants of the two inputs [s].
    """

    def __init__(self, networks: dict[str, BPNetwork], input_mean, input_std, output_scale, output_clip,
                 feature_tau_s: Sequence[float] | np.ndarray = (0.1, 1.0), warmup_s: float = 1.0):
        self.networks = {k: networks[k] for k in STATES}
        self.input_mean = np.asarray(input_mean, dtype=float).reshape(3, N_INPUT)
        self.input_std = np.asarray(input_std, dtype=float).reshape(3, N_INPUT)
        self.output_scale = np.asarray(output_scale, dtype=float).reshape(3)
        self.output_clip = np.asarray(output_clip, dtype=float).reshape(3)
        self.feature_tau_s = np.asarray(feature_tau_s, dtype=float).reshape(N_INPUT)
        self.warmup_s = float(warmup_s)
        self.reset()

    def fresh(self) -> "BPCorrection":
        """A copy with its own (reset) feature history, same networks."""
        return BPCorrection(self.networks, self.input_mean, self.input_std, self.output_scale,
                            self.output_clip, self.feature_tau_s, self.warmup_s)

    def reset(self) -> None:
        self._t: Optional[float] = None
        self._t0: Optional[float] = None
        self._features = np.zeros((3, N_INPUT))

    @property
    def features(self) -> np.ndarray:
        """Current ``(3, 2)`` inputs before normalisation (correction rates [state unit/s])."""
        return self._features.copy()

    def update_features(self, t: float, correction: np.ndarray) -> bool:
        """Low-pass the correction rate ``correction / dt``; False (unchanged) for a bad sample."""
        correction = np.asarray(correction, dtype=float).reshape(3)
        if self._t is None:
            self._t = self._t0 = float(t)
            return False
        dt = float(t) - self._t
        if not (dt > 0.0 and math.isfinite(dt) and np.all(np.isfinite(correction))):
            return False
        self._t = float(t)
        a = 1.0 - np.exp(-dt / self.feature_tau_s)              # per time constant
        rate = correction / dt
        self._features += (rate[:, None] - self._features) * a[None, :]
        return True

    def predict(self, features: np.ndarray) -> np.ndarray:
        """``B_perr`` for feature rows ``(N, 3, 2)`` or ``(3, 2)``: shape ``(N, 3)`` / ``(3,)``."""
        f = np.asarray(features, dtype=float)
        single = f.ndim == 2
        f = f.reshape(-1, 3, N_INPUT)
        u = (f - self.input_mean) / self.input_std
        out = np.stack([self.networks[k].forward(u[:, j]) for j, k in enumerate(STATES)], axis=1)
        out = np.clip(out * self.output_scale, -self.output_clip, self.output_clip)
        return out[0] if single else out

    def step(self, t: float, correction: np.ndarray) -> np.ndarray:
        """Feed one UKF correction ``X_k|k - X_k|k-1``; returns ``B_perr`` (Eq. 5)."""
        self.update_features(t, correction)
        if self._t is None or self._t0 is None or self._t - self._t0 < self.warmup_s:
            return np.zeros(3)
        return self.predict(self._features)


# ----------------------------------------------------------------------------------------
def default_weights_path(vehicle: str = "sedan_d_class") -> Path:
    """The shipped weights for ``vehicle``: ``vehicle_estimation/models/gabpnn_<vehicle>.npz``."""
    return MODELS_DIR / f"gabpnn_{vehicle}.npz"


def _expected_shapes() -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {
        "input_mean": (3, N_INPUT), "input_std": (3, N_INPUT), "output_scale": (3,), "output_clip": (3,),
        "feature_tau_s": (N_INPUT,), "warmup_s": (),
    }
    for k in STATES:
        shapes.update({f"{k}_w1": (N_HIDDEN, N_INPUT), f"{k}_b1": (N_HIDDEN,), f"{k}_w2": (N_HIDDEN,), f"{k}_b2": ()})
    return shapes


def save_correction(correction: BPCorrection, path: str | Path, **metadata: str) -> None:
    """Write ``correction`` to ``path`` (``.npz``, plain arrays only; ``metadata`` as strings)."""
    arrays: dict[str, np.ndarray] = {
        "format": np.array(FORMAT), "states": np.array(STATES),
        "input_mean": correction.input_mean, "input_std": correction.input_std,
        "output_scale": correction.output_scale, "output_clip": correction.output_clip,
        "feature_tau_s": correction.feature_tau_s, "warmup_s": np.array(correction.warmup_s),
    }
    for k, net in correction.networks.items():
        arrays.update({f"{k}_w1": net.w1, f"{k}_b1": net.b1, f"{k}_w2": net.w2, f"{k}_b2": np.array(net.b2)})
    for key, value in metadata.items():
        arrays[f"meta_{key}"] = np.array(str(value))
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)  # type: ignore[arg-type]  # numpy stub: kwds are arrays


def load_correction(path: str | Path) -> BPCorrection:
    """Read a file written by :func:`save_correction`, never unpickling anything.

    Raises ``ValueError`` naming the problem: not an npz / object arrays, wrong format tag,
    missing or unexpected arrays, wrong shapes, non-finite values, non-positive scales."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path}: cannot read GA-BPNN weights: {exc}") from None
    except ValueError as exc:    # object arrays need pickle: refused
        raise ValueError(f"{path}: not a plain-array GA-BPNN weights file: {exc}") from None
    if "format" not in arrays or str(arrays["format"]) != FORMAT:
        raise ValueError(f"{path}: format tag is {arrays.get('format')!r}, expected {FORMAT!r}")
    if "states" not in arrays or tuple(str(s) for s in arrays["states"]) != STATES:
        raise ValueError(f"{path}: states must be {STATES}")
    shapes = _expected_shapes()
    missing = sorted(set(shapes) - set(arrays))
    if missing:
        raise ValueError(f"{path}: missing arrays {missing}")
    unexpected = sorted(k for k in arrays if k not in shapes and k not in ("format", "states")
                        and not k.startswith("meta_"))
    if unexpected:
        raise ValueError(f"{path}: unexpected arrays {unexpected}")
    values: dict[str, np.ndarray] = {}
    for key, shape in shapes.items():
        a = arrays[key]
        if a.dtype.kind not in "fi":
            raise ValueError(f"{path}: {key} must be numeric, got dtype {a.dtype}")
        if a.shape != shape:
            raise ValueError(f"{path}: {key} has shape {a.shape}, expected {shape}")
        a = a.astype(float)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: {key} has non-finite values")
        values[key] = a
    for key in ("input_std", "output_scale", "feature_tau_s"):
        if not np.all(values[key] > 0.0):
            raise ValueError(f"{path}: {key} must be positive")
    if not np.all(values["output_clip"] >= 0.0) or values["warmup_s"] < 0.0:
        raise ValueError(f"{path}: output_clip and warmup_s must be >= 0")
    nets = {k: BPNetwork(values[f"{k}_w1"], values[f"{k}_b1"], values[f"{k}_w2"], float(values[f"{k}_b2"]))
            for k in STATES}
    return BPCorrection(nets, values["input_mean"], values["input_std"], values["output_scale"],
                        values["output_clip"], values["feature_tau_s"], float(values["warmup_s"]))
