"""A CPU stand-in for a GPU array module, as strict as CuPy about the host/device boundary.

No GPU is needed by the tests, yet `--device cuda` must be tested. `guard` is a numpy-compatible
module whose arrays (`GuardArray`) live "on the device": numpy computes them, but they refuse what
a CuPy array refuses, so a step that would fail on a GPU fails here:

* implicit conversion to a host array (`np.asarray(d)`, `host[:] = d`, LAPACK on it): TypeError
  (`d.get()` is the explicit copy, as in CuPy);
* host arrays as operands or `out=` of device operations (`d * host`, `guard.moveaxis(host)`):
  TypeError (only `guard.asarray` / `guard.array` upload, as `cupy.asarray` does);
* numpy scalars and Python numbers mix freely, host integer arrays may index (both as in CuPy);
  a 0-d numpy array is a host array (CuPy refuses it as an operand).

Operations run through numpy's dispatch protocols (`__array_ufunc__`, `__array_function__`), as
CuPy's do, so `np.add(d, d)` works as on CuPy. `guard.transfers` counts explicit copies each way.
"""
from __future__ import annotations

from typing import Any

import numpy as np

_UPLOAD = {"asarray", "array", "asanyarray"}


class HostDeviceMix(TypeError):
    """A host array met a device array without an explicit transfer."""


def _is_host_array(v: Any) -> bool:
    return isinstance(v, np.ndarray)                    # 0-d too: CuPy takes Python and numpy scalars only


def _unwrap(v: Any, allow_host: bool = False) -> Any:
    if isinstance(v, GuardArray):
        return v._a
    if isinstance(v, (tuple, list)):
        return type(v)(_unwrap(x, allow_host) for x in v)
    if _is_host_array(v) and not allow_host:
        raise HostDeviceMix(f"a host (numpy) array of shape {v.shape} used as a device operand: "
                            "copy it to the device first (xp.asarray)")
    return v


def _wrap(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return GuardArray(v)
    if isinstance(v, tuple):
        return tuple(_wrap(x) for x in v)
    if isinstance(v, list):
        return [_wrap(x) for x in v]
    return v


def _call(f, args, kwargs, allow_host=False):
    a = _unwrap(list(args), allow_host)
    k = {key: _unwrap(val, allow_host) for key, val in kwargs.items()}
    return _wrap(f(*a, **k))


class _Namespace:
    """The `guard` module: numpy's functions on device arrays; creation functions make device arrays."""

    __name__ = "device_guard"

    def __init__(self) -> None:
        self.transfers = {"to_device": 0, "to_host": 0}

    def __getattr__(self, name: str):
        f = getattr(np, name)
        if isinstance(f, type) or not callable(f):
            return f                                        # dtypes, constants
        upload = name in _UPLOAD

        def fn(*args, **kwargs):
            if upload and any(_is_host_array(a) for a in args):
                self.transfers["to_device"] += 1
            return _call(f, args, kwargs, allow_host=upload)
        fn.__name__ = name
        return fn


guard = _Namespace()


def _binary(name: str, reflected: bool = False, inplace: bool = False):
    uf = getattr(np, name)
    if inplace:
        return lambda self, other: _ufunc(uf, (self, other), {"out": (self,)})
    if reflected:
        return lambda self, other: _ufunc(uf, (other, self), {})
    return lambda self, other: _ufunc(uf, (self, other), {})


def _ufunc(uf, inputs, kwargs, method="__call__"):
    return _call(getattr(uf, method), inputs, kwargs)          # out=(device, ...) is unwrapped too


class GuardArray:
    """A device array of the emulator (see the module docstring)."""

    __slots__ = ("_a",)
    __array_priority__ = 100

    def __init__(self, a: np.ndarray):
        self._a = a

    # -- the boundary
    def __array__(self, *args, **kwargs):
        raise HostDeviceMix("implicit conversion of a device array to a host (numpy) array: use .get()")

    def get(self) -> np.ndarray:
        guard.transfers["to_host"] += 1
        return self._a.copy()

    def __array_namespace__(self, api_version=None):
        return guard

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        return _ufunc(ufunc, inputs, kwargs, method)

    def __array_function__(self, func, types, args, kwargs):
        return _call(func, args, kwargs)

    # -- attributes and methods
    shape = property(lambda self: self._a.shape)
    ndim = property(lambda self: self._a.ndim)
    dtype = property(lambda self: self._a.dtype)
    size = property(lambda self: self._a.size)
    strides = property(lambda self: self._a.strides)
    flags = property(lambda self: self._a.flags)
    T = property(lambda self: GuardArray(self._a.T))

    def __getattr__(self, name: str):
        if name.startswith("__"):                  # __array_interface__ & co. would hand numpy the buffer
            raise AttributeError(name)
        m = getattr(self._a, name)
        if not callable(m):
            return _wrap(m)
        return lambda *args, **kwargs: _call(m, args, kwargs)

    def __len__(self) -> int:
        return len(self._a)

    def __repr__(self) -> str:
        return f"GuardArray({self._a!r})"

    def __bool__(self) -> bool:                    # a device scalar syncs, as in CuPy
        return bool(self._a)

    def __float__(self) -> float:
        return float(self._a)

    def __int__(self) -> int:
        return int(self._a)

    def __getitem__(self, key):
        return _wrap(self._a[_unwrap(key, allow_host=True)])

    def __setitem__(self, key, value) -> None:
        self._a[_unwrap(key, allow_host=True)] = _unwrap(value)

    __add__, __radd__, __iadd__ = _binary("add"), _binary("add", True), _binary("add", inplace=True)
    __sub__, __rsub__, __isub__ = _binary("subtract"), _binary("subtract", True), _binary("subtract", inplace=True)
    __mul__, __rmul__, __imul__ = _binary("multiply"), _binary("multiply", True), _binary("multiply", inplace=True)
    __truediv__, __rtruediv__, __itruediv__ = (_binary("divide"), _binary("divide", True),
                                               _binary("divide", inplace=True))
    __pow__, __rpow__ = _binary("power"), _binary("power", True)
    __matmul__, __rmatmul__ = _binary("matmul"), _binary("matmul", True)
    __lt__, __le__, __gt__, __ge__ = (_binary("less"), _binary("less_equal"), _binary("greater"),
                                      _binary("greater_equal"))
    __eq__, __ne__ = _binary("equal"), _binary("not_equal")
    __hash__ = None

    def __neg__(self):
        return _ufunc(np.negative, (self,), {})

    def __abs__(self):
        return _ufunc(np.absolute, (self,), {})


__all__ = ["GuardArray", "HostDeviceMix", "guard"]
