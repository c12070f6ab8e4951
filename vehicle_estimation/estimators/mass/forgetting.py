"""What the least-squares mass estimators share: the scalar RLS with forgetting of paper 003
Eqs. (7)-(9), its tuning, and the mass estimate built on it (variance, convergence flag,
clipped output, rejection counters, persistence).

Paper 003's RLS (:mod:`~vehicle_estimation.estimators.mass.mass_rls`) and paper 004's FFRLS
(:mod:`~vehicle_estimation.estimators.mass.mass_ffrls`) differ only in what they regress
and which samples they take; everything here they have in common. Pure Python, no ROS.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common.guard import finite_number


@dataclasses.dataclass
class ForgettingConfig:
    """The tuning every forgetting least-squares mass estimator has (SI units). Subclasses
    set the paper's values as their defaults."""

    forgetting_factor: float = setting(0.9995, "Forgetting factor lambda of the RLS",
                                       low=0.0, high=1.0, low_open=True)
    initial_mass: float = setting(1000.0, "Initial mass estimate m(0) [kg]", low=0.0, low_open=True)
    initial_gain: float = setting(1000.0, "Initial RLS gain p(0) [s^4/m^2]", low=0.0, low_open=True)
    min_speed: float = setting(2.0, "Samples below this speed are not used [m/s]", low=0.0)
    max_abs_slope: float = setting(0.15, "Samples on a steeper grade are not used [rad]",
                                   low=0.0, high=math.pi / 2, high_open=True)
    convergence_window: int = setting(200, "Converged when the last this many accepted updates agree",
                                      low=2)
    convergence_max_cv: float = setting(0.01, "Converged only if std/mean of the estimates in the window is "
                                        "below this", low=0.0, low_open=True)
    convergence_max_rel_change: float = setting(0.01, "Converged only if |last - first| / mean over the "
                                                "window is below this", low=0.0, low_open=True)
    # Not in the papers: the stability window above needs 200 accepted updates (minutes of
    # driving); a controller can use an estimate much earlier if the variance says how good it is.
    convergence_max_rel_std: float = setting(
        0.0, "Also converged once the published sigma is at most this share of the mass, after "
        "convergence_min_updates updates (0 = off: the stability window alone)", low=0.0, high=1.0)
    convergence_min_updates: int = setting(20, "Updates before the sigma rule may flag convergence", low=1)
    # Not in the papers: the stability window flags an estimate that has stopped moving, which on a
    # drive that cannot separate the mass from the road load (a truck cruising without GNSS: sigma
    # 27 %) is a stable wrong value. A controller reads the flag as "usable".
    convergence_max_rel_sigma: float = setting(
        0.0, "Never converged while the published sigma exceeds this share of the mass, whichever rule "
        "(0 = no bound: the paper's stability window alone)", low=0.0, high=1.0)
    # Not in the papers: regression calibration of the window acceleration (see
    # ForgettingMassEstimator._calibrated_accel); 0 keeps the measured acceleration as it is.
    accel_calibration_time_s: float = setting(
        120.0, "Time constant of the running mean and variance of the moving windows' accelerations for "
        "their regression calibration [s] (0 = off: the measured acceleration as it is)", low=0.0)
    initial_residual_std: float = setting(500.0, "Prior sigma of the force residual for the variance [N]",
                                          low=0.0, low_open=True)
    # Not in the papers: the residuals' share of the variance, p sigma^2, holds for white
    # residuals; a calibrated torque map's error and the road load's are correlated over seconds
    # (paper 003's campaign: 0.9 between consecutive 4 Hz windows), and least squares averages
    # them out far less (ForgettingMassEstimator class docstring).
    correlated_residuals: bool = setting(
        True, "Widen the residuals' share of the variance by their correlation between consecutive "
        "samples, estimated online (false: the residuals taken as white)")
    min_mass: float = setting(300.0, "The published mass is clipped to [min_mass, max_mass] [kg]",
                              low=0.0, low_open=True)
    max_mass: float = setting(60000.0, "Upper clip of the published mass [kg]", low=0.0, low_open=True)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        check_settings(self)
        if self.min_mass >= self.max_mass:
            raise ValueError("min_mass must be below max_mass")


