"""The fusion's updates by the compiled kernels of :mod:`.ins_kernels`.

:class:`FusionCompiledSteps` is a part of
:class:`~vehicle_estimation.estimators.fusion.esekf.FusionEKF`, written apart: each method
here does what a numpy method of the filter does (named in its docstring), with the same
outcomes and the same numbers to 1e-12 (``test_model_kernels``); the filter calls them while
its ``compiled`` flag is set.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from vehicle_estimation.estimators.fusion import ins_kernels
from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.error_state import N_ERR

__all__ = ["FusionCompiledSteps"]

# Body y, z: the non-holonomic constraint. Writable like every kernel argument (numba types a
# read-only array apart, which would compile the kernel a second time); never written.
_MOVING_ROWS = np.array([1, 2], dtype=np.int64)


class FusionCompiledSteps:
    """The compiled steps of :class:`FusionEKF` (a mixin of it)."""

    config: FusionConfig
    rejected: dict[str, int]
    _t: float | None
    _p: np.ndarray
    _v: np.ndarray
    _q: np.ndarray
    _R: np.ndarray
    _Rm: np.ndarray
    _ba: np.ndarray
    _bg: np.ndarray
    _P: np.ndarray
    _qd: np.ndarray
    _g_vec: np.ndarray
    _a_lp: np.ndarray
    _w_lp: np.ndarray
    _f_prev: np.ndarray | None
    _w_prev: np.ndarray | None
    _speed_scale_error: np.ndarray
    # FusionEKF's methods these steps share with its numpy path:
    _update_process_noise: Callable[[float], None]
    _held_direction: Callable[[], np.ndarray]
    _invariant_reset_due: Callable[[], bool]
    _mounting_min_speeds: Callable[[], tuple[float, float]]
    _moving_constraint_noise: Callable[[], np.ndarray]

    def _update_compiled(self, y: np.ndarray, H: np.ndarray, W: np.ndarray, gate, held: np.ndarray) -> int:
        """``_update`` (Eqs. (37)-(44)) by :func:`.ins_kernels.joseph_update`,
        :func:`.ins_kernels.inject` and :func:`.ins_kernels.invariant_reset`."""
        c = self.config
        P, dz = np.empty((N_ERR, N_ERR)), np.empty(N_ERR)
        res = ins_kernels.joseph_update(self._P, H, W, y, 0.0 if gate is None else float(gate), gate is not None,
                                        held, P, dz)
        if res == ins_kernels.UPDATE_FAILED:
            self.rejected["update_numerical"] += 1
            return -1
        if res == ins_kernels.UPDATE_GATED:
            return 0
        self._P = P
        q, R, Rm = np.empty(4), np.empty((3, 3)), np.empty((3, 3))
        ins_kernels.inject(dz, self._p, self._v, self._q, self._ba, self._bg, self._Rm, c.estimate_mounting,
                           self._speed_scale_error, q, R, Rm)
        if self._invariant_reset_due():
            ins_kernels.invariant_reset(self._P, dz)
        self._q, self._R = q, R
        if c.estimate_mounting:
            self._Rm = Rm
        return 1

    def _constraint_update_compiled(self, rows: list[int], W: np.ndarray) -> None:
        """``_nh_update``'s update by :func:`.ins_kernels.constraint_update` (one call)."""
        c = self.config
        q, R, Rm, P = np.empty(4), np.empty((3, 3)), np.empty((3, 3)), np.empty((N_ERR, N_ERR))
        res = ins_kernels.constraint_update(self._R, self._Rm, self._v, np.asarray(rows, dtype=np.int64), W,
                                            c.full_velocity_jacobian, *self._mounting_min_speeds(),
                                            c.estimate_mounting, self._held_direction(), self._invariant_reset_due(),
                                            self._p, self._ba, self._bg, self._speed_scale_error,
                                            self._q, self._P, q, R, Rm, P)
        self._take_constraint_outcome(res, q, R, Rm, P)

    def _imu_step_compiled(self, t: float, dt: float) -> None:
        """``_propagate`` over ``dt`` and the non-holonomic update of a moving vehicle, in one
        call of :func:`.ins_kernels.imu_step`; ``_t`` becomes ``t`` in between, as in
        ``process_imu`` (the process noise reads the old stamp, the held direction the new one)."""
        c = self.config
        assert self._f_prev is not None and self._w_prev is not None   # only after the first sample
        self._update_process_noise(dt)
        self._t = t
        q, R, Rm, P = np.empty(4), np.empty((3, 3)), np.empty((3, 3)), np.empty((N_ERR, N_ERR))
        res = ins_kernels.imu_step(dt, c.stationary_imu_tau_s, self._f_prev, self._w_prev, self._ba, self._bg,
                                   self._g_vec, self._p, self._v, self._q, self._R, self._a_lp, self._w_lp, self._P,
                                   self._qd, _MOVING_ROWS, self._moving_constraint_noise(), c.full_velocity_jacobian,
                                   *self._mounting_min_speeds(), c.estimate_mounting, self._held_direction(),
                                   self._invariant_reset_due(), self._Rm, self._speed_scale_error,
                                   q, R, Rm, P)
        self._q, self._R, self._P = q, R, P      # the propagation, at least
        self._take_constraint_outcome(res, q, R, Rm, P)

    def _take_constraint_outcome(self, res: int, q: np.ndarray, R: np.ndarray, Rm: np.ndarray,
                                 P: np.ndarray) -> None:
        if res == ins_kernels.UPDATE_FAILED:
            self.rejected["update_numerical"] += 1
        elif res == ins_kernels.UPDATE_APPLIED:
            self._q, self._R, self._P = q, R, P
            if self.config.estimate_mounting:
                self._Rm = Rm
