"""Is the IMU turned about the car's vertical the way the vehicle file says?

Gravity shows an IMU on its side or upside down, but not one that faces left or backwards: such
an IMU reads gravity as a level one does. The car's own accelerations do show it. Above walking
pace the car's horizontal acceleration in ``base_link`` is ``(dv/dt, v r)``, from the speed and
the yaw rate, and an IMU whose horizontal axes are where the nominal mounting puts them reads
that same vector. So a 2-D Procrustes fit of the IMU's horizontal specific force, turned into
``base_link`` by the nominal mounting, to ``(dv/dt, v r)`` gives the angle between them about
``base_link`` z. Means are taken out first: the accelerometer's bias and the mean grade.

The fusion's mounting states refine a few degrees; a nominal yaw that is tens of degrees off
puts the car's forward acceleration on the wrong axis in every node.
:class:`MountingYawCheck` accumulates the fit on samples (``inspect`` feeds it a bag's
samples at once, the fusion node a running drive) and says nothing until the drive can tell.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from vehicle_estimation.estimators.common.rotations import rotmat_from_euler

__all__ = ["MountingYawCheck"]

#: IMU samples wait at most this long beyond the centred span for a speed [s].
MAX_SPEED_LAG_S = 10.0


class MountingYawCheck:
    """The angle about ``base_link`` z from the car's horizontal acceleration to the IMU's.

    Parameters
    ----------
    mounting_rpy:
        the nominal mounting, roll, pitch, yaw of ``imu_link`` in ``base_link`` [rad].
    baseline_s:
        dv/dt is the speed's change over this span, centred (CAN speeds come in 1 km/h steps:
        a step between two samples 10 ms apart reads as 8 m/s^2).
    min_speed:
        samples below this speed [m/s] are left out (v r is small and the speed coarse).
    min_accel:
        the car's horizontal acceleration must vary by at least this RMS [m/s^2].
    min_coherence:
        the fit must explain at least this share of the IMU's horizontal force (vibration or
        a drive that never accelerates: no verdict).
    mismatch_deg:
        beyond this angle the nominal yaw is not the IMU's.
    sample_period_s:
        the streaming input keeps one IMU sample per this period.
    """

    def __init__(self, mounting_rpy=(0.0, 0.0, 0.0), *, baseline_s: float = 2.0, min_speed: float = 3.0,
                 min_accel: float = 0.3, min_coherence: float = 0.8, mismatch_deg: float = 10.0,
                 sample_period_s: float = 0.1, min_samples: int = 50) -> None:
        self.rotation = rotmat_from_euler(*(float(a) for a in mounting_rpy))
        self.nominal_yaw = float(mounting_rpy[2])
        self.baseline_s = float(baseline_s)
        self.min_speed = float(min_speed)
        self.min_accel = float(min_accel)
        self.min_coherence = float(min_coherence)
        self.mismatch = math.radians(mismatch_deg)
        self.sample_period_s = float(sample_period_s)
        self.min_samples = int(min_samples)
        self.reset()

    def reset(self) -> None:
        self._n = 0
        self._sum_a = np.zeros(2)
        self._sum_f = np.zeros(2)
        self._sum_aa = self._sum_ff = self._sum_dot = self._sum_cross = 0.0
        self._speeds: collections.deque = collections.deque()
        # IMU samples waiting for the speed after them; bounded, for a speed that never comes
        self._pending: collections.deque = collections.deque(
            maxlen=math.ceil((self.baseline_s + MAX_SPEED_LAG_S) / self.sample_period_s))
        self._last_imu_t = -math.inf

    # ------------------------------------------------------------------ batch
    def add(self, accel: np.ndarray, force: np.ndarray) -> None:
        """Samples of the car's horizontal acceleration ``(dv/dt, v r)`` and the IMU's horizontal
        specific force in ``base_link`` (nominal mounting), shape (n, 2) each."""
        a = np.asarray(accel, dtype=float).reshape(-1, 2)
        f = np.asarray(force, dtype=float).reshape(-1, 2)
        ok = np.isfinite(a).all(axis=1) & np.isfinite(f).all(axis=1)
        a, f = a[ok], f[ok]
        self._n += a.shape[0]
        self._sum_a += a.sum(axis=0)
        self._sum_f += f.sum(axis=0)
        self._sum_aa += float(np.sum(a * a))
        self._sum_ff += float(np.sum(f * f))
        self._sum_dot += float(np.sum(a[:, 0] * f[:, 0] + a[:, 1] * f[:, 1]))
        self._sum_cross += float(np.sum(a[:, 0] * f[:, 1] - a[:, 1] * f[:, 0]))

    def add_samples(self, t, force, yaw_rate, speed_t, speed) -> None:
        """IMU samples at stamps ``t`` already in base_link (:meth:`to_base`: the horizontal
        specific force (n, 2) and the yaw rate (n,)) and the speed samples (increasing stamps
        ``speed_t``) around them: each IMU sample with speed ``baseline_s / 2`` before and after
        it, at or above ``min_speed``, enters the fit with (dv/dt over ``baseline_s``, v r)."""
        t = np.asarray(t, dtype=float)
        st, sv = np.asarray(speed_t, dtype=float), np.asarray(speed, dtype=float)
        if t.size == 0 or st.size < 2:
            return
        half = 0.5 * self.baseline_s
        covered = (t - half >= st[0]) & (t + half <= st[-1])
        t = t[covered]
        v = np.interp(t, st, sv)
        dvdt = (np.interp(t + half, st, sv) - np.interp(t - half, st, sv)) / self.baseline_s
        moving = v >= self.min_speed
        accel = np.column_stack([dvdt, v * np.asarray(yaw_rate, dtype=float)[covered]])
        self.add(accel[moving], np.asarray(force, dtype=float).reshape(-1, 2)[covered][moving])

    def to_base(self, specific_force: np.ndarray, angular_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """imu_link samples (n, 3) turned into base_link by the nominal mounting: the horizontal
        specific force (n, 2) and the yaw rate (n,)."""
        f = np.asarray(specific_force, dtype=float).reshape(-1, 3) @ self.rotation.T
        w = np.asarray(angular_rate, dtype=float).reshape(-1, 3) @ self.rotation.T
        return f[:, :2], w[:, 2]

    # ------------------------------------------------------------------ streaming
    def add_imu(self, t: float, specific_force, angular_rate) -> None:
        """One IMU sample (imu_link) at stamp ``t``; kept every ``sample_period_s``, and fitted
        once the speed is known ``baseline_s / 2`` after it."""
        if t - self._last_imu_t < self.sample_period_s:
            return
        self._last_imu_t = t
        f, r = self.to_base(specific_force, angular_rate)
        self._pending.append((t, float(f[0, 0]), float(f[0, 1]), float(r[0])))

    def add_speed(self, t: float, speed: float) -> None:
        """One speed sample [m/s] at stamp ``t`` (in stamp order)."""
        if not math.isfinite(speed) or (self._speeds and t <= self._speeds[-1][0]):
            return
        self._speeds.append((t, float(speed)))
        ready = []
        while self._pending and self._pending[0][0] + 0.5 * self.baseline_s <= t:
            ready.append(self._pending.popleft())
        if ready:
            ti, fx, fy, r = np.array(ready).T
            st, sv = np.array(self._speeds).T
            self.add_samples(ti, np.column_stack([fx, fy]), r, st, sv)
        # keep what the pending samples (at most baseline_s / 2 old) still need
        while len(self._speeds) > 2 and self._speeds[1][0] < t - self.baseline_s - self.sample_period_s:
            self._speeds.popleft()

    # ------------------------------------------------------------------ verdict
    @property
    def samples(self) -> int:
        return self._n

    @property
    def offset(self) -> float | None:
        """The angle [rad] about base_link z from the car's acceleration to the IMU's force
        turned by the nominal mounting (the IMU's yaw is the nominal yaw minus it); None until
        the samples can tell."""
        n = self._n
        if n < self.min_samples:
            return None
        mean_a, mean_f = self._sum_a / n, self._sum_f / n
        power_a = self._sum_aa - n * float(mean_a @ mean_a)
        power_f = self._sum_ff - n * float(mean_f @ mean_f)
        if power_a < self.min_accel ** 2 * n or power_f <= 0.0:
            return None
        dot = self._sum_dot - n * float(mean_a @ mean_f)
        cross = self._sum_cross - n * float(mean_a[0] * mean_f[1] - mean_a[1] * mean_f[0])
        if math.hypot(dot, cross) < self.min_coherence * math.sqrt(power_a * power_f):
            return None
        return math.atan2(cross, dot)

    @property
    def mismatched(self) -> bool:
        offset = self.offset
        return offset is not None and abs(offset) > self.mismatch

    def implied_yaw_deg(self) -> float | None:
        """The IMU's yaw in base_link [deg, -180..180) that the fit implies."""
        offset = self.offset
        if offset is None:
            return None
        return (math.degrees(self.nominal_yaw - offset) + 180.0) % 360.0 - 180.0

    def status(self) -> str:
        """One line for ``/diagnostics``."""
        offset = self.offset
        if offset is None:
            return (f"no verdict yet ({self._n} samples above {self.min_speed:g} m/s; needs "
                    f"{self.min_accel:g} m/s^2 RMS of acceleration and turning)")
        if abs(offset) > self.mismatch:
            return (f"the IMU's horizontal axes are {abs(math.degrees(offset)):.0f} deg about base_link z from "
                    f"vehicle.imu_mounting_rpy: its yaw is about {self.implied_yaw_deg():.0f} deg; give it in "
                    "the vehicle file")
        return f"agrees with vehicle.imu_mounting_rpy ({math.degrees(offset):+.1f} deg)"
