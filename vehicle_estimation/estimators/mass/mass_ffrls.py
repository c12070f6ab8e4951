"""Vehicle mass by forgetting-factor RLS with braking and a threshold judgment: Chen et al. 2021
(paper 004), Sec. 6, Eqs. (28)-(31).

Pure Python, no ROS imports; same outward API as
:class:`vehicle_estimation.estimators.mass.mass_rls.LongitudinalMassEstimator`, so the mass node can
switch between the two by name.

Equation map (paper 004):

* Eq. (28)  longitudinal dynamics *with the braking torque*::

      T_tq i_g i_0 eta_t / R_t = m g sin(theta) + m g zeta cos(theta) + m dv_x/dt
                                 + 1/2 C_d A rho_air v_x^2 + T_b / R_t

  (T_tq engine torque, i_g gearbox and i_0 final-drive ratio, eta_t driveline efficiency,
  R_t wheel radius, T_b total braking torque, zeta rolling-resistance coefficient). The paper
  has no rotating-mass term: the wheel and engine inertias are lumped into m.
* Eq. (29)  the linear regression Omega_m x_m = y with x_m = m (sin theta ~ theta,
  cos theta ~ 1)::

      y       = (T_tq i_g i_0 eta_t - T_b) / R_t - C_d A rho_air v_x^2 / 2     [N]
      Omega_m = g theta + g zeta + dv_x/dt                                     [m/s^2]

* Eq. (30)  FFRLS with forgetting factor lambda_m (0.998 in Sec. 7.1)::

      K_k = P_{k-1} Omega_k / (lambda_m + Omega_k^2 P_{k-1})
      x_k = x_{k-1} + K_k (y_k - Omega_k x_{k-1})
      P_k = (P_{k-1} - K_k Omega_k P_{k-1}) / lambda_m

  This is algebraically the scalar RLS of paper 003 Eqs. (7)-(9) (there p_k Omega_k equals
  the gain K_k above), so :class:`RecursiveLeastSquares` is reused rather than duplicated.
* Eq. (31)  threshold judgment on the preprocessed data::

      epsilon = |g theta + g f + dv_x/dt|,   update only if epsilon >= threshold

  ``f`` is the rolling-resistance coefficient (the paper writes zeta in Eqs. 28-29 and f in
  Eq. 31), so epsilon is exactly |Omega_m| of Eq. (29): the judgment passes a sample only when
  the regressor carries enough excitation. It does *not* threshold the residual or the
  acceleration alone. A rejected sample leaves both the mass and P unchanged ("it remains the
  same as the last moment"), so there is no forgetting, and no covariance wind-up, while the
  excitation is low. Because Omega_m keeps its sign, braking and down-hill samples (Omega_m
  negative, y negative) are used as well as driving ones: the braking torque is in y.

Choices the paper leaves open (documented engineering choices, see :class:`FFRLSMassConfig`):
the threshold value, the initial covariance P_0, the "data preprocessing" (left to the
caller; the mass node averages its inputs over each update period), a minimum speed (Eq. 28
with rolling resistance only holds for a rolling vehicle), a maximum |grade| (the paper's
small-angle assumption, Sec. 5: theta <= 0.08 rad), an optional wheel/engine inertia term, the
variance and convergence outputs, and clipping of the *published* mass.

Forgetting and sample rate: lambda_m = 0.998 was used at the paper's sampling time
tau = 0.01 s (Sec. 7.1), a memory of 1 / (1 - lambda) = 500 samples = 5 s. Applied per sample
at another rate it means another memory in seconds (125 s at 4 Hz); use
:func:`equivalent_forgetting_factor` to keep the paper's memory in seconds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from vehicle_estimation.contract.settings import setting
from vehicle_estimation.contract.vehicle import VehicleParams, dataclass_from_mapping
from vehicle_estimation.estimators.common.guard import finite_number
from vehicle_estimation.estimators.mass.forgetting import ForgettingConfig, ForgettingMassEstimator
from vehicle_estimation.estimators.mass.mass_rls import predict_gear

#: The paper's sampling time tau (Sec. 7.1), at which lambda_m = 0.998 was tuned [s].
PAPER_SAMPLE_PERIOD_S = 0.01

#: Rejection reasons counted in :attr:`FFRLSMassEstimator.rejected`.
REJECT_REASONS = (
    "nan",        # t, vx, ax, slope or brake_torque not finite, or a non-finite RLS result
    "speed",      # vx < min_speed (standstill / creeping: Eq. 28 does not hold)
    "slope",      # |slope| > max_abs_slope (outside the small-angle linearisation of Eq. 29)
    "no_force",   # no drive force, drive torque or engine torque available
    "gear",       # engine torque given but no gear known (needed for i_g of Eq. 28)
    "threshold",  # Eq. (31): epsilon = |Omega_m| below the threshold
)


def equivalent_forgetting_factor(forgetting_factor: float, reference_period_s: float,
                                 period_s: float) -> float:
    """lambda at ``period_s`` with the same memory in seconds as ``forgetting_factor`` at
    ``reference_period_s``: lambda^(period / reference).

    A sample k steps old carries weight lambda^k = exp(k ln lambda); keeping that weight a
    function of the age in seconds, k·period, gives the exponent. Example: the paper's 0.998 at
    0.01 s is 0.9512 at 0.25 s (4 Hz), both a time constant of about 5 s.
    """
    lam, ref, period = float(forgetting_factor), float(reference_period_s), float(period_s)
    if not (math.isfinite(lam) and 0.0 < lam <= 1.0):
        raise ValueError(f"forgetting_factor must be in (0, 1], got {forgetting_factor!r}")
    if not (math.isfinite(ref) and ref > 0.0):
        raise ValueError(f"reference_period_s must be finite and > 0, got {reference_period_s!r}")
    if not (math.isfinite(period) and period > 0.0):
        raise ValueError(f"period_s must be finite and > 0, got {period_s!r}")
    return lam ** (period / ref)


@dataclasses.dataclass
class FFRLSMassConfig(ForgettingConfig):
    """Tuning of :class:`FFRLSMassEstimator` (SI units).

    From the paper: ``forgetting_factor`` (lambda_m = 0.998, Sec. 7.1, at tau = 0.01 s) and
    ``initial_mass`` (1300 kg, Sec. 7.1; the true mass there is 1529.98 kg). The rest are
    choices the paper leaves open:

    * ``excitation_threshold``: the threshold of Eq. (31) on |Omega_m| [m/s^2]. 0.3 m/s^2 is
      about 2.4 times the rolling-resistance floor g·zeta (0.13 m/s^2 at zeta = 0.013), so
      steady cruising on the level is skipped, and about 3.5 times the regressor error of a
      0.5 deg grade error (0.086 m/s^2), so that error stays below about 30 % of Omega_m in
      every accepted sample.
    * ``initial_gain``: P_0 [s^4/m^2]. The mass variance is about P·sigma^2 (sigma the
      force residual); P_0 = 10 with sigma ~ 200 N is a prior std of about 600 kg, weak
      enough to leave 1300 kg within a few strongly excited samples.
    * ``min_speed``, ``max_abs_slope``: validity of Eqs. (28)-(29).
    * ``rotating_inertia_correction``: off (paper). On, y also loses (I_w/R_t^2)·dv_x/dt for
      a drive force or wheel torque input, plus I_e G^2·dv_x/dt for an engine-torque input,
      so the estimate is the mass rather than mass plus the equivalent rotating mass.
    """

    forgetting_factor: float = setting(0.998, "lambda_m of Eq. (30); Sec. 7.1 (at tau = 0.01 s)",
                                       low=0.0, high=1.0, low_open=True)
    initial_mass: float = setting(1300.0, "x_m,0 [kg], Sec. 7.1", low=0.0, low_open=True)
    initial_gain: float = setting(10.0, "P_m,0 [s^4/m^2] (not in the paper)", low=0.0, low_open=True)
    excitation_threshold: float = setting(0.3, "Eq. (31) threshold on |Omega_m| [m/s^2] (not in the paper)",
                                          low=0.0)
    rotating_inertia_correction: bool = setting(False, "Take the rotating inertia out of y (not in the paper)")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> FFRLSMassConfig:
        """Build from a flat mapping (e.g. ROS parameters); unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown FFRLS mass estimator parameter {key!r}")


