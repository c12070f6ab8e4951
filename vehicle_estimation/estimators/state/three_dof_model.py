"""The 3-DOF vehicle model with Magic-Formula tyres of paper 002 (Sec. 2, Eqs. 1-3).

Liu, Cui, Peng 2023, "Vehicle state and parameter estimation based on adaptive anti-outlier
unscented Kalman filter and GA-BPNN method", J. Vibroengineering, doi 10.21595/jve.2023.23441.

State ``x = [vx, vy, r]``, input ``u = ax`` and observation ``y = [ay, r]`` (Sec. 2.3), plus
the wheel-speed ``vx`` of :mod:`.aoukf`. The tyre parameters come from
:class:`~vehicle_estimation.estimators.state.aoukf.AOUKFConfig` (see there for how ``B`` and
``D`` are matched to the vehicle).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from vehicle_estimation.contract.vehicle import VehicleParams

__all__ = ["PAPER_REFERENCE_LOAD", "ThreeDofModel"]

#: Mean tyre load of the paper's Table-1 car (1522 kg), the load the paper's D refers to [N].
PAPER_REFERENCE_LOAD = 1522.0 * 9.81 / 4.0


@dataclasses.dataclass(frozen=True)
class ThreeDofModel:
    """The 3-DOF model of Sec. 2 on batches of states ``X = [vx, vy, r]`` (shape ``(..., 3)``).

    Eq. 1 with ``F_T / m`` = the measured longitudinal acceleration less gravity along the
    slope (the model's input ``u = ax``, Sec. 2.3)::

        vx' = vy r + (ax_imu - g sin(theta))
        vy' = -vx r + 2 (F_yf + F_yr) / m
        r'  = 2 (a F_yf - b F_yr) / I_z

    ``F_y = D sin(C atan(B alpha - E (B alpha - atan(B alpha))))`` per tyre (Sec. 2.2) with
    ``alpha_f = delta - (vy + a r) / vx``, ``alpha_r = (b r - vy) / vx`` and ``D`` from the
    axle load of Eq. 3, ``F_zf = m g b / (a + b)``, ``F_zr = m g a / (a + b)`` (per tyre: half).
    Observation (Sec. 2.3) ``[ay, r]`` with ``ay = 2 (F_yf + F_yr) / m``, plus ``vx`` (the
    wheel-speed extension).
    """

    mass: float
    a: float
    b: float
    yaw_inertia: float
    gravity: float
    B_front: float      # [1/rad]
    B_rear: float
    C: float
    D_front: float      # [N per tyre]
    D_rear: float
    E: float
    min_speed: float
    max_substep: float

    @classmethod
    def from_params(cls, params: VehicleParams, config: Any) -> "ThreeDofModel":
        """The model of ``params`` with the tyre of ``config`` (an ``AOUKFConfig``: its ``mf_*``
        fields (peak ``D`` from ``params.road_friction`` or the paper's ``mf_d``), ``min_speed`` and ``max_substep``)."""
        m, a, b, g = params.mass, params.lf, params.lr, params.gravity
        fz_front = 0.5 * m * g * b / (a + b)      # Eq. 3, per tyre
        fz_rear = 0.5 * m * g * a / (a + b)
        if config.mf_peak_from_road_friction:
            peak_per_load = params.road_friction
        else:
            peak_per_load = config.mf_d / config.mf_reference_load
        d_front = peak_per_load * fz_front
        d_rear = peak_per_load * fz_rear
        if config.mf_match_cornering_stiffness:
            b_front = params.cornering_stiffness_front / (config.mf_c * d_front)
            b_rear = params.cornering_stiffness_rear / (config.mf_c * d_rear)
        else:
            b_front = b_rear = config.mf_b * 180.0 / math.pi
        return cls(m, a, b, params.yaw_inertia, g, b_front, b_rear, config.mf_c, d_front, d_rear,
                   config.mf_e, config.min_speed, config.max_substep)

    def tyre_force(self, alpha, B: float, D: float):
        """Magic Formula (Sec. 2.2), lateral force per tyre [N] for slip angle ``alpha`` [rad]."""
        ba = B * alpha
        return D * np.sin(self.C * np.arctan(ba - self.E * (ba - np.arctan(ba))))

    def lateral_forces(self, X: np.ndarray, delta: float):
        vx = np.maximum(X[..., 0], self.min_speed)
        vy, r = X[..., 1], X[..., 2]
        alpha_f = delta - (vy + self.a * r) / vx
        alpha_r = (self.b * r - vy) / vx
        return self.tyre_force(alpha_f, self.B_front, self.D_front), self.tyre_force(alpha_r, self.B_rear, self.D_rear)

    def derivative(self, X: np.ndarray, ax_kin: float, delta: float) -> np.ndarray:
        """Eq. 1 for a batch of states; ``ax_kin = ax_imu - g sin(theta)`` [m/s^2]."""
        fyf, fyr = self.lateral_forces(X, delta)
        out = np.empty_like(X)
        out[..., 0] = X[..., 1] * X[..., 2] + ax_kin
        out[..., 1] = -X[..., 0] * X[..., 2] + 2.0 * (fyf + fyr) / self.mass
        out[..., 2] = 2.0 * (self.a * fyf - self.b * fyr) / self.yaw_inertia
        return out

    def transition(self, X: np.ndarray, dt: float, ax_kin: float, delta: float) -> np.ndarray:
        """``x_k+1`` by ``ceil(dt / max_substep)`` explicit Euler sub-steps of Eq. 1."""
        X = np.array(X, dtype=float)
        if dt <= 0.0:
            return X
        n = max(1, int(math.ceil(dt / self.max_substep - 1e-9)))
        h = dt / n
        for _ in range(n):
            X = X + h * self.derivative(X, ax_kin, delta)
        return X

    def measurement(self, X: np.ndarray, delta: float) -> np.ndarray:
        """``[ay, r, vx]`` (Sec. 2.3 plus the wheel-speed vx), shape ``(..., 3)``."""
        fyf, fyr = self.lateral_forces(X, delta)
        out = np.empty(X.shape[:-1] + (3,))
        out[..., 0] = 2.0 * (fyf + fyr) / self.mass
        out[..., 1] = X[..., 2]
        out[..., 2] = X[..., 0]
        return out
