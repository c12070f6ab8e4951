"""Transformer-aided adaptive EKF for the vehicle mass: Zhang et al. 2023 (paper 000),
Secs. 2.3-2.4, Eqs. (16)-(36), Algorithm 1.

NumPy only, no ROS; the transformer of Sec. 2.2 lives in
:mod:`vehicle_estimation.estimators.mass.transformer.model` and is imported lazily, only when a model is
loaded, so the filter itself (and the "EKF alone" baseline) needs no torch.

Equation map (paper 000):

* Eqs. (16)-(19)  confidence level tau: a Gaussian N(mu, Sigma) fitted to
  x' = [F_t, a_x, v_x, alpha] of the training set; tau_k = p(x'_k) / p_max
  = exp(-1/2 (x'_k - mu)^T Sigma^-1 (x'_k - mu)) (:func:`confidence_level`,
  :func:`gaussian_density`, :func:`peak_density`, :func:`fit_confidence_gaussian`).
* Eqs. (6)-(14)  longitudinal dynamics, rearranged for the acceleration (:func:`longitudinal_accel`)::

      delta m a_x = F_t - 1/2 rho C_d A v^2 - m g (f cos(alpha) + sin(alpha))

* Eqs. (20)-(28)  EKF: prediction x^- = g(x, u), P^- = A P A^T + Q, gain, update (Joseph form
  here, algebraically Eq. 26 but it keeps P symmetric and positive with R -> 0).
* Eqs. (29)-(30)  state x = [v_x, 1/m], transition v_k = v_{k-1} + a_x dT, (1/m)_k = (1/m)_{k-1}
  (:func:`transition`).
* Eqs. (32)-(34)  Jacobian A (:func:`transition_jacobian`).
* Eqs. (31), (35)-(36)  observation y~ = [v_x, 1/m_nn], H = I; R~ = diag(R_v, (1-tau)/tau R_nn)
  (Algorithm 1; :class:`AdaptiveEKF`).

Units and the rotating-mass factor: SI throughout (REP-103); the paper's Eqs. (33)-(34) carry
v in km/h (the 3.6, 3/25 and 12.96 factors). delta is the rotating mass conversion factor
1 + J/m with J = I_w/r^2 the rotating inertia downstream of the measured drive force; since it
depends on the state 1/m we differentiate through it. With J = 0 (delta = 1) the Jacobian is
exactly Eqs. (33)-(34) in SI units (``test_ta_aekf.py`` checks both, and against finite
differences)::

      A11 = 1 - dT/(delta m) (P_e / v^2 + rho C_d A v)        (Eq. 33; F_t = P_e / v by Eq. 13)
      A12 = dT/delta (P_e / v - 1/2 rho C_d A v^2)            (Eq. 34)

The driving force F_t: the paper uses Eq. (13), F_t = eta T_tq n pi / (30 v) (engine power over
speed). Here, first available: the driveline force reported on CAN (dF_t/dv = 0), engine torque
x eta x i_g i_0 / r with a known gear (dF_t/dv = 0), or Eq. (13) from engine torque and speed
(dF_t/dv = -F_t/v). Engineering addition (not in the paper, whose drives have no braking): the
brake force T_b / r is subtracted from F_t, so braking samples obey the same model.

Not in the paper, for an honest variance (each can be switched off; see
:mod:`~vehicle_estimation.estimators.mass.ta_aekf_filter`): the network's lasting error and the
slope's error as filter states, and an innovation gate on the network's output.

The transformer runs every ``inference_period_steps`` samples on a window of block means of
the Eq. (15) features (see :class:`TaAekfConfig`); its output 1/m_nn enters only at the
samples where it is fresh, so one network output is used once.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.estimators.common.guard import finite_number
from vehicle_estimation.contract.vehicle import VehicleParams, dataclass_from_mapping
from vehicle_estimation.estimators.mass.ta_aekf_filter import AdaptiveEKF, DriveInput, drive_force_input
from vehicle_estimation.estimators.mass.transformer.features import FeatureBlocks, eq15_features
from vehicle_estimation.paths import MODELS_DIR


def slope_error_deg(grade_error_variance: float, gravity: float) -> float:
    """The slope's RMS error [deg] that a grade-error variance [m^2/s^4] of g sin(slope) stands
    for (a network told the slope's error takes it); 0 when none is given (an exact slope)."""
    if not (finite_number(grade_error_variance) and grade_error_variance > 0.0):
        return 0.0
    return math.degrees(math.asin(min(math.sqrt(grade_error_variance) / gravity, 1.0)))


if TYPE_CHECKING:   # torch only when a model is loaded
    from vehicle_estimation.estimators.mass.transformer.model import MassModel

#: Rejection reasons counted in :attr:`TaAekfMassEstimator.rejected`.
REJECT_REASONS = (
    "nan",        # t, vx or slope not finite
    "time",       # t not increasing
    "absurd",     # |vx|, |ax|, |slope| or a force outside physical bounds
    "speed",      # vx < min_speed: Eq. (14) with rolling resistance needs a rolling vehicle
    "no_force",   # no drive force, no engine torque with gear, no engine torque + speed
    "no_brake",   # brake torque unknown (NaN) and no positive drive force: braking may be unseen
    "gap",        # time step above max_step_s: the velocity state restarts from the measurement
    "numeric",    # an update would make the state or covariance non-finite: skipped
)

DEFAULT_MODEL_STEM = MODELS_DIR / "mass_transformer"


# --------------------------------------------------------------------- configuration
@dataclasses.dataclass(frozen=True)
class TaAekfConfig:
    """Tuning of :class:`TaAekfMassEstimator` (SI units).

    * ``model_path``: stem of the model files (``<stem>.safetensors`` + ``<stem>.json``);
      empty: the shipped model (``vehicle_estimation/models/mass_transformer``).
    * ``use_network``: False runs the EKF alone (the paper's "EKF" row), no torch needed.
    * ``fixed_tau``: NaN = the adaptive tau of Eq. (19); a value in (0, 1] fixes it
      (Table 6: 1e-15 and 1).
    * ``inference_period_steps`` (N): the transformer runs once every N samples, when a new
      block of ``N`` samples is complete, so N is also the block length of the features. 10
      samples (0.1 s at 100 Hz) costs one inference of ~1 ms per 0.1 s (about 1 % of one core)
      and is far faster than the mass can change (only at stops, by loading), yet gives the
      filter a fresh observation every 0.1 s so that it converges within a couple of seconds
      of driving. It must equal the block length the model was trained with.
    * ``initial_mass``: x_0 of Algorithm 1 [kg]; NaN: the mean gross mass of the model's
      training set (the vehicle's mass parameter with ``use_network`` False), or, for a
      vehicle whose mass parameter lies outside the training masses, its curb mass. The
      trucks' 28 t is no prior for a car: from it, with a std of 1/m_0 on 1/m, FASTSim's 1.6 t
      car was 16 sigma out, and an EKF whose prior excludes the truth is bold until the data
      outweigh the prior some 60-fold (flagged converged at 12.6 s, 18 % high at sigma 3.6 %,
      beyond 3 sigma for a minute). A wider std instead cost paper 000's drives their start
      (RMSE 120 -> 2300 kg at 10 / m_0).
    * ``initial_mass_rel_std``: prior std of 1/m relative to 1/m_0.
    * ``velocity_noise_std``: sqrt(R_v) of the speed observation [m/s].
    * ``accel_noise_density``: process noise of v [m/s^2 sqrt(s)] (model errors: slope error,
      wind, tyre slip), Q_v = density^2 dT.
    * ``mass_walk_rel``: random walk of 1/m relative to 1/m per sqrt(s), Q_theta =
      (rel / m)^2 dT: the mass is constant while driving; a small walk keeps the filter alive.
    * ``network_rel_std``: sqrt(R_nn) relative to 1/m_nn; NaN: the relative RMSE of the
      model on its validation set (stored with the model). Times ``network_std_scale``
      (default 3 ~ sqrt(w) for w = 10 blocks per window): consecutive outputs share w - 1 of
      their w blocks, so their errors are strongly correlated; inflating R_nn by ~w keeps
      the filter from counting the same information w times (the paper feeds every output
      with R_nn = sigma^2 and does not discuss this).
    * ``network_bias_rel_std``, ``network_bias_time_s``: the network's lasting error as a
      Gauss-Markov state of :class:`AdaptiveEKF`, 30 % by default: the lasting error of the shipped
      network on a truck it was not trained on (FASTSim's class 8: -25 % without GNSS, +20 % with),
      where its validation error (14 %) is the training truck's and left the filter 6.4 % off at
      NEES 3.6 there; NaN: the model's validation relative RMSE; 0: none, every output independent
      (the paper: 10.7 % off, sigma 0.7 %, on FASTSim's truck). Its correlation time is 10 h: the
      error belongs to the vehicle, its load and the slope source, and a process that forgot it
      every 300 s let the network pull the mass again each time (FASTSim's truck without GNSS:
      3.64 % off over the last half, 2.49 % at 10 h, the EKF alone 2.39 %). Where GNSS is lost or
      back the network is told another slope error and the state is primed anew.
    * ``network_input_max_z``: outputs of windows outside the training data are not used.
    * ``grade_error_state``, ``grade_error_max_time_s``: the slope's error as a Gauss-Markov
      state of :class:`~vehicle_estimation.estimators.mass.ta_aekf_filter.AdaptiveEKF`, of the
      variance and correlation time :meth:`TaAekfMassEstimator.step` is given (the node: the
      slope's own variance; seconds while GNSS aids the fusion, else the drive), the time capped
      (see :meth:`TaAekfMassEstimator._grade_process`). False: the paper, the slope taken as
      exact (on FASTSim's truck without GNSS: 13 % off at sigma 0.8 %).
    * ``accel_from_speed``: the network's a_x feature is the least-squares slope of the last
      ``accel_fit_samples`` speeds given to :meth:`TaAekfMassEstimator.step` (20 = 0.2 s at
      100 Hz), exactly how the training data defines it; False: the ``ax`` argument. The
      filter itself never uses a measured a_x (Eq. 30 predicts it from Eq. 14).
    * ``network_gate_sigma``: a network output whose innovation 1/m_nn - 1/m exceeds this
      many sigma of its innovation covariance is not used (0: off, the paper's Algorithm 1).
      Not in the paper: tau of Eq. (19) only asks whether [F_t, a_x, v_x, alpha] look like
      the training drives, and a car on the same roads and speeds does (its forces are
      inside the truck's low-force range), so tau alone would let a truck-trained network
      drag a car's estimate to truck masses; once the physics has converged the gate stops it.
    """

    model_path: str = setting("", "Stem of the model files (<stem>.safetensors + <stem>.json); empty: the "
                              "shipped model")
    use_network: bool = setting(True, "False runs the EKF alone (the paper's EKF row), no torch needed")
    fixed_tau: float = setting(math.nan, "NaN: the adaptive tau of Eq. (19); a value in (0, 1] fixes it "
                               "(Table 6: 1e-15 and 1)", low=0.0, high=1.0, low_open=True, allow_nan=True)
    inference_period_steps: int = setting(10, "The network runs once every this many samples (the block "
                                          "length the model was trained with)", low=1)
    initial_mass: float = setting(math.nan, "x_0 of Algorithm 1 [kg]; NaN: the mean mass of the model's "
                                  "training set (the vehicle's curb mass where its mass lies outside the "
                                  "training masses)", low=0.0, low_open=True, allow_nan=True)
    initial_mass_rel_std: float = setting(1.0, "Prior std of 1/m relative to 1/m_0", low=0.0, low_open=True)
    velocity_noise_std: float = setting(0.05, "sqrt(R_v) of the speed observation [m/s]", low=0.0, low_open=True)
    accel_noise_density: float = setting(0.05, "Process noise of v [m/s^2 sqrt(s)]: slope error, wind, tyre "
                                         "slip", low=0.0, low_open=True)
    mass_walk_rel: float = setting(2e-4, "Random walk of 1/m relative to 1/m [per sqrt(s)]", low=0.0)
    network_rel_std: float = setting(math.nan, "sqrt(R_nn) relative to 1/m_nn; NaN: the model's validation "
                                     "relative RMSE", low=0.0, low_open=True, allow_nan=True)
    network_std_scale: float = setting(3.0, "R_nn inflation for correlated network outputs (~sqrt(w) for "
                                       "w blocks per window)", low=0.0, low_open=True)
    network_bias_rel_std: float = setting(
        0.3, "Std of the network's lasting error relative to 1/m_nn, a filter state (0.3: the shipped network "
        "on a truck it was not trained on, FASTSim's class 8, reads 25 % low to 20 % high); NaN: the model's "
        "validation relative RMSE (the training truck's); 0: none, every output independent (the paper)",
        low=0.0, allow_nan=True)
    network_bias_time_s: float = setting(
        36000.0, "Correlation time of the network's lasting error [s]: a property of the vehicle, its load "
        "and the slope source, so a constant for the drive (10 h; it is primed anew where GNSS is lost or "
        "back)", low=0.0, low_open=True)
    grade_error_state: bool = setting(
        True, "The slope's error as a filter state, of the variance and correlation time the caller gives "
        "(the node: the slope's own variance, GNSS aiding); False: the slope taken as exact (the paper)")
    grade_error_max_time_s: float = setting(
        300.0, "Upper bound on the grade error's correlation time [s]: a bias taken as lasting for the "
        "drive would hold the value the filter read first", low=0.0, low_open=True)
    network_gate_sigma: float = setting(4.0, "A network output beyond this many sigma of its innovation is "
                                        "not used (0: off, Algorithm 1)", low=0.0)
    network_input_max_z: float = setting(
        6.0, "A network output whose per-window inputs (window features, slope error) lie more than this "
        "many training standard deviations from the training mean is not used: the network would "
        "extrapolate (a car's window reads a mass the truck network never saw); 0: off (Algorithm 1)", low=0.0)
    accel_from_speed: bool = setting(True, "The network's a_x feature is the slope of the last speeds (as "
                                     "in training); False: the ax argument")
    accel_fit_samples: int = setting(20, "Speeds in the least-squares a_x feature (20 = 0.2 s at 100 Hz)",
                                     low=1)
    min_speed: float = setting(1.0, "Below this speed the filter only tracks v [m/s]", low=0.0)
    max_step_s: float = setting(0.5, "A larger time step restarts v from the measurement [s]",
                                low=0.0, low_open=True)
    max_abs_slope: float = setting(0.35, "Samples on a steeper grade are absurd [rad]", low=0.0, low_open=True)
    max_abs_accel: float = setting(15.0, "An |a_x| above this is absurd [m/s^2]", low=0.0, low_open=True)
    max_speed: float = setting(100.0, "A speed above this is absurd [m/s]", low=0.0, low_open=True)
    max_abs_force: float = setting(1.0e6, "A drive force above this is absurd [N]", low=0.0, low_open=True)
    # --- convergence flag over the last `convergence_window` estimates
    convergence_window: int = setting(200, "Mass updates the convergence flag looks back over", low=1)
    convergence_max_cv: float = setting(0.01, "c_v (Eq. 40) of those updates below this: converged",
                                        low=0.0, low_open=True)
    convergence_max_rel_std: float = setting(0.05, "Converged only with sqrt(variance) / mass below this",
                                             low=0.0, low_open=True)
    min_mass: float = setting(300.0, "The published mass is clipped to [min_mass, max_mass] [kg]",
                              low=0.0, low_open=True)
    max_mass: float = setting(100000.0, "Upper clip of the published mass [kg]", low=0.0, low_open=True)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        check_settings(self)
        if self.min_mass >= self.max_mass:
            raise ValueError("min_mass must be below max_mass")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> TaAekfConfig:
        """Build from a flat mapping (e.g. ROS parameters); unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown ta_aekf mass estimator parameter {key!r}")


# --------------------------------------------------------------------- node-facing estimator
class TaAekfMassEstimator:
    """Online mass by TA-AEKF (paper 000 Algorithm 1), same outward API as
    :class:`~vehicle_estimation.estimators.mass.mass_ffrls.FFRLSMassEstimator`.

    Call :meth:`step` once per powertrain sample (100 Hz). Properties: :attr:`mass` (clipped
    to the configured bounds), :attr:`variance` [kg^2] (delta method from P of 1/m:
    var(m) = P_22 m^4), :attr:`converged`, :attr:`samples_used` (EKF updates of the mass),
    :attr:`rejected`; diagnostics :attr:`last_tau`, :attr:`last_network_mass`.
    """

    REJECT_REASONS = REJECT_REASONS
    #: Algorithm 1 steps at every sample (0.01 s); the core averages its network features over
    #: blocks itself, and gaps restart its speed state.
    steps_on_windows = False
    window_brake = "max"    # no windows: each sample carries its own brake torque
    needs_heading = False

    def __init__(self, params: VehicleParams, config: TaAekfConfig | None = None,
                 model: MassModel | None = None) -> None:
        self.params = params
        self.config = config if config is not None else TaAekfConfig()
        self.config.validate()
        cfg = self.config
        self.model: MassModel | None = None
        if cfg.use_network:
            if model is None:
                from vehicle_estimation.estimators.mass.transformer.model import MassModel
                model = MassModel.load(cfg.model_path or DEFAULT_MODEL_STEM)
            if model.spec.block_steps != cfg.inference_period_steps:
                raise ValueError(
                    f"inference_period_steps ({cfg.inference_period_steps}) must equal the block "
                    f"length the model was trained with ({model.spec.block_steps})")
            self.model = model
        # delta of Eq. (8) for the *features* only: a constant, which feature normalisation
        # absorbs; the filter uses the exact 1 + J/m (see the module docstring).
        self.feature_delta = 1.0 + params.wheel_inertia / params.wheel_radius ** 2 / params.curb_mass
        self.reset()

    # ------------------------------------------------------------------ state
    def _prior_mass(self) -> float:
        m0 = self.config.initial_mass
        if math.isnan(m0):
            if self.model is None:
                m0 = self.params.mass
            else:
                # the network's vehicles say nothing of one outside their masses
                trained = self.model.metadata.get("train_mass_range_kg")
                outside = trained is not None and not trained[0] <= self.params.mass <= trained[1]
                m0 = self.params.curb_mass if outside else self.model.training_mean_mass
        return float(m0)

    def _network_bias_rel_std(self) -> float:
        """The network's lasting relative error (0 without a network, or switched off)."""
        if self.model is None:
            return 0.0
        rel = self.config.network_bias_rel_std
        return self.model.validation_rel_rmse if math.isnan(rel) else rel

    def reset(self, mass: float | None = None) -> None:
        """Restart from ``mass`` (default the configured prior) and clear all statistics."""
        m0 = self._prior_mass() if mass is None else float(mass)
        if not (math.isfinite(m0) and m0 > 0.0):
            raise ValueError(f"reset mass must be finite and > 0, got {mass!r}")
        theta0 = 1.0 / m0
        p0 = np.diag([1.0, (self.config.initial_mass_rel_std * theta0) ** 2])
        self.ekf = AdaptiveEKF(np.array([0.0, theta0]), p0, (self._network_bias_rel_std() * theta0) ** 2,
                               grade_error=self.config.grade_error_state)
        self._grade_variance = 0.0    # the lasting grade error's variance so far (cap infinite)
        self._grade_t = -math.inf     # the grade error state's last prediction
        self._grade_tau: float | None = None   # its correlation time then
        self.features = FeatureBlocks(self.config.inference_period_steps,
                                      self.model.spec.window if self.model is not None else 1)
        self._v_initialised = False
        self._bias_primed = False     # the network-bias state's variance set from the first output
        self._slope_aided: bool | None = None   # whether the slope's error had a finite correlation time
        self._speed_history: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=self.config.accel_fit_samples)
        self._t_last = -math.inf
        self._window: collections.deque[float] = collections.deque(maxlen=self.config.convergence_window)
        self.samples_used = 0
        self.rejected: dict[str, int] = {reason: 0 for reason in REJECT_REASONS}
        self.last_tau = math.nan
        self.last_network_mass = math.nan
        self.network_updates = 0      # network outputs used by the filter
        self.network_gated = 0        # network outputs refused by network_gate_sigma
        self.network_out_of_domain = 0  # network outputs refused by network_input_max_z

    def state_dict(self) -> dict[str, float]:
        """Plain floats for persistence: 1/m with its variance and the counters (the velocity
        and the feature window restart from the next samples)."""
        return {"mass": float(1.0 / self.ekf.x[1]), "inv_mass": float(self.ekf.x[1]),
                "inv_mass_variance": float(self.ekf.P[1, 1]),
                "samples_used": float(self.samples_used)}

    def load_state_dict(self, state: Mapping[str, float]) -> None:
        """Restore :meth:`state_dict` output; ``ValueError`` on missing or invalid values."""
        try:
            inv_mass = float(state["inv_mass"])
            var = float(state["inv_mass_variance"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"ta_aekf state needs finite 'inv_mass' and 'inv_mass_variance': {exc}") from None
        if not (math.isfinite(inv_mass) and inv_mass > 0.0 and math.isfinite(var) and var > 0.0):
            raise ValueError(f"ta_aekf state out of range: inv_mass={inv_mass!r}, variance={var!r}")
        self.reset(mass=1.0 / inv_mass)
        self.ekf.P[1, 1] = var
        used = float(state.get("samples_used", 0.0))
        self.samples_used = int(used) if math.isfinite(used) and used >= 0 else 0

    # ------------------------------------------------------------------ outputs
    @property
    def raw_mass(self) -> float:
        return float(1.0 / self.ekf.x[1]) if self.ekf.x[1] > 0.0 else math.inf

    @property
    def mass(self) -> float:
        """Estimated mass [kg], clipped to [min_mass, max_mass] (the state is not)."""
        return min(max(self.raw_mass, self.config.min_mass), self.config.max_mass)

    @property
    def variance(self) -> float:
        """var(m) ~ P_22 / theta^4 [kg^2] (first-order propagation through m = 1/theta)."""
        theta = float(self.ekf.x[1])
        return float(self.ekf.P[1, 1]) / theta ** 4 if theta > 0.0 else math.inf

    @property
    def converged(self) -> bool:
        """The last ``convergence_window`` mass updates vary by less than
        ``convergence_max_cv`` (c_v of Eq. 40) and the std is below ``convergence_max_rel_std``."""
        w = self._window
        if len(w) < (w.maxlen or 0):
            return False
        arr = np.fromiter(w, float)
        mean = float(arr.mean())
        if not mean > 0.0:
            return False
        return (float(arr.std()) / mean < self.config.convergence_max_cv
                and math.sqrt(self.variance) / self.mass < self.config.convergence_max_rel_std)

    def status(self) -> dict[str, str]:
        values = {"confidence level tau (Eq. 19)": f"{self.last_tau:.3g}",
                  "effective tau (the network's gain on the mass)": f"{self.ekf.last_effective_tau:.3g}",
                  "network mass [kg]": f"{self.last_network_mass:.1f}",
                  "network outputs used / gated / outside its training data":
                      f"{self.network_updates} / {self.network_gated} / {self.network_out_of_domain}"}
        i = self.ekf.i_grade
        if i is not None:
            values["slope's grade error [m/s^2]"] = f"{self.ekf.x[i]:.4g}"
            values["slope's grade error std [m/s^2]"] = f"{math.sqrt(max(float(self.ekf.P[i, i]), 0.0)):.4g}"
        return values

    # ------------------------------------------------------------------ update
    def _reject(self, reason: str) -> bool:
        self.rejected[reason] += 1
        return False

    def _drive(self, vx: float, drive_force: Any, engine_torque: Any, engine_speed: Any,
               gear: Any, brake_torque: Any) -> tuple[float, float] | None:
        return drive_force_input(self.params, vx, drive_force, engine_torque, engine_speed, gear,
                                 brake_torque, self.config.min_speed)

    def step(self, t: float, vx: float, ax: float, slope: float, *,
             drive_force: float = math.nan, engine_torque: float = math.nan,
             engine_speed: float = math.nan, engine_load: float = math.nan,
             gear: float = math.nan, brake_torque: float = 0.0, heading: float = math.nan,
             grade_error_variance: float = math.nan, grade_error_correlation_s: float = math.inf) -> bool:
        """Process one sample; True when the mass estimate was updated.

        ``t`` [s], ``vx`` longitudinal speed [m/s] (observation y_k of Eq. 31), ``ax``
        dv_x/dt [m/s^2] without gravity (a network feature only, and only with
        ``accel_from_speed`` False; by default the core derives it from ``vx`` as the training
        data does; the filter predicts a_x from Eq. 14), ``slope`` road grade alpha [rad,
        + uphill] (the slope node's estimate), ``brake_torque`` total over the
        wheels [N m]; NaN: not known, and then only samples with a positive drive force are used
        (a driver on the throttle is not braking; an unseen brake force would be read as mass:
        FASTSim's car without joint states, 17.5 % off at NEES 1700 before). Drive force: ``drive_force`` [N] at the wheels, else ``engine_torque``
        [N m] with ``gear`` (1-based) or with ``engine_speed`` [rad/s] (Eq. 13).
        ``engine_load`` and ``heading`` are accepted for call compatibility with
        :meth:`~vehicle_estimation.estimators.mass.mass_rls.LongitudinalMassEstimator.step` and not used.
        ``grade_error_variance`` [m^2/s^4]: the variance of a lasting error in g sin(slope) (NaN
        or 0: none), ``grade_error_correlation_s`` [s] how long it lasts (infinite: the drive),
        for the grade error state (``grade_error_state``).
        """
        cfg = self.config
        if not all(finite_number(v) for v in (t, vx, slope)):
            return self._reject("nan")
        t, vx, slope = float(t), float(vx), float(slope)
        aided = finite_number(grade_error_correlation_s)
        if aided != self._slope_aided:
            # The network's lasting error depends on the slope error it is told and has (told a
            # GNSS-aided slope it reads a truck it never saw 20 % heavy, told an unaided one 25 %
            # light): where GNSS is lost or back it is another error, primed anew from the next output.
            if self._slope_aided is not None:
                self._bias_primed = False
            self._slope_aided = aided
        if not t > self._t_last:
            return self._reject("time")
        ax_f = float(ax) if finite_number(ax) and not cfg.accel_from_speed else math.nan
        if abs(vx) > cfg.max_speed or abs(slope) > cfg.max_abs_slope \
                or (math.isfinite(ax_f) and abs(ax_f) > cfg.max_abs_accel):
            return self._reject("absurd")
        dt = t - self._t_last
        self._t_last = t
        if dt > cfg.max_step_s:
            self._speed_history.clear()
        self._speed_history.append((t, vx))
        if cfg.accel_from_speed:
            ax_f = self._history_slope()
            if not abs(ax_f) <= cfg.max_abs_accel:     # a speed glitch: no network input
                ax_f = math.nan
        drive = self._drive(vx, drive_force, engine_torque, engine_speed, gear, brake_torque)
        if drive is not None and not (math.isfinite(drive[0]) and abs(drive[0]) <= cfg.max_abs_force):
            return self._reject("absurd")

        if not self._v_initialised or dt > cfg.max_step_s:
            gap = self._v_initialised
            self.ekf.restart_speed(vx, cfg.velocity_noise_std ** 2)
            self._v_initialised = True
            self.features.clear()
            return self._reject("gap") if gap else False
        if vx < cfg.min_speed:
            self._track_speed_only(vx)
            self.features.clear()
            return self._reject("speed")
        if drive is None:
            self._track_speed_only(vx)
            self.features.clear()
            return self._reject("no_force")
        force, dforce_dv = drive
        if not finite_number(brake_torque) and not force > 0.0:
            self._track_speed_only(vx)
            self.features.clear()
            return self._reject("no_brake")

        # Network: block features; a completed block with a full window gives 1/m_nn and tau.
        # Without a_x (the first accel_fit_samples) only the network waits, not the filter.
        nn_obs: tuple[float, float, float] | None = None
        if self.model is not None and not math.isfinite(ax_f):
            self.features.clear()
        elif self.model is not None:
            nn_features = eq15_features(force, vx, ax_f, slope, self.params, self.feature_delta)
            if self.features.add(nn_features, (force, ax_f, vx, slope)) and self.features.full:
                window = self.features.array()[None]
                slope_error = slope_error_deg(grade_error_variance, self.params.gravity)
                masses, distances = self.model.predict_with_input_distance(window, slope_error)
                m_nn = float(masses[0])
                tau = cfg.fixed_tau if not math.isnan(cfg.fixed_tau) else \
                    float(self.model.confidence(self.features.last_tau_features))
                if cfg.network_input_max_z > 0.0 and not float(distances[0]) <= cfg.network_input_max_z:
                    self.network_out_of_domain += 1
                    tau = math.nan       # no weight: published as NaN, not used
                self.last_network_mass, self.last_tau = m_nn, tau
                if math.isfinite(m_nn) and m_nn > 0.0 and math.isfinite(tau):
                    rel = cfg.network_rel_std if not math.isnan(cfg.network_rel_std) \
                        else self.model.validation_rel_rmse
                    rel *= cfg.network_std_scale
                    nn_obs = (1.0 / m_nn, (rel / m_nn) ** 2, tau)
                    if self.ekf.with_bias and not self._bias_primed:
                        # Relative to the network's own output (a prior far off would mute it).
                        self.ekf.reset_network_bias((self._network_bias_rel_std() / m_nn) ** 2)
                        self._bias_primed = True

        x_before, p_before = self.ekf.x.copy(), self.ekf.P.copy()
        theta = max(float(self.ekf.x[1]), 1e-9)
        q_diag = [cfg.accel_noise_density ** 2 * dt, (cfg.mass_walk_rel * theta) ** 2 * dt]
        decay = 1.0
        if self.ekf.with_bias:     # Gauss-Markov: stationary variance (rel theta)^2
            decay = math.exp(-dt / cfg.network_bias_time_s)
            q_diag.append((self._network_bias_rel_std() * theta) ** 2 * (1.0 - decay * decay))
        grade_decay = 1.0
        if self.ekf.i_grade is not None:
            grade_decay, grade_q = self._grade_process(t, grade_error_variance, grade_error_correlation_s)
            q_diag.append(grade_q)
        q = np.diag(q_diag)
        u = DriveInput(force, dforce_dv, slope)
        try:
            self.ekf.predict(u, dt, q, self.params, decay, grade_decay)   # Eqs. (22)-(23)
            if nn_obs is None:
                self.ekf.update(vx, cfg.velocity_noise_std ** 2)          # Eqs. (24)-(26)
            elif self.ekf.update(vx, cfg.velocity_noise_std ** 2, *nn_obs,   # Algorithm 1
                                 gate_sigma=cfg.network_gate_sigma):
                self.network_updates += 1
            else:
                self.network_gated += 1
        except np.linalg.LinAlgError:
            self.ekf.x, self.ekf.P = x_before, p_before
            return self._reject("numeric")
        if not (np.all(np.isfinite(self.ekf.x)) and np.all(np.isfinite(self.ekf.P))
                and self.ekf.x[1] > 0.0 and self.ekf.P[1, 1] > 0.0 and self.ekf.P[0, 0] > 0.0):
            self.ekf.x, self.ekf.P = x_before, p_before
            return self._reject("numeric")
        self.samples_used += 1
        self._window.append(self.raw_mass)
        return True

    def _grade_process(self, t: float, variance: float, correlation_s: float) -> tuple[float, float]:
        """(decay, driving noise) of the grade error from the last prediction to ``t``: a
        first-order Gauss-Markov process of the caller's variance and correlation time, the time
        capped by ``grade_error_max_time_s``. Why the cap: without GNSS the fusion's bias error
        is not a constant for the drive (it keeps re-estimating the bias from the CAN speed and
        the attitude); on FASTSim's truck the slope's error went from +0.05 to -0.017 m/s^2
        over half an hour, and a random constant locked onto the first value (11.5 % off at
        sigma 1.4 %). Where the correlation time changes (the first sample, GNSS lost or back)
        the slope's error is another process: the state's variance is raised to the caller's at
        once (a new, independent share), not over the new correlation time. Only with the cap
        set infinite does a lasting error neither decay nor get driven; the growth of its
        variance (the bias drifting unobserved) then joins the state the same way."""
        var = float(variance) if finite_number(variance) and variance > 0.0 else 0.0
        tau = float(correlation_s) if finite_number(correlation_s) else math.inf
        tau = min(tau, self.config.grade_error_max_time_s)
        elapsed, self._grade_t = t - self._grade_t, t
        i = self.ekf.i_grade
        if tau != self._grade_tau and i is not None:
            self.ekf.add_grade_variance(var - float(self.ekf.P[i, i]))
            self._grade_tau, self._grade_variance = tau, var
        if tau == math.inf:
            self.ekf.add_grade_variance(var - self._grade_variance)
            self._grade_variance = max(var, self._grade_variance)
            return 1.0, 0.0
        decay = math.exp(-elapsed / tau) if tau > 0.0 else 0.0
        return decay, var * (1.0 - decay * decay)

    def _history_slope(self) -> float:
        """Least-squares slope of the last ``accel_fit_samples`` speeds over their stamps
        (NaN until there are that many), the a_x of the training data (training/truck_data.py)."""
        hist = self._speed_history
        if len(hist) < (hist.maxlen or 0):
            return math.nan
        arr = np.asarray(hist)
        tc = arr[:, 0] - arr[:, 0].mean()
        den = float(tc @ tc)
        return float(tc @ arr[:, 1]) / den if den > 0.0 else math.nan

    def _track_speed_only(self, vx: float) -> None:
        """Outside the model's validity: follow the measured speed, keep 1/m and its variance."""
        self.ekf.restart_speed(vx, self.config.velocity_noise_std ** 2)
