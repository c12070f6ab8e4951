"""The body's pitch on its suspension (squat and dive), which the IMU sees and the road does not have."""

from __future__ import annotations

import math

__all__ = ["SuspensionPitch"]


class SuspensionPitch:
    """Body pitch on the suspension from longitudinal acceleration, positive nose up [rad].

    The fusion pitch is the IMU's, i.e. the body's; the road's grade is that minus the pitch
    the suspension adds, ``gain * a_x`` through a first-order lag of ``time_constant``
    (``VehicleParams.pitch_gain`` and ``pitch_time_constant``). Uncorrected, it makes the grade
    error follow the acceleration, which is exactly what the mass estimator's regressor cannot
    tolerate. The accelerometer is tilted by the same angle, so the observers take it out too.
    """

    def __init__(self, gain: float, time_constant: float) -> None:
        self.gain, self.tau = gain, time_constant
        self.state = 0.0
        self.t: float | None = None

    def update(self, t: float, accel: float) -> float:
        """The pitch at stamp ``t`` [s] after the acceleration ``accel`` [m/s^2] (gravity
        along the slope removed). A non-finite ``accel`` leaves the pitch as it was; a step
        longer than 1 s counts as 1 s."""
        if not math.isfinite(accel):
            return self.state
        target = self.gain * accel
        if self.t is None or self.tau <= 0.0:
            self.state = target
        else:
            dt = min(max(t - self.t, 0.0), 1.0)
            self.state += (target - self.state) * (1.0 - math.exp(-dt / self.tau))
        self.t = t
        return self.state

    def reset(self) -> None:
        self.state, self.t = 0.0, None
