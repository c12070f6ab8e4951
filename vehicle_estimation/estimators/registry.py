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
    if config.use_network:
        import torch
        # One window per inference: intra-op threads only contend with the other nodes for
        # the cores (with two threads on two loaded cores an inference takes 120 ms, with one 0.6 ms).
        torch.set_num_threads(1)
    try:
        return TaAekfMassEstimator(vehicle, config)
    except ValueError as exc:   # the model files failed a check: name the parameter
        raise ValueError(f"parameter 'ta_aekf.model_path': {exc}") from exc


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
