"""Four-wheel vehicle model with Dugoff tyres on a sloped road (paper 004, Sec. 3, Eqs. 1-9).

Chen et al. 2021, "An effective joint soft-sensing strategy for multi-information under
diverse vehicle driving scenarios", Electronics 10, 505.

Conventions (REP-103, SI): body frame FLU (x forward, y left, z up), yaw rate ``r``
positive counter-clockwise, road-wheel steer angle ``delta`` positive to the left, road
slope ``theta`` positive uphill [rad]. Wheels are ordered ``[fl, fr, rl, rr]`` = paper
subscripts 1, 2, 3, 4. All vehicle constants come from :class:`VehicleParams`.

State ``x = [vx, vy, r, ax, ay]`` (paper Eq. 10). ``ax``/``ay`` are the *kinematic*
accelerations of Eq. 1 (``vx' = ax + r vy``, ``vy' = ay - r vx``), i.e. ``ax`` includes the
gravity component ``-g sin(theta)`` of Eq. 2. An accelerometer measures the specific
force, ``ax + g sin(theta)`` (paper Eq. 21); :func:`measurement` predicts exactly that.

Discretisation. The paper gives the continuous model only. Here ``ax``/``ay`` are algebraic
outputs of Eqs. 2-3 carried as states: :func:`transition` integrates ``vx, vy, r`` with
(semi-implicit, sub-stepped) Euler using the *model* accelerations, then sets
``ax_{k+1}, ay_{k+1}`` to Eqs. 2-3 evaluated at the propagated state (and the inputs of
the step). Load transfer (Eq. 5) uses the accelerations already in the state, which
avoids the algebraic loop.

Fallback when wheel speeds are missing (any NaN): the longitudinal tyre forces of
Eqs. 8-9 cannot be formed. Then

* if ``drive_torque``/``brake_torques`` are given, quasi-static tyre forces
  ``Fx_i = (T_drive,i - T_brake,i) / R`` are used (wheel inertia neglected, clipped to
  ``mu Fz``);
* otherwise ``Fx_i`` is ``VehicleInputs.drive_force`` (the state cores set it from their
  acceleration estimate, ``m (ax + g sin theta) + F_drag`` where positive; a braking force is
  left out, as its share per axle is not known) in equal parts on the wheels of
  ``driven_axle``, or 0, and ``ax`` is a random walk (``ax_{k+1} = ax_k``):
  ``vx`` is propagated with the filter's ``ax``, which the accelerometer measurement keeps
  close to the measured value (``vx`` is then only dead-reckoned and drifts).

  In both, the lateral Dugoff force is taken at zero slip with the friction the longitudinal
  force leaves, ``sqrt((mu Fz)^2 - Fx^2)`` (the friction ellipse; Eq. 9 couples the two
  directions through the measured slip, which is missing here). It changes nothing in the
  tyre's linear range; near the limit a wheel that drives has less lateral force left (without
  it a car leaving a limit corner under power kept the full lateral grip on its driven wheels,
  and on the real Stanford drive the filters read half the true sideslip there).

Deviations from the printed equations (documented, small):

* Eq. 5 uses ``ax``; here the longitudinal load transfer uses the *specific* force
  ``ax + g sin(theta)`` (the tyre-force sum / m), which is what physically transfers
  load (difference ``m h g sin(theta) / 2L``, ~40 N per wheel at 3 %).
* Eq. 8, ``sigma = omega R / v_t - 1``, is written as ``(omega R - v_t) / max(|v_t|,
  v_min)`` (identical above ``v_min``) and the slip-angle denominators of Eq. 6 are
  floored at ``v_min`` so that the model stays finite at stand-still.
* Eq. 9 is evaluated in the algebraically identical form
  ``f(lambda)/(1+sigma) = (2-lambda) mu Fz / (2 sqrt(...))`` for ``lambda < 1`` so a locked
  wheel (``1 + sigma = 0``) gives the saturated force instead of 0/0.
* Drag uses ``vx |vx|`` (sign-correct when reversing); rolling resistance is not in
  Eq. 2 and is omitted here as well.

Extension beside the paper (off by default): load-sensitive tyre stiffness. Eq. 9 takes
``C_sigma`` and ``C_alpha`` constant, while its friction limit ``mu F_z`` follows the load
transfer of Eq. 5. A tyre whose stiffness grows with its load (a Magic-Formula tyre has
``K_y = p_ky1 F_z``) then behaves differently in a corner: Eq. 9 keeps the full stiffness on
the unloaded inner wheels and saturates them early (``lambda < 1`` once the linear force
passes ``mu F_z / 2``), so the axle loses lateral force the real tyres still have (on the
CommonRoad BMW 320i at 4.7 m/s^2: inner front tyre at 1780 N of load asked for 1334 N, 11 %
lost, 10 % of the car's ay in all) and a filter makes up for it with too much slip angle,
i.e. too much sideslip. With ``VehicleParams.tyre_load_exponent`` ``n > 0`` both stiffnesses
of Eq. 9 are ``C (F_z / F_z0)^n`` per wheel, ``F_z0`` the static load of Eq. 5 at the
nominal mass on a level road, so they are the paper's constants at the static load and the
axle's linear stiffness is unchanged by load transfer for ``n = 1``. ``n = 0`` is Eq. 9
exactly (our simulator's tyre).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Optional

import numpy as np

from vehicle_estimation.contract.vehicle import DRIVEN_WHEELS, VehicleParams

__all__ = [
    "VehicleInputs",
    "TyreForces",
    "tyre_forces",
    "state_derivative",
    "transition",
    "measurement",
    "sideslip",
    "free_rolling_wheel_speeds",
    "wheel_forward_speeds",
    "aerodynamic_drag",
    "longitudinal_forces_known",
    "STATE_NAMES",
    "MEASUREMENT_NAMES",
    "DEFAULT_MIN_SPEED",
    "DEFAULT_MAX_SUBSTEP",
    "ACCEL_TIME_CONSTANT",
]

STATE_NAMES = ("vx", "vy", "r", "ax", "ay")
MEASUREMENT_NAMES = ("ax_imu", "ay_imu", "r")

DEFAULT_MIN_SPEED = 3.0       # v_min [m/s], regularisation of Eqs. 6 and 8
DEFAULT_MAX_SUBSTEP = 0.01    # Euler sub-step [s] (paper tau = 0.01 s)
ACCEL_TIME_CONSTANT = 0.01    # [s] relaxation of ax/ay in state_derivative (= tau)
_EPS = 1e-9


@dataclasses.dataclass(frozen=True, eq=False)
class VehicleInputs:
    """Inputs ``u_s = [delta, omega_i, theta, m]`` of paper Eq. 10 (+ optional torques).

    Attributes:
        steer_angle: road-wheel steer angle ``delta`` [rad], +left (steering-wheel angle
            divided by ``VehicleParams.steering_ratio``, paper Sec. 3).
        wheel_speeds: ``(4,)`` wheel rotational speeds ``omega`` [rad/s], order
            ``[fl, fr, rl, rr]``; any NaN selects the fallback (module docstring).
        slope: road slope ``theta`` [rad], +uphill (from the slope observer).
        mass: vehicle mass ``m`` [kg] (from the mass estimator); ``None`` means
            ``VehicleParams.mass``.
        drive_torque: optional total drive torque at the driven wheels [N m], split
            equally over the wheels of ``VehicleParams.driven_axle``. Fallback only.
        brake_torques: optional ``(4,)`` brake torques per wheel [N m], >= 0 retarding.
            Fallback only.
        drive_force: optional drive force at the driven wheels' contact patches [N], split
            equally over the wheels of ``VehicleParams.driven_axle``; used only where no
            torques are given. Fallback only (module docstring).
    """

    steer_angle: float = 0.0
    wheel_speeds: np.ndarray = dataclasses.field(
        default_factory=lambda: np.full(4, np.nan))
    slope: float = 0.0
    mass: Optional[float] = None
    drive_torque: Optional[float] = None
    brake_torques: Optional[np.ndarray] = None
    drive_force: Optional[float] = None

    def __post_init__(self) -> None:
        ws = np.asarray(self.wheel_speeds, dtype=float).reshape(-1)
        if ws.shape != (4,):
            raise ValueError(f"wheel_speeds must have 4 entries, got shape {ws.shape}")
        object.__setattr__(self, "wheel_speeds", ws)
        if self.brake_torques is not None:
            bt = np.asarray(self.brake_torques, dtype=float).reshape(-1)
            if bt.shape != (4,):
                raise ValueError(f"brake_torques must have 4 entries, got shape {bt.shape}")
            object.__setattr__(self, "brake_torques", bt)

    @property
    def wheel_speeds_valid(self) -> bool:
        return bool(np.isfinite(self.wheel_speeds).all())

    @property
    def torques_valid(self) -> bool:
        ok = self.drive_torque is not None or self.brake_torques is not None
        if self.drive_torque is not None:
            ok = ok and math.isfinite(self.drive_torque)
        if self.brake_torques is not None:
            ok = ok and bool(np.isfinite(self.brake_torques).all())
        return ok

    def is_valid(self) -> bool:
        """Steer, slope finite and mass (if given) finite positive."""
        if not (math.isfinite(self.steer_angle) and math.isfinite(self.slope)):
            return False
        if self.mass is not None and not (math.isfinite(self.mass) and self.mass > 0.0):
            return False
        return True

    def mass_or(self, params: VehicleParams) -> float:
        return params.mass if self.mass is None else float(self.mass)


class TyreForces(NamedTuple):
    """Per-wheel tyre quantities, arrays of shape ``(..., 4)`` ordered [fl, fr, rl, rr].

    ``fx``/``fy`` are in the *wheel* frame (paper Eq. 9), ``fz`` vertical loads (Eq. 5),
    ``slip`` the longitudinal slip ``sigma`` (Eq. 8), ``slip_angle`` ``alpha_t`` (Eq. 6),
    ``v_wheel`` the forward wheel speed ``v_t`` (Eq. 7). ``longitudinal_from_slip`` is
    False when the fallback (no wheel speeds) produced ``fx``.
    """

    fx: np.ndarray
    fy: np.ndarray
    fz: np.ndarray
    slip: np.ndarray
    slip_angle: np.ndarray
    v_wheel: np.ndarray
    longitudinal_from_slip: bool


class _WheelGeometry(NamedTuple):
    """Per-wheel constants (fl, fr, rl, rr) of Eqs. 5-7, computed once per parameter set."""

    x_from_r: np.ndarray      # v_x,wheel = vx + x_from_r * r  (-+ half tracks)
    y_from_vy: np.ndarray     # v_y,wheel = y_from_vy * vy + y_from_r * r  (vyf, vyf, vyr, vyr)
    y_from_r: np.ndarray
    steered: np.ndarray       # 1 on the front wheels
    alpha_sign: np.ndarray    # alpha = steered * delta + alpha_sign * atan(v_y / v_x)
    c_alpha: np.ndarray       # cornering stiffness per wheel
    load_static: np.ndarray   # F_z per wheel per (m g cos theta)
    fz_nominal: np.ndarray    # static F_z per wheel at the nominal mass, level road [N]
    load_ax: np.ndarray       # F_z per wheel per (m a_x)
    load_ay: np.ndarray       # F_z per wheel per (m a_y)
    drive_share: np.ndarray   # share of the drive force per wheel (driven_axle)


_GEOMETRY: dict[int, tuple[VehicleParams, _WheelGeometry]] = {}


def _geometry(params: VehicleParams) -> _WheelGeometry:
    # Keyed on identity: hashing the frozen dataclass (all fields) would cost more than the
    # lookup saves, and a parameter set lives as long as the filter that holds it.
    entry = _GEOMETRY.get(id(params))
    if entry is None or entry[0] is not params:
        if len(_GEOMETRY) > 64:
            _GEOMETRY.clear()
        entry = (params, _make_geometry(params))
        _GEOMETRY[id(params)] = entry
    return entry[1]


def _make_geometry(params: VehicleParams) -> _WheelGeometry:
    hf, hr = 0.5 * params.track_front, 0.5 * params.track_rear
    L, h = params.wheelbase, params.cg_height
    cf, cr = params.cornering_stiffness_front, params.cornering_stiffness_rear
    front, rear = params.lr / (2.0 * L), params.lf / (2.0 * L)
    dfront, drear = h * params.lr / (L * params.track_front), h * params.lf / (L * params.track_rear)
    return _WheelGeometry(
        x_from_r=np.array([-hf, hf, -hr, hr]),
        y_from_vy=np.array([1.0, 1.0, -1.0, -1.0]),
        y_from_r=np.array([params.lf, params.lf, params.lr, params.lr]),
        steered=np.array([1.0, 1.0, 0.0, 0.0]),
        alpha_sign=np.array([-1.0, -1.0, 1.0, 1.0]),
        c_alpha=np.array([cf, cf, cr, cr]),
        load_static=np.array([front, front, rear, rear]),
        fz_nominal=np.array([front, front, rear, rear]) * params.mass * params.gravity,
        load_ax=np.array([-h / (2.0 * L), -h / (2.0 * L), h / (2.0 * L), h / (2.0 * L)]),
        load_ay=np.array([-dfront, dfront, -drear, drear]),
        drive_share=_drive_share(params.driven_axle),
    )


def _drive_share(driven_axle: str) -> np.ndarray:
    """Share of the drive per wheel: equal parts on the driven wheels."""
    wheels = DRIVEN_WHEELS[driven_axle]
    share = np.zeros(4)
    share[list(wheels)] = 1.0 / len(wheels)
    return share


def _wheel_velocities(vx, vy, r, delta, params: VehicleParams, min_speed: float):
    """Eqs. 6-7: slip angles ``alpha_t`` and forward wheel speeds ``v_t``, shape (..., 4).

    Per wheel, ``v_x = vx -+ (track/2) r`` and ``v_y = vy + l_F r`` (front) or
    ``-vy + l_R r`` (rear, the sign of Eq. 6); ``alpha = delta - atan(v_y / v_x)`` at the
    front and ``atan(v_y / v_x)`` at the rear; ``v_t = v_x cos(delta) + v_y sin(delta)`` at the
    front and ``v_x`` at the rear. Evaluated as (..., 4) arrays in a handful of operations: the
    filters call this for every cubature point at every step.
    """
    g = _geometry(params)
    vx = np.asarray(vx, dtype=float)[..., None]
    vy = np.asarray(vy, dtype=float)[..., None]
    r = np.asarray(r, dtype=float)[..., None]
    vxw = vx + g.x_from_r * r
    vyw = g.y_from_vy * vy + g.y_from_r * r
    alpha = g.steered * delta + g.alpha_sign * np.arctan(vyw / np.maximum(vxw, min_speed))
    cd, sd = math.cos(delta), math.sin(delta)
    front = g.steered
    vt = vxw * (front * (cd - 1.0) + 1.0) + vyw * (front * sd)
    return alpha, vt


def wheel_forward_speeds(x, steer_angle: float, params: VehicleParams) -> np.ndarray:
    """Forward wheel-centre speeds ``v_t`` of Eq. 7 for state(s) ``x``, shape (..., 4)."""
    x = np.asarray(x, dtype=float)
    _, vt = _wheel_velocities(x[..., 0], x[..., 1], x[..., 2], float(steer_angle), params, _EPS)
    return vt


def free_rolling_wheel_speeds(x, steer_angle: float, params: VehicleParams,
                              slip=0.0) -> np.ndarray:
    """Wheel speeds ``omega = v_t (1 + sigma) / R`` that produce slip ``sigma`` (Eq. 8).

    Convenience for simulation and tests; ``slip`` broadcasts against ``(..., 4)``.
    """
    vt = wheel_forward_speeds(x, steer_angle, params)
    return vt * (1.0 + np.asarray(slip, dtype=float)) / params.wheel_radius


def _vertical_loads(ax_spec, ay, slope, mass, params: VehicleParams):
    """Eq. 5 (load transfer with the specific force ``ax_spec``), shape (..., 4), >= 0."""
    g = _geometry(params)
    ax_spec = np.asarray(ax_spec, dtype=float)[..., None]
    ay = np.asarray(ay, dtype=float)[..., None]
    fz = mass * (g.load_static * (params.gravity * math.cos(slope)) + g.load_ax * ax_spec + g.load_ay * ay)
    return np.maximum(fz, 0.0)


def _dugoff(slip, alpha, fz, params: VehicleParams, mu_fz=None):
    """Eq. 9, Dugoff tyre, arrays (..., 4). Returns (Fx, Fy) in the wheel frame.

    With ``params.tyre_load_exponent`` ``n > 0`` the stiffnesses are ``C (F_z / F_z0)^n``
    (module docstring); ``n = 0`` is Eq. 9 as printed. ``mu_fz``: the friction force the tyre
    has (default ``road_friction F_z``).
    """
    geometry = _geometry(params)
    c_sigma = params.longitudinal_stiffness
    c_alpha = geometry.c_alpha
    n = params.tyre_load_exponent
    if n != 0.0:
        load = (np.asarray(fz, dtype=float) / geometry.fz_nominal) ** n
        c_sigma = c_sigma * load
        c_alpha = c_alpha * load
    if mu_fz is None:
        mu_fz = params.road_friction * fz
    one_p = np.maximum(1.0 + slip, 1e-6)
    kx = c_sigma * slip
    ky = c_alpha * np.tan(alpha)
    d = np.maximum(np.sqrt(kx * kx + ky * ky), _EPS)
    lam = mu_fz * one_p / (2.0 * d)
    # f(lambda)/(1+sigma): 1/(1+sigma) if lambda >= 1, else (2-lambda) mu Fz / (2 D)
    scale = np.where(lam < 1.0, (2.0 - lam) * mu_fz / (2.0 * d), 1.0 / one_p)
    return kx * scale, ky * scale


def _fallback_fx(inputs: VehicleInputs, mu_fz, params: VehicleParams):
    """Quasi-static longitudinal forces from torques or the drive force (wheel inertia
    neglected), clipped to the friction limit ``mu_fz``."""
    fx = wheel_torques(inputs, params) / params.wheel_radius
    return np.clip(fx, -mu_fz, mu_fz)


def longitudinal_forces_known(inputs: VehicleInputs, slip_forces: bool = True) -> bool:
    """Whether the model has the longitudinal tyre forces (and so ``ax``): from the measured
    wheel slip (with ``slip_forces``) or from torques. Else the fallback: the drive force the
    caller sets from its own ``ax`` estimate, and ``ax`` a random walk (module docstring)."""
    return (slip_forces and inputs.wheel_speeds_valid) or inputs.torques_valid


def wheel_torques(inputs: VehicleInputs, params: VehicleParams) -> np.ndarray:
    """Net torque per wheel [N m]: the drive torque split over the driven wheels, less the
    brake torques (the fallback's longitudinal force before its friction limit); without
    torques, the drive force's (``VehicleInputs.drive_force``) torque."""
    t = np.zeros(4)
    if not inputs.torques_valid:
        force = inputs.drive_force
        if force is not None and math.isfinite(force) and force > 0.0:
            t = force * params.wheel_radius * _geometry(params).drive_share
        return t
    if inputs.drive_torque is not None:
        t = t + inputs.drive_torque * _geometry(params).drive_share
    if inputs.brake_torques is not None:
        t = t - inputs.brake_torques
    return t


def tyre_forces(state, inputs: VehicleInputs, params: VehicleParams, *,
                min_speed: float = DEFAULT_MIN_SPEED, slip_forces: bool = True) -> TyreForces:
    """Tyre forces of all four wheels (Eqs. 5-9) for state(s) ``x`` of shape (..., 5).

    Vertical loads (Eq. 5) use the accelerations in the state (``ax`` converted to the
    specific force ``ax + g sin(theta)``, ``ay`` as is). Without valid wheel speeds, or with
    ``slip_forces`` False (the wheel speeds are read as a speed elsewhere, not as slip), the
    longitudinal forces follow the fallback of the module docstring.
    """
    x = np.asarray(state, dtype=float)
    vx, vy, r, ax, ay = (x[..., i] for i in range(5))
    delta = float(inputs.steer_angle)
    theta = float(inputs.slope)
    mass = inputs.mass_or(params)
    alpha, vt = _wheel_velocities(vx, vy, r, delta, params, min_speed)
    fz = _vertical_loads(ax + params.gravity * math.sin(theta), ay, theta, mass, params)
    if slip_forces and inputs.wheel_speeds_valid:
        slip = (inputs.wheel_speeds * params.wheel_radius - vt) / np.maximum(np.abs(vt), min_speed)
        fx, fy = _dugoff(slip, alpha, fz, params)
        from_slip = True
    else:
        slip = np.zeros_like(vt)
        mu_fz = params.road_friction * fz
        fx = _fallback_fx(inputs, mu_fz, params)
        # the friction ellipse: the lateral force has what the longitudinal one leaves
        _, fy = _dugoff(slip, alpha, fz, params, np.sqrt(np.maximum(mu_fz * mu_fz - fx * fx, 0.0)))
        fx = np.broadcast_to(fx, fy.shape)
        from_slip = False
    return TyreForces(fx, fy, fz, slip, alpha, vt, from_slip)


def aerodynamic_drag(vx, params: VehicleParams):
    """The drag of Eq. 2, ``0.5 rho C_d A vx |vx|`` [N] (sign-correct when reversing)."""
    return 0.5 * params.drag_coefficient * params.frontal_area * params.air_density * vx * np.abs(vx)


def _force_to_body(delta: float, params: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """(4, 3) matrices ``Mx``, ``My`` with ``[sum Fx_body, sum Fy_body, M_z] = Fx @ Mx + Fy @ My``
    (the tyre forces in their wheel frames, front wheels steered by ``delta``): Eqs. 2-4 as
    two matrix products."""
    cd, sd = math.cos(delta), math.sin(delta)
    lf, lr = params.lf, params.lr
    hf, hr = 0.5 * params.track_front, 0.5 * params.track_rear
    mx = np.array([[cd, sd, lf * sd - hf * cd],
                   [cd, sd, lf * sd + hf * cd],
                   [1.0, 0.0, -hr],
                   [1.0, 0.0, hr]])
    my = np.array([[-sd, cd, lf * cd + hf * sd],
                   [-sd, cd, lf * cd - hf * sd],
                   [0.0, 1.0, -lr],
                   [0.0, 1.0, -lr]])
    return mx, my


def _body_accelerations(x, inputs: VehicleInputs, params: VehicleParams, min_speed: float,
                        slip_forces: bool = True):
    """Eqs. 2-4: model ``ax``, ``ay`` and ``r' = M_z / I_z``; plus whether ``ax`` is known.

    ``ax`` is kinematic (includes ``-g sin(theta)``). ``ax_known`` is False in the
    no-wheel-speed, no-torque fallback (``ax`` from the model is then meaningless).

    Eq. 2: ``m ax = (Fx1 + Fx2) cos d + Fx3 + Fx4 - (Fy1 + Fy2) sin d - F_drag``;
    Eq. 3: ``m ay = (Fx1 + Fx2) sin d + Fy3 + Fy4 + (Fy1 + Fy2) cos d``;
    Eq. 4: ``M_z = l_F (Fx1 + Fx2) sin d - l_R (Fy3 + Fy4) + l_F (Fy1 + Fy2) cos d
    - (B_F/2)(Fx1 - Fx2) cos d + (B_F/2)(Fy1 - Fy2) sin d - (B_R/2)(Fx3 - Fx4)``.
    """
    tf = tyre_forces(x, inputs, params, min_speed=min_speed, slip_forces=slip_forces)
    mass = inputs.mass_or(params)
    mx, my = _force_to_body(float(inputs.steer_angle), params)
    sums = tf.fx @ mx + tf.fy @ my
    vx = np.asarray(x, dtype=float)[..., 0]
    drag = aerodynamic_drag(vx, params)
    ax = (sums[..., 0] - drag) / mass - params.gravity * math.sin(inputs.slope)   # Eq. 2
    ay = sums[..., 1] / mass                                                        # Eq. 3
    ax_known = longitudinal_forces_known(inputs, slip_forces)
    return ax, ay, sums[..., 2] / params.yaw_inertia, ax_known                    # Eq. 4


def state_derivative(x, inputs: VehicleInputs, params: VehicleParams, *,
                     min_speed: float = DEFAULT_MIN_SPEED,
                     accel_time_constant: float = ACCEL_TIME_CONSTANT,
                     slip_forces: bool = True) -> np.ndarray:
    """Continuous model ``x' = f(x, u)`` of Eq. 10 for ``x = [vx, vy, r, ax, ay]`` (..., 5).

    Rows 0-2 are Eq. 1 with ``ax``, ``ay`` from Eqs. 2-3 and ``M_z`` from Eq. 4. Rows 3-4
    relax the ``ax``/``ay`` states towards Eqs. 2-3 with ``accel_time_constant`` (they
    are algebraic in the paper; :func:`transition` sets them directly). In the fallback
    without wheel speeds or torques, row 0 uses the state ``ax`` and row 3 is 0.
    """
    x = np.asarray(x, dtype=float)
    ax_m, ay_m, rdot, ax_known = _body_accelerations(x, inputs, params, min_speed, slip_forces)
    vx, vy, r, ax, ay = (x[..., i] for i in range(5))
    ax_used = ax_m if ax_known else ax
    out = np.empty(np.broadcast(vx, ax_m).shape + (5,))
    out[..., 0] = ax_used + r * vy
    out[..., 1] = ay_m - r * vx
    out[..., 2] = rdot
    out[..., 3] = (ax_m - ax) / accel_time_constant if ax_known else 0.0
    out[..., 4] = (ay_m - ay) / accel_time_constant
    return out


def transition(x, inputs: VehicleInputs, params: VehicleParams, dt: float, *,
               min_speed: float = DEFAULT_MIN_SPEED,
               max_substep: float = DEFAULT_MAX_SUBSTEP, slip_forces: bool = True) -> np.ndarray:
    """Discrete process model ``x_{k+1} = F(x_k, u_{k+1}, dt)`` used by the filters.

    Vectorised: ``x`` may be ``(5,)`` or a batch ``(n, 5)`` (cubature points). ``dt`` is
    split into ``ceil(dt / max_substep)`` semi-implicit Euler sub-steps of Eq. 1 with the
    accelerations of Eqs. 2-4; afterwards ``ax``, ``ay`` are set to Eqs. 2-3 at the
    propagated state (algebraic outputs). Fallback (no wheel speeds, no torques):
    ``vx`` is integrated with the state ``ax``, which is kept constant (random walk).
    """
    x = np.array(x, dtype=float)  # copy
    if dt <= 0.0:
        return x
    n = max(1, int(math.ceil(dt / max_substep - 1e-9)))
    h = dt / n
    ax_known = True
    for _ in range(n):
        ax_m, ay_m, rdot, ax_known = _body_accelerations(x, inputs, params, min_speed, slip_forces)
        vx = x[..., 0]
        r = x[..., 2]
        ax_used = ax_m if ax_known else x[..., 3]
        vx_new = vx + h * (ax_used + r * x[..., 1])
        x[..., 1] += h * (ay_m - r * vx)
        x[..., 0] = vx_new
        x[..., 2] += h * rdot
        x[..., 3] = ax_used
        x[..., 4] = ay_m
    ax_m, ay_m, _, ax_known = _body_accelerations(x, inputs, params, min_speed, slip_forces)
    if ax_known:
        x[..., 3] = ax_m
    x[..., 4] = ay_m
    return x


def measurement(x, inputs: VehicleInputs, params: VehicleParams) -> np.ndarray:
    """Predicted IMU measurement ``z = [ax_imu, ay_imu, r]`` (Eq. 10), shape (..., 3).

    ``ax_imu = ax + g sin(theta)`` is the accelerometer's specific force (Eq. 21 with the
    exact sine); ``ay_imu = ay`` (no roll/bank in the model); ``r`` the gyro yaw rate.
    """
    x = np.asarray(x, dtype=float)
    out = np.empty(x.shape[:-1] + (3,))
    out[..., 0] = x[..., 3] + params.gravity * math.sin(float(inputs.slope))
    out[..., 1] = x[..., 4]
    out[..., 2] = x[..., 2]
    return out


def measurement_affine(inputs: VehicleInputs, params: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """``(H, c)`` with :func:`measurement` ``= H x + c``: the IMU measurement is affine in the
    state, so the filters take its moments in closed form (a test checks the identity)."""
    return _MEASUREMENT_H, np.array([params.gravity * math.sin(float(inputs.slope)), 0.0, 0.0])


_MEASUREMENT_H = np.zeros((3, 5))
_MEASUREMENT_H[0, 3] = _MEASUREMENT_H[1, 4] = _MEASUREMENT_H[2, 2] = 1.0
_MEASUREMENT_H.setflags(write=False)


def sideslip(x) -> float:
    """Vehicle sideslip ``beta = arctan(vy / vx)`` (Eq. 14) [rad].

    Undefined at stand-still: returns 0 for ``|vx| < 1e-3`` m/s.
    """
    vx = float(x[0])
    vy = float(x[1])
    if abs(vx) < 1e-3:
        return 0.0
    return math.atan(vy / vx)


def sideslip_variance(x, P) -> float:
    """First-order variance of :func:`sideslip` from the ``(vx, vy)`` block of ``P`` [rad^2];
    ``inf`` where ``vx^2 + vy^2 < 1e-6`` (the angle is undefined there)."""
    vx, vy = x[0], x[1]
    s = vx * vx + vy * vy
    if s < 1e-6:
        return float("inf")
    J = np.array([-vy / s, vx / s])
    return float(J @ P[:2, :2] @ J)
