"""Where the field's nodes are: the `field_coordinates` and `grid_shape` keys of an FMU plant.

An FMU knows its variables, not where they sit, so the scenario says it. `field_coordinates`:

* omitted: node i (0-based) at x = i metres;
* a list of n numbers: x of every node; or n lists of 1-3 numbers: x, y, z of every node;
* an expression in ``i`` (0-based node index) and ``n`` (node count), e.g. ``"(i + 0.5) / n"``,
  for x; or a list of 1-3 such expressions for x, y, z (numbers, + - * / ** %, pi, e and the
  numpy functions of the problem's target expressions);
* ``{origin: [...], spacing: [...]}``: a regular grid of `grid_shape` (C order: the last axis
  fastest), node (j_1, .., j_d) at origin + j * spacing per axis.

`grid_shape` (1-3 axes, product n) marks the field as a regular grid (heat maps); an FMI 3.0
array field or an FMI 2.0 ``T[i,j]`` array gives its shape by default. Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from sep_plant.plants import keys
from sep_plant.problem import ProblemError, evaluate_expression


def grid_shape_of(value: Any, n: int) -> tuple[int, ...] | None:
    """The checked `grid_shape` key (None stays None)."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or not 1 <= len(value) <= 3:
        raise keys.PlantConfigError(f"grid_shape must be a list of 1-3 node counts, got {value!r}")
    shape = tuple(keys.integer(f"grid_shape[{a}]", s, lo=1) for a, s in enumerate(value))
    if int(np.prod(shape)) != n:
        raise keys.PlantConfigError(f"grid_shape {list(shape)} holds {int(np.prod(shape))} nodes but the field has {n}")
    return shape


def _expression(text: str, n: int, axis: str) -> np.ndarray:
    i = np.arange(n, dtype=float)
    try:
        v = evaluate_expression(text, {"i": i, "n": np.full(n, float(n))})
    except ProblemError as exc:
        msg = str(exc).replace("target expression", f"field_coordinates {axis} expression")
        raise keys.PlantConfigError(msg) from None
    v = np.broadcast_to(np.asarray(v, dtype=float), (n,))
    if not np.all(np.isfinite(v)):
        raise keys.PlantConfigError(f"field_coordinates {axis} expression {text!r} is not finite at every node")
    return v


def coordinates(value: Any, n: int, grid_shape: tuple[int, ...] | None) -> np.ndarray:
    """(n, 3) node positions [m] from the `field_coordinates` key (see the module docstring)."""
    xyz = np.zeros((n, 3))
    if value is None:
        xyz[:, 0] = np.arange(n)
        return xyz
    if isinstance(value, str):
        xyz[:, 0] = _expression(value, n, "x")
        return xyz
    if isinstance(value, Mapping):
        return _grid(value, n, grid_shape)
    if not isinstance(value, (list, tuple)) or not value:
        raise keys.PlantConfigError("field_coordinates must be a list of positions, an expression in i and n, "
                                    f"or {{origin: [...], spacing: [...]}}, got {value!r}")
    if all(isinstance(v, str) for v in value):
        if len(value) > 3:
            raise keys.PlantConfigError(f"field_coordinates: at most 3 expressions (x, y, z), got {len(value)}")
        for a, text in enumerate(value):
            xyz[:, a] = _expression(text, n, "xyz"[a])
        return xyz
    if len(value) != n:
        raise keys.PlantConfigError(f"field_coordinates has {len(value)} entries but the field has {n} nodes")
    if all(isinstance(v, (list, tuple)) for v in value):
        for k, p in enumerate(value):
            if not 1 <= len(p) <= 3:
                raise keys.PlantConfigError(f"field_coordinates[{k}] must have 1-3 numbers, got {p!r}")
            xyz[k, :len(p)] = [keys.number(f"field_coordinates[{k}]", c) for c in p]
        return xyz
    xyz[:, 0] = keys.numbers("field_coordinates", value, length=n)
    return xyz


def _grid(value: Mapping, n: int, grid_shape: tuple[int, ...] | None) -> np.ndarray:
    if grid_shape is None:
        raise keys.PlantConfigError("field_coordinates {origin, spacing} needs grid_shape (the grid's node counts)")
    unknown = sorted(set(value) - {"origin", "spacing"})
    if unknown:
        raise keys.PlantConfigError(f"field_coordinates: unknown key(s) {unknown} (a grid has origin and spacing)")
    d = len(grid_shape)
    origin = keys.numbers("field_coordinates.origin", value.get("origin", [0.0] * d), length=d)
    spacing = keys.numbers("field_coordinates.spacing", value.get("spacing", [1.0] * d), length=d)
    mesh = np.meshgrid(*[o + s * np.arange(m) for o, s, m in zip(origin, spacing, grid_shape)], indexing="ij")
    xyz = np.zeros((n, 3))
    for a, m in enumerate(mesh):
        xyz[:, a] = m.ravel()
    return xyz


__all__ = ["coordinates", "grid_shape_of"]
