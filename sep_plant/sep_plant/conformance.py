"""Plant conformance: catch a bad plant in a second, before hours of experiments.

`check_plant(plant)` runs the plant protocol's rules (module `sep_plant.protocol`) on a small
batch and raises `PlantError` listing every problem found, each naming what to fix:

* missing attributes or methods; dimensions, time step and names of the wrong type or length;
* `config()` not plain JSON data, or not rebuilding an identical plant;
* arrays of the wrong shape (initial_state, step, observe, field, field_coordinates, grid_shape);
* non-finite outputs (initial state, a few steps along the given input, observe, field);
* a step that modifies its input state, that is not deterministic for the same state, input
  and noise, whose batch differs from its runs stepped one by one, or (noise on the inputs)
  where step(x, u, w) differs from step(x, u + w).

A plant whose states are opaque (`state_is_opaque`, e.g. a Co-Simulation FMU's serialized
state) is compared by what its states do, never by their values: two states are the same when
they give the same outputs and field now and after one more step under the same input.

The design, evaluate, validate and the plant node call it first. Pure numpy: no ROS import.
"""
from __future__ import annotations

import json
from typing import Any

import numpy as np

from sep_plant.protocol import REQUIRED_ATTRIBUTES, REQUIRED_METHODS, PlantError, noise_channels

#: relative tolerance of the batch-vs-one-by-one and noise-on-inputs comparisons (round-off of
#: a batched solve against single solves; a real difference is many orders larger)
RTOL = 1e-9


class _Abort(Exception):
    """A problem after which further checks make no sense."""


def _label(plant: Any) -> str:
    from sep_plant.device import base_plant

    cls = type(base_plant(plant))
    return f"{cls.__module__}:{cls.__qualname__}"


def check_plant(plant: Any, u: np.ndarray | None = None, *, batch: int = 3, steps: int = 3,
                name: str | None = None) -> None:
    """Raise `PlantError` naming every way `plant` breaks the protocol (silent when it conforms).

    Parameters
    ----------
    plant : object
        The object to check against the plant protocol (`sep_plant.protocol`).
    u : ndarray, shape (n_u,), optional
        The input to step with (the optimizer's start, typically); zeros if None.
    batch : int, default 3
        Runs of the batched calls (a batch must equal its runs stepped one by one).
    steps : int, default 3
        Steps of the test trajectories.
    name : str, optional
        The plant's name in the message (default ``module:Class`` of the plant).

    Raises
    ------
    PlantError
        The plant does not conform; the message lists every problem (`conformance_problems`).
    """
    problems = conformance_problems(plant, u, batch=batch, steps=steps)
    if problems:
        who = name or _label(plant)
        raise PlantError(f"plant {who} does not meet the plant protocol (sep_plant.protocol):\n  - "
                         + "\n  - ".join(problems))


def conformance_problems(plant: Any, u: np.ndarray | None = None, *, batch: int = 3,
                         steps: int = 3) -> list[str]:
    """Every protocol problem of `plant` as a list of sentences (empty when it conforms)."""
    out: list[str] = []
    try:
        _check(plant, u, batch, steps, out)
    except _Abort:
        pass
    return out


def _call(out: list[str], what: str, fn, *args):
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - any exception of user code is a finding
        out.append(f"{what} raised {type(exc).__name__}: {exc}")
        raise _Abort from None


