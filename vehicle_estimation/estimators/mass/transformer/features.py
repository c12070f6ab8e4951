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
#: Window-level inputs beside Eq. (15) (``ModelSpec.window_features``; not in the paper), appended
#: to every block of a window: two estimates of the inverse mass 1/m [1/(10 t)] from Eq. (14)
#: over the window, the speed gain plus integrated grade [m/s] and the RMS of delta a_x + grade
#: [m/s^2] they rest on, and the mean net force [10 kN]. See :func:`window_features`.
WINDOW_FEATURES = ("inverse_mass_integral", "inverse_mass_regression", "speed_gain_plus_grade",
                   "rms_acceleration_demand", "mean_net_force")
#: The stated RMS error of the slope input [deg] (``ModelSpec.slope_error_input``), appended to
#: every block: one network for an exact slope (the paper's setting) and for a slope estimate.
SLOPE_ERROR_FEATURE = "slope_error_deg"
#: 1/m is given in 1/(10 t) and clipped to +-INVERSE_MASS_CLIP (a window without drive force).
INVERSE_MASS_UNIT = 1.0e4
INVERSE_MASS_CLIP = 5.0


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


def window_features(windows: np.ndarray, block_s: float) -> np.ndarray:
    """:data:`WINDOW_FEATURES` of raw Eq. (15) windows (B, w, 5) whose blocks are ``block_s``
    apart: (B, 5).

    Eq. (14) over a window, m (delta a + G) = F_t - F_w with G = g (f cos alpha + sin alpha),
    integrated between the first and the last block: m (v_w - v_1 + int G dt) = int (F_t - F_w) dt.
    The integral needs no differentiated speed (a_x of a wheel speed is the noisiest input:
    with it, least squares over a 1 s window of error-free data is 10 % off, with the true
    a_x 4 %), and it is written for 1/m, with the noisy speed and grade in the numerator and the
    well-measured force in the denominator: bounded where the excitation is small, and without
    the errors-in-variables bias a regression for m would have. The second estimate regresses
    delta a + G on F block by block (1/m = sum F phi / sum F^2)."""
    w = np.asarray(windows, dtype=float)
    force = w[..., 0] - w[..., 1]
    grade, demand = w[..., 3], w[..., 2] + w[..., 3]
    speed = w[..., 4] / 3.6
    force_integral = block_s * 0.5 * (force[:, 1:] + force[:, :-1]).sum(axis=1)
    gain = speed[:, -1] - speed[:, 0] + block_s * 0.5 * (grade[:, 1:] + grade[:, :-1]).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_integral = gain / force_integral * INVERSE_MASS_UNIT
        inverse_regression = (force * demand).sum(axis=1) / (force * force).sum(axis=1) * INVERSE_MASS_UNIT
    span = max(w.shape[1] - 1, 1) * block_s
    out = np.stack([inverse_integral, inverse_regression, gain, np.sqrt(np.mean(demand * demand, axis=1)),
                    force_integral / span / INVERSE_MASS_UNIT], axis=1)
    out[:, :2] = np.clip(np.nan_to_num(out[:, :2], nan=0.0), -INVERSE_MASS_CLIP, INVERSE_MASS_CLIP)
    return out


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
