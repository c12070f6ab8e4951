"""The filter of paper 000's TA-AEKF (Zhang et al. 2023, Secs. 2.3-2.4): the longitudinal
dynamics of Eqs. (6)-(14), the transition and Jacobian of Eqs. (29)-(34), the EKF of
Eqs. (20)-(28) with Algorithm 1's expanded observation, and the drive force of Eq. (13).

NumPy only; :mod:`vehicle_estimation.estimators.mass.ta_aekf` wraps it into the node-facing
estimator (network, confidence level, gates, flags). The equation map, units and the
rotating-mass factor are in that module's docstring.

Two optional states, neither in the paper, make the variance honest where its assumptions
fail (each is inert at zero variance, which leaves the paper's two-state filter):

* b, the network's lasting error: 1/m_nn = 1/m + b + white noise (see :class:`AdaptiveEKF`).
* e, the lasting error of the gravity term g (f cos(alpha) + sin(alpha)) computed from the
  estimated slope [m/s^2]. Paper 000 takes the slope as exact (its 0.3 deg error is a test,
  not a model), but a slope estimated from an accelerometer carries that accelerometer's bias,
  for the whole drive when no GNSS observes it; a 0.3 deg grade error is 0.05 m/s^2, the size
  of a heavy truck's whole excitation at highway speed. With e in the state the speed
  dynamics read a = a(alpha) + e / delta, and the filter's 1/m variance grows by what it
  cannot tell apart from e: little where the force varies, much on a steady cruise.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common.guard import finite_number


# --------------------------------------------------------------------- dynamics, Eqs. (14), (30)-(34)
@dataclasses.dataclass(frozen=True)
class DriveInput:
    """Control input u of Eq. (30) for one step.

    ``force``: F_t [N], the net force the driveline (minus the brakes) applies at the wheels
    at the current speed; ``dforce_dv``: its derivative with respect to v [N s/m] (0 for a
    measured force, -F/v for Eq. 13); ``slope`` alpha [rad]."""

    force: float
    dforce_dv: float
    slope: float


def _grade_accel(u: DriveInput, params: VehicleParams, grade_error: float) -> float:
    """g (f cos(alpha) + sin(alpha)) at the true slope: the estimated slope's term less e."""
    return params.gravity * (params.rolling_resistance * math.cos(u.slope) + math.sin(u.slope)) - grade_error


def longitudinal_accel(v: float, inv_mass: float, u: DriveInput, params: VehicleParams,
                       grade_error: float = 0.0) -> float:
    """a_x from Eq. (14) with delta = 1 + J/m (J = I_w / r^2)::

        a_x = (1/m (F_t - F_w) - g (f cos(alpha) + sin(alpha)) + e) / (1 + J/m)

    ``grade_error`` e [m/s^2]: the lasting error of the gravity term (module docstring; 0 in
    the paper)."""
    p = params
    drag = 0.5 * p.air_density * p.drag_area * v * abs(v)                     # F_w, Eq. (9)
    j = p.wheel_inertia / p.wheel_radius ** 2
    return (inv_mass * (u.force - drag) - _grade_accel(u, p, grade_error)) / (1.0 + j * inv_mass)


def transition(x: np.ndarray, u: DriveInput, dt: float, params: VehicleParams,
               grade_error: float = 0.0) -> np.ndarray:
    """g(x, u) of Eq. (30): [v + a_x dT, 1/m]."""
    v, inv_mass = float(x[0]), float(x[1])
    return np.array([v + longitudinal_accel(v, inv_mass, u, params, grade_error) * dt, inv_mass])


def transition_jacobian(x: np.ndarray, u: DriveInput, dt: float, params: VehicleParams,
                        grade_error: float = 0.0) -> np.ndarray:
    """A = dg/dx of Eqs. (32)-(34), analytic.

    With theta = 1/m, D = 1 + J theta, G = g (f cos + sin) - e and N = theta (F_t - F_w) - G::

        A11 = 1 + dT theta (dF_t/dv - rho C_d A |v|) / D                       (Eq. 33)
        A12 = dT ((F_t - F_w) D - J N) / D^2 = dT ((F_t - F_w) + J G) / D^2    (Eq. 34)

    For J = 0, e = 0 and F_t = P_e/v (Eq. 13, dF_t/dv = -F_t/v) these are Eqs. (33)-(34) in SI.
    (dv/de = dT / D is added by :class:`AdaptiveEKF` where e is a state.)
    """
    p = params
    v, theta = float(x[0]), float(x[1])
    j = p.wheel_inertia / p.wheel_radius ** 2
    rho_cda = p.air_density * p.drag_area
    drag = 0.5 * rho_cda * v * abs(v)
    d = 1.0 + j * theta
    a11 = 1.0 + dt * theta * (u.dforce_dv - rho_cda * abs(v)) / d
    a12 = dt * ((u.force - drag) + j * _grade_accel(u, p, grade_error)) / (d * d)
    return np.array([[a11, a12], [0.0, 1.0]])


