"""Checks of a plant's own keys (constructor arguments), with messages that name the key.

Built-in plants call these in their constructors; a failed check raises `PlantConfigError`
(a ValueError), which the scenario loader reports as "plant <type>: <message>".
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np


class PlantConfigError(ValueError):
    """A plant key is missing, of the wrong type or out of range."""


def number(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False) -> float:
    """A finite float in [lo, hi] (or (lo, hi] with lo_open)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise PlantConfigError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise PlantConfigError(f"{name} must be finite, got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise PlantConfigError(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise PlantConfigError(f"{name} must be <= {hi:g}, got {v:g}")
    return v


def positive(name: str, value: Any) -> float:
    return number(name, value, lo=0.0, lo_open=True)


def integer(name: str, value: Any, *, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise PlantConfigError(f"{name} must be an integer, got {value!r}")
    v = int(value)
    if lo is not None and v < lo:
        raise PlantConfigError(f"{name} must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        raise PlantConfigError(f"{name} must be <= {hi}, got {v}")
    return v


def numbers(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
            length: int | None = None, nonempty: bool = True) -> tuple[float, ...]:
    """A list of finite floats in [lo, hi]."""
    if not isinstance(value, (list, tuple, np.ndarray)) or (nonempty and len(value) == 0):
        raise PlantConfigError(f"{name} must be a non-empty list of numbers, got {value!r}")
    out = tuple(number(f"{name}[{i}]", v, lo=lo, hi=hi) for i, v in enumerate(value))
    if length is not None and len(out) != length:
        raise PlantConfigError(f"{name} must have {length} entries, got {len(out)}")
    return out


def points(name: str, value: Any, dim: int, *, lo: float = 0.0, hi: float = 1.0) -> tuple[tuple[float, ...], ...]:
    """A non-empty list of `dim`-vectors (e.g. [[0.25, 0.5], ...]) with entries in [lo, hi]."""
    if not isinstance(value, (list, tuple)) or not value:
        raise PlantConfigError(f"{name} must be a non-empty list of {dim}-element positions, got {value!r}")
    out = []
    for i, p in enumerate(value):
        if not isinstance(p, (list, tuple)) or len(p) != dim:
            raise PlantConfigError(f"{name}[{i}] must be a list of {dim} numbers, got {p!r}")
        out.append(tuple(number(f"{name}[{i}]", c, lo=lo, hi=hi) for c in p))
    return tuple(out)


def distinct(name: str, nodes: Sequence[int]) -> None:
    """Refuse two sensors (or actuators) on the same grid node."""
    if len(set(nodes)) != len(nodes):
        raise PlantConfigError(f"two of {name} map to the same grid node: refine the grid or move them")
