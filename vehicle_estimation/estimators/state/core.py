"""What every vehicle-state core shares, whatever its model and filter.

The paper-004 CKF / VB-ACKF (:mod:`.ckf`, :mod:`.vbackf`) and the paper-002 AO-UKF
(:mod:`.aoukf`) step on IMU samples with the chassis inputs of
:class:`~vehicle_estimation.estimators.state.vehicle_model.VehicleInputs`, and all of them:

* admit a sample only with a finite stamp that increases, valid inputs and ``z`` of three
  values (:class:`~vehicle_estimation.estimators.common.guard.StepGuard`);
* start vx from the mean speed of two wheels times the wheel radius when asked to;
* re-initialise, and count it, when the moments stop being a valid Gaussian (absurd inputs);
* take a direct vx measurement (:meth:`VehicleStateCore.update_speed`) where there are no
  wheel speeds (a bus speed, or the speed each corner shows: :class:`CorneringSpeed`), and
  an extra vx process noise (:attr:`extra_vx_noise_density`) that the node sets while an
  input is unknown;
* report the sideslip of Eq. 14 of paper 004 with its first-order variance;
* publish a covariance that carries the tyre-stiffness error and the road bank the filters do
  not model (:class:`ModelErrorSettings`).

A core satisfies :class:`~vehicle_estimation.estimators.interfaces.StateEstimator`.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections import Counter
from typing import Optional, Sequence

import numpy as np

from vehicle_estimation.contract.settings import setting
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common.guard import StepGuard
from vehicle_estimation.estimators.common.noise import white_equivalent_variance
from vehicle_estimation.estimators.common import small_linalg
from vehicle_estimation.estimators.common.sigma_points import AdditiveNoiseFilter, valid_moments
from vehicle_estimation.estimators.state import vehicle_model as vm
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs


#: The state node's defaults (``cornering_speed_accel_std``, ``cornering_speed_min_yaw_rate``).
DEFAULT_CORNERING_ACCEL_STD = 0.7
DEFAULT_CORNERING_MIN_YAW_RATE = 0.2


@dataclasses.dataclass
class CorneringSpeed:
    """``v_x = mean(a_y) / mean(r)`` per window of ``window_s``, with its variance: the speed
    cornering shows while nothing measures it.

    A car's lateral acceleration is ``a_y = v_y' + v_x r`` (the body-frame kinematics, no
    tyre model in it). Over a window the mean ``v_y'`` is small next to ``v_x r`` whenever the
    car turns, so ``v_x ~ mean(a_y) / mean(r)``: the speed from the IMU alone, in every corner.
    A car without wheel speeds and without a bus speed otherwise dead-reckons ``v_x`` from the
    accelerometer, and only the tyre model pulls it back, the wrong way at the limit (the real
    Stanford drive: the AO-UKF's vx up to 50 m/s off).

    The window's ``mean(v_y')`` and the ay the IMU reads for other reasons (body roll, road
    bank) are ``accel_std``, over ``|mean(r)|`` in vx. On the real Stanford drive (100 Hz, a
    track, |ay| up to 16.6 m/s^2) the 0.5 s windows at ``|r| > 0.2 rad/s`` (46 % of them) give
    vx with no bias and that error at 0.6 m/s^2, most of it the window's ``v_y'`` (correlation
    0.8); successive windows share little of it (0.19: ``correlation_s``). The mean's own
    error, the spread of the window's samples over their number (vibration), adds to it. Below
    ``min_yaw_rate`` the ratio says nothing: no measurement.

    Feed every filter step's (roll-compensated) lateral acceleration and yaw rate to
    :meth:`step` (:meth:`add` once nothing else measures vx); at the end of each window it
    returns ``(v_x, variance)``, or None while the window fills, where the car turns too
    little, or when the value is not finite.
    """

    accel_std: float = DEFAULT_CORNERING_ACCEL_STD        # the window's v_y' and unmodelled a_y [m/s^2]
    min_yaw_rate: float = DEFAULT_CORNERING_MIN_YAW_RATE  # [rad/s]
    window_s: float = 0.5
    correlation_s: float = 0.25                           # [s]

    def __post_init__(self) -> None:
        for name in ("accel_std", "min_yaw_rate", "window_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.correlation_s) and self.correlation_s >= 0.0):
            raise ValueError(f"correlation_s must be >= 0, got {self.correlation_s!r}")
        self.reset()

    def reset(self) -> None:
        self._start = self._last = math.nan
        self._ay_sum = self._ay_square_sum = self._r_sum = 0.0
        self._count = 0

    def step(self, t: float, ay: float, yaw_rate: float, vx_measured: bool) -> tuple[float, float] | None:
        """One filter step as the state node takes it: while something else (wheel speeds, a
        bus speed) measures vx, no window fills and the open one is dropped; else :meth:`add`."""
        if vx_measured:
            self.reset()
            return None
        return self.add(t, ay, yaw_rate)

    def add(self, t: float, ay: float, yaw_rate: float) -> tuple[float, float] | None:
        """One filter step's ``a_y`` [m/s^2] and ``r`` [rad/s] at ``t`` [s]. A stamp going back
        (a bag loop) or a gap of a window or more (a dropout) starts a new window: a mean over
        samples that far apart is no window's."""
        if not (math.isfinite(ay) and math.isfinite(yaw_rate)):
            return None
        if not math.isfinite(self._start) or t < self._last or t - self._last >= self.window_s:
            self.reset()
            self._start = t
        self._last = t
        self._ay_sum += ay
        self._ay_square_sum += ay * ay
        self._r_sum += yaw_rate
        self._count += 1
        span = t - self._start
        if span < self.window_s:
            return None
        n = self._count
        ay_mean, r_mean = self._ay_sum / n, self._r_sum / n
        # the mean's own error, from the spread within the window (vibration, engine)
        ay_mean_variance = max(self._ay_square_sum / n - ay_mean * ay_mean, 0.0) / max(n - 1, 1)
        self.reset()
        if abs(r_mean) < self.min_yaw_rate:
            return None
        vx = ay_mean / r_mean
        variance = white_equivalent_variance((self.accel_std ** 2 + ay_mean_variance) / r_mean ** 2,
                                             self.correlation_s, span)
        return (vx, variance) if math.isfinite(vx) else None


