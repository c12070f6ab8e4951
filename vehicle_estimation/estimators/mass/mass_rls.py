"""Vehicle mass estimation by recursive least squares: Jensen et al. 2022 (paper 003).

Pure Python/NumPy, no ROS imports; the ROS node feeds :class:`LongitudinalMassEstimator`.

Equation map (paper 003):

* Eq. (1)  longitudinal dynamics F_i = F_p - F_a - F_r - F_g with the rotating-inertia term
  (m + I_w/r^2 + I_e G^2)·a, propulsion F_p = eta_dt T_e G, drag 1/2 rho C_a v^2,
  rolling m g C_r cos(alpha), grade m g sin(alpha), effective gearing G = i_t,j i_d / r
  (:meth:`VehicleParams.effective_gearing`).
* Eqs. (2), (4)-(6)  the regression form phi·m = y + eps with
  phi = a + g C_r cos(alpha) + g sin(alpha)                       (Eq. 5) and
  y   = eta_dt T_e G - 1/2 rho C_a v^2 - (I_w/r^2 + I_e G^2)·a    (Eq. 6).
* Eqs. (7)-(9)  scalar RLS with exponential forgetting (:class:`RecursiveLeastSquares`);
  paper values lambda = 0.9995, m(0) = 1000 kg, p(0) = 1000 s^4/m^2 (Sec. 3, Sec. 7.4).
* Eqs. (10)-(11)  gear prediction from the engine/vehicle speed ratio (:func:`predict_gear`).
* Eq. (49)  engine torque regression T_load = w0 + w1 L + w2 N_e + ... + w_n N_e^(n-1)
  (:class:`EngineTorqueRegression`); with the regression the drivetrain efficiency is
  implicitly one (Sec. 6.1), so the propulsion force is T_load·G.

Sample selection: Sec. 7.1 of the paper ("Estimation of torque and mass from the
longitudinal dynamics was only performed for samples where the vehicle acceleration was
greater than 0 m/s^2, to avoid estimates during braking"). The paper's Eq. (10) also
needs a moving vehicle and no drivetrain slip. This module adds, as documented
engineering choices (not from the paper): a minimum speed, a maximum |grade|, an explicit
brake-torque gate, a hold-off after gear shifts, a minimum regressor |phi|, a minimum
propulsion force (none from the Eq.-49 map at zero engine load), and clipping of the
*published* mass to sane bounds (the RLS state is never clipped).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Any, Callable, Mapping, Sequence

from vehicle_estimation.estimators.mass.wind import WindEstimator, WindEstimatorConfig
from vehicle_estimation.contract.vehicle import VehicleParams, dataclass_from_mapping

RPM_PER_RAD_S = 30.0 / math.pi

#: Rejection reasons counted in :attr:`LongitudinalMassEstimator.rejected`.
REJECT_REASONS = (
    "nan",          # t, vx, ax or slope not finite
    "speed",        # vx < min_speed (standstill / creeping)
    "accel",        # ax <= min_accel (paper: only a > 0 is used)
    "slope",        # |slope| > max_abs_slope
    "braking",      # brake_torque > max_brake_torque
    "gear",         # the propulsion source needs a gear and none is known (idle, slip)
    "gear_shift",   # within gear_shift_holdoff_s of a gear change
    "no_force",     # no propulsion source available
    "propulsion",   # propulsion force <= min_propulsion_force (coasting, engine braking)
    "phi",          # |phi| < min_phi (too little excitation)
)

DRIVE_FORCE_KINDS = ("wheel", "propulsion", "tractive")


def _finite(value: Any) -> bool:
    """True for a real number (int, float, NumPy scalar) that is finite."""
    if value is None or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def finite_field(config: Any, name: str) -> float:
    """``config.<name>`` as a finite float, else ``ValueError`` naming the field."""
    value = getattr(config, name)
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


def validate_forgetting_fields(config: Any, more_positive: Sequence[str] = ()) -> Callable[[str], float]:
    """Checks shared by the RLS and FFRLS configs (lambda in (0, 1], positive initial values,
    bounds and convergence limits); returns the field reader for the caller's own checks."""

    def finite(name: str) -> float:
        return finite_field(config, name)

    lam = finite("forgetting_factor")
    if not 0.0 < lam <= 1.0:
        raise ValueError(f"forgetting_factor must be in (0, 1], got {lam!r}")
    for name in ("initial_mass", "initial_gain", "initial_residual_std", "min_mass", "max_mass",
                 "convergence_max_cv", "convergence_max_rel_change", *more_positive):
        if finite(name) <= 0.0:
            raise ValueError(f"{name} must be > 0, got {getattr(config, name)!r}")
    return finite