#: Consecutive residuals farther apart than this are no pair for their correlation [s].
MAX_RESIDUAL_PAIR_GAP_S = 1.0
#: Pairs of consecutive residuals before their correlation is used.
MIN_RESIDUAL_PAIRS = 40
#: Upper bound of that correlation (0.99: a variance at most 199 times the white one).
MAX_RESIDUAL_CORRELATION = 0.99


def _correlated_sum(spread: float, lever: float, u: float, lam: float, rho: float) -> tuple[float, float]:
    """One step of ``V_n = sum_j sum_k w_j w_k rho^|n_j - n_k|`` with ``w_k = lambda^(n-k) u_k``:
    ``(V_n, L_n)`` from ``(V_n-1, L_n-1)``, the lever ``L_n = sum_k w_k rho^(n-k)`` carrying the
    cross terms (``rho`` the correlation since the previous sample; 0: uncorrelated, V = sum w^2)."""
    carried = lam * rho * lever
    return lam * lam * spread + u * u + 2.0 * u * carried, carried + u


class RecursiveLeastSquares:
    """Scalar-parameter RLS with exponential forgetting, paper 003 Eqs. (7)-(9).

    Model ``phi·theta = y + eps``. One :meth:`update` does

    * eps  = y - phi·theta(t-1)                                          (Eq. 9)
    * p(t) = [p(t-1) - p(t-1)^2 phi^2 / (lambda + phi^2 p(t-1))] / lambda  (Eq. 7)
    * theta(t) = theta(t-1) + p(t)·phi·eps                               (Eq. 8)
    """

    def __init__(self, forgetting_factor: float, theta0: float, p0: float) -> None:
        lam = float(forgetting_factor)
        if not (math.isfinite(lam) and 0.0 < lam <= 1.0):
            raise ValueError(f"forgetting_factor must be in (0, 1], got {forgetting_factor!r}")
        if not (math.isfinite(p0) and p0 > 0.0):
            raise ValueError(f"p0 must be finite and > 0, got {p0!r}")
        if not math.isfinite(theta0):
            raise ValueError(f"theta0 must be finite, got {theta0!r}")
        self.forgetting_factor = lam
        self.theta = float(theta0)
        self.p = float(p0)
        self.last_residual = math.nan   # a-priori residual eps of Eq. (9)

    def update(self, phi: float, y: float) -> float:
        """Apply one sample; return the updated estimate theta(t)."""
        phi = float(phi)
        y = float(y)
        if not (math.isfinite(phi) and math.isfinite(y)):
            raise ValueError(f"RLS sample must be finite, got phi={phi!r}, y={y!r}")
        lam = self.forgetting_factor
        p_prev = self.p
        eps = y - phi * self.theta                                            # Eq. (9)
        self.p = (p_prev - (p_prev * phi * phi * p_prev) / (lam + phi * p_prev * phi)) / lam  # Eq. (7)
        self.theta = self.theta + self.p * phi * eps                          # Eq. (8)
        self.last_residual = eps
        return self.theta


