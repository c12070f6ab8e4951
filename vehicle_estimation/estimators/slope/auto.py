"""The slope source a car can afford right now: the fusion grade, else the IMU + speed observer.

Paper 003's grade (the fusion pitch,
:class:`~vehicle_estimation.estimators.slope.pitch_grade.PitchGradeSlope`) is the more accurate
where GNSS aids the fusion; paper 004's observer
(:class:`~vehicle_estimation.estimators.slope.cubic_prediction.CubicPredictionSlopeObserver`)
needs only the IMU and a speed. :class:`AutoSlope` steps neither: the caller
(:class:`~vehicle_estimation.estimators.slope.road_slope.RoadSlopeEstimator`) steps both cores on
every sample, so the observer is converged whenever the fusion grade drops out (a node started
without GNSS, a fusion that has not aligned, a stale upstream), and asks :meth:`AutoSlope.update`
which one to publish.

A switch must not make the published slope jump (a controller acting on the grade would feel
it as a step of ``g`` times the difference in its feed-forward force). At a switch the
difference between the two sources becomes an offset that fades out with
``switch_time_constant_s``, and the offset still left is added to the variance, so the
variance says how far the published value may be from the source now in use.
"""

from __future__ import annotations

import dataclasses
import math

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.estimators.interfaces import SlopeEstimator

__all__ = ["AutoSlope", "AutoSlopeConfig", "SOURCE_FUSION", "SOURCE_OBSERVER"]

SOURCE_FUSION = "fusion_pitch"
SOURCE_OBSERVER = "cubic_prediction"
#: The ``slope source`` entry of ``/diagnostics``, per source.
SOURCE_STATUS = {
    SOURCE_FUSION: "fusion_pitch (fusion grade)",
    SOURCE_OBSERVER: "cubic_prediction (IMU + speed observer: fusion grade missing or not converged)",
}


@dataclasses.dataclass
class AutoSlopeConfig:
    """Source selection of the ``auto`` slope method."""

    switch_time_constant_s: float = setting(
        2.0, "The offset between the sources at a switch fades out with this time constant [s]",
        low=0.0, low_open=True)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        check_settings(self)


class AutoSlope:
    """Publishes ``fusion`` while it is usable, else ``observer``, without a jump at a switch.

    Parameters
    ----------
    fusion, observer:
        the two slope cores; the caller steps them.
    config:
        :class:`AutoSlopeConfig`.
    """

    def __init__(self, fusion: SlopeEstimator, observer: SlopeEstimator,
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

    def _core(self, source: str) -> SlopeEstimator:
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

    def status(self) -> dict[str, str]:
        """The source in use and how often it changed, for ``/diagnostics``."""
        return {"slope source": SOURCE_STATUS[self.source], "slope source switches": str(self.switches)}
