"""Measurement noise that is not white.

A sensor error that lasts ``tau`` seconds (a speed quantised to 1 km/h stays off by one amount
while the speed stays in one step) is not averaged away by taking more samples. A filter that
treats it as white noise at sample spacing ``dt`` weighs its variance ``2 tau / dt`` times (the
white noise of the same spectral density at zero frequency), so that many samples together
count for no more than one correlation time's worth.

And the other way round: a sensor's white noise read off the samples themselves
(:class:`SuccessiveDifferenceNoise`), for an output whose covariance must hold it.
"""

from __future__ import annotations

import math

import numpy as np


def white_equivalent_variance(variance: float, correlation_s: float, spacing_s: float) -> float:
    """``variance`` weighed ``max(1, 2 correlation_s / spacing_s)`` times; unchanged for
    ``correlation_s <= 0`` (white) or a spacing that is not a finite positive number (the
    first sample, or one after a gap)."""
    if correlation_s > 0.0 and 0.0 < spacing_s < math.inf:
        return variance * max(1.0, 2.0 * correlation_s / spacing_s)
    return variance


class SuccessiveDifferenceNoise:
    """The white noise of a sampled vector signal, per axis, from its successive differences.

    For white noise of variance s^2 on a signal that moves little between samples, half the
    mean square of ``x_k - x_(k-1)`` is s^2 (a gyro at 100 Hz: a yaw acceleration of 0.5 rad/s^2
    moves the rate 0.005 rad/s per sample, so in a corner's entry the figure runs high, on the
    cautious side). It includes whatever shakes the sensor (engine, road), which an IMU's stated
    covariance does not; noise correlated over several samples (an IMU's internal low-pass)
    reads low, hence :func:`with_floor` takes the larger of this and a stated figure.
    An exponential mean over about ``memory_samples`` samples; ``variance`` is None until
    ``min_samples`` differences have been seen.
    """

    def __init__(self, dimension: int = 3, memory_samples: float = 500.0, min_samples: int = 20) -> None:
        self._rate = 1.0 / max(1.0, memory_samples)
        self._min = min_samples
        self._dimension = dimension
        self.reset()

    def reset(self) -> None:
        self._previous: np.ndarray | None = None
        self._mean_square = np.zeros(self._dimension)
        self._count = 0

    def add(self, sample) -> None:
        x = np.asarray(sample, dtype=float)
        if self._previous is not None:
            half_square = 0.5 * (x - self._previous) ** 2
            self._count += 1
            # the plain mean until the memory is full, then exponential
            rate = max(self._rate, 1.0 / self._count)
            self._mean_square += rate * (half_square - self._mean_square)
        self._previous = x

    @property
    def variance(self) -> np.ndarray | None:
        return self._mean_square.copy() if self._count >= self._min else None


def with_floor(stated: np.ndarray | None, measured: np.ndarray | None) -> np.ndarray:
    """A 3 x 3 noise covariance: ``stated`` (or zeros) with each diagonal element raised to
    ``measured`` (per-axis variances, or None) where that is larger."""
    cov = np.zeros((3, 3)) if stated is None else np.array(stated, dtype=float).reshape(3, 3)
    if measured is not None:
        diagonal = np.diag(cov)
        cov[np.diag_indices(3)] = np.maximum(diagonal, measured)
    return cov
