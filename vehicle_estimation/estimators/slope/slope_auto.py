"""The slope source a car can afford right now: the fusion grade, else the IMU + speed observer.

Paper 003's grade (the fusion pitch, :class:`~vehicle_estimation.estimators.slope.slope.PitchGradeSlope`)
is the more accurate where GNSS aids the fusion; paper 004's observer
(:class:`~vehicle_estimation.estimators.slope.slope.CubicPredictionSlopeObserver`) needs only the IMU and a
speed. :class:`AutoSlope` steps neither: the caller steps both cores on every sample, so the
observer is converged whenever the fusion grade drops out (a node started without GNSS, a
fusion that has not aligned, a stale upstream), and asks :meth:`AutoSlope.update` which one to
publish.

A switch must not make the published slope jump (a controller acting on the grade would feel
it as a step of ``g`` times the difference in its feed-forward force). At a switch the
difference between the two sources becomes an offset that fades out with
``switch_time_constant_s``, and the offset still left is added to the variance, so the
variance says how far the published value may be from the source now in use.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Protocol

__all__ = ["AutoSlope", "AutoSlopeConfig", "SlopeEstimate", "SOURCE_FUSION", "SOURCE_OBSERVER"]

SOURCE_FUSION = "fusion_pitch"
SOURCE_OBSERVER = "cubic_prediction"


class SlopeEstimate(Protocol):
    """What every slope core offers (see :mod:`vehicle_estimation.estimators.slope.slope`)."""

    @property
    def slope(self) -> float: ...

    @property
    def variance(self) -> float: ...

    @property
    def converged(self) -> bool: ...


@dataclasses.dataclass
class AutoSlopeConfig:
    """Source selection of the ``auto`` slope method.

    Attributes:
        switch_time_constant_s: the offset between the sources at a switch fades out with
            this time constant [s].
        uncompensated_accel_bias_std: std of an accelerometer bias the observer cannot remove
            while the fusion's bias estimate is missing [m/s^2]; enters the observer's variance
            as (std / g)^2. 0.05 m/s^2 is a typical MEMS turn-on bias.
    """

    switch_time_constant_s: float = 2.0
    uncompensated_accel_bias_std: float = 0.05

    def validate(self) -> None:
        if not (math.isfinite(self.switch_time_constant_s) and self.switch_time_constant_s > 0.0):
            raise ValueError(f"switch_time_constant_s must be > 0, got {self.switch_time_constant_s!r}")
        if not (math.isfinite(self.uncompensated_accel_bias_std) and self.uncompensated_accel_bias_std >= 0.0):
            raise ValueError("uncompensated_accel_bias_std must be >= 0, "
                             f"got {self.uncompensated_accel_bias_std!r}")


class AutoSlope:
    """Publishes ``fusion`` while it is usable, else ``observer``, without a jump at a switch.

    Parameters
    ----------
    fusion, observer:
        the two slope cores; the caller steps them.
    config:
        :class:`AutoSlopeConfig`.
    """

    def __init__(self, fusion: SlopeEstimate, observer: SlopeEstimate,
                 config: AutoSlopeConfig | None = None) -> None:
        self.fusion = fusion
        self.observer = observer
        self.config = AutoSlopeConfig() if config is None else config
        self.config.validate()
        self.switches = 0
        self.reset()

    def reset(self) -> None:
        self.source = SOURCE_OBSERVER
        self._offset = 0.0          # published minus source at the last switch [rad]
        self._t_switch = -math.inf
        self._t = -math.inf
        self._extra_variance = 0.0
        self._published = math.nan

    def _core(self, source: str) -> SlopeEstimate:
        return self.fusion if source == SOURCE_FUSION else self.observer

    def update(self, t: float, fusion_usable: bool, observer_extra_variance: float = 0.0) -> None:
        """Choose the source for stamp ``t``.

        ``fusion_usable``: the fusion grade is fresh and converged. ``observer_extra_variance``:
        model errors the observer does not represent (an uncompensated accelerometer bias),
        added to its variance [rad^2].
        """
        self._t = t
        self._extra_variance = observer_extra_variance if math.isfinite(observer_extra_variance) else 0.0
        wanted = SOURCE_FUSION if fusion_usable else SOURCE_OBSERVER
        if wanted != self.source:
            new = self._core(wanted).slope
            if math.isfinite(new):
                previous = self._published
                self.source = wanted
                self.switches += 1
                self._t_switch = t
                self._offset = previous - new if math.isfinite(previous) else 0.0
        self._published = self.slope

    @property
    def _remaining_offset(self) -> float:
        if self._offset == 0.0:
            return 0.0
        return self._offset * math.exp(-max(self._t - self._t_switch, 0.0) / self.config.switch_time_constant_s)

    @property
    def slope(self) -> float:
        return self._core(self.source).slope + self._remaining_offset

    @property
    def variance(self) -> float:
        core = self._core(self.source)
        extra = self._extra_variance if self.source == SOURCE_OBSERVER else 0.0
        return core.variance + extra + self._remaining_offset ** 2

    @property
    def converged(self) -> bool:
        return bool(self._core(self.source).converged)