class RollAccelerationTerm:
    """The lateral acceleration a body-fixed IMU feels from the body's roll acceleration.

    An IMU ``h`` above the roll axis of a body rolling at ``p`` is accelerated by ``-h p'``
    along its y axis on top of the acceleration of the roll axis, which is what the tyres
    push (the roll-plane model: ``m (v_y' + v_x r) - m_s h phi'' = sum F_y``, Rajamani,
    "Vehicle Dynamics and Control", Sec. 3.x). The filters' models have no roll, so the term
    is added back to the measured ay: ``+h p'``, with ``p'`` the difference of the mean gyro
    roll rates of consecutive filter steps over their spacing. ``h = 0``: the term is 0.
    Feed every roll-rate sample with :meth:`add`; :meth:`step` at every filter step returns
    the term for the step's mean ay [m/s^2]."""

    def __init__(self, lever: float) -> None:
        self.lever = float(lever)
        self._sum, self._count = 0.0, 0
        self._last: Optional[tuple[float, float]] = None     # (t, mean roll rate) of the last step

    def add(self, roll_rate: float) -> None:
        if self.lever > 0.0 and math.isfinite(roll_rate):
            self._sum += roll_rate
            self._count += 1

    def step(self, t: float) -> float:
        if self._count == 0:
            self._last = None
            return 0.0
        mean = self._sum / self._count
        self._sum, self._count = 0.0, 0
        last, self._last = self._last, (t, mean)
        if last is None or not t > last[0]:
            return 0.0
        return self.lever * (mean - last[1]) / (t - last[0])

    def reset(self) -> None:
        self._sum, self._count, self._last = 0.0, 0, None


