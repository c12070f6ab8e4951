"""The checks that open every core's ``step()``: valid inputs, an increasing stamp, a gap.

Every core steps on message stamps and must survive what a bag or a live bus can hand it: NaN
or infinite values, a stamp that repeats or goes back (a bag loop, a restarted driver) and a
gap after which the state is no longer worth propagating. :class:`StepGuard` is the one
implementation; each core keeps its own counter names, so ``/diagnostics`` reads the same.

A core that mixes it in provides ``t`` (its last stamp, None before the first step),
``rejected`` (a :class:`collections.Counter`), ``last_event`` (str) and ``reinitialisations``.
"""

from __future__ import annotations

import math
from collections import Counter

#: Tolerance of comparisons between stamps in float seconds: near 1.7e9 s (any ROS epoch stamp)
#: a float64 resolves only 2.4e-7 s, so a 10 ms period can come out as 9.99976 ms.
STAMP_TOLERANCE_S = 1e-6


class StepGuard:
    """Mixin: :meth:`admit` a sample, :meth:`note_reinitialised` after a gap reset."""

    t: float | None
    rejected: Counter
    last_event: str
    reinitialisations: int

    def admit(self, t: float, valid: bool, *, invalid: str = "invalid_input",
              invalid_event: str = "invalid input", show_stamps: bool = True) -> float | None:
        """The time since the last step [s] (``inf`` before the first) if the sample may be
        used; None if it is rejected, counted as ``invalid`` (``valid`` False or a non-finite
        ``t``) or ``stamp_not_increasing``, with :attr:`last_event` saying why."""
        if not valid or not math.isfinite(t):
            self.rejected[invalid] += 1
            self.last_event = invalid_event
            return None
        if self.t is not None and t <= self.t:
            self.rejected["stamp_not_increasing"] += 1
            self.last_event = (f"stamp not increasing ({t:.6f} <= {self.t:.6f})" if show_stamps
                               else "stamp not increasing")
            return None
        return math.inf if self.t is None else t - self.t

    def note_reinitialised(self, gap: float) -> None:
        """Count a re-initialisation after ``gap`` seconds without samples."""
        self.reinitialisations += 1
        self.last_event = f"re-initialised after a {gap:.3f} s gap"


def finite_number(value: object) -> bool:
    """True for a real number (int, float, NumPy scalar) that is finite; False for None, a
    bool, NaN, infinity or anything that is not a number."""
    if value is None or isinstance(value, bool):
        return False
    try:
        return math.isfinite(float(value))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False


def all_finite(*values: object) -> bool:
    """:func:`finite_number` of every value."""
    return all(finite_number(v) for v in values)