def _array(out: list[str], what: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        out.append(f"{what} returned {type(value).__name__}, expected a numpy array of shape {shape}")
        raise _Abort
    if value.shape != shape:
        out.append(f"{what} returned shape {value.shape}, expected {shape}")
        raise _Abort
    if value.dtype.kind not in "fiu":
        out.append(f"{what} returned dtype {value.dtype}, expected real numbers (float64, or integers)")
        raise _Abort
    if not np.all(np.isfinite(value)):
        bad = int(np.count_nonzero(~np.isfinite(value)))
        out.append(f"{what} returned {bad} non-finite values (NaN/Inf)")
        raise _Abort
    return value


def _close(a: np.ndarray, b: np.ndarray) -> bool:
    scale = max(float(np.max(np.abs(b))), 1.0)
    return bool(np.max(np.abs(a - b)) <= RTOL * scale)


def _same(plant: Any, A: np.ndarray, B: np.ndarray, U: np.ndarray, out: list[str], exact: bool = False) -> bool:
    """A and B hold the same states: equal (`exact`) or close. Opaque states: the same outputs
    and field now and after one more step under the inputs U (see the module docstring)."""
    if getattr(plant, "state_is_opaque", False):
        A, B = _signature(plant, A, U, out), _signature(plant, B, U, out)
    return bool(np.array_equal(A, B)) if exact else _close(A, B)


def _signature(plant: Any, X: np.ndarray, U: np.ndarray, out: list[str]) -> np.ndarray:
    """What opaque states do: outputs and field of X and of one step from X under U, per run."""
    M = X.shape[0]
    nxt = _array(out, "step() of opaque states", _call(out, "step()", plant.step, X.copy(), U.copy(), None),
                 X.shape)
    parts = [_call(out, "observe()", plant.observe, X), _call(out, "field()", plant.field, X),
             _call(out, "observe()", plant.observe, nxt), _call(out, "field()", plant.field, nxt)]
    return np.hstack([np.asarray(p, dtype=float).reshape(M, -1) for p in parts])


def _describe(plant: Any, out: list[str]) -> None:
    missing = [a for a in REQUIRED_ATTRIBUTES if not hasattr(plant, a)]
    missing += [f"{m}()" for m in REQUIRED_METHODS if not callable(getattr(plant, m, None))]
    if missing:
        out.append(f"missing {', '.join(missing)}")
        raise _Abort
    for a in ("n_x", "n_u", "n_y", "n_field"):
        v = getattr(plant, a)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            out.append(f"{a} must be a positive integer, got {v!r}")
    dt = plant.dt
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)) or not np.isfinite(dt) or dt <= 0:
        out.append(f"dt must be a finite number > 0, got {dt!r}")
    for a, n in (("input_names", "n_u"), ("output_names", "n_y")):
        names = getattr(plant, a)
        try:
            names = list(names)
        except TypeError:
            out.append(f"{a} must be a sequence of strings, got {names!r}")
            continue
        if not all(isinstance(x, str) and x for x in names):
            out.append(f"{a} must be non-empty strings, got {names!r}")
        elif len(set(names)) != len(names):
            out.append(f"{a} must be unique, got {names!r}")
        if isinstance(getattr(plant, n), (int, np.integer)) and len(names) != getattr(plant, n):
            out.append(f"{a} has {len(names)} entries but {n} = {getattr(plant, n)}")
    for a in ("field_name", "field_unit"):
        if not isinstance(getattr(plant, a), str):
            out.append(f"{a} must be a string, got {getattr(plant, a)!r}")
    if isinstance(plant.field_name, str) and not plant.field_name.isidentifier():
        out.append(f"field_name must be an identifier (it names a PointCloud2 channel), got {plant.field_name!r}")
    grid = getattr(plant, "grid_shape", None)
    if grid is not None:
        try:
            size = int(np.prod([int(g) for g in grid]))
        except (TypeError, ValueError):
            out.append(f"grid_shape must be a tuple of integers, got {grid!r}")
        else:
            if size != plant.n_field or not 1 <= len(grid) <= 3:
                out.append(f"grid_shape {tuple(grid)} must have 1-3 axes with prod = n_field = {plant.n_field}")
    n_w = getattr(plant, "n_w", None)
    if getattr(plant, "noise_on_inputs", True) and n_w is not None and n_w != plant.n_u:
        out.append(f"noise_on_inputs is true but n_w = {n_w!r} != n_u = {plant.n_u}")
    elif n_w is not None and (isinstance(n_w, bool) or not isinstance(n_w, (int, np.integer)) or n_w < 1):
        out.append(f"n_w must be a positive integer, got {n_w!r}")
    if getattr(plant, "field_is_state", False) and plant.n_field != plant.n_x:
        out.append(f"field_is_state is true but n_field = {plant.n_field} != n_x = {plant.n_x}")
    if getattr(plant, "field_is_state", False) and getattr(plant, "state_is_opaque", False):
        out.append("field_is_state and state_is_opaque are both true: an opaque state cannot be the field")
    if out:
        raise _Abort