class AdaptiveEKF:
    """The EKF of Eqs. (20)-(28) on x = [v_x, 1/m] with the expanded observation of
    Algorithm 1: y~ = [v_x, 1/m_nn], R~ = diag(R_v, (1 - tau)/tau R_nn).

    ``update`` takes the network row only when given; tau -> 0 gives an infinite variance,
    i.e. that row is dropped (the limit of the paper's law, computed without inf/NaN).

    Optional states after [v_x, 1/m] (not in the paper), each a first-order Gauss-Markov
    process whose decay ``predict`` takes and whose driving noise Q carries:

    * ``network_bias_variance`` > 0: b at :attr:`i_bias`, the network's lasting error,
      1/m_nn = 1/m + b + white noise. The outputs for one vehicle share most of their error (a
      truck that is not the training truck), which the paper's independent R_nn would count
      thousands of times; with b the network can pull the mass no closer than its own lasting
      accuracy while the speed dynamics observe 1/m alone.
    * ``grade_error``: e at :attr:`i_grade` [m/s^2], the lasting error of the slope's gravity
      term (module docstring), created at zero variance (inert) and given its variance by
      :meth:`add_grade_variance` as the slope's source says how far it may be off.
    """

    def __init__(self, x0: np.ndarray, p0: np.ndarray, network_bias_variance: float = 0.0,
                 grade_error: bool = False) -> None:
        x = np.array(x0, dtype=float).reshape(2)
        P = np.array(p0, dtype=float).reshape(2, 2)
        self.with_bias = network_bias_variance > 0.0
        self.i_bias: int | None = None
        self.i_grade: int | None = None
        extra = []
        if self.with_bias:
            self.i_bias = 2
            extra.append(network_bias_variance)
        if grade_error:
            self.i_grade = 2 + len(extra)
            extra.append(0.0)
        if extra:
            x = np.append(x, np.zeros(len(extra)))
            P = np.pad(P, ((0, len(extra)), (0, len(extra))))
            P[2:, 2:] = np.diag(extra)
        self.x, self.P = x, P
        self.last_effective_tau = math.nan

    @property
    def grade_error(self) -> float:
        """e [m/s^2] (0 without the state)."""
        return float(self.x[self.i_grade]) if self.i_grade is not None else 0.0

    def restart_speed(self, v: float, variance: float) -> None:
        """v_x from a measurement, uncorrelated with the rest (a start, a gap, a stop)."""
        self.x[0] = v
        self.P[0, :] = self.P[:, 0] = 0.0
        self.P[0, 0] = variance

    def reset_network_bias(self, variance: float) -> None:
        """b a new error: zero, of ``variance``, uncorrelated with the rest (from the first network
        output, and again where the network's conditions change)."""
        i = self.i_bias
        if i is not None:
            self.x[i] = 0.0
            self.P[i, :] = self.P[:, i] = 0.0
            self.P[i, i] = variance

    def add_grade_variance(self, variance: float) -> None:
        """A new, independent share of the grade error (its source's variance grew)."""
        if self.i_grade is not None and variance > 0.0:
            self.P[self.i_grade, self.i_grade] += variance

    def predict(self, u: DriveInput, dt: float, q: np.ndarray, params: VehicleParams,
                bias_decay: float = 1.0, grade_decay: float = 1.0) -> None:
        """Eqs. (22)-(23): x^- = g(x, u), P^- = A P A^T + Q (A at the prior x); the network
        bias and the grade error, where they are states, decay by ``bias_decay`` and
        ``grade_decay`` (Q carries their driving noise)."""
        e = self.grade_error
        n = self.x.size
        a = np.eye(n)
        a[:2, :2] = transition_jacobian(self.x, u, dt, params, e)
        x = self.x.copy()
        x[:2] = transition(self.x, u, dt, params, e)
        if self.i_bias is not None:
            a[self.i_bias, self.i_bias] = bias_decay
            x[self.i_bias] *= bias_decay
        if self.i_grade is not None:
            j = params.wheel_inertia / params.wheel_radius ** 2
            a[0, self.i_grade] = dt / (1.0 + j * float(self.x[1]))         # dv/de
            a[self.i_grade, self.i_grade] = grade_decay
            x[self.i_grade] *= grade_decay
        self.x = x
        self.P = a @ self.P @ a.T + q
        self.P = 0.5 * (self.P + self.P.T)

    def update(self, v_meas: float, r_v: float, inv_mass_nn: float | None = None,
               r_nn: float | None = None, tau: float | None = None, gate_sigma: float = 0.0) -> bool:
        """Eqs. (24)-(26) with Algorithm 1's adaptive R~. Returns whether the network row was
        used. ``gate_sigma`` > 0 (not in the paper) drops the network row when its innovation
        exceeds that many standard deviations of its innovation covariance H P H^T + R~_22."""
        n = self.x.size
        rows = [np.eye(n)[0]]
        y = [v_meas]
        r = [r_v]
        used = False
        if inv_mass_nn is not None and r_nn is not None and tau is not None:
            weight = (1.0 - tau) / tau if tau > 0.0 else math.inf       # (1 - tau_k)/tau_k
            if math.isfinite(weight):
                r_scaled = weight * r_nn
                h_nn = np.zeros(n)
                h_nn[1] = 1.0                                             # 1/m
                if self.i_bias is not None:
                    h_nn[self.i_bias] = 1.0                               # + the network's bias
                innovation_var = float(h_nn @ self.P @ h_nn) + r_scaled
                self.last_effective_tau = effective_tau(float((self.P @ h_nn)[1]), float(self.P[1, 1]),
                                                        innovation_var, r_nn)
                gated = gate_sigma > 0.0 and \
                    (inv_mass_nn - float(h_nn @ self.x)) ** 2 > gate_sigma ** 2 * innovation_var
                if not gated:
                    rows.append(h_nn)
                    y.append(inv_mass_nn)
                    r.append(r_scaled)
                    used = True
        h = np.array(rows)                                                # H of Eq. (28)
        rr = np.diag(r)
        s = h @ self.P @ h.T + rr
        k = np.linalg.solve(s.T, (self.P @ h.T).T).T                      # Eq. (24)
        innovation = np.asarray(y) - h @ self.x
        self.x = self.x + k @ innovation                                  # Eq. (25)
        i_kh = np.eye(n) - k @ h
        self.P = i_kh @ self.P @ i_kh.T + k @ rr @ k.T                    # Eq. (26), Joseph form
        self.P = 0.5 * (self.P + self.P.T)
        return used


