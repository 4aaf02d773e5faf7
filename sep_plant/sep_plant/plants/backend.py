"""Array modules for the built-in plants: numpy on the CPU, or a numpy-compatible GPU module (CuPy).

The built-in plants' `step` works on whatever array module its state comes in: a numpy state
is stepped exactly as always (LAPACK line solves, bitwise unchanged), a CuPy state is stepped on
its GPU with the same formulas, its line solves by parallel cyclic reduction (`adi.solve_pcr`:
log2(n) passes over all lines at once instead of n dependent ones). What a device array must
not do, and CuPy does not, is turn into a host array behind our back: every host constant a
step needs (actuator profiles, quadrature weights) is copied to the device once
(`DeviceConstants`) and the result comes back only through `to_host`.

`namespace(x)` picks the module: numpy for numpy arrays and scalars, `cupy` for CuPy arrays,
otherwise the array's `__array_namespace__()` (the array API standard's hook; the tests' device
emulator uses it). Pure numpy: no ROS import, and CuPy is imported only when a CuPy array is seen.
"""
from __future__ import annotations

import sys
from typing import Any, Callable

import numpy as np


def namespace(*arrays: Any):
    """The array module of the first non-numpy array among `arrays` (numpy if there is none)."""
    for a in arrays:
        if a is None or isinstance(a, (np.ndarray, np.generic, float, int, bool)):
            continue
        root = type(a).__module__.split(".")[0]
        if root == "cupy":                     # its __array_namespace__ may be the strict array API one
            return sys.modules["cupy"]
        hook = getattr(a, "__array_namespace__", None)
        if hook is not None:
            return hook()
    return np


def to_host(a: Any) -> np.ndarray:
    """A numpy copy of a device array (`.get()`, CuPy's explicit transfer); numpy passes through."""
    if isinstance(a, np.ndarray):
        return a
    get = getattr(a, "get", None)
    if get is None:
        return np.asarray(a)
    return get()


class DeviceConstants:
    """A plant's host constants copied to each array module once (keyed by the module)."""

    def __init__(self) -> None:
        self._cache: dict[int, dict[str, Any]] = {}

    def get(self, xp, name: str, make: Callable[[], np.ndarray]):
        """`make()` on the host for numpy; for another module its device copy, made on first use."""
        if xp is np:
            return make()
        per = self._cache.setdefault(id(xp), {})
        if name not in per:
            per[name] = xp.asarray(make())
        return per[name]

    def __getstate__(self) -> dict:                  # a plant shipped to a worker leaves its copies behind
        return {"_cache": {}}


__all__ = ["DeviceConstants", "namespace", "to_host"]
