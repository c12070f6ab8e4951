"""Method name -> estimator, per kind: the one place a node's ``method`` parameter is resolved.

Each :class:`Method` says which config dataclass tunes it (declared by the node as
``<config_prefix>.*`` parameters) and how to build the core from the vehicle and that config.
Nodes, the paper reproductions and the validation build estimators from here, so a method
added here is offered everywhere at once.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.interfaces import MassEstimator


@dataclasses.dataclass(frozen=True)
class Method:
    """One estimator method: its name, a one-line description, its config and its builder."""

    name: str
    description: str
    config_prefix: str
    config_type: Callable[[], Any]
    build: Callable[..., Any]


def lookup(methods: Mapping[str, Method], name: str, kind: str) -> Method:
    """``methods[name]``, or ``ValueError`` listing the methods of this kind."""
    try:
        return methods[name]
    except KeyError:
        raise ValueError(f"unknown {kind} method {name!r}; one of {sorted(methods)}") from None


def _rls(vehicle: VehicleParams, config: Any) -> MassEstimator:
    from vehicle_estimation.estimators.mass.mass_rls import LongitudinalMassEstimator
    return LongitudinalMassEstimator(vehicle, config)


def _ffrls(vehicle: VehicleParams, config: Any) -> MassEstimator:
    from vehicle_estimation.estimators.mass.mass_ffrls import FFRLSMassEstimator
    return FFRLSMassEstimator(vehicle, config)


def _ta_aekf(vehicle: VehicleParams, config: Any) -> MassEstimator:
    from vehicle_estimation.estimators.mass.ta_aekf import TaAekfMassEstimator
    return TaAekfMassEstimator(vehicle, config)


def _mass_rls_config() -> Any:
    from vehicle_estimation.estimators.mass.mass_rls import MassRLSConfig
    return MassRLSConfig()


def _mass_ffrls_config() -> Any:
    from vehicle_estimation.estimators.mass.mass_ffrls import FFRLSMassConfig
    return FFRLSMassConfig()


def _ta_aekf_config() -> Any:
    from vehicle_estimation.estimators.mass.ta_aekf import TaAekfConfig
    return TaAekfConfig()


MASS_METHODS: dict[str, Method] = {
    "ffrls": Method("ffrls", "paper 004 Sec. 6: forgetting-factor RLS with braking samples and "
                    "the threshold judgment (Eqs. 28-31)", "ffrls", _mass_ffrls_config, _ffrls),
    "rls": Method("rls", "paper 003 Secs. 2-4: RLS with forgetting on driving samples, gear "
                  "prediction and the OBD-II torque map (Eqs. 4-11, 49)", "mass", _mass_rls_config, _rls),
    "ta_aekf": Method("ta_aekf", "paper 000: adaptive EKF on [v, 1/m] aided by a transformer's "
                      "mass, weighted by the confidence level tau (Alg. 1)", "ta_aekf", _ta_aekf_config, _ta_aekf),
}


# -- vehicle state ------------------------------------------------------------------------
from vehicle_estimation.estimators.interfaces import StateEstimator  # noqa: E402


@dataclasses.dataclass(frozen=True)
class StateSettings:
    """The vehicle-state node's own tuning: the diagonals of ``P0``, ``Q`` (per 0.01 s step)
    and ``R`` of the paper-004 filters, and how vx starts, for every filter (a filter config
    with the :data:`NODE_STATE_FIELDS` takes them from here: :func:`with_state_settings`)."""

    p0_diag: tuple[float, ...]
    q_diag: tuple[float, ...]
    r_diag: tuple[float, ...]
    initial_vx: float
    init_vx_from_wheel_speeds: bool


#: The fields of :class:`StateSettings` that every filter takes from the node.
NODE_STATE_FIELDS = ("initial_vx", "init_vx_from_wheel_speeds")


@dataclasses.dataclass(frozen=True)
class StateFilter(Method):
    """A vehicle-state filter: ``build(vehicle, config, settings, correction)`` returns a
    :class:`~vehicle_estimation.estimators.interfaces.StateEstimator`. ``config`` is None for
    a filter without a config of its own (``config_type`` returns None); ``correction`` is
    the GA-BPNN output correction of paper 002 Eq. 5, for the filters with
    ``output_correction`` (node parameter ``aoukf_correction``)."""

    output_correction: bool = False


def with_state_settings(config: Any, settings: StateSettings) -> tuple[Any, tuple[str, ...]]:
    """``config`` with its :data:`NODE_STATE_FIELDS` taken from ``settings``, and the names of
    those fields (the node declares them once, not under the filter's prefix)."""
    names = {f.name for f in dataclasses.fields(config)}
    shared = tuple(name for name in NODE_STATE_FIELDS if name in names)
    return dataclasses.replace(config, **{name: getattr(settings, name) for name in shared}), shared


def _paper004_config(settings: StateSettings) -> Any:
    from vehicle_estimation.estimators.state.ckf import VehicleStateConfig
    return VehicleStateConfig.from_diagonals(settings.p0_diag, settings.q_diag, settings.r_diag,
                                             initial_vx=settings.initial_vx,
                                             init_vx_from_wheel_speeds=settings.init_vx_from_wheel_speeds)


def _ckf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.ckf import VehicleStateCKF
    return VehicleStateCKF(vehicle, _paper004_config(settings))


def _vbackf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.vbackf import VehicleStateVBACKF
    return VehicleStateVBACKF(vehicle, _paper004_config(settings), config)


def _aoukf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.aoukf import VehicleStateAOUKF
    return VehicleStateAOUKF(vehicle, config, correction)


def _no_config() -> None:
    return None


def _vb_config() -> Any:
    from vehicle_estimation.estimators.state.vbackf import VBConfig
    return VBConfig()


def _aoukf_config() -> Any:
    from vehicle_estimation.estimators.state.aoukf import AOUKFConfig
    return AOUKFConfig()


STATE_FILTERS: dict[str, StateFilter] = {
    "ckf": StateFilter("ckf", "paper 004 Sec. 7: the plain cubature Kalman filter on the 4-wheel Dugoff "
                       "model (Eqs. 1-9), the paper's contrast", "", _no_config, _ckf),
    "vbackf": StateFilter("vbackf", "paper 004 Sec. 4: the variational Bayesian adaptive CKF, the "
                          "measurement noise learnt online (Eqs. 10-13)", "vbackf", _vb_config, _vbackf),
    "aoukf": StateFilter("aoukf", "paper 002: the adaptive anti-outlier UKF on the 3-DOF Magic-Formula "
                         "model (Sec. 3.3, Eqs. 6-7) with the GA-BPNN output correction (Eq. 5)",
                         "aoukf", _aoukf_config, _aoukf, output_correction=True),
}
