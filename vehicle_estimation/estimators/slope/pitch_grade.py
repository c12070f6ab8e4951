"""Paper 003's road grade: the (negated) pitch of the IMU/GNSS fusion, Sec. 7.2.

The grade arrives from the fusion as ``road_grade`` (+uphill) with its variance and is
optionally smoothed by a linearly weighted moving average (LWMA, 25 samples in paper 003
Sec. 7.1).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections import Counter
from typing import Optional

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.estimators.common.guard import StepGuard

__all__ = ["PitchGradeConfig", "PitchGradeSlope", "grade_from_pitch"]


def grade_from_pitch(pitch: float) -> float:
    """Road grade from a REP-103 pitch angle: nose-up is negative pitch about +y, so
    ``theta = -pitch`` (paper 003 Sec. 7.2: "the sign of the road gradient is opposite to
    the vehicle pitch angle"). Dynamic pitch from acceleration is not compensated."""
    return -float(pitch)


@dataclasses.dataclass
class PitchGradeConfig:
    """Tuning of :class:`PitchGradeSlope`."""

    lwma_window: int = setting(1, "LWMA length in samples (1 = pass-through; paper 003 uses 25)", low=1)
    max_gap_s: float = setting(0.5, "Stamp gap that clears the LWMA buffer [s]", low=0.0, low_open=True)
    converged_std: float = setting(
        0.02, "Converged once the buffer is full and sqrt(variance) is below this [rad]", low=0.0, low_open=True)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field."""
        check_settings(self)


class PitchGradeSlope(StepGuard):
    """Road grade from the fusion pitch (paper 003 Sec. 7.2), optional LWMA low-pass.

    With weights ``w_i = i`` (newest ``N``) the LWMA delays a ramp by ``(N - 1)/3``
    samples (8 samples = 40 ms for ``N = 25`` at 200 Hz). The reported variance is the
    weighted mean of the input variances, i.e. the fully-correlated (conservative) case,
    since consecutive fusion pitch estimates are strongly correlated.
    """

    def __init__(self, config: Optional[PitchGradeConfig] = None):
        self.config = PitchGradeConfig() if config is None else config
        self.config.validate()
        n = int(self.config.lwma_window)
        self._weights = np.arange(1, n + 1, dtype=float)
        self.rejected: Counter[str] = Counter({"nonfinite_input": 0, "stamp_not_increasing": 0})
        self.reinitialisations = 0
        self.last_event = ""
        self.reset()

    def reset(self) -> None:
        n = int(self.config.lwma_window)
        self._grades: collections.deque = collections.deque(maxlen=n)
        self._vars: collections.deque = collections.deque(maxlen=n)
        self.t: Optional[float] = None
        self._slope = float("nan")
        self._variance = float("inf")

    def step(self, t: float, road_grade: float, variance: float) -> bool:
        """Add a grade sample [rad, +uphill] with its variance [rad^2] at stamp ``t``."""
        t = float(t)
        gap = self.admit(t, math.isfinite(road_grade) and math.isfinite(variance) and variance >= 0.0,
                         invalid="nonfinite_input", invalid_event="non-finite input", show_stamps=False)
        if gap is None:
            return False
        if self.t is not None and gap > self.config.max_gap_s:
            self.reset()
            self.note_reinitialised(gap)
        self.t = t
        self._grades.append(float(road_grade))
        self._vars.append(float(variance))
        w = self._weights[: len(self._grades)]
        self._slope = float(np.dot(w, self._grades) / w.sum())
        self._variance = float(np.dot(w, self._vars) / w.sum())
        return True

    @property
    def slope(self) -> float:
        return self._slope

    @property
    def variance(self) -> float:
        return self._variance

    @property
    def converged(self) -> bool:
        return (len(self._grades) == self._grades.maxlen
                and math.sqrt(self._variance) < self.config.converged_std)
