"""Compiled kernels for the per-sample filter maths, with numba where it is installed.

A filter step on a 5-state model is a few hundred floating-point operations; in numpy each
small-array call costs microseconds of interpreter and dispatch, so a step costs 100-1000x its
arithmetic. The hot loops (the vehicle model through the cubature points, the variational
iterations, the INS propagation) are therefore also written as plain loops over scalars and
compiled by numba (the `fast` extra: ``pip install -e '.[fast]'``).

The numpy implementations stay the definition: every kernel has a test that requires the same
numbers from both (to 1e-12 relative; the compiled code may sum in another order). Without numba
the filters run their numpy code, with the same results to that tolerance.

Rules for a kernel: ``error_model="numpy"`` (a division by zero gives inf/NaN as numpy does, never
an exception), no ``fastmath`` (no reassociation beyond what the order of the loops already
changes), ``cache=True`` (compiled once per machine into ``__pycache__``, loaded in each node
process). ``VEHICLE_ESTIMATION_COMPILED=0`` turns them off (the bench compares both).
"""

from __future__ import annotations

import os
from types import ModuleType
from typing import Any, Callable, Optional, TypeVar, cast

__all__ = ["AVAILABLE", "enabled", "kernel"]

F = TypeVar("F", bound=Callable)

_SWITCHED_OFF = os.environ.get("VEHICLE_ESTIMATION_COMPILED", "1") == "0"

_numba: Optional[ModuleType] = None
if not _SWITCHED_OFF:   # switched off, numba is not even imported (it costs ~60 MiB per process)
    try:  # the `fast` extra
        import numba as _numba
    except ImportError:  # pragma: no cover - depends on the environment
        _numba = None

AVAILABLE = _numba is not None


def enabled() -> bool:
    """Whether filters built now use their compiled kernels: numba is installed and the
    environment did not say ``VEHICLE_ESTIMATION_COMPILED=0`` when this module was imported."""
    return AVAILABLE


def kernel(fn: F) -> F:
    """``fn`` compiled by numba (lazily, at its first call), or ``fn`` itself without numba
    (then callers do not use it: :func:`enabled` is False)."""
    if _numba is None:
        return fn
    dispatcher: Any = _numba.njit(cache=True, nogil=True, error_model="numpy")(fn)
    return cast(F, dispatcher)
