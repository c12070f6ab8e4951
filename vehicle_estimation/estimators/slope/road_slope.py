"""The road slope on every IMU sample: the suspension pitch taken out, the method's sources stepped.

A slope method (:data:`vehicle_estimation.estimators.registry.SLOPE_METHODS`) is one source or
two with the choice between them:

* the fusion grade of paper 003 Sec. 7.2
  (:class:`~vehicle_estimation.estimators.slope.pitch_grade.PitchGradeSlope`), stepped with the
  fusion's grade fresh at the sample's stamp;
* an IMU + speed observer of paper 004
  (:class:`~vehicle_estimation.estimators.slope.observers.ClassicalSlopeObserver`,
  :class:`~vehicle_estimation.estimators.slope.cubic_prediction.CubicPredictionSlopeObserver`),
  stepped with the longitudinal specific force and a speed;
* with both, :class:`~vehicle_estimation.estimators.slope.auto.AutoSlope`, which publishes the
  grade while it is usable and the observer otherwise.

:class:`RoadSlopeEstimator` runs them; the slope node only finds the inputs at each stamp.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.interfaces import SlopeEstimator
from vehicle_estimation.estimators.slope.auto import AutoSlope, AutoSlopeConfig
from vehicle_estimation.estimators.slope.observers import SlopeObserver
from vehicle_estimation.estimators.slope.pitch_grade import PitchGradeSlope
from vehicle_estimation.estimators.slope.suspension import SuspensionPitch

__all__ = ["GradeSample", "RoadSlopeEstimator"]


class GradeSample(NamedTuple):
    """The fusion's road grade as of a stamp."""

    value: float        #: [rad], + uphill (the body's pitch, suspension included)
    variance: float     #: [rad^2]
    converged: bool     #: as the fusion published it


class RoadSlopeEstimator:
    """One slope method: its sources, the choice between two, and the suspension pitch.

    Parameters
    ----------
    vehicle:
        gravity and the suspension's pitch gain and time constant.
    grade:
        the fusion-grade source, or None.
    observer:
        the IMU + speed observer, or None.
    auto:
        with both sources, how :class:`AutoSlope` chooses between them; None with one.
    """

    def __init__(self, vehicle: VehicleParams, *, grade: PitchGradeSlope | None = None,
                 observer: SlopeObserver | None = None, auto: AutoSlopeConfig | None = None) -> None:
        if (grade is not None and observer is not None) != (auto is not None):
            raise ValueError("two slope sources need the auto selection, one source none")
        self.gravity = vehicle.gravity
        self.grade = grade
        self.observer = observer
        self.auto: AutoSlope | None = None
        self.published: SlopeEstimator
        if grade is not None and observer is not None:
            self.auto = self.published = AutoSlope(grade, observer, auto)
        elif grade is not None:
            self.published = grade
        elif observer is not None:
            self.published = observer
        else:
            raise ValueError("a slope method needs the fusion grade, an observer or both")
        self.suspension = SuspensionPitch(vehicle.pitch_gain, vehicle.pitch_time_constant)
        self._observer_bias_variance = 0.0   # [rad^2], the observer's input bias as a slope

    @property
    def uses_grade(self) -> bool:
        """Whether the fusion grade is an input."""
        return self.grade is not None

    @property
    def uses_observer(self) -> bool:
        """Whether the IMU + speed observer runs (it needs a speed and the fusion's IMU bias)."""
        return self.observer is not None

    @property
    def requires_grade(self) -> bool:
        """Whether the fusion grade is the only source: without it the estimate is missing,
        where with an observer the observer stands in."""
        return self.grade is not None and self.observer is None

    def step(self, t: float, accel_x: float, yaw_rate: float, *, grade: GradeSample | None = None,
             velocity: tuple[float, float] | None = None, accel_bias_variance: float | None = None) -> int:
        """One IMU sample at stamp ``t`` [s].

        ``accel_x``: longitudinal specific force in base_link [m/s^2], bias-compensated where
        the fusion's estimate is known; ``yaw_rate`` [rad/s]; ``grade``: the fusion's grade
        fresh at ``t``, None when there is none; ``velocity``: ``(vx, vy)`` [m/s] for the
        observer, None when no speed is known; ``accel_bias_variance``: the variance of the
        bias left in ``accel_x`` [m^2/s^4], None without the fusion's estimate.
        Returns how many sources rejected the sample.
        """
        rejected = 0
        grade_usable = False
        # The body's pitch on its suspension (one filter step per IMU sample), driven by the
        # acceleration less gravity along the best slope known now: it tilts both the fusion
        # pitch and the accelerometer, so both sources take it out to get the road's grade.
        reference = (grade.value if grade is not None
                     else self.observer.slope if self.observer is not None else 0.0)
        squat = self.suspension.update(t, accel_x - self.gravity * math.sin(reference))
        if grade is not None and self.grade is not None:
            if not self.grade.step(t, grade.value - squat, grade.variance):
                rejected += 1
            grade_usable = grade.converged and self.grade.converged
        if self.observer is not None and velocity is not None:
            # Eq. 21: a_x,acc = vx' - r vy + g theta (the observer adds r vy back).
            ax = accel_x - self.gravity * math.sin(squat)
            if not self.observer.step(t, ax, velocity[0], yaw_rate=yaw_rate, vy=velocity[1]):
                rejected += 1
        if self.observer is not None:
            # The accelerometer bias left in the observer's input goes into its slope one to one:
            # the fusion's bias uncertainty, or without the fusion the sensor's turn-on bias.
            # The observer's own covariance has no bias state, so this is all that says so.
            if accel_bias_variance is None or not math.isfinite(accel_bias_variance):
                accel_bias_variance = self.observer.config.uncompensated_accel_bias_std ** 2
            self._observer_bias_variance = accel_bias_variance / self.gravity ** 2
        if self.auto is not None:
            self.auto.update(t, grade_usable, self._observer_bias_variance)
        return rejected

    @property
    def slope(self) -> float:
        """The published slope [rad], + uphill."""
        return self.published.slope

    @property
    def variance(self) -> float:
        if self.published is self.observer:
            return self.observer.variance + self._observer_bias_variance
        return self.published.variance

    @property
    def converged(self) -> bool:
        return self.published.converged

    def reset(self) -> None:
        self.suspension.reset()
        self._observer_bias_variance = 0.0
        for part in (self.grade, self.observer, self.auto):
            if part is not None:
                part.reset()

    def status(self) -> dict[str, str]:
        """What this method adds to ``/diagnostics``: with two sources, the one in use."""
        return self.auto.status() if self.auto is not None else {}