@dataclasses.dataclass
class MassRLSConfig:
    """Tuning of :class:`LongitudinalMassEstimator` (SI units unless stated).

    The RLS values are the paper's (Sec. 3 and 7.4); the gates beyond ``min_accel`` are
    engineering choices documented in the module docstring.
    """

    forgetting_factor: float = 0.9995       # lambda, Eq. (7)
    initial_mass: float = 1000.0            # m(0) [kg], Sec. 3
    initial_gain: float = 1000.0            # p(0) [s^4/m^2], Sec. 3
    # --- gating (a sample must pass all to update the RLS)
    min_speed: float = 2.0                  # [m/s]
    min_accel: float = 0.0                  # the sample needs ax > min_accel [m/s^2] (Sec. 7.1)
    max_abs_slope: float = 0.15             # [rad]
    max_brake_torque: float = 1.0           # a sample counts only if brake_torque <= this [N m]
    gear_shift_holdoff_s: float = 0.5       # [s] rejected after a gear change
    min_phi: float = 0.05                   # |phi| of Eq. (5) must be >= this [m/s^2]
    min_propulsion_force: float = 0.0       # F_p must be > this [N]
    # --- gear prediction, Eqs. (10)-(11)
    gear_ratio_tolerance: float = 0.10      # max relative |G_meas - G_j| / G_j, else slip
    # --- propulsion sources
    drive_force_kind: str = "wheel"         # meaning of the drive_force input, see step()
    torque_regression: list[float] = dataclasses.field(default_factory=list)  # Eq. (49) w0..wn
    torque_regression_speed_unit: str = "rpm"  # unit of N_e in Eq. (49) ("rpm" as Table 6, or "rad/s")
    # --- convergence flag (over the last `convergence_window` accepted updates)
    convergence_window: int = 200
    convergence_max_cv: float = 0.01        # std/mean of the estimates in the window
    convergence_max_rel_change: float = 0.01  # |last - first| / mean over the window
    # --- residual variance and output sanity
    initial_residual_std: float = 500.0     # prior sigma of eps [N] for the variance estimate
    min_mass: float = 300.0                 # published mass is clipped to [min_mass, max_mass]
    max_mass: float = 60000.0
    # --- ambient wind (not in the paper, its Sec. 8 open problem): with wind_compensation the
    # drag term of Eq. (6) uses the wind of estimators/mass/wind.py (EKF on [m, w_E, w_N] from the same
    # samples) projected on the heading passed to step(heading=...); off: the paper's still air.
    wind_compensation: bool = False        # estimate the wind online (estimators/mass/wind.py) and compensate the drag; needs a heading
    wind_force_std: float = 150.0           # WindEstimatorConfig.force_std [N]
    wind_random_walk: float = 0.02          # WindEstimatorConfig.random_walk [m/s per sqrt(s)]
    wind_mass_random_walk: float = 5.0      # WindEstimatorConfig.mass_random_walk [kg per sqrt(s)]
    wind_initial_std: float = 6.0           # WindEstimatorConfig.initial_wind_std [m/s]
    wind_min_speed: float = 8.0             # WindEstimatorConfig.min_speed [m/s]

    def wind_config(self) -> WindEstimatorConfig:
        """The wind estimator's config from the ``wind_*`` fields (validated, errors name them)."""
        config = WindEstimatorConfig(force_std=self.wind_force_std, random_walk=self.wind_random_walk,
                                     mass_random_walk=self.wind_mass_random_walk,
                                     initial_wind_std=self.wind_initial_std, min_speed=self.wind_min_speed)
        names = {"force_std": "wind_force_std", "random_walk": "wind_random_walk",
                 "mass_random_walk": "wind_mass_random_walk", "initial_wind_std": "wind_initial_std",
                 "min_speed": "wind_min_speed"}
        try:
            config.validate()
        except ValueError as exc:
            msg = str(exc)
            field = msg.split(" ", 1)[0]
            raise ValueError(msg.replace(field, names.get(field, field), 1)) from None
        return config

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        finite = validate_forgetting_fields(self, ("gear_ratio_tolerance",))
        if not isinstance(self.wind_compensation, bool):
            raise ValueError(f"wind_compensation must be a bool, got {self.wind_compensation!r}")
        self.wind_config()
        for name in ("min_speed", "max_abs_slope", "max_brake_torque", "gear_shift_holdoff_s",
                     "min_phi"):
            if finite(name) < 0.0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        finite("min_accel")
        finite("min_propulsion_force")
        if self.max_abs_slope >= math.pi / 2:
            raise ValueError(f"max_abs_slope must be below pi/2, got {self.max_abs_slope!r}")
        if self.min_mass >= self.max_mass:
            raise ValueError("min_mass must be below max_mass")
        if isinstance(self.convergence_window, bool) or int(self.convergence_window) != self.convergence_window \
                or self.convergence_window < 2:
            raise ValueError(f"convergence_window must be an integer >= 2, got {self.convergence_window!r}")
        if self.drive_force_kind not in DRIVE_FORCE_KINDS:
            raise ValueError(f"drive_force_kind must be one of {DRIVE_FORCE_KINDS}, got {self.drive_force_kind!r}")
        if self.torque_regression_speed_unit not in ("rpm", "rad/s"):
            raise ValueError("torque_regression_speed_unit must be 'rpm' or 'rad/s', "
                             f"got {self.torque_regression_speed_unit!r}")
        coeffs = list(self.torque_regression or [])
        if len(coeffs) == 1:
            raise ValueError("torque_regression needs at least [w0, w1] (Eq. 49), got one coefficient")
        for i, w in enumerate(coeffs):
            if not math.isfinite(float(w)):
                raise ValueError(f"torque_regression[{i}] must be finite, got {w!r}")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "MassRLSConfig":
        """Build from a flat mapping (e.g. ROS parameters); unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown mass estimator parameter {key!r}")


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


def predict_gear(engine_speed: float, vehicle_speed: float, params: VehicleParams, *,
                 min_vehicle_speed: float = 1.0, tolerance: float = 0.10) -> int | None:
    """Predict the engaged gear from the engine/vehicle speed ratio, Eqs. (10)-(11).

    ``engine_speed`` is in rad/s (the paper's N_e·pi/30) and ``vehicle_speed`` in m/s, so the
    measured effective gearing is G = omega_e / v [1/m] (Eq. 10) and the gear j in 1..N_gear
    minimising |i_t,j i_d / r - G| is returned (Eq. 11).

    Returns ``None`` (no gear can be trusted) at standstill (v < ``min_vehicle_speed``), for a
    non-finite input, an engine below half its idle speed (stalled/off), and when the best
    gear still mismatches by more than ``tolerance`` relative to its gearing: the clutch is
    slipping or open, e.g. idling while rolling, or the car is in neutral.
    """
    try:
        w = float(engine_speed)
        v = float(vehicle_speed)
    except (TypeError, ValueError):
        return None
    if not (math.isfinite(w) and math.isfinite(v)):
        return None
    if abs(v) < min_vehicle_speed or w < 0.5 * params.engine_idle_speed:
        return None
    measured = w / abs(v)                                                   # Eq. (10)
    best_gear, best_err = None, math.inf
    for j in range(1, len(params.gear_ratios) + 1):                         # Eq. (11)
        err = abs(params.effective_gearing(j) - measured)
        if err < best_err:
            best_gear, best_err = j, err
    if best_gear is None or best_err > tolerance * params.effective_gearing(best_gear):
        return None
    return best_gear


class EngineTorqueRegression:
    """Engine torque from OBD-II load and engine speed, paper 003 Eq. (49).

    T_load = w0 + w1·L + w2·N_e + w3·N_e^2 + ... + w_n·N_e^(n-1), with coefficients
    ``[w0, w1, ..., w_n]``. L is the engine load in the unit the coefficients were fitted
    with (the paper: OBD-II calculated load, percent). N_e is in rpm by default, as in the
    paper's Table 6 (w2 in N m/rpm); :meth:`torque` takes the engine speed in rad/s and
    converts. The fitted torque implicitly contains the drivetrain efficiency (Sec. 6.1).
    Paper's Table 6: w = [-17.85, 9.64, 2.50e-3, -1.44e-6].
    """

    def __init__(self, coefficients: Sequence[float], speed_unit: str = "rpm") -> None:
        coeffs = [float(c) for c in coefficients]
        if len(coeffs) < 2:
            raise ValueError("torque regression needs at least [w0, w1] (Eq. 49)")
        if not all(math.isfinite(c) for c in coeffs):
            raise ValueError(f"torque regression coefficients must be finite, got {coeffs!r}")
        if speed_unit not in ("rpm", "rad/s"):
            raise ValueError(f"speed_unit must be 'rpm' or 'rad/s', got {speed_unit!r}")
        self.coefficients = tuple(coeffs)
        self.speed_unit = speed_unit

    @classmethod
    def from_coefficients(cls, coefficients: Sequence[float] | None,
                          speed_unit: str = "rpm") -> "EngineTorqueRegression | None":
        """``None`` for an empty coefficient list (regression not configured)."""
        if not coefficients:
            return None
        return cls(coefficients, speed_unit)

    def torque(self, load: float, engine_speed: float) -> float:
        """T_load [N m] for load ``load`` and engine speed ``engine_speed`` [rad/s]."""
        n = float(engine_speed) * (RPM_PER_RAD_S if self.speed_unit == "rpm" else 1.0)
        w = self.coefficients
        total = w[0] + w[1] * float(load)
        power = 1.0
        for wk in w[2:]:
            total += wk * power * n
            power *= n
        return total


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
    (tau infinite) V = S^2 with S = sum w_k. On FASTSim's hills without GNSS the mass was 3 %
    off while p·sigma^2 said 0.2 %; with GNSS the fully correlated term said 6x the error.
    """

    REJECT_REASONS: tuple[str, ...] = ()

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
        used = float(state.get("samples_used", 0.0))
        self.samples_used = int(used) if math.isfinite(used) and used >= 0 else 0

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
        """The share of :attr:`variance` that a lasting regressor error leaves [kg^2]."""
        return (self.mass * self.rls.p) ** 2 * self._bias_spread

    @property
    def variance(self) -> float:
        """Estimated variance of the mass [kg^2] = p·sigma^2 + the lasting error's share."""
        return self.rls.p * self.residual_variance + self.bias_variance

    @property
    def converged(self) -> bool:
        """True when the last ``convergence_window`` updates have a coefficient of variation
        below ``convergence_max_cv`` and moved by less than ``convergence_max_rel_change``."""
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

    # ------------------------------------------------------------------ update
    def _reject(self, reason: str) -> bool:
        self.rejected[reason] += 1
        return False

    def _accepted(self, t: float, phi: float, y: float, residual_sq: float,
                  regressor_bias_variance: float = 0.0, regressor_bias_correlation_s: float = math.inf) -> bool:
        """Book-keeping after an RLS update at ``t`` with a-priori squared residual
        ``residual_sq``; ``regressor_bias_variance`` [m^2/s^4] and its correlation time
        ``regressor_bias_correlation_s`` [s] feed the lasting error's share of the variance."""
        lam = self.config.forgetting_factor
        self._res_weight = lam * self._res_weight + 1.0
        self._res_sq = lam * self._res_sq + residual_sq
        var = regressor_bias_variance
        u = abs(phi) * (math.sqrt(var) if _finite(var) and var > 0.0 else 0.0)
        tau, dt = regressor_bias_correlation_s, t - self._bias_t
        # rho = exp(-dt / tau): 1 for a bias that lasts (tau infinite, or the first sample)
        rho = math.exp(-dt / tau) if math.isfinite(dt) and dt > 0.0 and tau < math.inf else 1.0
        carried = lam * rho * self._bias_lever
        self._bias_spread = lam * lam * self._bias_spread + u * u + 2.0 * u * carried
        self._bias_lever = carried + u
        self._bias_t = t
        self._window.append(self.rls.theta)
        self.samples_used += 1
        self.last_phi, self.last_y = phi, y
        return True



class LongitudinalMassEstimator(ForgettingMassEstimator):
    """Online mass estimate from the longitudinal dynamics, paper 003 Eqs. (4)-(9) with gating.

    Feed one sample per call of :meth:`step`. Properties: :attr:`mass` (clipped to the
    configured bounds), :attr:`variance`, :attr:`converged`, :attr:`samples_used`,
    :attr:`rejected` (count per reason in :data:`REJECT_REASONS`).

    Variance: see :class:`ForgettingMassEstimator` (p of Eq. (7), residuals eps of Eq. (9)).
    """

    REJECT_REASONS = REJECT_REASONS

    def __init__(self, params: VehicleParams, config: MassRLSConfig | None = None) -> None:
        config = config if config is not None else MassRLSConfig()
        config.validate()   # names a bad field before the regression is built from it
        self.regression = EngineTorqueRegression.from_coefficients(
            config.torque_regression, config.torque_regression_speed_unit)
        super().__init__(params, config)

    def _reset_method_state(self) -> None:
        self._last_gear: int | None = None
        self._last_shift_t = -math.inf
        # The wind is re-estimated after every reset (it is not persisted: it changes between drives).
        self.wind: WindEstimator | None = None
        if self.config.wind_compensation:
            self.wind = WindEstimator(self.params.air_density, self.params.drag_area, self.config.initial_mass,
                                      self.config.wind_config())

    def _gear(self, gear: float, engine_speed: float, vx: float) -> int | None:
        n_gears = len(self.params.gear_ratios)
        if _finite(gear):
            g = int(round(gear))
            return g if 1 <= g <= n_gears else None   # 0 (neutral), reverse: no gear
        return predict_gear(engine_speed, vx, self.params, tolerance=self.config.gear_ratio_tolerance)

    def step(self, t: float, vx: float, ax: float, slope: float, *,
             drive_force: float = math.nan, engine_torque: float = math.nan,
             engine_speed: float = math.nan, engine_load: float = math.nan,
             gear: float = math.nan, brake_torque: float = 0.0, heading: float = math.nan,
             regressor_bias_variance: float = 0.0, regressor_bias_correlation_s: float = math.inf) -> bool:
        """Process one sample; return True when it updated the RLS.

        ``t`` [s], ``vx`` longitudinal speed [m/s], ``ax`` longitudinal acceleration dv/dt
        [m/s^2] (not the IMU specific force), ``slope`` road grade alpha [rad, + uphill];
        ``regressor_bias_variance`` [m^2/s^4] the variance of a lasting error in
        ax + g sin(slope), i.e. of the accelerometer bias, ``regressor_bias_correlation_s``
        [s] how long that error lasts (class docstring).

        Propulsion force F_p, first available of:

        1. ``drive_force`` [N] if finite. ``config.drive_force_kind`` says what it is:
           ``"wheel"`` (default) the driveshaft torque over r, i.e. after the engine-side
           inertia: y = F - F_a - (I_w/r^2)·a; ``"propulsion"`` eta T_e G of Eq. (1): the
           full Eq. (6) inertia term (needs a gear); ``"tractive"`` the tyre-road force:
           y = F - F_a.
        2. ``engine_torque`` [N m] × eta_dt × G(gear)  (Eq. 1/6), the gear from the
           ``gear`` signal (1-based; 0 = neutral) or else predicted by Eqs. (10)-(11) from
           ``engine_speed`` [rad/s] and ``vx``.
        3. Eq. (49) regression of ``engine_load`` and ``engine_speed`` × G (eta = 1, Sec. 6.1)
           when ``config.torque_regression`` is set.

        A non-finite ``brake_torque`` is treated as "not braking" (unknown).

        ``heading`` [rad]: ENU yaw of the vehicle (the fusion odometry's), used only with
        ``config.wind_compensation``: the sample then also updates the wind estimator
        (:attr:`wind`) and the drag term uses the air speed v - w_a; a non-finite heading
        leaves that sample uncompensated.
        """
        cfg = self.config
        p = self.params
        vals = (t, vx, ax, slope)
        if not all(_finite(v) for v in vals):
            return self._reject("nan")
        t, vx, ax, slope = (float(v) for v in vals)

        # Gear tracking runs on every finite sample so the shift hold-off sees all shifts.
        current_gear = self._gear(gear, engine_speed, vx)
        if current_gear is not None:
            if self._last_gear is not None and current_gear != self._last_gear:
                self._last_shift_t = t
            self._last_gear = current_gear
        self.last_gear = current_gear

        if vx < cfg.min_speed:
            return self._reject("speed")
        if not ax > cfg.min_accel:
            return self._reject("accel")
        if abs(slope) > cfg.max_abs_slope:
            return self._reject("slope")
        if _finite(brake_torque) and float(brake_torque) > cfg.max_brake_torque:
            return self._reject("braking")

        have_drive = _finite(drive_force)
        have_torque = _finite(engine_torque)
        have_reg = self.regression is not None and _finite(engine_load) and _finite(engine_speed)
        if not (have_drive or have_torque or have_reg):
            return self._reject("no_force")

        needs_gear = not have_drive or cfg.drive_force_kind == "propulsion"
        G = math.nan
        if needs_gear:
            if current_gear is None:
                return self._reject("gear")
            G = p.effective_gearing(current_gear)
        if current_gear is not None and t - self._last_shift_t < cfg.gear_shift_holdoff_s:
            return self._reject("gear_shift")

        wheel_inertia = p.wheel_inertia / p.wheel_radius ** 2
        if have_drive:
            force = float(drive_force)
            if cfg.drive_force_kind == "wheel":
                inertia = wheel_inertia
            elif cfg.drive_force_kind == "propulsion":
                inertia = wheel_inertia + p.engine_inertia * G * G
            else:
                inertia = 0.0
        elif have_torque:
            force = p.driveline_efficiency * float(engine_torque) * G           # Eq. (1) F_p
            inertia = wheel_inertia + p.engine_inertia * G * G
        else:
            assert self.regression is not None   # have_reg
            if not float(engine_load) > 0.0:
                # Closed throttle (the load reads 0: overrun fuel cut): the engine is not
                # propelling, and Eq. 49 there is an extrapolation that may come out positive
                # (calibrate does not fit such windows when the bag cannot show the brakes).
                return self._reject("propulsion")
            force = self.regression.torque(float(engine_load), float(engine_speed)) * G      # Eq. (49), eta = 1
            inertia = wheel_inertia + p.engine_inertia * G * G
        if not force > cfg.min_propulsion_force:
            return self._reject("propulsion")

        g = p.gravity
        phi = ax + g * p.rolling_resistance * math.cos(slope) + g * math.sin(slope)  # Eq. (5)
        if self.wind is not None:
            self.wind.update(t, vx, heading, phi, force - inertia * ax)
            drag = self.wind.drag(vx, heading)                                  # F_a with the wind
        else:
            drag = 0.5 * p.air_density * p.drag_area * vx * vx                 # F_a, Eq. (1)
        if abs(phi) < cfg.min_phi:
            return self._reject("phi")
        y = force - drag - inertia * ax                                          # Eq. (6)

        self.rls.update(phi, y)                                                   # Eqs. (7)-(9)
        return self._accepted(t, phi, y, self.rls.last_residual ** 2, regressor_bias_variance,
                              regressor_bias_correlation_s)
