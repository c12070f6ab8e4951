"""Measurement noise that is not white.

A sensor error that lasts ``tau`` seconds (a speed quantised to 1 km/h stays off by one amount
while the speed stays in one step) is not averaged away by taking more samples. A filter that
treats it as white noise at sample spacing ``dt`` weighs its variance ``2 tau / dt`` times (the
white noise of the same spectral density at zero frequency), so that many samples together
count for no more than one correlation time's worth.
"""

from __future__ import annotations

import math


def white_equivalent_variance(variance: float, correlation_s: float, spacing_s: float) -> float:
    """``variance`` weighed ``max(1, 2 correlation_s / spacing_s)`` times; unchanged for
    ``correlation_s <= 0`` (white) or a spacing that is not a finite positive number (the
    first sample, or one after a gap)."""
    if correlation_s > 0.0 and 0.0 < spacing_s < math.inf:
        return variance * max(1.0, 2.0 * correlation_s / spacing_s)
    return variance