class SpeedPresence:
    """Whether vx has a measurement, with a hold either way.

    A filter that takes vx as a measurement (paper 002's AO-UKF) must not run without one, and
    filters swapped at every short CAN dropout would run neither well. Feed the stamp of every
    speed sample (a wheel speed, a CAN speed) with :meth:`sample` and the clock with
    :meth:`clock`: :meth:`lost` once no sample has come for ``hold_s`` (from the first clock,
    where none came yet), :meth:`back` once samples have come for ``hold_s`` without a gap of
    more than ``max_gap_s``."""

    def __init__(self, hold_s: float, max_gap_s: float) -> None:
        self.hold_s = float(hold_s)
        self.max_gap_s = float(max_gap_s)
        self.reset()

    def reset(self) -> None:
        self._first_t: Optional[float] = None
        self._last_t = -math.inf        # the last speed sample
        self._run_from = -math.inf      # the first sample after the last gap

    def sample(self, t: float) -> None:
        if t - self._last_t > self.max_gap_s:
            self._run_from = t
        self._last_t = max(self._last_t, t)

    def clock(self, t: float) -> None:
        if self._first_t is None:
            self._first_t = t

    @property
    def ever(self) -> bool:
        """Whether any speed sample came (since the start or the last reset)."""
        return math.isfinite(self._last_t)

    #: Stamps are floats: a hold that ends on a sample's stamp counts as over.
    _TOLERANCE_S = 1e-9

    def lost(self, t: float) -> bool:
        start = self._first_t if self._first_t is not None else t
        return t - max(self._last_t, start) >= self.hold_s - self._TOLERANCE_S

    def back(self, t: float) -> bool:
        return (t - self._last_t <= self.max_gap_s
                and self._last_t - self._run_from >= self.hold_s - self._TOLERANCE_S)


@dataclasses.dataclass(frozen=True)
class ModelErrorSettings:
    """Model errors that no filter represents and that every core adds to its published
    covariance (:attr:`VehicleStateCore.P`); the estimates do not change."""

    tyre_stiffness_std: float = setting(
        0.0, "Relative uncertainty of the tyres' cornering stiffness, which every filter takes as "
        "exact [-]. The rear axle's lateral force is fixed by the measured ay and yaw rate, so a "
        "stiffness off by this share moves its slip angle, and vy with it, by this share of the "
        "rear axle's slip velocity vy - l_r r: (std (vy - l_r r))^2 is added to the published vy "
        "variance (0 = paper: the filter's own covariance)", low=0.0, high=1.0)
    road_bank_std_deg: float = setting(
        0.0, "Std of the road's cross slope (crown, superelevation, track camber) that no filter "
        "sees [deg]. On a bank phi the tyres also hold m g sin(phi) against gravity, which a "
        "kinematic or roll-compensated ay does not show; the rear axle takes l_f/L of it, so its "
        "slip angle, and vy with it, moves by vx (l_f/L) m g sin(phi) / C_rear: that variance is "
        "added to the published vy variance (0 = a level road, the paper)", low=0.0, high=15.0)