class ForgettingMassEstimator:
    """What the least-squares mass estimators share (paper 003's RLS, paper 004's FFRLS): the
    scalar RLS with forgetting, the residual-variance and convergence statistics, the clipped
    output, the rejection counters and persistence. Subclasses set :attr:`REJECT_REASONS`,
    implement ``step`` and call :meth:`_accepted` after each update.

    Variance: ``p·sigma^2``, where p is the RLS gain (for unit-weighted least squares
    p ~ (sum lambda^k phi_k^2)^-1, so p·sigma^2 is the classical parameter variance) and
    sigma^2 an exponentially weighted (same lambda) mean of the squared a-priori residuals,
    seeded with ``initial_residual_std^2`` at weight one; plus the share of a lasting
    regressor error. The residuals cannot show an error that stays: an accelerometer bias
    that no GNSS has observed is in the fusion's grade, in the observer's slope and in the
    IMU acceleration alike, and biases the regressor phi by d_b on every sample. The estimate
    is then off by d_m = -m p sum(lambda^k phi_k d_b,k). With the bias variance the caller
    gives (``regressor_bias_variance``: the fusion's bias variance) and the bias error taken
    as a first-order Gauss-Markov process of correlation time tau
    (``regressor_bias_correlation_s``: infinite while no GNSS aids the fusion, which then holds
    its bias; seconds while GNSS keeps correcting it), that is a 'consider' term
    (m p)^2 V with V = sum_j sum_k w_j w_k rho^|t_j - t_k|, w_k = lambda^(n-k) |phi_k| sigma_b,k,
    computed recursively (|phi_k|: conservative where phi changes sign). Fully correlated
    (tau infinite) V = S^2 with S = sum w_k. Why it matters: on FASTSim's hills without GNSS
    the mass is 3 % off where p·sigma^2 alone says 0.2 %, and with GNSS the fully correlated
    term says 6x the error.

    Correlated residuals (``correlated_residuals``): p·sigma^2 is the variance for white
    residuals. Those of a calibrated torque map are not: its error depends on the operating
    point, which changes over seconds, and so does the road load's. With the residuals taken
    as an AR(1) sequence of correlation rho between consecutive accepted samples (estimated
    online from the a-priori residuals, exponentially weighted with lambda, clipped to
    [0, MAX_RESIDUAL_CORRELATION]: a negative estimate never narrows the variance), the
    weighted least squares' variance grows by F = sum_j sum_k w_j w_k rho^|j-k| / sum_k w_k^2,
    w_k = lambda^(n-k) phi_k (the Newey-West idea for a known correlation shape), computed by the
    recursion of the lasting term; p·sigma^2 becomes p·sigma^2·max(F, 1). Why: on paper 003's
    campaign the consecutive residuals correlate at 0.9, and the variance of their means over 50
    to 200 s is 15-19 times the white figure (AR(1) with 0.9: 19); taken as white, 81 % of the
    errors over its 22 drives lay within 2 sigma (NEES 2.1, 3 % of the flagged beyond 3 sigma).

    A calibration's own error (``lasting_force_sensitivity`` of :meth:`_accepted`) is the same
    on every sample of every drive: its mass error p sum(lambda^(n-k) phi_k dy_k) is exact, and
    enters the variance beside the regressor's (:attr:`bias_variance`). Paper 003's quick
    campaign (15-minute calibration): 61 % -> 85 % within 2 sigma with the map's scale alone,
    96 % with the fit's joint covariance.
    """

    REJECT_REASONS: tuple[str, ...] = ()
    #: The node feeds these estimators the means of each update window (paper 003's 4 Hz).
    steps_on_windows = True
    #: The window's brake-torque statistic: "max" (one braking sample spoils the window) or
    #: "mean" (the brake torque enters the regression).
    window_brake = "max"
    #: Whether :meth:`step` wants the vehicle's heading (the wind compensation).
    needs_heading = False
    #: The running statistics of the regression calibration need this much moving time [s] (20
    #: windows at 4 Hz) before they calibrate anything.
    calibration_warmup_s = 5.0

    def __init__(self, params: VehicleParams, config: Any) -> None:
        self.params = params
        self.config = config
        self.config.validate()
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, mass: float | None = None, gain: float | None = None) -> None:
        """Restart the RLS at ``mass``/``gain`` (config defaults) and clear all statistics."""
        cfg = self.config
        m0 = cfg.initial_mass if mass is None else float(mass)
        p0 = cfg.initial_gain if gain is None else float(gain)
        if not (math.isfinite(m0) and m0 > 0.0):
            raise ValueError(f"reset mass must be finite and > 0, got {mass!r}")
        if not (math.isfinite(p0) and p0 > 0.0):
            raise ValueError(f"reset gain must be finite and > 0, got {gain!r}")
        self.rls = RecursiveLeastSquares(cfg.forgetting_factor, m0, p0)
        self._res_weight = 1.0
        self._res_sq = cfg.initial_residual_std ** 2
        self._bias_lever = 0.0       # sum_k w_k rho^(t_n - t_k) (S when fully correlated) [m/s^2]
        self._bias_spread = 0.0      # V of the class docstring [m^2/s^4]
        self._bias_t = math.nan      # stamp of the last accepted sample [s]
        self._noise_sum = 0.0        # sum_k lambda^(n-k) sigma_k^2 of phi's white noise [m^2/s^4]
        # sum_k lambda^(n-k) phi_k s_k of a calibration's lasting errors (s_k: the force's
        # sensitivity to each parameter, lasting_force_covariance their covariance) [N m/s^2]
        self._model_lever = np.zeros(0)
        # Correlation of consecutive a-priori residuals: weighted sums of e_k e_k-1 and e_k-1^2,
        # the last residual and its stamp, the pairs seen, their mean spacing [s].
        self._res_cross, self._res_lagged_sq = 0.0, 0.0
        self._res_last, self._res_last_t = math.nan, math.nan
        self._res_pairs, self._res_spacing = 0, math.nan
        # F of the class docstring: sum_j sum_k w_j w_k rho^|j-k| (with its lever sum_k w_k rho^(n-k))
        # and sum_k w_k^2 [m^2/s^4]
        self._corr_lever, self._corr_spread, self._white_spread = 0.0, 0.0, 0.0
        self._accel_mean = 0.0       # running mean and variance of the moving windows' ax [m/s^2, m^2/s^4]
        self._accel_var = 0.0
        self._accel_t0 = math.nan    # first and last moving window of those statistics [s]
        self._accel_t = math.nan
        self._window: collections.deque[float] = collections.deque(maxlen=int(cfg.convergence_window))
        self.samples_used = 0
        self.rejected: dict[str, int] = {reason: 0 for reason in self.REJECT_REASONS}
        self.last_phi = math.nan       # regressor of the last accepted sample [m/s^2]
        self.last_y = math.nan         # output of the last accepted sample [N]
        self.last_gear: int | None = None
        self._reset_method_state()

    def _reset_method_state(self) -> None:
        """Subclass hook: clear what only the subclass keeps."""

    def state_dict(self) -> dict[str, float]:
        """Plain floats for persistence (e.g. a YAML/JSON file between drives)."""
        return {
            "mass": float(self.rls.theta),
            "gain": float(self.rls.p),
            "residual_weight": float(self._res_weight),
            "residual_sq": float(self._res_sq),
            "bias_lever": float(self._bias_lever),
            "bias_spread": float(self._bias_spread),
            "noise_sum": float(self._noise_sum),
            **{f"model_lever_{i}": float(v) for i, v in enumerate(self._model_lever)},
            "residual_cross": float(self._res_cross),
            "residual_lagged_sq": float(self._res_lagged_sq),
            "residual_pairs": float(self._res_pairs),
            "residual_spacing": float(self._res_spacing),
            "residual_corr_lever": float(self._corr_lever),
            "residual_corr_spread": float(self._corr_spread),
            "residual_white_spread": float(self._white_spread),
            "samples_used": float(self.samples_used),
        }

    def load_state_dict(self, state: Mapping[str, float]) -> None:
        """Restore :meth:`state_dict` output; raises ``ValueError`` on missing/invalid values."""
        try:
            mass = float(state["mass"])
            gain = float(state["gain"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"mass estimator state needs finite 'mass' and 'gain': {exc}") from None
        self.reset(mass=mass, gain=gain)
        weight = float(state.get("residual_weight", 1.0))
        sq = float(state.get("residual_sq", self.config.initial_residual_std ** 2))
        if math.isfinite(weight) and weight > 0.0 and math.isfinite(sq) and sq >= 0.0:
            self._res_weight, self._res_sq = weight, sq
        lever = float(state.get("bias_lever", 0.0))
        self._bias_lever = lever if math.isfinite(lever) and lever >= 0.0 else 0.0
        spread = float(state.get("bias_spread", self._bias_lever ** 2))   # older files: fully correlated
        self._bias_spread = spread if math.isfinite(spread) and spread >= 0.0 else self._bias_lever ** 2
        noise_sum = float(state.get("noise_sum", 0.0))
        self._noise_sum = noise_sum if math.isfinite(noise_sum) and noise_sum >= 0.0 else 0.0
        model_lever = [float(state[key]) for key in sorted(
            (k for k in state if k.startswith("model_lever_")), key=lambda k: int(k.rsplit("_", 1)[1]))]
        if not model_lever and "force_lever" in state:
            model_lever = [float(state["force_lever"])]   # files of the map's scale alone (2026-12-05)
        if model_lever and all(math.isfinite(v) for v in model_lever):
            self._model_lever = np.asarray(model_lever)
        cross, lagged = float(state.get("residual_cross", 0.0)), float(state.get("residual_lagged_sq", 0.0))
        pairs = float(state.get("residual_pairs", 0.0))
        if math.isfinite(cross) and math.isfinite(lagged) and lagged >= 0.0 and math.isfinite(pairs) and pairs >= 0.0:
            self._res_cross, self._res_lagged_sq, self._res_pairs = cross, lagged, int(pairs)
        spacing = float(state.get("residual_spacing", math.nan))
        self._res_spacing = spacing if math.isfinite(spacing) and spacing > 0.0 else math.nan
        sums = [float(state.get(key, 0.0)) for key in
                ("residual_corr_lever", "residual_corr_spread", "residual_white_spread")]
        if all(math.isfinite(v) for v in sums) and sums[1] >= 0.0 and sums[2] >= 0.0:   # older files: F = 1
            self._corr_lever, self._corr_spread, self._white_spread = sums
        used = float(state.get("samples_used", 0.0))
        self.samples_used = int(used) if math.isfinite(used) and used >= 0 else 0
        self._reset_method_state()      # what the method keeps beside the RLS starts from the loaded state

    # ------------------------------------------------------------------ outputs
    @property
    def mass(self) -> float:
        """Estimated mass [kg], clipped to [min_mass, max_mass] (the RLS state is not)."""
        return min(max(self.rls.theta, self.config.min_mass), self.config.max_mass)

    @property
    def raw_mass(self) -> float:
        return self.rls.theta

    @property
    def gain(self) -> float:
        return self.rls.p

    @property
    def residual_variance(self) -> float:
        """sigma^2 of the residual eps [N^2] (exponentially weighted, see class docstring)."""
        return self._res_sq / self._res_weight

    @property
    def bias_variance(self) -> float:
        """The share of :attr:`variance` that regressor errors leave, which the residuals cannot
        show [kg^2]: the caller's lasting bias, the errors-in-variables bias of phi's white
        noise, and a force error that lasts (see :meth:`_accepted`)."""
        lever_sq = self._bias_spread + self._noise_sum ** 2
        return (self.mass * self.rls.p) ** 2 * lever_sq + self.rls.p ** 2 * self._model_spread()

    #: Covariance of the calibrated parameters whose force sensitivities :meth:`_accepted` gets
    #: (``lasting_force_sensitivity``); None: none given. Set by the method (from its config).
    lasting_force_covariance: np.ndarray | None = None

    def _model_spread(self) -> float:
        """L^T C L [N^2 m^2/s^4] of the calibrated parameters' errors (0 without a covariance)."""
        cov, lever = self.lasting_force_covariance, self._model_lever
        if cov is None or lever.size != cov.shape[0]:
            return 0.0
        return max(float(lever @ cov @ lever), 0.0)

    @property
    def residual_correlation(self) -> float:
        """rho of the class docstring: the correlation of consecutive a-priori residuals, 0
        until :data:`MIN_RESIDUAL_PAIRS` pairs are in or with ``correlated_residuals`` off."""
        if not (self.config.correlated_residuals and self._res_pairs >= MIN_RESIDUAL_PAIRS
                and self._res_lagged_sq > 0.0):
            return 0.0
        return min(max(self._res_cross / self._res_lagged_sq, 0.0), MAX_RESIDUAL_CORRELATION)

    @property
    def residual_inflation(self) -> float:
        """F of the class docstring (at least 1): how much the residuals' correlation widens
        their share of the variance."""
        if not self._white_spread > 0.0:
            return 1.0
        return max(self._corr_spread / self._white_spread, 1.0)

    @property
    def residual_share(self) -> float:
        """The residuals' share of :attr:`variance` [kg^2]: p·sigma^2·F (class docstring)."""
        return self.rls.p * self.residual_variance * self.residual_inflation

    @property
    def variance(self) -> float:
        """Estimated variance of the mass [kg^2] = p·sigma^2·F (correlated residuals) + the
        lasting error's share."""
        return self.residual_share + self.bias_variance

    @property
    def converged(self) -> bool:
        """True when the last ``convergence_window`` updates have a coefficient of variation
        below ``convergence_max_cv`` and moved by less than ``convergence_max_rel_change``, or,
        with ``convergence_max_rel_std`` > 0, once ``convergence_min_updates`` updates are in and
        the published sigma is at most that share of the mass (the variance is honest: it
        carries the residuals and the regressor's lasting error). Neither rule flags a sigma
        above ``convergence_max_rel_sigma`` of the mass (when that is > 0)."""
        cfg = self.config
        mass, variance = self.mass, self.variance
        if cfg.convergence_max_rel_sigma > 0.0 and not variance <= (cfg.convergence_max_rel_sigma * mass) ** 2:
            return False
        if (cfg.convergence_max_rel_std > 0.0 and self.samples_used >= cfg.convergence_min_updates
                and mass > 0.0 and math.isfinite(variance) and variance <= (cfg.convergence_max_rel_std * mass) ** 2):
            return True
        window = self._window
        assert window.maxlen is not None   # built with maxlen=convergence_window
        if len(window) < window.maxlen:
            return False
        n = len(window)
        mean = sum(window) / n
        if mean <= 0.0:
            return False
        std = math.sqrt(max(sum((x - mean) ** 2 for x in window) / n, 0.0))
        return (std / mean < self.config.convergence_max_cv
                and abs(window[-1] - window[0]) / mean < self.config.convergence_max_rel_change)

    def status(self) -> dict[str, str]:
        """Method-specific ``/diagnostics`` entries: which share of the published sigma the
        residuals give and which the regressor's errors (:attr:`bias_variance`)."""
        residual = self.residual_share
        if not (finite_number(residual) and finite_number(self.bias_variance)):
            return {}
        return {"mass sigma: residuals / regressor errors [kg]":
                f"{math.sqrt(max(residual, 0.0)):.1f} / {math.sqrt(max(self.bias_variance, 0.0)):.1f}",
                "residual correlation / variance inflation":
                f"{self.residual_correlation:.2f} / {self.residual_inflation:.1f}"}

    # ------------------------------------------------------------------ update
    def _calibrated_accel(self, t: float, vx: float, ax: float, noise_variance: float) -> float:
        """The window acceleration ``ax`` by regression calibration (Carroll et al., Measurement
        Error in Nonlinear Models, 2nd ed. 2006, ch. 4): its expectation given the measurement,
        ``mu + s^2 / (s^2 + sigma^2) (ax - mu)``, where sigma^2 is ``noise_variance`` (the white
        noise of ``ax``) and mu, s^2 the mean and the variance of the true accelerations, from a
        running mean and variance of the moving windows' ``ax`` (time constant
        ``accel_calibration_time_s``) less sigma^2.

        Why: least squares on a regressor with noise in it is biased towards zero
        (errors-in-variables), and the Sec. 7.1 gate a > 0 on the same noisy ``ax`` keeps the
        windows whose noise is positive. Where the true acceleration hardly varies (a truck
        cruising: s ~ 0.05 against sigma ~ 0.02 m/s^2) both are several per cent of the mass
        (FASTSim's 36 t truck: 7.7 % low). The calibrated acceleration's error is independent
        of its value (Berkson), so neither the regression nor a gate on it is biased; where the
        acceleration varies (s >> sigma, any car) it is ``ax`` itself. Every moving window
        counts, whether or not it passes the gates; without a noise variance, or before the
        statistics span ``calibration_warmup_s``, ``ax`` is returned unchanged."""
        tau = self.config.accel_calibration_time_s
        if not (tau > 0.0 and vx >= self.config.min_speed):
            return ax
        last = self._accel_t
        if math.isnan(last):
            self._accel_t0 = self._accel_t = t
            self._accel_mean, self._accel_var = ax, 0.0
        elif t > last:
            w = min(1.0, (t - last) / tau)
            d = ax - self._accel_mean
            self._accel_mean += w * d
            self._accel_var = (1.0 - w) * (self._accel_var + w * d * d)
            self._accel_t = t
        if not (finite_number(noise_variance) and noise_variance > 0.0) \
                or t - self._accel_t0 < self.calibration_warmup_s:
            return ax
        true_variance = max(self._accel_var - noise_variance, 0.0)
        return self._accel_mean + true_variance / (true_variance + noise_variance) * (ax - self._accel_mean)

    def _track_residual_correlation(self, t: float, phi: float) -> None:
        """After an update at ``t`` with regressor ``phi``: the correlation of this a-priori
        residual with the previous one (pairs at most :data:`MAX_RESIDUAL_PAIR_GAP_S` apart) and
        the sums of the variance inflation F (class docstring)."""
        lam = self.config.forgetting_factor
        e, dt = self.rls.last_residual, t - self._res_last_t
        consecutive = math.isfinite(dt) and 0.0 < dt <= MAX_RESIDUAL_PAIR_GAP_S
        if finite_number(e):
            if consecutive and finite_number(self._res_last):
                self._res_cross = lam * self._res_cross + e * self._res_last
                self._res_lagged_sq = lam * self._res_lagged_sq + self._res_last ** 2
                self._res_pairs += 1
                self._res_spacing = dt if math.isnan(self._res_spacing) else self._res_spacing + 0.05 * (dt - self._res_spacing)
            self._res_last, self._res_last_t = e, t
        rho = self.residual_correlation
        rho_dt = rho ** (dt / self._res_spacing) if rho > 0.0 and math.isfinite(dt) and dt > 0.0 \
            and self._res_spacing > 0.0 else 0.0
        self._corr_spread, self._corr_lever = _correlated_sum(self._corr_spread, self._corr_lever, phi, lam, rho_dt)
        self._white_spread, _ = _correlated_sum(self._white_spread, 0.0, phi, lam, 0.0)

    def _reject(self, reason: str) -> bool:
        self.rejected[reason] += 1
        return False

    def _accepted(self, t: float, phi: float, y: float, residual_sq: float,
                  regressor_bias_variance: float = 0.0, regressor_bias_correlation_s: float = math.inf,
                  regressor_noise_variance: float = 0.0,
                  lasting_force_sensitivity: np.ndarray | None = None) -> bool:
        """Book-keeping after an RLS update at ``t`` with a-priori squared residual
        ``residual_sq``; ``regressor_bias_variance`` [m^2/s^4] and its correlation time
        ``regressor_bias_correlation_s`` [s] feed the lasting error's share of the variance.
        ``regressor_noise_variance`` [m^2/s^4]: phi's white noise on this sample (the
        acceleration's), which biases least squares towards zero by m p sum(lambda^k sigma_k^2)
        (errors-in-variables): that bias, which the residuals cannot show, enters the variance.
        ``lasting_force_sensitivity`` [N per unit of each parameter]: how this sample's force
        moves with the errors d of parameters that are the same on every sample (a calibration's,
        with the covariance :attr:`lasting_force_covariance`; a torque map's scale alone is one
        parameter). The force error is s_k^T d, the mass error p L^T d with L = sum
        lambda^(n-k) phi_k s_k, exactly, whatever the excitation; the residuals cannot show it."""
        lam = self.config.forgetting_factor
        if lasting_force_sensitivity is not None:
            s_k = np.asarray(lasting_force_sensitivity, dtype=float)
            if self._model_lever.shape != s_k.shape:
                self._model_lever = np.zeros_like(s_k)
            if np.all(np.isfinite(s_k)):
                self._model_lever = lam * self._model_lever + phi * s_k
        else:
            self._model_lever = lam * self._model_lever
        noise = regressor_noise_variance if finite_number(regressor_noise_variance) else 0.0
        self._noise_sum = lam * self._noise_sum + max(noise, 0.0)
        self._res_weight = lam * self._res_weight + 1.0
        self._res_sq = lam * self._res_sq + residual_sq
        var = regressor_bias_variance
        u = abs(phi) * (math.sqrt(var) if finite_number(var) and var > 0.0 else 0.0)
        tau, dt = regressor_bias_correlation_s, t - self._bias_t
        # rho = exp(-dt / tau): 1 for a bias that lasts (tau infinite, or the first sample)
        rho = math.exp(-dt / tau) if math.isfinite(dt) and dt > 0.0 and tau < math.inf else 1.0
        self._bias_spread, self._bias_lever = _correlated_sum(self._bias_spread, self._bias_lever, u, lam, rho)
        self._bias_t = t
        self._track_residual_correlation(t, phi)
        self._window.append(self.rls.theta)
        self.samples_used += 1
        self.last_phi, self.last_y = phi, y
        return True
