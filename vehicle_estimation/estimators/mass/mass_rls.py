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

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

from vehicle_estimation.contract.settings import setting
from vehicle_estimation.contract.vehicle import VehicleParams, dataclass_from_mapping
from vehicle_estimation.estimators.common.guard import finite_number
from vehicle_estimation.estimators.mass.calibration import GRID_PARAMETERS
from vehicle_estimation.estimators.mass.forgetting import ForgettingConfig, ForgettingMassEstimator
from vehicle_estimation.estimators.mass.wind import WindEstimator, WindEstimatorConfig

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


@dataclasses.dataclass
class MassRLSConfig(ForgettingConfig):
    """Tuning of :class:`LongitudinalMassEstimator` (SI units unless stated).

    The RLS values are the paper's (Sec. 3 and 7.4); the gates beyond ``min_accel`` are
    engineering choices documented in the module docstring.
    """

    forgetting_factor: float = setting(0.9995, "Forgetting factor lambda, Eq. (7) (paper: 0.9995)",
                                       low=0.0, high=1.0, low_open=True)
    initial_mass: float = setting(1000.0, "Initial mass m(0) [kg], Sec. 3", low=0.0, low_open=True)
    initial_gain: float = setting(1000.0, "Initial gain p(0) [s^4/m^2], Sec. 3", low=0.0, low_open=True)
    # --- gating (a sample must pass all to update the RLS)
    min_accel: float = setting(0.0, "A sample needs ax above this [m/s^2] (Sec. 7.1: only a > 0)")
    max_brake_torque: float = setting(1.0, "A sample counts only with a total brake torque at most this [N m]",
                                      low=0.0)
    gear_shift_holdoff_s: float = setting(0.5, "Samples this long after a gear change are not used [s]",
                                          low=0.0)
    min_phi: float = setting(0.05, "|phi| of Eq. (5) must be at least this [m/s^2]", low=0.0)
    min_propulsion_force: float = setting(0.0, "The propulsion force must be above this [N]")
    # --- gear prediction, Eqs. (10)-(11)
    gear_ratio_tolerance: float = setting(0.10, "Max relative |G_meas - G_j| / G_j of Eq. (11), else the "
                                          "clutch slips", low=0.0, low_open=True)
    # --- propulsion sources
    drive_force_kind: str = setting("wheel", "Meaning of the drive force input: wheel (driveshaft torque "
                                    "over r), propulsion (eta T_e G of Eq. 1) or tractive (tyre-road force)",
                                    choices=DRIVE_FORCE_KINDS)
    torque_regression: list[float] = setting([], "Engine torque map w0..wn of Eq. (49) (calibrate writes it)")
    torque_regression_relative_std: float = setting(
        0.0, "Relative std of that map's torque where the calibration drive ran (calibrate writes it from "
        "the fit's coefficient covariance): a scale error of the propulsion force that lasts, which the "
        "mass variance carries [-]", low=0.0, high=1.0)
    torque_model_covariance: list[float] = setting(
        [], "Joint covariance of the calibration's fit, row by row: [w0..wn of Eq. (49), C_a, C_r, I_e, I_w] "
        "((n + 5)^2 values; calibrate writes it): parameter errors that last, which the mass variance "
        "carries (instead of torque_regression_relative_std)")
    torque_regression_speed_unit: str = setting("rpm", "Unit of N_e in Eq. (49) (rpm as Table 6, or rad/s)",
                                                choices=("rpm", "rad/s"))
    # --- ambient wind (not in the paper, its Sec. 8 open problem): with wind_compensation the
    # drag term of Eq. (6) uses the wind of estimators/mass/wind.py (EKF on [m, w_E, w_N] from
    # the same samples) projected on the heading passed to step(heading=...); off: still air.
    wind_compensation: bool = setting(False, "Estimate the wind online (estimators/mass/wind.py) and "
                                      "compensate the drag; needs a heading")
    wind_force_std: float = setting(150.0, "WindEstimatorConfig.force_std [N]", low=0.0, low_open=True)
    wind_random_walk: float = setting(0.02, "WindEstimatorConfig.random_walk [m/s per sqrt(s)]", low=0.0)
    wind_mass_random_walk: float = setting(5.0, "WindEstimatorConfig.mass_random_walk [kg per sqrt(s)]",
                                           low=0.0)
    wind_initial_std: float = setting(6.0, "WindEstimatorConfig.initial_wind_std [m/s]", low=0.0, low_open=True)
    wind_min_speed: float = setting(8.0, "WindEstimatorConfig.min_speed [m/s]", low=0.0)
    # --- rolling resistance (not in the paper): a tyre pressure the calibration never saw is a
    # force the RLS would read as mass; the same EKF also estimates dC_r, and Eq. (5) uses C_r + dC_r.
    rolling_resistance_estimation: bool = setting(
        False, "Estimate the rolling resistance's deviation dC_r online with the mass (the road-load EKF "
        "of estimators/mass/wind.py) and use C_r + dC_r in Eq. (5)")
    rolling_resistance_std: float = setting(0.004, "Prior sigma of dC_r [-]", low=0.0, low_open=True, high=0.05)
    rolling_resistance_walk: float = setting(2e-5, "Random walk of dC_r [1 per sqrt(s)]", low=0.0)
    # The torque map's errors are correlated in time; at the wind's 150 N per sample the EKF takes
    # them for a C_r that trades against its mass on low-excitation stretches (paper 003 campaign:
    # reference drive 3 dropped to 92.5 % of windows within +-5 %; 100 % at 600 N).
    rolling_resistance_force_std: float = setting(
        600.0, "WindEstimatorConfig.force_std while dC_r is estimated [N]", low=0.0, low_open=True)

    @property
    def road_load_estimation(self) -> bool:
        """Whether the road-load EKF runs (wind, rolling resistance or both)."""
        return bool(self.wind_compensation or self.rolling_resistance_estimation)

    def wind_config(self, initial_mass_std: float) -> WindEstimatorConfig:
        """The road-load EKF's config from the ``wind_*`` and ``rolling_resistance_*`` fields, its
        nuisance mass a priori ``initial_mass_std`` from the RLS's own [kg]."""
        force_std = self.rolling_resistance_force_std if self.rolling_resistance_estimation else self.wind_force_std
        return WindEstimatorConfig(force_std=force_std, random_walk=self.wind_random_walk,
                                   initial_mass_std=initial_mass_std,
                                   mass_random_walk=self.wind_mass_random_walk,
                                   initial_wind_std=self.wind_initial_std, min_speed=self.wind_min_speed,
                                   estimate_wind=bool(self.wind_compensation),
                                   rolling_resistance_std=(self.rolling_resistance_std
                                                           if self.rolling_resistance_estimation else 0.0),
                                   rolling_resistance_walk=self.rolling_resistance_walk)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        super().validate()
        if len(self.torque_regression or []) == 1:
            raise ValueError("torque_regression needs at least [w0, w1] (Eq. 49), got one coefficient")
        if self.torque_model_covariance:
            self.model_covariance()

    def model_covariance(self) -> "np.ndarray | None":
        """``torque_model_covariance`` as a matrix (None when not given); ``ValueError`` naming
        the field when it does not fit the regression or is no covariance."""
        values = list(self.torque_model_covariance or [])
        if not values:
            return None
        n = len(self.torque_regression or []) + len(GRID_PARAMETERS)
        if len(values) != n * n:
            raise ValueError(f"torque_model_covariance needs {n * n} values ({n} x {n}: the "
                             f"{len(self.torque_regression or [])} torque_regression coefficients and "
                             f"{', '.join(GRID_PARAMETERS)}), got {len(values)}")
        cov = np.asarray(values, dtype=float).reshape(n, n)
        if not (np.all(np.isfinite(cov)) and np.allclose(cov, cov.T, rtol=1e-6, atol=0.0)
                and np.all(np.diag(cov) >= 0.0)):
            raise ValueError("torque_model_covariance must be a finite symmetric matrix with a "
                             "non-negative diagonal")
        return cov

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "MassRLSConfig":
        """Build from a flat mapping (e.g. ROS parameters); unknown keys are an error."""
        return dataclass_from_mapping(cls, values, "unknown mass estimator parameter {key!r}")


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

    def features(self, load: float, engine_speed: float) -> list[float]:
        """The Eq.-(49) terms the coefficients multiply, [1, L, N_e, N_e^2, ...], N_e in the
        coefficients' unit, for ``engine_speed`` [rad/s]."""
        n = float(engine_speed) * (RPM_PER_RAD_S if self.speed_unit == "rpm" else 1.0)
        return [1.0, float(load)] + [n ** k for k in range(1, len(self.coefficients) - 1)]

    def torque(self, load: float, engine_speed: float) -> float:
        """T_load [N m] for load ``load`` and engine speed ``engine_speed`` [rad/s]."""
        return sum(w * f for w, f in zip(self.coefficients, self.features(load, engine_speed)))


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
        # The calibration's lasting force error: its joint covariance, else the map's scale
        # alone (one parameter, in units of its std: sensitivity std |F|, covariance 1).
        covariance = config.model_covariance()
        if covariance is None and config.torque_regression_relative_std > 0.0:
            covariance = np.ones((1, 1))
        self.lasting_force_covariance = covariance
        super().__init__(params, config)

    def _reset_method_state(self) -> None:
        self._last_gear: int | None = None
        self._last_shift_t = -math.inf
        # The wind is re-estimated after every reset (it is not persisted: it changes between drives).
        self.wind: WindEstimator | None = None
        if self.config.road_load_estimation:
            # The EKF's mass starts where the RLS stands and as uncertain: with a tighter prior
            # than the RLS's (a 36 t truck against the paper's 1000 kg m(0)), the EKF explains
            # the missing mass as rolling resistance, and Eq. (5) then takes it from the RLS.
            self.wind = WindEstimator(self.params.air_density, self.params.drag_area, self.rls.theta,
                                      self.config.wind_config(math.sqrt(self.variance)))

    @property
    def needs_heading(self) -> bool:  # type: ignore[override]
        return bool(self.config.wind_compensation)

    def status(self) -> dict[str, str]:
        out = super().status()
        if self.wind is None:
            return out
        if self.config.wind_compensation:
            east, north = self.wind.wind_enu
            out.update({"wind east, north [m/s]": f"{east:.2f}, {north:.2f}",
                        "wind from [deg]": f"{self.wind.wind_from_deg:.0f}"})
        if self.config.rolling_resistance_estimation:
            out["rolling resistance"] = (f"{self.rolling_resistance:.4f} +- "
                                         f"{self.wind.rolling_resistance_offset_std:.4f}")
        return out

    @property
    def rolling_resistance(self) -> float:
        """C_r in use in Eq. (5): the vehicle's, plus the estimated dC_r where it is estimated."""
        offset = self.wind.rolling_resistance_offset if self.wind is not None else 0.0
        return self.params.rolling_resistance + offset

    def _gear(self, gear: float, engine_speed: float, vx: float) -> int | None:
        n_gears = len(self.params.gear_ratios)
        if finite_number(gear):
            g = int(round(gear))
            return g if 1 <= g <= n_gears else None   # 0 (neutral), reverse: no gear
        return predict_gear(engine_speed, vx, self.params, tolerance=self.config.gear_ratio_tolerance)

    def step(self, t: float, vx: float, ax: float, slope: float, *,
             drive_force: float = math.nan, engine_torque: float = math.nan,
             engine_speed: float = math.nan, engine_load: float = math.nan,
             gear: float = math.nan, brake_torque: float = 0.0, heading: float = math.nan,
             regressor_bias_variance: float = 0.0, regressor_bias_correlation_s: float = math.inf,
             accel_noise_variance: float = 0.0) -> bool:
        """Process one sample; return True when it updated the RLS.

        ``t`` [s], ``vx`` longitudinal speed [m/s], ``ax`` longitudinal acceleration dv/dt
        [m/s^2] (not the IMU specific force), ``slope`` road grade alpha [rad, + uphill];
        ``regressor_bias_variance`` [m^2/s^4] the variance of a lasting error in
        ax + g sin(slope), i.e. of the accelerometer bias, ``regressor_bias_correlation_s``
        [s] how long that error lasts (class docstring); ``accel_noise_variance`` [m^2/s^4] the
        variance of ``ax``'s white noise (a speed fit's over a 0.25 s window: ~0.03 m/s^2), whose
        errors-in-variables bias enters the variance.

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
        if not all(finite_number(v) for v in vals):
            return self._reject("nan")
        t, vx, ax, slope = (float(v) for v in vals)
        ax = self._calibrated_accel(t, vx, ax, accel_noise_variance)

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
        if finite_number(brake_torque) and float(brake_torque) > cfg.max_brake_torque:
            return self._reject("braking")

        have_drive = finite_number(drive_force)
        have_torque = finite_number(engine_torque)
        have_reg = self.regression is not None and finite_number(engine_load) and finite_number(engine_speed)
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
        g_normal = g * math.cos(slope)
        phi = ax + g * p.rolling_resistance * math.cos(slope) + g * math.sin(slope)  # Eq. (5)
        if self.wind is not None:
            self.wind.update(t, vx, heading, phi, force - inertia * ax, g_normal)
            drag = self.wind.drag(vx, heading)                                  # F_a with the wind
            phi += g_normal * self.wind.rolling_resistance_offset               # C_r + dC_r
        else:
            drag = 0.5 * p.air_density * p.drag_area * vx * vx                 # F_a, Eq. (1)
        if abs(phi) < cfg.min_phi:
            return self._reject("phi")
        y = force - drag - inertia * ax                                          # Eq. (6)

        sensitivity = None
        if have_reg and not (have_drive or have_torque) and self.lasting_force_covariance is not None:
            sensitivity = (self._calibration_sensitivity(float(engine_load), float(engine_speed), G, vx, ax, g_normal)
                           if self.lasting_force_covariance.shape[0] > 1
                           else np.array([cfg.torque_regression_relative_std * abs(force)]))
        self.rls.update(phi, y)                                                   # Eqs. (7)-(9)
        return self._accepted(t, phi, y, self.rls.last_residual ** 2, regressor_bias_variance,
                              regressor_bias_correlation_s, regressor_noise_variance=accel_noise_variance,
                              lasting_force_sensitivity=sensitivity)

    def _calibration_sensitivity(self, load: float, engine_speed: float, G: float, vx: float, ax: float,
                                 g_normal: float) -> np.ndarray:
        """How the residual y - m phi of Eq. (6) moves per unit error of each calibrated value
        (``torque_model_covariance``'s order) [N per unit]: the map's G x (Eq. 49's features),
        the drag -1/2 rho v^2, the rolling resistance -m g cos(theta), the inertias -G^2 a and
        -a / r^2; the calibration's own Z row (calibration.dynamics_torque_basis) times G."""
        assert self.regression is not None
        p = self.params
        return np.array([G * f for f in self.regression.features(load, engine_speed)]
                        + [-0.5 * p.air_density * vx * vx, -self.rls.theta * g_normal,
                           -G * G * ax, -ax / p.wheel_radius ** 2])