def _config(plant: Any, out: list[str]) -> None:
    cfg = _call(out, "config()", plant.config)
    if not isinstance(cfg, dict):
        out.append(f"config() must return a dict of the plant's keys, got {type(cfg).__name__}")
        return
    try:
        text = json.dumps(cfg, sort_keys=True)
    except (TypeError, ValueError) as exc:
        out.append(f"config() must be plain JSON data (numbers, strings, lists, dicts): {exc}")
        return
    try:
        from sep_plant.device import base_plant

        again = type(base_plant(plant))(**cfg).config()        # a DevicePlant: the plant it steps
    except Exception as exc:  # noqa: BLE001
        out.append(f"type(plant)(**config()) raised {type(exc).__name__}: {exc} (config() must hold "
                   "exactly the constructor's keys)")
        return
    if json.dumps(again, sort_keys=True) != text:
        out.append("type(plant)(**config()).config() differs from config(): the keys do not rebuild the plant")


def _check(plant: Any, u: np.ndarray | None, batch: int, steps: int, out: list[str]) -> None:
    _describe(plant, out)
    n_x, n_u, n_y, n_f = int(plant.n_x), int(plant.n_u), int(plant.n_y), int(plant.n_field)
    n_w = noise_channels(plant)
    _config(plant, out)
    _array(out, "field_coordinates()", _call(out, "field_coordinates()", plant.field_coordinates), (n_f, 3))
    X0 = _array(out, f"initial_state({batch})", _call(out, "initial_state()", plant.initial_state, batch),
                (batch, n_x))
    one = _array(out, "initial_state(1)", _call(out, "initial_state()", plant.initial_state, 1), (1, n_x))
    if not np.array_equal(X0, np.repeat(one, batch, axis=0)):
        out.append("initial_state(batch) rows differ from initial_state(1): the initial state must be known and fixed")
    u0 = np.zeros(n_u) if u is None else np.asarray(u, dtype=float).reshape(n_u)
    rng = np.random.default_rng(0)
    scale = 0.01 * (np.abs(u0) + 1e-3)
    # a few steps with different inputs per run, so the batch holds different states
    X = X0.copy()
    for k in range(steps):
        Uk = u0 + scale * rng.standard_normal((batch, n_u))
        X = _array(out, f"step() at step {k} from the initial state",
                   _call(out, "step()", plant.step, X, Uk, None), (batch, n_x))
    _array(out, "observe()", _call(out, "observe()", plant.observe, X), (batch, n_y))
    _array(out, "field()", _call(out, "field()", plant.field, X), (batch, n_f))

    U = u0 + scale * rng.standard_normal((batch, n_u))
    W = (scale if n_w == n_u else 0.01) * rng.standard_normal((batch, n_w))
    X_before = X.copy()
    X1 = _array(out, "step(x, u, w)", _call(out, "step()", plant.step, X, U, W), (batch, n_x))
    if not np.array_equal(X, X_before):
        out.append("step() modified its input state in place: states are snapshots that sep restarts "
                   "experiments from; return a new array")
        X = X_before
    X2 = _call(out, "step()", plant.step, X.copy(), U.copy(), W.copy())
    if not _same(plant, X1, X2, U, out, exact=True):
        out.append("step() is not deterministic: the same state, input and noise gave different results "
                   "(every random number must come in through w)")
    rows = [_call(out, "step()", plant.step, X[i:i + 1].copy(), U[i:i + 1].copy(), W[i:i + 1].copy())
            for i in range(batch)]
    if all(isinstance(r, np.ndarray) and r.shape == (1, n_x) for r in rows):
        if not _same(plant, np.vstack(rows), X1, U, out):
            out.append("step() of a batch differs from its runs stepped one by one (runs must not interact)")
    else:
        out.append(f"step() of one run (batch 1) must return shape (1, {n_x})")
    if getattr(plant, "noise_on_inputs", True) and n_w == n_u:
        Xn = _call(out, "step()", plant.step, X.copy(), U + W, None)
        if not (isinstance(Xn, np.ndarray) and Xn.shape == X1.shape and _same(plant, Xn, X1, U, out)):
            out.append("noise_on_inputs is true but step(x, u, w) differs from step(x, u + w): declare "
                       "noise_on_inputs = False, or add w to the inputs")
    Xb = _call(out, "step()", plant.step, X.copy(), U[0].copy(), None)
    if not (isinstance(Xb, np.ndarray) and Xb.shape == (batch, n_x)):
        out.append(f"step(x, u) with u of shape ({n_u},) must apply u to every run (return ({batch}, {n_x}))")