class VehicleStateCore(StepGuard, ABC):
    """Bookkeeping of a vehicle-state core around its Kalman filter :attr:`filter`.

    A subclass builds ``self._filter`` and implements ``step`` with :meth:`_begin_step`,
    :meth:`_with_extra_vx_noise` and :meth:`_reinitialised_after_failure`, and
    :meth:`_vx_after_gap` and :meth:`_correct_speed` (for :meth:`update_speed`).

    Args:
        params: the vehicle (validated by the subclass, with its config, first).
        initial_vx: the start speed without wheel speeds [m/s].
        P0: the initial covariance.
        speed_wheels: indices of the wheels whose mean speed starts vx.
        max_gap_s: a stamp gap above which the core re-initialises [s].
    """

    _filter: AdditiveNoiseFilter

    def __init__(self, params: VehicleParams, initial_vx: float, P0: np.ndarray, speed_wheels: Sequence[int],
                 max_gap_s: float):
        self.params = params
        self._max_gap_s = max_gap_s
        self._initial_vx = initial_vx
        self._P0 = P0
        self._speed_wheels = list(speed_wheels)
        self.t: Optional[float] = None
        self.initialised = False
        self.rejected: Counter = Counter(
            {"nonfinite_measurement": 0, "invalid_input": 0, "stamp_not_increasing": 0})
        self.reinitialisations = 0
        self.last_event = ""
        self.updates = 0
        self.speed_updates = 0
        #: Extra process noise on vx [(m/s^2)^2 s], added as ``density * dt`` per step: the
        #: owner sets it while an input is unknown (the node: no slope estimate, so the grade's
        #: g sin(theta) acts on vx as a correlated acceleration error).
        self.extra_vx_noise_density = 0.0
        #: :attr:`ModelErrorSettings.tyre_stiffness_std`, set by the owner (the registry's builders).
        self.tyre_stiffness_std = 0.0
        #: :attr:`ModelErrorSettings.road_bank_std_deg` in radians, set by the owner likewise.
        self.road_bank_std = 0.0
        #: The per-step validity check by a compiled kernel (set with the filter's kernels).
        self.compiled_checks = False
        self._factor_work = np.empty_like(P0, dtype=float)
        self._known_noise: Optional[np.ndarray] = None
        self._handed_over: Optional[tuple[np.ndarray, np.ndarray]] = None   # see start_from

    #: True for a filter that learns its measurement noise (the VB-ACKF): the owner then gives
    #: it the sensor's stated noise as a floor (:meth:`set_known_noise`), which a filter with a
    #: fixed ``R`` already has.
    learns_measurement_noise = False

    #: What each channel of the filter's measurement is, in order: the step's ``z = [ax, ay, r]``
    #: itself for the paper-004 filters; a core whose filter measures something else (the
    #: AO-UKF: ``[ay, r, vx]``, with ax a model input) says so, so that a known noise reaches
    #: the channel it belongs to.
    measurement_channels: tuple[str, ...] = ("ax", "ay", "r")

    def set_known_noise(self, ax: float = 0.0, ay: float = 0.0, r: float = 0.0) -> None:
        """Known variances of the step's ``z = [ax, ay, r]`` on top of the filter's (learnt)
        ``R`` from the next update on (a non-finite or non-positive one counts as 0; all 0
        removes them), each on the filter's channel of that name (:attr:`measurement_channels`;
        a quantity the filter does not measure has none). The owner sets them from its inputs'
        own uncertainty: the fusion roll's error enters the roll-compensated ay one for one, and
        the IMU's stated noise floors what a filter that learns ``R`` learns."""
        named = {"ax": ax, "ay": ay, "r": r}
        values = [float(named.get(name, 0.0)) for name in self.measurement_channels]
        values = [v if math.isfinite(v) and v > 0.0 else 0.0 for v in values]
        if not any(values):
            self._filter.known_noise = None
            return
        if self._known_noise is None:   # one matrix, rewritten at every step
            self._known_noise = np.zeros((self._filter.m, self._filter.m))
        for channel, value in enumerate(values):
            self._known_noise[channel, channel] = value
        self._filter.known_noise = self._known_noise

    # -- helpers -------------------------------------------------------------------------
    def _x0(self, vx0: Optional[float]) -> np.ndarray:
        """``[vx0, 0, ...]`` (``vx0`` default: the initial speed)."""
        x0 = np.zeros(self._P0.shape[0])
        x0[0] = self._initial_vx if vx0 is None else float(vx0)
        return x0

    def _initial_moments(self, vx0: Optional[float]) -> tuple[np.ndarray, np.ndarray]:
        """The first step's mean and covariance: :meth:`start_from`'s where one was handed
        over (with ``vx0``, from the wheels, in place of its vx), else ``[vx0, 0, ...]`` and P0."""
        if self._handed_over is None:
            return self._x0(vx0), self._P0
        x0, P0 = self._handed_over[0].copy(), self._handed_over[1]
        if vx0 is not None:
            x0[0] = float(vx0)
        return x0, P0

    def start_from(self, x: np.ndarray, P: np.ndarray) -> None:
        """Start, at the next step, from another filter's ``[vx, vy, r]`` and their covariance
        (the filter's other states at their prior). A filter that takes a drive over mid-way
        (the state node's no-speed filter, and back) then does not begin a corner from
        vy = r = 0. Ignored where those moments are not finite and positive definite; a reset
        (a stamp gap, a numerical failure) starts from the prior again."""
        x3 = np.asarray(x, dtype=float)[:3]
        P3 = np.asarray(P, dtype=float)[:3, :3]
        self.reset(float(x3[0]) if np.isfinite(x3[0]) else None)
        if not (np.isfinite(x3).all() and np.isfinite(P3).all()):
            return
        try:
            np.linalg.cholesky(P3)
        except np.linalg.LinAlgError:
            return
        x0, P0 = self._x0(float(x3[0])), self._P0.copy()
        x0[:3] = x3
        P0[:3, :] = 0.0
        P0[:, :3] = 0.0
        P0[:3, :3] = 0.5 * (P3 + P3.T)
        self._handed_over = (x0, P0)
        self._filter.reset(x0, P0)

    def _vx_from_wheels(self, inputs: VehicleInputs) -> Optional[float]:
        """Mean speed of the :attr:`_speed_wheels` times the wheel radius; None unless all are finite."""
        ws = inputs.wheel_speeds[self._speed_wheels]
        if np.isfinite(ws).all():
            return float(np.mean(ws) * self.params.wheel_radius)
        return None

    def _begin_step(self, t, inputs, z) -> Optional[tuple[float, np.ndarray, float]]:
        """``(t, z, time since the last step)`` if the sample may be used, else None (counted:
        non-numeric or non-finite ``t``, invalid ``inputs``, ``z`` not 3 values, or a stamp
        that does not increase). After a gap above ``max_gap_s`` the core is re-initialised
        (from :meth:`_vx_after_gap`) and the sample is its first."""
        try:
            t = float(t)
            z = np.asarray(z, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            t, z = math.nan, np.empty(0)
        valid = isinstance(inputs, VehicleInputs) and inputs.is_valid() and z.shape == (3,)
        dt = self.admit(t, valid)
        if dt is None:
            return None
        if self.t is not None and dt > self._max_gap_s:
            self.reset(self._vx_after_gap(inputs))
            self.note_reinitialised(dt)
        return t, z, dt

    def _vx_now(self) -> Optional[float]:
        """The current vx estimate of the filter, None if it is not finite."""
        vx = float(self._filter.x[0])
        return vx if math.isfinite(vx) else None

    @abstractmethod
    def _vx_after_gap(self, inputs: VehicleInputs) -> Optional[float]:
        """The vx a re-initialisation after a stamp gap starts from (None: initial)."""

    def _with_extra_vx_noise(self, Q: np.ndarray, dt: float) -> np.ndarray:
        """``Q`` plus :attr:`extra_vx_noise_density` ``* dt`` on vx (a copy when that is added)."""
        if self.extra_vx_noise_density > 0.0:
            Q = np.array(Q, dtype=float)
            Q[0, 0] += self.extra_vx_noise_density * dt
        return Q

    def _vx_after_failure(self, inputs: VehicleInputs) -> Optional[float]:
        """The vx a re-initialisation after a numerical failure starts from (None: initial)."""
        return None

    def _reinitialised_after_failure(self, inputs: VehicleInputs) -> bool:
        """Re-initialise (and count it) when the mean is not finite or the covariance is no
        longer positive definite (absurd inputs, rounding); True if it did."""
        x, P = self._filter._x, self._filter._P
        if self.compiled_checks:
            if small_linalg.valid_moments(x, P, self._factor_work):
                return False
        elif valid_moments(x, P):
            return False
        self.reset(self._vx_after_failure(inputs))
        self.reinitialisations += 1
        self.last_event = "re-initialised after numerical failure"
        return True

    def reset(self, vx0: Optional[float] = None) -> None:
        """Back to ``x0 = [vx0, 0, ...]`` (``vx0`` default: the initial speed), ``P0``; forget the stamp."""
        self._handed_over = None
        self._filter.reset(self._x0(vx0), self._P0)
        self.t = None
        self.initialised = False

    # -- speed measurement ---------------------------------------------------------------
    def update_speed(self, vx: float, variance: float) -> bool:
        """Update with a direct measurement of the longitudinal speed ``vx`` [m/s].

        Not in papers 004 and 002, whose models observe vx through the wheel speeds only:
        without them (a car whose bus reports only the vehicle speed, a log without wheel
        speeds) vx would be dead-reckoned from the accelerometer and drift with its bias. The
        measurement is linear (``H = [1, 0, ...]``), so the exact Kalman update on the
        current moments. Returns False (nothing changes) for a non-finite value or
        variance <= 0, or before the filter has started.
        """
        vx, variance = float(vx), float(variance)
        if not (self.initialised and math.isfinite(vx) and math.isfinite(variance) and variance > 0.0):
            return False
        self._correct_speed(vx, variance)
        self.speed_updates += 1
        return True

    @abstractmethod
    def _correct_speed(self, vx: float, variance: float) -> None:
        """Correct the filter with a measured vx of ``variance`` (the filter's own update)."""

    # -- outputs -------------------------------------------------------------------------
    @property
    def filter(self) -> AdditiveNoiseFilter:
        """The Kalman filter the core runs."""
        return self._filter

    @property
    def x(self) -> np.ndarray:
        return self._filter.x

    @property
    def P(self) -> np.ndarray:
        """The covariance of :attr:`x` as published: the filter's, plus on vy the variances of
        a tyre stiffness off by :attr:`tyre_stiffness_std` and of a road bank of
        :attr:`road_bank_std` (:class:`ModelErrorSettings`); both move the rear slip angle,
        which the filters take as fixed by the measured ay and yaw rate."""
        P = np.array(self._filter.P, dtype=float)
        x = self.x              # the published estimate (the AO-UKF's after its output correction)
        if self.tyre_stiffness_std > 0.0:
            P[1, 1] += (self.tyre_stiffness_std * (x[1] - self.params.lr * x[2])) ** 2
        if self.road_bank_std > 0.0:
            P[1, 1] += self.bank_vy_std(float(x[0])) ** 2
        return P

    def bank_vy_std(self, vx: float) -> float:
        """The std of the vy error that a road bank of :attr:`road_bank_std` causes at ``vx``
        [m/s]. A bank phi leans gravity across the road: the tyres hold ``m g sin(phi)`` that
        the measured (kinematic, or roll-compensated) ay does not contain; the yaw moment is
        unchanged (r is measured), so the rear axle carries ``l_f / L`` of it and its slip angle
        ``(vy - l_r r) / vx`` is off by that force over the axle's stiffness."""
        p = self.params
        rear_axle_stiffness = 2.0 * p.cornering_stiffness_rear
        force = p.mass * p.gravity * math.sin(self.road_bank_std) * p.lf / p.wheelbase
        return abs(vx) * force / rear_axle_stiffness

    @property
    def sideslip(self) -> float:
        """``beta = arctan(vy / vx)`` of :attr:`x` (paper 004 Eq. 14) [rad]; 0 below 1 mm/s."""
        return vm.sideslip(self.x)

    @property
    def sideslip_variance(self) -> float:
        """First-order variance of :attr:`sideslip` from the ``(vx, vy)`` block of ``P`` [rad^2]."""
        return vm.sideslip_variance(self.x, self.P)

    def status(self) -> dict[str, str]:
        """What this filter adds to ``/diagnostics`` (none by default)."""
        return {}
