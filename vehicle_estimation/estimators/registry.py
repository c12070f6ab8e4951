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


# ------------------------------------------------------------------------------ road slope
#: ``configure(prefix, defaults)``: the config of a source a method combines (``<prefix>.*``).
Configure = Callable[[str, Any], Any]


def _configs_as_given(prefix: str, defaults: Any) -> Any:
    return defaults


def _fusion_pitch(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
    from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeSlope
    from vehicle_estimation.estimators.slope.road_slope import RoadSlopeEstimator
    return RoadSlopeEstimator(vehicle, grade=PitchGradeSlope(config))


def _classical(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
    from vehicle_estimation.estimators.slope.observers import ClassicalSlopeObserver
    from vehicle_estimation.estimators.slope.road_slope import RoadSlopeEstimator
    return RoadSlopeEstimator(vehicle, observer=ClassicalSlopeObserver(config))


def _cubic_prediction(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
    from vehicle_estimation.estimators.slope.cubic_prediction import CubicPredictionSlopeObserver
    from vehicle_estimation.estimators.slope.road_slope import RoadSlopeEstimator
    return RoadSlopeEstimator(vehicle, observer=CubicPredictionSlopeObserver(config))


def _auto_slope(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
    from vehicle_estimation.estimators.slope.cubic_prediction import CubicPredictionSlopeObserver
    from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeSlope
    from vehicle_estimation.estimators.slope.road_slope import RoadSlopeEstimator
    grade, observer = (SLOPE_METHODS[name] for name in ("fusion_pitch", "cubic_prediction"))
    return RoadSlopeEstimator(
        vehicle, grade=PitchGradeSlope(configure(grade.config_prefix, grade.config_type())),
        observer=CubicPredictionSlopeObserver(configure(observer.config_prefix, observer.config_type())),
        auto=config)


def _auto_slope_config() -> Any:
    from vehicle_estimation.estimators.slope.auto import AutoSlopeConfig
    return AutoSlopeConfig()


def _classical_config() -> Any:
    from vehicle_estimation.estimators.slope.observers import ClassicalSlopeConfig
    return ClassicalSlopeConfig()


def _cubic_prediction_config() -> Any:
    from vehicle_estimation.estimators.slope.cubic_prediction import CubicPredictionSlopeConfig
    return CubicPredictionSlopeConfig()


def _fusion_pitch_config() -> Any:
    from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeConfig
    return PitchGradeConfig()


#: Each builds a :class:`~vehicle_estimation.estimators.slope.road_slope.RoadSlopeEstimator`
#: (a :class:`~vehicle_estimation.estimators.interfaces.SlopeEstimator`) as
#: ``build(vehicle, config, configure)``; ``auto`` combines two of the others and asks
#: ``configure(prefix, defaults)`` for their configs (a node declares them as parameters; by
#: default the defaults are used).
SLOPE_METHODS: dict[str, Method] = {
    "auto": Method("auto", "fusion_pitch while the fusion grade is fresh and converged, else "
                   "cubic_prediction, without a jump at a switch", "auto", _auto_slope_config, _auto_slope),
    "classical": Method("classical", "paper 004 Eqs. 32-33: the contrasted observer on the theta' = 0 "
                        "slope model", "classical", _classical_config, _classical),
    "cubic_prediction": Method("cubic_prediction", "paper 004 Sec. 5: the slope prediction model "
                               "(Eqs. 15-20) with the cubic observer (Eqs. 21-27)", "cubic_prediction",
                               _cubic_prediction_config, _cubic_prediction),
    "fusion_pitch": Method("fusion_pitch", "paper 003 Sec. 7.2: the grade from the fusion's pitch, "
                           "LWMA-smoothed", "fusion_pitch", _fusion_pitch_config, _fusion_pitch),
}
