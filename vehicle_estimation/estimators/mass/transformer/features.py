"""Paper 000's inputs: the network features of Eq. (15) in blocks, and the confidence tau of
Eqs. (16)-(19). Shared by the TA-AEKF (``ta_aekf``), its network (``transformer.model``) and
the training data (``training.truck_data``), so that training and use cannot differ.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from vehicle_estimation.contract.vehicle import VehicleParams

#: Names of the tau features x' of Eq. (16): F_t [N], a_x [m/s^2], v_x [m/s], alpha [rad].
TAU_FEATURES = ("F_t", "a_x", "v_x", "alpha")
#: Names of the network input features of Eq. (15): F_t [N], F_w [N], delta a_x [m/s^2],
#: (f cos(alpha) + sin(alpha)) g [m/s^2], v_x [km/h] (the paper's unit).
NN_FEATURES = ("F_t", "F_w", "delta_a_x", "g_f_cos_plus_sin", "v_x_kmh")


# --------------------------------------------------------------------- tau, Eqs. (16)-(19)
def fit_confidence_gaussian(samples: np.ndarray, ridge: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """mu and Sigma of Eq. (16) from training samples x' (N, n): the sample mean and the
    (ddof = 1) covariance, with ``ridge`` x its diagonal added so that it is invertible."""
    x = np.asarray(samples, dtype=float)
    if x.ndim != 2 or x.shape[0] < x.shape[1] + 1:
        raise ValueError(f"need (N, n) samples with N > n, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("confidence samples must be finite")
    mu = x.mean(axis=0)
    cov = np.cov(x, rowvar=False, ddof=1)
    cov = cov + ridge * np.diag(np.diag(cov))
    np.linalg.cholesky(cov)          # raises LinAlgError when not positive definite
    return mu, cov


def _mahalanobis_sq(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    d = np.asarray(x, dtype=float) - np.asarray(mean, dtype=float)
    chol = np.linalg.cholesky(np.asarray(cov, dtype=float))
    z = np.linalg.solve(chol, d[..., None])[..., 0] if d.ndim > 1 else np.linalg.solve(chol, d)
    return np.sum(z * z, axis=-1)


def gaussian_density(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """p(x'; mu, Sigma), Eqs. (16)/(18); x may be (n,) or (..., n)."""
    return peak_density(cov) * np.exp(-0.5 * _mahalanobis_sq(x, mean, cov))


def peak_density(cov: np.ndarray) -> float:
    """p_max = 1 / ((2 pi)^(n/2) |Sigma|^(1/2)), Eq. (17), the density at mu."""
    c = np.asarray(cov, dtype=float)
    n = c.shape[0]
    sign, logdet = np.linalg.slogdet(c)
    if sign <= 0:
        raise ValueError("covariance must be positive definite")
    return float(np.exp(-0.5 * n * math.log(2.0 * math.pi) - 0.5 * logdet))


def confidence_level(x: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """tau = p(x') / p_max = exp(-1/2 (x' - mu)^T Sigma^-1 (x' - mu)), Eq. (19), in (0, 1].

    Computed from the Mahalanobis distance directly (not as a ratio of densities, whose
    factors cancel), so it does not underflow before the exponential itself does."""
    return np.exp(-0.5 * _mahalanobis_sq(x, mean, cov))


# --------------------------------------------------------------------- features, Eq. (15)
def eq15_features(force: float, v: float, ax: float, slope: float, params: VehicleParams,
                  delta: float) -> tuple[float, float, float, float, float]:
    """A_input of Eq. (15) for one sample: [F_t, F_w, delta a_x, (f cos + sin) g, v_x (km/h)]."""
    p = params
    drag = 0.5 * p.air_density * p.drag_area * v * abs(v)
    grade = p.gravity * (p.rolling_resistance * math.cos(slope) + math.sin(slope))
    return (force, drag, delta * ax, grade, 3.6 * v)


class FeatureBlocks:
    """Block means of the Eq. (15) features and of x' (Eq. 16), and a window of the last
    ``window`` blocks.

    The paper feeds the network every 0.01 s sample; here ``block_steps`` consecutive samples
    are averaged first (0.1 s by default) so that a window of a few tokens spans a second
    or more, the wheel-speed derivative noise in a_x averages down, and one network call per
    block carries all the information the samples have. The same class builds the training
    windows (:mod:`vehicle_estimation.training.truck_data`), so training and use cannot differ.
    """

    def __init__(self, block_steps: int, window: int) -> None:
        self.block_steps = int(block_steps)
        self.window = int(window)
        self.clear()

    def clear(self) -> None:
        self._sum_nn = np.zeros(len(NN_FEATURES))
        self._sum_tau = np.zeros(len(TAU_FEATURES))
        self._count = 0
        self.blocks: collections.deque[np.ndarray] = collections.deque(maxlen=self.window)
        self.last_tau_features = np.full(len(TAU_FEATURES), np.nan)

    def add(self, nn_features: tuple[float, ...], tau_features: tuple[float, ...]) -> bool:
        """Add one sample; True when it completed a block."""
        self._sum_nn += nn_features
        self._sum_tau += tau_features
        self._count += 1
        if self._count < self.block_steps:
            return False
        self.blocks.append(self._sum_nn / self._count)
        self.last_tau_features = self._sum_tau / self._count
        self._sum_nn[:] = 0.0
        self._sum_tau[:] = 0.0
        self._count = 0
        return True

    @property
    def full(self) -> bool:
        return len(self.blocks) == self.window

    def array(self) -> np.ndarray:
        """The window (window, 5), oldest block first."""
        return np.stack(list(self.blocks))