def effective_tau(cross: float, p_mass: float, innovation_var: float, r_nn: float) -> float:
    """The confidence level of Eq. (36) that, in the paper's filter on [v_x, 1/m] alone, would give
    a network output the gain on 1/m it has here: tau' = R_nn / (R_nn + R'), where R' is the
    variance with which P_mass / (P_mass + R') equals this filter's gain ``cross / innovation_var``
    (``cross`` = the 1/m entry of P h^T, ``p_mass`` = P of 1/m, both before the update).

    Without the network-bias state it is the tau in use. With it, once the speed dynamics have
    pinned 1/m and the bias has taken up the network's lasting error, a network output moves
    the bias and hardly the mass: the gain, and tau', fall towards 0. NaN where undefined."""
    if not (p_mass > 0.0 and innovation_var > 0.0 and r_nn > 0.0):
        return math.nan
    gain = cross / innovation_var
    if not gain > 0.0:
        return 0.0
    r_equivalent = p_mass / gain - p_mass
    return r_nn / (r_nn + max(r_equivalent, 0.0))


def drive_force_input(params: VehicleParams, vx: float, drive_force: Any, engine_torque: Any,
                      engine_speed: Any, gear: Any, brake_torque: Any,
                      min_speed: float) -> tuple[float, float] | None:
    """(F_t, dF_t/dv) from the first available source (see :mod:`.ta_aekf`'s docstring), less
    the brake force T_b / r; None when no source is available."""
    p = params
    brake = max(float(brake_torque), 0.0) / p.wheel_radius if finite_number(brake_torque) else 0.0
    if finite_number(drive_force):
        return float(drive_force) - brake, 0.0
    if not finite_number(engine_torque):
        return None
    torque = float(engine_torque)
    if finite_number(gear) and 1 <= round(float(gear)) <= len(p.gear_ratios):
        force = torque * p.driveline_efficiency * p.effective_gearing(int(round(float(gear))))
        return force - brake, 0.0
    if finite_number(engine_speed) and vx >= max(min_speed, 0.5):
        force = p.driveline_efficiency * torque * float(engine_speed) / vx         # Eqs. (7), (13)
        return force - brake, -force / vx
    return None