class FFRLSMassEstimator(ForgettingMassEstimator):
    """Online mass estimate, paper 004 Eqs. (28)-(31).

    Feed one sample per :meth:`step`. Properties: :attr:`mass` (clipped to the configured
    bounds), :attr:`variance`, :attr:`converged`, :attr:`samples_used`, :attr:`rejected`
    (count per reason in :data:`REJECT_REASONS`), as :class:`LongitudinalMassEstimator`.

    Variance: P·sigma^2 with P of Eq. (30) and sigma^2 an exponentially weighted (same
    lambda) mean of the squared a-priori residuals y - Omega_m x_m, seeded with
    ``initial_residual_std^2`` at weight one, plus the regressor's lasting errors
    (:class:`ForgettingMassEstimator`). Without ``rotating_inertia_correction`` (the paper's
    Eq. 28) y keeps the force (I_w/R_t^2 + I_e G^2)·dv_x/dt that turns the wheels and the
    engine, on every sample: a lasting force error of known size, which the residuals cannot
    show and which the variance therefore carries whole (a lasting force sensitivity of that
    force, covariance 1). Why: on FASTSim's car (wheels 31 kg equivalent) the paper's estimate
    ends 1.6 % high, where P·sigma^2 alone said 0.7 % (32 % of the last half within 2 sigma).
    """

    REJECT_REASONS = REJECT_REASONS
    window_brake = "mean"    # Eq. (28) regresses the braking force: the window's mean

    def __init__(self, params: VehicleParams, config: FFRLSMassConfig | None = None) -> None:
        super().__init__(params, config if config is not None else FFRLSMassConfig())
        # The lumped rotating inertia's force, in units of itself (see the class docstring).
        self.lasting_force_covariance = None if self.config.rotating_inertia_correction else np.ones((1, 1))

    def _reset_method_state(self) -> None:
        self.last_epsilon = math.nan   # epsilon of Eq. (31) of the last sample that reached it

    @property
    def gain(self) -> float:
        """P_m of Eq. (30) [s^4/m^2]."""
        return self.rls.p

    # ------------------------------------------------------------------ update
    def _gear(self, gear: Any, engine_speed: Any, vx: float) -> int | None:
        if finite_number(gear):
            g = round(float(gear))
            return g if 1 <= g <= len(self.params.gear_ratios) else None   # neutral, reverse: none
        return predict_gear(engine_speed, vx, self.params)                 # paper 003 Eqs. (10)-(11)

    def regressor(self, ax: float, slope: float) -> float:
        """Omega_m of Eq. (29) = g theta + g zeta + dv_x/dt [m/s^2]; |Omega_m| is the epsilon
        of Eq. (31)."""
        g = self.params.gravity
        return g * slope + g * self.params.rolling_resistance + ax

    def step(self, t: float, vx: float, ax: float, slope: float, *,
             drive_force: float = math.nan, drive_torque: float = math.nan,
             engine_torque: float = math.nan, engine_speed: float = math.nan,
             engine_load: float = math.nan, gear: float = math.nan,
             brake_torque: float = 0.0, heading: float = math.nan,
             regressor_bias_variance: float = 0.0, regressor_bias_correlation_s: float = math.inf,
             accel_noise_variance: float = 0.0) -> bool:
        """Process one sample; return True when it updated the estimate (Eq. 30).

        ``regressor_bias_variance`` [m^2/s^4]: the variance of a lasting error in Omega_m (the
        accelerometer bias), ``regressor_bias_correlation_s`` [s] how long it lasts, see
        :class:`~vehicle_estimation.estimators.mass.mass_rls.ForgettingMassEstimator`.

        ``t`` [s], ``vx`` longitudinal speed [m/s], ``ax`` the longitudinal acceleration
        dv_x/dt [m/s^2] (not the IMU specific force, which contains g sin(theta)), ``slope``
        the road grade theta [rad, + uphill], ``brake_torque`` the total braking torque T_b
        over all wheels [N m] (0 when not braking; a non-finite value is rejected because y
        needs it; a negative one is read as 0).

        The drive term T_tq i_g i_0 eta_t / R_t of Eq. (28) is, first available of:

        1. ``drive_force`` [N], the driveline force at the wheels;
        2. ``drive_torque`` [N m], the driveline torque at the wheels (sum over the driven
           wheels), divided by R_t;
        3. ``engine_torque`` [N m] × eta_t × i_g i_0 / R_t, the gear from ``gear`` (1-based)
           or predicted from ``engine_speed`` [rad/s] and ``vx`` (paper 003 Eqs. 10-11).

        ``accel_noise_variance`` [m^2/s^4]: the white noise of ``ax``, whose errors-in-variables
        bias enters the variance (as for the RLS).

        ``engine_load`` and ``heading`` are accepted for call compatibility with
        :meth:`LongitudinalMassEstimator.step` and not used (paper 004 has no torque map and
        no wind compensation).
        """
        cfg = self.config
        p = self.params
        values = (t, vx, ax, slope, brake_torque)
        if not all(finite_number(v) for v in values):
            return self._reject("nan")
        t, vx, ax, slope, brake_torque = (float(v) for v in values)
        brake_torque = max(brake_torque, 0.0)   # a magnitude; sensor noise can dip below zero
        ax = self._calibrated_accel(t, vx, ax, accel_noise_variance)

        current_gear = self._gear(gear, engine_speed, vx) if finite_number(engine_torque) else None
        self.last_gear = current_gear

        if vx < cfg.min_speed:
            return self._reject("speed")
        if abs(slope) > cfg.max_abs_slope:
            return self._reject("slope")

        # Drive term of Eq. (28) and, for the optional correction, the rotating inertia
        # downstream of where that drive term is measured.
        wheel_inertia = p.wheel_inertia / p.wheel_radius ** 2
        if finite_number(drive_force):
            drive = float(drive_force)
            rotating_inertia = wheel_inertia
        elif finite_number(drive_torque):
            drive = float(drive_torque) / p.wheel_radius
            rotating_inertia = wheel_inertia
        elif finite_number(engine_torque):
            if current_gear is None:
                return self._reject("gear")
            gearing = p.effective_gearing(current_gear)                  # i_g i_0 / R_t
            drive = float(engine_torque) * gearing * p.driveline_efficiency
            rotating_inertia = wheel_inertia + p.engine_inertia * gearing ** 2
        else:
            return self._reject("no_force")

        # Eq. (31): data judgment on the excitation epsilon = |Omega_m|.
        omega = self.regressor(ax, slope)                                  # Eq. (29)
        epsilon = abs(omega)
        self.last_epsilon = epsilon
        if not epsilon >= cfg.excitation_threshold:
            return self._reject("threshold")

        aero_drag = 0.5 * p.air_density * p.drag_area * vx * vx            # C_d A rho v^2 / 2
        y = drive - brake_torque / p.wheel_radius - aero_drag              # Eq. (29)
        lumped = None
        if cfg.rotating_inertia_correction:
            y -= rotating_inertia * ax
        else:
            lumped = np.array([rotating_inertia * ax])      # y - m Omega_m, whatever m
        if not (math.isfinite(y) and math.isfinite(omega)):
            return self._reject("nan")

        theta_before, p_before, residual_before = self.rls.theta, self.rls.p, self.rls.last_residual
        self.rls.update(omega, y)                                          # Eq. (30)
        lam = cfg.forgetting_factor
        residual = self.rls.last_residual
        residual_sq = lam * self._res_sq + residual * residual
        if not (math.isfinite(self.rls.theta) and math.isfinite(self.rls.p) and self.rls.p > 0.0
                and math.isfinite(residual_sq)):
            # Overflow on absurd but finite inputs: keep the last estimate, as Eq. (31) does.
            self.rls.theta, self.rls.p, self.rls.last_residual = theta_before, p_before, residual_before
            return self._reject("nan")
        return self._accepted(t, omega, y, residual * residual, regressor_bias_variance,
                              regressor_bias_correlation_s, regressor_noise_variance=accel_noise_variance,
                              lasting_force_sensitivity=lumped)
