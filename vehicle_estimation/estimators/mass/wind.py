"""Online estimate of a steady ambient wind from the longitudinal force balance, for the drag
term of paper 003's mass estimator. Plain Python/NumPy, no ROS.

Why: paper 003 (Jensen et al. 2022) Secs. 7.4-7.5 show that ambient wind biases the RLS mass at
highway speed (a 5 m/s headwind at 110 km/h adds ~100 N of drag, which Eq. (6) books as mass),
and name its compensation as the open problem (Sec. 8). Fig. 17 of the paper compensates a
*known* wind by projecting it on the heading; here the wind is *estimated*.

Model. With the air velocity w = (w_E, w_N) in ENU (the direction the air moves to) and the
vehicle heading psi (ENU yaw, from east, counter-clockwise), the air speed along the vehicle is
v - w_a with w_a = w_E cos(psi) + w_N sin(psi) (a tailwind has w_a > 0), and Eq. (1) reads::

    z = F_p - (I_w/r^2 + I_e G^2) a = m phi + 1/2 rho C_a (v - w_a) |v - w_a|          (*)

with phi of Eq. (5). The force residual of a wrong wind changes sign with the heading while
the mass term does not; so over a drive with heading changes (any real route) (*) separates
m from w. An extended Kalman filter on x = [m, w_E, w_N] with random-walk process noise does
this jointly (the mass is a nuisance state here, so that a load change is not mistaken for wind;
the published mass stays the paper's scalar RLS, which then uses this wind in its drag term)::

    predict:  P <- P + diag(q_m, q_w, q_w) dt
    update:   H = [phi, -rho C_a |v - w_a| cos(psi), -rho C_a |v - w_a| sin(psi)],
              S = H P H^T + sigma^2, K = P H^T / S, x <- x + K (z - h(x)),
              P <- (I - K H) P (I - K H)^T + K sigma^2 K^T          (Joseph form)

Rolling resistance (optional, ``rolling_resistance_std > 0``). A tyre-pressure or temperature
change the calibration never saw moves C_r, and a C_r error is a force that grows with the mass
only through g cos(theta), m g cos(theta) dC_r, which the scalar RLS books as mass (paper 003
drive 12: C_r x 1.4, 87 % of windows within +-5 %). A fourth state dC_r (the deviation from the
vehicle's C_r, a random walk) with ``H_4 = m g cos(theta)`` separates it from the mass where phi
varies (accelerations, grades): phi of Eq. (5) then uses C_r + dC_r. Without ``estimate_wind``
the wind states stay at zero (no prior variance) and the heading is not needed.

Inputs per sample (all already computed by the mass core for Eq. (6)): time, speed v [m/s],
heading psi [rad] (the fusion node's odometry yaw in ENU), phi [m/s^2] and z [N]. It needs
nothing else: the drag area C_a and air density come from the (calibrated) vehicle. Vertical
wind and gusts are not modelled; the random walk lets the wind drift slowly (``random_walk``).

Limits (documented, not hidden): the wind is only observable after the heading has changed by a
good fraction of a turn; any force-model error that depends on the heading (none in theory)
would be read as wind; a wrong C_a makes the wind estimate absorb part of the drag error on
straight stretches, which is harmless for the mass (the compensation then corrects that too).
Samples are gated: v >= ``min_speed`` (the wind term scales with v), finite inputs, increasing
time, and an innovation test |z - h| <= ``gate`` sqrt(S) (gusts, model outliers); rejected
samples are counted in :attr:`WindEstimator.rejected`, never raised.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.estimators.common.guard import all_finite

REJECT_REASONS = ("nan", "time", "speed", "innovation")


@dataclasses.dataclass(frozen=True)
class WindEstimatorConfig:
    """Tuning of :class:`WindEstimator` (SI)."""

    force_std: float = setting(150.0, "Sigma of z in (*) per 0.25 s sample: torque-map and grade errors [N]",
                               low=0.0, low_open=True)
    random_walk: float = setting(0.02, "Wind random walk [m/s per sqrt(s)] (1.2 m/s per hour)", low=0.0)
    mass_random_walk: float = setting(5.0, "Nuisance-mass random walk [kg per sqrt(s)] (follows load changes)",
                                      low=0.0)
    initial_wind_std: float = setting(6.0, "Prior sigma of each wind component [m/s]", low=0.0, low_open=True)
    initial_mass_std: float = setting(600.0, "Prior sigma of the nuisance mass [kg]", low=0.0, low_open=True)
    min_speed: float = setting(8.0, "No wind update below this speed [m/s]", low=0.0)
    gate: float = setting(5.0, "Innovation test in standard deviations", low=0.0, low_open=True)
    max_abs_wind: float = setting(25.0, "The published wind is clipped to this magnitude [m/s]",
                                  low=0.0, low_open=True)
    estimate_wind: bool = setting(True, "Estimate the wind (else it stays 0 and no heading is needed)")
    rolling_resistance_std: float = setting(0.0, "Prior sigma of the rolling-resistance deviation dC_r "
                                            "(0 = not estimated) [-]", low=0.0, high=0.05)
    rolling_resistance_walk: float = setting(2e-5, "Random walk of dC_r [1 per sqrt(s)] (0.0012 per hour)",
                                             low=0.0)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        check_settings(self)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> "WindEstimatorConfig":
        from vehicle_estimation.contract.vehicle import dataclass_from_mapping
        return dataclass_from_mapping(cls, values, "unknown wind estimator parameter {key!r}")


class WindEstimator:
    """EKF on [m, w_E, w_N, dC_r] from the longitudinal force balance (*) of the module docstring;
    a state whose prior sigma is 0 (the wind without ``estimate_wind``, dC_r without
    ``rolling_resistance_std``) stays at 0."""

    def __init__(self, air_density: float, drag_area: float, initial_mass: float,
                 config: WindEstimatorConfig | None = None) -> None:
        self.config = config if config is not None else WindEstimatorConfig()
        self.config.validate()
        if not (all_finite(air_density, drag_area, initial_mass) and air_density > 0 and drag_area > 0
                and initial_mass > 0):
            raise ValueError("air_density, drag_area and initial_mass must be finite and > 0")
        self.k_drag = 0.5 * float(air_density) * float(drag_area)
        self.initial_mass = float(initial_mass)
        self.reset()

    def reset(self) -> None:
        cfg = self.config
        wind_var = cfg.initial_wind_std ** 2 if cfg.estimate_wind else 0.0
        self.x = np.array([self.initial_mass, 0.0, 0.0, 0.0])
        self.P = np.diag([cfg.initial_mass_std ** 2, wind_var, wind_var, cfg.rolling_resistance_std ** 2])
        self._p_max = np.diag(self.P).copy()
        # Random-walk densities; a state without prior variance (not estimated) gets none.
        walk = np.array([cfg.mass_random_walk, cfg.random_walk, cfg.random_walk, cfg.rolling_resistance_walk])
        self._q_density = np.where(self._p_max > 0.0, walk ** 2, 0.0)
        self._last_t = math.nan
        self.samples_used = 0
        self.rejected: dict[str, int] = {reason: 0 for reason in REJECT_REASONS}

    # ------------------------------------------------------------------ outputs
    @property
    def wind_enu(self) -> tuple[float, float]:
        """Estimated air velocity (E, N) [m/s], clipped to ``max_abs_wind`` in magnitude."""
        e, n = float(self.x[1]), float(self.x[2])
        speed = math.hypot(e, n)
        if speed > self.config.max_abs_wind:
            e, n = e * self.config.max_abs_wind / speed, n * self.config.max_abs_wind / speed
        return e, n

    @property
    def wind_std(self) -> tuple[float, float]:
        return math.sqrt(max(self.P[1, 1], 0.0)), math.sqrt(max(self.P[2, 2], 0.0))

    @property
    def wind_speed(self) -> float:
        return math.hypot(*self.wind_enu)

    @property
    def wind_from_deg(self) -> float:
        """Meteorological direction the wind blows *from*, degrees clockwise from north."""
        e, n = self.wind_enu
        return math.degrees(math.atan2(-e, -n)) % 360.0

    @property
    def nuisance_mass(self) -> float:
        return float(self.x[0])

    @property
    def rolling_resistance_offset(self) -> float:
        """Estimated dC_r, the deviation from the vehicle's C_r (0 when not estimated) [-]."""
        return float(self.x[3])

    @property
    def rolling_resistance_offset_std(self) -> float:
        return math.sqrt(max(self.P[3, 3], 0.0))

    def along(self, heading: float) -> float:
        """Wind component along the heading w_a [m/s] (+: tailwind); 0 for a non-finite heading."""
        if not all_finite(heading):
            return 0.0
        e, n = self.wind_enu
        return e * math.cos(heading) + n * math.sin(heading)

    def drag(self, v: float, heading: float) -> float:
        """Aerodynamic drag 1/2 rho C_a (v - w_a)|v - w_a| [N] with the estimated wind."""
        va = float(v) - self.along(heading)
        return self.k_drag * va * abs(va)

    # ------------------------------------------------------------------ update
    def update(self, t: float, v: float, heading: float, phi: float, net_force: float,
               gravity_normal: float = math.nan) -> bool:
        """One sample of (*): ``net_force`` = F_p - (I_w/r^2 + I_e G^2) a [N], ``phi`` of Eq. (5)
        with the vehicle's C_r, ``gravity_normal`` = g cos(theta) [m/s^2] (needed when dC_r is
        estimated). True when used."""
        cfg = self.config
        if not cfg.estimate_wind:
            heading = 0.0      # the wind states stay at zero: any heading gives the same
        if cfg.rolling_resistance_std == 0.0:
            gravity_normal = 0.0
        if not all_finite(t, v, heading, phi, net_force, gravity_normal):
            self.rejected["nan"] += 1
            return False
        t, v, heading, phi, z = float(t), float(v), float(heading), float(phi), float(net_force)
        if math.isfinite(self._last_t) and t <= self._last_t:
            self.rejected["time"] += 1
            return False
        if v < cfg.min_speed:
            self.rejected["speed"] += 1
            return False
        dt = 0.0 if math.isnan(self._last_t) else t - self._last_t
        P = self.P + np.diag(self._q_density * dt)
        # A long stop must not inflate the covariance beyond the prior.
        d = np.minimum(np.diag(P), self._p_max)
        P[np.diag_indices(4)] = d
        c, s = math.cos(heading), math.sin(heading)
        m, we, wn, dcr = self.x
        va = v - (we * c + wn * s)
        phi_c = phi + gravity_normal * dcr
        h = m * phi_c + self.k_drag * va * abs(va)
        H = np.array([phi_c, -2.0 * self.k_drag * abs(va) * c, -2.0 * self.k_drag * abs(va) * s,
                      m * gravity_normal])
        R = cfg.force_std ** 2
        PHt = P @ H
        S = float(H @ PHt) + R
        innov = z - h
        self._last_t = t
        if not (math.isfinite(S) and S > 0.0) or abs(innov) > cfg.gate * math.sqrt(S):
            self.P = P
            self.rejected["innovation"] += 1
            return False
        K = PHt / S
        x_new = self.x + K * innov
        IKH = np.eye(4) - np.outer(K, H)
        P_new = IKH @ P @ IKH.T + np.outer(K, K) * R
        if not (np.all(np.isfinite(x_new)) and np.all(np.isfinite(P_new))):
            self.P = P
            self.rejected["nan"] += 1
            return False
        self.x = x_new
        self.P = 0.5 * (P_new + P_new.T)
        self.samples_used += 1
        return True
