"""The CAN speed's offset that lasts while its reported value does not change, as a position covariance.

A bus speed quantised to 1 km/h is off by up to 0.14 m/s, and by the same amount for as long as
the car's speed stays within one step: at a steady cruise, tens of seconds. The filter weighs
the speed as an error correlated over ``speed_error_correlation_s`` (1 s shipped), which keeps
the velocity honest, but integrated into the position it counts the offset as averaging out
after a second; it does not, and without GNSS nothing else knows the absolute speed. FASTSim's
car without GNSS, whose cycle holds integer speeds (24 m/s reads 86 km/h, 0.11 m/s low, for up
to 40 s): the position error along the track is the integral of that offset to the metre
(-6.8 m after 2 min) at a published σ of 2.3 m.

:class:`LastingSpeedOffset` splits the drive into the spans in which the reported speed keeps one
value. Each span's offset is its own unknown constant δ with the speed's stated variance σ²,
along the car's forward axis u(t), so it moves the position by δ D with D = ∫ u dt over the span
(at a steady heading, the span's duration along the track), and the covariance it adds is
σ² D Dᵀ, summed over the spans (the open one up to now). A speed that changes every sample (not
quantised, or noisy wheel speeds) closes a span every sample and adds nearly nothing. It is a
consider term: the estimates do not change.

A scale error k of the speed (the rolling radius), which the filter holds without GNSS, lasts
for the whole drive: it moves the position by k d, d the distance vector (the reported speed
times the forward axis, integrated), and :attr:`distance` gives d since the last fix.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LastingSpeedOffset"]


class LastingSpeedOffset:
    """Position covariance [m^2] of the speed's offsets held over spans of one reported value."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget the spans: a position fix has tied the position down."""
        self._closed = np.zeros((3, 3))      # sum of sigma^2 D D^T over the ended spans
        self._value: float | None = None    # the reported speed of the open span [m/s]
        self._variance = 0.0                # its stated variance [m^2/s^2]
        self._direction_time = np.zeros(3)  # D of the open span [s]
        self._distance = np.zeros(3)        # the reported speed times the forward axis, integrated [m]
        self._t: float | None = None

    def add(self, t: float, speed: float, variance: float, forward: np.ndarray) -> None:
        """A speed sample at stamp ``t`` [s] as reported (``speed`` [m/s], stated ``variance``),
        with the car's forward axis ``forward`` (a unit vector) in the position's frame: a new
        value ends the open span and begins another."""
        if self._t is not None:
            self._direction_time += forward * (t - self._t)
            if self._value is not None:
                self._distance += forward * (self._value * (t - self._t))
        self._t = t
        if speed == self._value:
            return
        D = self._direction_time
        self._closed += self._variance * np.outer(D, D)
        self._value, self._variance, self._direction_time = speed, variance, np.zeros(3)

    @property
    def covariance(self) -> np.ndarray:
        """The ended spans' term and the open span's up to the last sample [m^2]."""
        D = self._direction_time
        return self._closed + self._variance * np.outer(D, D)

    @property
    def distance(self) -> np.ndarray:
        """The distance vector travelled since the last reset, as the reported speed says [m]."""
        return self._distance.copy()
