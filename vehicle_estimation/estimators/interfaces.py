"""What a node may rely on from an estimator of each kind, whatever its method.

A node builds its estimator through :mod:`vehicle_estimation.estimators.registry` from the
``method`` (or ``filter``) parameter and then talks to it only through one of these
protocols, so it never branches on the method's name; what a method adds to
``/diagnostics`` comes from its :meth:`status`. The protocols are structural
(:class:`typing.Protocol`): a core satisfies one by having the members, without inheriting.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class MassEstimator(Protocol):
    """A vehicle-mass estimator (paper 003 RLS, paper 004 FFRLS, paper 000 TA-AEKF).

    ``steps_on_windows``: True for estimators fed the means of each update window
    (:mod:`~vehicle_estimation.estimators.mass.update_window`), with ``window_brake`` the brake
    statistic they take ("max" or "mean"); False for one step per powertrain sample.
    ``needs_heading``: :meth:`step` uses ``heading`` (the wind compensation).
    """

    steps_on_windows: bool
    window_brake: str

    @property
    def needs_heading(self) -> bool: ...

    #: ``step(t, vx, ax, slope, **signals) -> bool``: one sample (or window): speed [m/s],
    #: dv/dt [m/s^2], grade [rad], and the drive and brake signals by name (drive_force,
    #: engine_torque, engine_speed, engine_load, gear, brake_torque; heading and the
    #: regressor's bias variance and correlation for the methods that take them). Each method
    #: names the signals it reads, so the signature is not fixed here.
    @property
    def step(self) -> Callable[..., bool]: ...

    @property
    def mass(self) -> float:
        """The published mass [kg]."""

    @property
    def variance(self) -> float:
        """Its variance [kg^2], honest: an error within 2 sigma about 95 % of the time."""

    @property
    def converged(self) -> bool: ...

    @property
    def samples_used(self) -> int: ...

    @property
    def rejected(self) -> Mapping[str, int]:
        """Samples not used, per reason."""

    def reset(self) -> None: ...

    def state_dict(self) -> dict[str, float]:
        """Everything needed to resume after a restart (:meth:`load_state_dict`)."""

    def load_state_dict(self, state: Mapping[str, float]) -> None: ...

    def status(self) -> dict[str, str]:
        """What this method adds to ``/diagnostics`` (name -> text)."""


@runtime_checkable
class StateEstimator(Protocol):
    """A vehicle-state filter: x = [vx, vy, r, ...] with sideslip (paper 004 CKF / VB-ACKF,
    paper 002 AO-UKF)."""

    initialised: bool
    reinitialisations: int
    last_event: str
    #: Extra white-noise density on vx [(m/s^2)^2 s] the node adds while it knows the
    #: acceleration input is worse than the model assumes (no slope, dead reckoning).
    extra_vx_noise_density: float
    #: Relative cornering-stiffness uncertainty whose vy error the published P carries.
    tyre_stiffness_std: float
    #: Std of the road bank [rad] whose vy error the published P carries.
    road_bank_std: float

    @property
    def x(self) -> np.ndarray: ...

    @property
    def P(self) -> np.ndarray: ...

    @property
    def sideslip(self) -> float: ...

    @property
    def sideslip_variance(self) -> float: ...

    def step(self, t: float, inputs: Any, z: Any) -> bool:
        """Predict to ``t`` with the chassis ``inputs`` and update with z = [ax, ay, r]."""

    def update_speed(self, vx: float, variance: float) -> bool:
        """Update vx with a measured speed (the CAN speed where no wheel speeds are)."""

    def start_from(self, x: np.ndarray, P: np.ndarray) -> None:
        """Start, at the next step, from another filter's [vx, vy, r] and their covariance."""

    def reset(self) -> None: ...

    def status(self) -> dict[str, str]: ...


@runtime_checkable
class SlopeEstimator(Protocol):
    """A road-slope estimate: grade [rad, + uphill], its variance and a converged flag."""

    @property
    def slope(self) -> float: ...

    @property
    def variance(self) -> float: ...

    @property
    def converged(self) -> bool: ...

    def reset(self) -> None: ...
