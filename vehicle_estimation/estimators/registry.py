"""Method name -> estimator, per kind: the one place a node's ``method`` parameter is resolved.

Each :class:`Method` says which config dataclass tunes it (declared by the node as
``<config_prefix>.*`` parameters) and how to build the core from the vehicle and that config.
Nodes, the paper reproductions and the validation build estimators from here, so a method
added here is offered everywhere at once.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from typing import Any, Callable, Mapping

from vehicle_estimation.contract.vehicle import VehicleParams, dataclass_from_mapping
from vehicle_estimation.estimators.interfaces import MassEstimator, StateEstimator


@dataclasses.dataclass(frozen=True)
class Method:
    """One estimator method: its name, a one-line description, its config and its builder."""

    name: str
    description: str
    config_prefix: str
    config_type: Callable[[], Any]
    build: Callable[..., Any]


def lazy(path: str) -> Callable[..., Any]:
    """``"module:Name"`` of :mod:`vehicle_estimation.estimators`, imported at the first call
    and called with its arguments: a node loads only the method it runs (TA-AEKF's torch
    stays out of a node that runs RLS)."""
    module, name = path.split(":")

    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(importlib.import_module(f"vehicle_estimation.estimators.{module}"), name)(*args, **kwargs)

    return call


def lookup(methods: Mapping[str, Method], name: str, kind: str) -> Method:
    """``methods[name]``, or ``ValueError`` listing the methods of this kind."""
    try:
        return methods[name]
    except KeyError:
        raise ValueError(f"unknown {kind} method {name!r}; one of {sorted(methods)}") from None


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


MASS_METHODS: dict[str, Method] = {
    "ffrls": Method("ffrls", "paper 004 Sec. 6: forgetting-factor RLS with braking samples and "
                    "the threshold judgment (Eqs. 28-31)", "ffrls",
                    lazy("mass.mass_ffrls:FFRLSMassConfig"), lazy("mass.mass_ffrls:FFRLSMassEstimator")),
    "rls": Method("rls", "paper 003 Secs. 2-4: RLS with forgetting on driving samples, gear "
                  "prediction and the OBD-II torque map (Eqs. 4-11, 49)", "mass",
                  lazy("mass.mass_rls:MassRLSConfig"), lazy("mass.mass_rls:LongitudinalMassEstimator")),
    "ta_aekf": Method("ta_aekf", "paper 000: adaptive EKF on [v, 1/m] aided by a transformer's "
                      "mass, weighted by the confidence level tau (Alg. 1)", "ta_aekf",
                      lazy("mass.ta_aekf:TaAekfConfig"), _ta_aekf),
}


# ------------------------------------------------------------------------------ road slope
#: ``configure(prefix, defaults)``: the config of a source a method combines (``<prefix>.*``).
Configure = Callable[[str, Any], Any]


def _configs_as_given(prefix: str, defaults: Any) -> Any:
    return defaults


def _one_source(role: str, core: str) -> Callable[..., Any]:
    """The builder of a slope method with one source: ``core`` (``"module:Name"``, built from
    the method's config) as the estimator's ``role``, ``"grade"`` or ``"observer"``."""

    def build(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
        return lazy("slope.road_slope:RoadSlopeEstimator")(vehicle, **{role: lazy(core)(config)})

    return build


def _auto_slope(vehicle: VehicleParams, config: Any, configure: Configure = _configs_as_given) -> Any:
    from vehicle_estimation.estimators.slope.cubic_prediction import CubicPredictionSlopeObserver
    from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeSlope
    from vehicle_estimation.estimators.slope.road_slope import RoadSlopeEstimator
    grade, observer = (SLOPE_METHODS[name] for name in ("fusion_pitch", "cubic_prediction"))
    return RoadSlopeEstimator(
        vehicle, grade=PitchGradeSlope(configure(grade.config_prefix, grade.config_type())),
        observer=CubicPredictionSlopeObserver(configure(observer.config_prefix, observer.config_type())),
        auto=config)


#: Each builds a :class:`~vehicle_estimation.estimators.slope.road_slope.RoadSlopeEstimator`
#: (a :class:`~vehicle_estimation.estimators.interfaces.SlopeEstimator`) as
#: ``build(vehicle, config, configure)``; ``auto`` combines two of the others and asks
#: ``configure(prefix, defaults)`` for their configs (a node declares them as parameters; by
#: default the defaults are used).
SLOPE_METHODS: dict[str, Method] = {
    "auto": Method("auto", "fusion_pitch while the fusion grade is fresh and converged, else "
                   "cubic_prediction, without a jump at a switch", "auto",
                   lazy("slope.auto:AutoSlopeConfig"), _auto_slope),
    "classical": Method("classical", "paper 004 Eqs. 32-33: the contrasted observer on the theta' = 0 "
                        "slope model", "classical", lazy("slope.observers:ClassicalSlopeConfig"),
                        _one_source("observer", "slope.observers:ClassicalSlopeObserver")),
    "cubic_prediction": Method("cubic_prediction", "paper 004 Sec. 5: the slope prediction model "
                               "(Eqs. 15-20) with the cubic observer (Eqs. 21-27)", "cubic_prediction",
                               lazy("slope.cubic_prediction:CubicPredictionSlopeConfig"),
                               _one_source("observer", "slope.cubic_prediction:CubicPredictionSlopeObserver")),
    "fusion_pitch": Method("fusion_pitch", "paper 003 Sec. 7.2: the grade from the fusion's pitch, "
                           "LWMA-smoothed", "fusion_pitch", lazy("slope.pitch_grade:PitchGradeConfig"),
                           _one_source("grade", "slope.pitch_grade:PitchGradeSlope")),
}


# -- vehicle state ------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class StateSettings:
    """The vehicle-state node's own tuning: the diagonals of ``P0``, ``Q`` (per 0.01 s step)
    and ``R`` of the paper-004 filters, and how vx starts, for every filter (a filter config
    with the :data:`NODE_STATE_FIELDS` takes them from here: :func:`with_state_settings`)."""

    p0_diag: tuple[float, ...]
    q_diag: tuple[float, ...]
    r_diag: tuple[float, ...]
    initial_vx: float = 0.0
    init_vx_from_wheel_speeds: bool = True
    wheel_slip_forces: bool = True
    wheel_radius_std: float = 0.01
    front_axle_force_std: float = 0.0
    rear_axle_force_std: float = 0.0
    tyre_stiffness_std: float = 0.0
    road_bank_std_deg: float = 0.0

    @classmethod
    def defaults(cls) -> "StateSettings":
        """Paper 004 Sec. 7.1's P0, Q and R diagonals, Q read as a density (Q tau per 0.01 s
        step: per step, 0.1 I would make the predicted measurement covariance ~100 R, the gain
        ~1 and R unidentifiable, so the VB-ACKF could learn nothing)."""
        from vehicle_estimation.estimators.state.ckf import VehicleStateConfig
        paper = VehicleStateConfig()
        return cls(tuple(float(v) for v in paper.P0.diagonal()),
                   tuple(float(v) for v in paper.Q.diagonal() * paper.nominal_dt),
                   tuple(float(v) for v in paper.R.diagonal()))

    @classmethod
    def from_parameters(cls, parameters: Mapping[str, Any]) -> "StateSettings":
        """The :meth:`defaults` with the fields that ``parameters`` (a state node's
        ``ros__parameters``, as in a params file) sets: how offline tools run a core with the
        shipped tuning."""
        fields = {f.name: parameters[f.name] for f in dataclasses.fields(cls) if f.name in parameters}
        for name in ("p0_diag", "q_diag", "r_diag"):
            if name in fields:
                fields[name] = tuple(float(v) for v in fields[name])
        return dataclasses.replace(cls.defaults(), **fields)


#: The fields of :class:`StateSettings` that every filter takes from the node.
NODE_STATE_FIELDS = ("initial_vx", "init_vx_from_wheel_speeds")


@dataclasses.dataclass(frozen=True)
class StateFilter(Method):
    """A vehicle-state filter: ``build(vehicle, config, settings, correction)`` returns a
    :class:`~vehicle_estimation.estimators.interfaces.StateEstimator`. ``config`` is None for
    a filter without a config of its own (``config_type`` returns None); ``correction`` is
    the GA-BPNN output correction of paper 002 Eq. 5, for the filters with
    ``output_correction`` (node parameter ``aoukf_correction``). A filter that
    ``needs_speed`` takes vx as a measurement (paper 002: [ay, r, vx]); without one its tyre
    model alone pulls vx tens of m/s off (the real Stanford drive), so on a drive with no
    speed of any kind the node runs another (node parameter ``no_speed_filter``)."""

    output_correction: bool = False
    needs_speed: bool = False


#: The filter a node that ``needs_speed`` runs on a drive without any speed (``no_speed_filter``).
DEFAULT_NO_SPEED_FILTER = "vbackf"
#: How long a speed must be missing before that filter runs, and back before the configured
#: one runs again [s]: a CAN dropout shorter than this swaps nothing.
NO_SPEED_HOLD_S = 1.0


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
                                             init_vx_from_wheel_speeds=settings.init_vx_from_wheel_speeds,
                                             wheel_slip_forces=settings.wheel_slip_forces,
                                             wheel_radius_std=settings.wheel_radius_std,
                                             front_axle_force_std=settings.front_axle_force_std,
                                             rear_axle_force_std=settings.rear_axle_force_std)


def _with_model_error(core: StateEstimator, settings: StateSettings) -> StateEstimator:
    """``core`` publishing the model error of ``settings`` (every filter alike)."""
    core.tyre_stiffness_std = settings.tyre_stiffness_std
    core.road_bank_std = math.radians(settings.road_bank_std_deg)
    return core


def _ckf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.ckf import VehicleStateCKF
    return _with_model_error(VehicleStateCKF(vehicle, _paper004_config(settings)), settings)


def _vbackf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.vbackf import VehicleStateVBACKF
    return _with_model_error(VehicleStateVBACKF(vehicle, _paper004_config(settings), config), settings)


def _aoukf(vehicle: VehicleParams, config: Any, settings: StateSettings, correction: Any) -> StateEstimator:
    from vehicle_estimation.estimators.state.aoukf import VehicleStateAOUKF
    if correction is not None and config is not None and config.mf_peak_from_road_friction:
        # the GA-BPNN learnt the residuals of the paper's tyre (train_gabpnn); on another
        # tyre it would correct errors the filter does not make
        config = dataclasses.replace(config, mf_peak_from_road_friction=False)
    return _with_model_error(VehicleStateAOUKF(vehicle, config, correction), settings)


STATE_FILTERS: dict[str, StateFilter] = {
    "ckf": StateFilter("ckf", "paper 004 Sec. 7: the plain cubature Kalman filter on the 4-wheel Dugoff "
                       "model (Eqs. 1-9), the paper's contrast", "", lambda: None, _ckf),
    "vbackf": StateFilter("vbackf", "paper 004 Sec. 4: the variational Bayesian adaptive CKF, the "
                          "measurement noise learnt online (Eqs. 10-13)", "vbackf",
                          lazy("state.vbackf:VBConfig"), _vbackf),
    "aoukf": StateFilter("aoukf", "paper 002: the adaptive anti-outlier UKF on the 3-DOF Magic-Formula "
                         "model (Sec. 3.3, Eqs. 6-7) with the GA-BPNN output correction (Eq. 5)",
                         "aoukf", lazy("state.aoukf:AOUKFConfig"), _aoukf, output_correction=True,
                         needs_speed=True),
}


def build_state_filter(name: str, vehicle: VehicleParams, settings: StateSettings | None = None,
                       correction: Any = None, parameters: Mapping[str, Any] | None = None) -> StateEstimator:
    """The filter ``name`` with the node's ``settings`` (default: :meth:`StateSettings.defaults`)
    and its default config, overridden by the ``<prefix>.*`` entries of ``parameters`` (a state
    node's ``ros__parameters``, as in a params file), as the state node builds it."""
    method = lookup(STATE_FILTERS, name, "vehicle-state filter")
    settings = settings if settings is not None else StateSettings.defaults()
    config = method.config_type()
    if config is not None:
        head = method.config_prefix + "."
        given = {key[len(head):]: value for key, value in (parameters or {}).items() if key.startswith(head)}
        config = dataclass_from_mapping(type(config), given, f"unknown parameter '{head}{{key}}'")
        config, _ = with_state_settings(config, settings)
    return method.build(vehicle, config, settings, correction)
