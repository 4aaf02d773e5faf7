"""The control problem, apart from the plant: horizon, objective, noise, limits, LQG weights.

A `Problem` holds the values of a scenario file's problem keys (every default is the
reference scenario of docs/method.md). It knows nothing about any particular plant; what depends
on the plant's dimensions (per-channel vectors, the target field over the plant's nodes) is
resolved against a `PlantInfo` and the field coordinates:

    J(U) = sum_{k=1..N} q_k mean_i (f_{k,i} - f*_i)^2 + r_u sum_{k=0..N-1} |u_k|^2,
    q_k = q_window for k in the band window [k_start, k_end], q_outside elsewhere;
    in band: |f_{k,i} - f*_i| <= band for every node i and every k in the window;
    LQR on the outputs: Q_y,k = (lqr_q_late if k >= lqr_k_switch else lqr_q_early) I / n_y, R = lqr_r I;
    or, lqr_weighting "field", on the reconstructed field f = G_k a: Q_f,k = q_lqr,k I / n_field
    (lqr_field_nodes "mean") or q_lqr,k I ("sum"), q_lqr,k the schedule above (lqr_field_time
    "lqr") or the objective's q_k ("objective");
    noise: w ~ N(0, diag(w_std^2)) (n_w channels), v ~ N(0, diag(v_std^2)) (n_y sensors).

The target f* is a constant, a list of n_field values, or an expression in the node
coordinates x, y, z [m] (e.g. "150 + 5 * sin(2 * pi * x)" or "tanh((x - 0.5) / 0.05)"),
evaluated by a small whitelisting parser (no Python eval). Vectors (w_std, v_std, u_min,
u_max, u_init) are a number for every channel or a list with one entry per channel.
Pure Python/numpy: no ROS import.
"""
from __future__ import annotations

import ast
import dataclasses
import math
import operator
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np


class ProblemError(ValueError):
    """A problem value is missing, unknown, of the wrong type or out of range."""


Vector = float | tuple[float, ...]


@dataclass(frozen=True)
class Problem:
    """The problem keys of a scenario (defaults: the reference scenario)."""

    n_steps: int = 250                          # N: horizon in steps of the plant's dt
    # objective
    target: float | tuple[float, ...] | str = 150.0   # f*: constant, per-node list, or expression
    band: float = 3.0                           # +- band around f* [field unit]
    band_window: tuple[int, int] | None = None  # [k_start, k_end] (steps, inclusive); None: last 40 %
    q_window: float = 1.0                       # q_k inside the band window
    q_outside: float = 1e-5                     # q_k elsewhere
    r_u: float = 0.1                            # input weight of the nominal cost
    # noise
    w_std: Vector = 0.3                         # process noise std per noise channel
    v_std: Vector = 1.0                         # sensor noise std per output
    # input limits (applied by the plant node, the LQR and the optimizer)
    u_min: Vector = -math.inf
    u_max: Vector = math.inf
    # LQR / Kalman filter weights (on the outputs)
    lqr_k_switch: int | None = None             # None: 12 % of N before the band window opens
    lqr_q_late: float = 1.0
    lqr_q_early: float = 0.1
    lqr_r: float = 0.01
    lqr_weighting: str = "output"               # the LQR's state weight: on the outputs, or on the field
    lqr_field_nodes: str = "mean"               # field weighting: mean or sum over the nodes
    lqr_field_time: str = "lqr"                 # field weighting's q_k: the LQR's schedule or the objective's
    # optimizer start: constant input
    u_init: Vector = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):            # lists -> tuples, ints -> floats ... (also via replace)
            object.__setattr__(self, f.name, _coerce(f.name, decode_inf(getattr(self, f.name)), "problem"))
        problems = list(_problems(self))
        if problems:
            raise ProblemError("invalid problem: " + "; ".join(problems))

    # ------------------------------------------------------------- steps
    @property
    def window(self) -> tuple[int, int]:
        """(k_start, k_end) of the band window, inclusive."""
        if self.band_window is not None:
            return int(self.band_window[0]), int(self.band_window[1])
        return int(round(0.6 * self.n_steps)), self.n_steps

    @property
    def k_switch(self) -> int:
        if self.lqr_k_switch is not None:
            return int(self.lqr_k_switch)
        return max(0, self.window[0] - int(round(0.12 * self.n_steps)))

    def q_weights(self) -> np.ndarray:
        """q_k for k = 0..N of the nominal cost (q_0 is unused: the initial state is fixed)."""
        k = np.arange(self.n_steps + 1)
        k0, k1 = self.window
        return np.where((k >= k0) & (k <= k1), self.q_window, self.q_outside)

    def lqr_output_weights(self, n_y: int) -> np.ndarray:
        """Scalar Q_y multiplier per step k = 0..N (Q_y,k = w_k I)."""
        k = np.arange(self.n_steps + 1)
        return np.where(k >= self.k_switch, self.lqr_q_late, self.lqr_q_early) / n_y

    def lqr_field_weights(self, n_field: int) -> np.ndarray:
        """Scalar Q_f multiplier per step k = 0..N of the field weighting (Q_f,k = w_k I over the
        n_field nodes): the LQR's schedule (lqr_q_early, lqr_q_late) or the objective's q_k
        (`lqr_field_time`), divided by n_field for the mean over the nodes (`lqr_field_nodes`)."""
        k = np.arange(self.n_steps + 1)
        q = (self.q_weights() if self.lqr_field_time == "objective"
             else np.where(k >= self.k_switch, self.lqr_q_late, self.lqr_q_early))
        return q / (n_field if self.lqr_field_nodes == "mean" else 1.0)

    # ------------------------------------------------------ per-plant values
    def channels(self, key: str, n: int) -> np.ndarray:
        """A vector key (w_std, v_std, u_min, u_max, u_init) as an (n,) array."""
        v = getattr(self, key)
        if isinstance(v, tuple):
            if len(v) != n:
                raise ProblemError(f"{key} has {len(v)} entries, the plant has {n} channels")
            return np.asarray(v, dtype=float)
        return np.full(n, float(v))

    def limits(self, n_u: int) -> tuple[np.ndarray, np.ndarray]:
        return self.channels("u_min", n_u), self.channels("u_max", n_u)

    def noise_covariances(self, n_w: int, n_y: int) -> tuple[np.ndarray, np.ndarray]:
        """W = diag(w_std^2) (n_w x n_w), V = diag(v_std^2) (n_y x n_y)."""
        return np.diag(self.channels("w_std", n_w) ** 2), np.diag(self.channels("v_std", n_y) ** 2)

    def u_start(self, n_u: int) -> np.ndarray:
        """The optimizer's start: u_init held over the horizon, (N, n_u)."""
        return np.tile(self.channels("u_init", n_u), (self.n_steps, 1))

    def target_field(self, coords: np.ndarray) -> np.ndarray:
        """f* at every field node, (n_field,), from the node coordinates (n_field, 3) [m]."""
        n = coords.shape[0]
        t = self.target
        if isinstance(t, str):
            values = evaluate_expression(t, {"x": coords[:, 0], "y": coords[:, 1], "z": coords[:, 2]})
            out = np.broadcast_to(np.asarray(values, dtype=float), (n,)).copy()
        elif isinstance(t, tuple):
            if len(t) != n:
                raise ProblemError(f"target has {len(t)} values, the plant's field has {n} nodes")
            out = np.asarray(t, dtype=float)
        else:
            out = np.full(n, float(t))
        if not np.all(np.isfinite(out)):
            raise ProblemError(f"target {t!r} is not finite at every node")
        return out

    def check_dims(self, n_u: int, n_y: int, n_w: int, coords: np.ndarray) -> None:
        """Raise ProblemError if a vector key or the target does not fit the plant."""
        problems = []
        for key, n in (("w_std", n_w), ("v_std", n_y), ("u_min", n_u), ("u_max", n_u), ("u_init", n_u)):
            try:
                self.channels(key, n)
            except ProblemError as exc:
                problems.append(str(exc))
        try:
            self.target_field(coords)
        except ProblemError as exc:
            problems.append(str(exc))
        if not problems:
            lo, hi = self.limits(n_u)
            u0 = self.channels("u_init", n_u)
            if np.any(lo >= hi):
                problems.append("u_min must be < u_max for every input")
            elif np.any((u0 < lo) | (u0 > hi)):
                problems.append("u_init must lie within [u_min, u_max] for every input")
        if problems:
            raise ProblemError("problem does not fit the plant: " + "; ".join(problems))

    # ------------------------------------------------------ (de)serialize
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (inf as the strings 'inf'/'-inf'; tuples as lists). The LQR weighting keys
        (`CHOICES`) only when not at their defaults: a default problem's dict is sep 0.8's."""
        return {f.name: _encode(getattr(self, f.name)) for f in fields(self)
                if not (f.name in CHOICES and getattr(self, f.name) == CHOICES[f.name][0])}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "problem") -> "Problem":
        known = {f.name: f for f in fields(cls)}
        unknown = sorted((str(k) for k in data if k not in known))
        if unknown:
            raise ProblemError(f"{source}: unknown key(s) {unknown}; problem keys: {sorted(known)} "
                               "(plant keys go under `plant:`)")
        kwargs = {k: _coerce(k, decode_inf(v), source) for k, v in data.items()}
        try:
            return cls(**kwargs)
        except ProblemError as exc:
            raise ProblemError(f"{source}: {exc}") from None

    def resolved(self) -> "Problem":
        """The same problem with the defaults that depend on N written out (band_window,
        lqr_k_switch), as stored in design files."""
        return dataclasses.replace(self, band_window=self.window, lqr_k_switch=self.k_switch)

    def replace(self, **changes: Any) -> "Problem":
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------- objective
@dataclass(frozen=True)
class Objective:
    """The resolved objective of a problem on one plant: what the cost and the metrics need."""

    target: np.ndarray          # (n_field,) f*
    q: np.ndarray               # (N+1,) q_k
    band: float
    window: tuple[int, int]     # (k_start, k_end) inclusive
    r_u: float

    @classmethod
    def of(cls, problem: Problem, coords: np.ndarray) -> "Objective":
        return cls(problem.target_field(coords), problem.q_weights(), float(problem.band), problem.window,
                   float(problem.r_u))

    @property
    def n_steps(self) -> int:
        return int(self.q.shape[0] - 1)

    def cost(self, F: np.ndarray, U: np.ndarray) -> np.ndarray:
        """The nominal cost J of field trajectories and inputs (docs/method.md):

            J = sum_{k=1..N} q_k mean_i (f_{k,i} - f*_i)^2 + r_u sum_{k=0..N-1} |u_k|^2.

        Parameters
        ----------
        F : ndarray, shape (..., N+1, n_field)
            Field trajectories f_k for k = 0..N (f_0 does not enter), a leading run axis optional.
        U : ndarray, shape (..., N, n_u)
            Inputs u_k for k = 0..N-1.

        Returns
        -------
        J : ndarray, shape (...)
            The cost of every run (a 0-d array without a run axis).
        """
        field = np.einsum("k,...k->...", self.q[1:], self.squared_error(F[..., 1:, :]))
        return field + self.r_u * np.sum(U**2, axis=(-2, -1))

    # the same J one step at a time (a streaming sum: `sep_control.evaluation.metrics.MetricsAccumulator`)
    def squared_error(self, f: np.ndarray) -> np.ndarray:
        """e = mean_i (f_i - f*_i)^2 of fields f (..., n_field): the field term of J before q_k."""
        return np.mean((f - self.target) ** 2, axis=-1)

    def field_cost(self, k: int, e_k: np.ndarray) -> np.ndarray:
        """Step k's field term of J, q_k e_k (0 for k = 0: f_0 does not enter)."""
        return self.q[k] * e_k if k >= 1 else np.zeros_like(e_k)

    def input_cost(self, u_k: np.ndarray) -> np.ndarray:
        """Step k's input term of J, r_u |u_k|^2, of inputs u_k (..., n_u)."""
        return self.r_u * np.sum(u_k**2, axis=-1)


# ------------------------------------------------------------ expressions
_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
           ast.Pow: operator.pow, ast.Mod: operator.mod}
_UNARY = {ast.USub: operator.neg, ast.UAdd: operator.pos}
_COMPARE = {ast.Lt: operator.lt, ast.LtE: operator.le, ast.Gt: operator.gt, ast.GtE: operator.ge}
_FUNCS = {name: getattr(np, name) for name in ("sin", "cos", "tan", "tanh", "exp", "log", "sqrt", "abs",
                                               "arctan", "arctan2", "minimum", "maximum", "where", "sign",
                                               "floor", "hypot")}
_CONSTS = {"pi": math.pi, "e": math.e}


def evaluate_expression(text: str, names: Mapping[str, np.ndarray]) -> np.ndarray:
    """Evaluate an arithmetic expression of `names` (arrays), numbers, pi, e and the numpy
    functions in `_FUNCS`; anything else (attributes, subscripts, other names) is refused."""
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        raise ProblemError(f"target expression {text!r}: syntax error ({exc.msg})") from None

    def ev(node: ast.AST):
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            return float(node.value)
        if isinstance(node, ast.Name):
            if node.id in names:
                return names[node.id]
            if node.id in _CONSTS:
                return _CONSTS[node.id]
            raise ProblemError(f"target expression {text!r}: unknown name {node.id!r} "
                               f"(use {', '.join(sorted(names))}, pi, e)")
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
            return _UNARY[type(node.op)](ev(node.operand))
        if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _COMPARE:
            a, b = ev(node.left), ev(node.comparators[0])
            return np.asarray(_COMPARE[type(node.ops[0])](a, b), dtype=float)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _FUNCS \
                and not node.keywords:
            return _FUNCS[node.func.id](*[ev(a) for a in node.args])
        raise ProblemError(f"target expression {text!r}: {type(node).__name__} is not allowed "
                           f"(numbers, x, y, z, pi, e, + - * / ** %, comparisons and "
                           f"{', '.join(sorted(_FUNCS))})")

    with np.errstate(all="ignore"):
        return ev(tree)


# ---------------------------------------------------------------- internals
def _encode(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_encode(x) for x in v]
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return v


def decode_inf(v: Any) -> Any:
    """A scenario value with the strings 'inf', '+inf', '.inf', '-inf', '-.inf' (any case, in
    lists too) as floats: YAML and strict JSON have no literal for infinity."""
    if isinstance(v, str) and v.strip().lower() in ("inf", "+inf", ".inf", "-inf", "-.inf"):
        return -math.inf if v.strip().startswith("-") else math.inf
    if isinstance(v, list):
        return [decode_inf(x) for x in v]
    return v


_VECTORS = ("w_std", "v_std", "u_min", "u_max", "u_init")
_INTS = ("n_steps",)
_OPT_INTS = ("lqr_k_switch",)
_FLOATS = ("band", "q_window", "q_outside", "r_u", "lqr_q_late", "lqr_q_early", "lqr_r")


def _num(key: str, v: Any, source: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
        raise ProblemError(f"{source}: {key} must be a number, got {v!r}")
    return float(v)


def _int(key: str, v: Any, source: str) -> int:
    if isinstance(v, float) and v.is_integer():
        return int(v)
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ProblemError(f"{source}: {key} must be an integer, got {v!r}")
    return int(v)


def _coerce(key: str, v: Any, source: str) -> Any:
    if key in _INTS:
        return _int(key, v, source)
    if key in _OPT_INTS:
        return None if v is None else _int(key, v, source)
    if key in _FLOATS:
        return _num(key, v, source)
    if key in _VECTORS or key == "target":
        if key == "target" and isinstance(v, str):
            return v
        if isinstance(v, (list, tuple)):
            if not v:
                raise ProblemError(f"{source}: {key} must be a number or a non-empty list of numbers"
                                   + (" or an expression" if key == "target" else ""))
            return tuple(_num(f"{key}[{i}]", x, source) for i, x in enumerate(v))
        return _num(key, v, source)
    if key == "band_window":
        if v is None:
            return None
        if not isinstance(v, (list, tuple)) or len(v) != 2:
            raise ProblemError(f"{source}: band_window must be [k_start, k_end] (steps), got {v!r}")
        return (_int("band_window[0]", v[0], source), _int("band_window[1]", v[1], source))
    return v


#: string keys and their values (the first is the default)
CHOICES = {"lqr_weighting": ("output", "field"), "lqr_field_nodes": ("mean", "sum"),
           "lqr_field_time": ("lqr", "objective")}


def _problems(p: Problem):
    for k, allowed in CHOICES.items():
        if getattr(p, k) not in allowed:
            yield f"{k} must be one of {', '.join(allowed)} (got {getattr(p, k)!r})"
    for k in ("band", "q_window", "lqr_r", "lqr_q_late", "lqr_q_early"):
        v = getattr(p, k)
        if not (math.isfinite(v) and v > 0):
            yield f"{k} must be a finite number > 0 (got {v!r})"
    for k in ("q_outside", "r_u"):
        v = getattr(p, k)
        if not (math.isfinite(v) and v >= 0):
            yield f"{k} must be a finite number >= 0 (got {v!r})"
    for k in ("w_std", "v_std", "u_init"):
        vals = getattr(p, k) if isinstance(getattr(p, k), tuple) else (getattr(p, k),)
        if not all(math.isfinite(v) for v in vals):
            yield f"{k} must be finite (got {getattr(p, k)!r})"
    ws = p.w_std if isinstance(p.w_std, tuple) else (p.w_std,)
    if any(v < 0 for v in ws):
        yield f"w_std must be >= 0 (got {p.w_std!r})"
    vs = p.v_std if isinstance(p.v_std, tuple) else (p.v_std,)
    if any(not v > 0 for v in vs):
        yield f"v_std must be > 0 (the Kalman filter needs a positive sensor noise; got {p.v_std!r})"
    for k in ("u_min", "u_max"):
        vals = getattr(p, k) if isinstance(getattr(p, k), tuple) else (getattr(p, k),)
        if any(math.isnan(v) for v in vals):
            yield f"{k} must not be NaN"
    if not isinstance(p.u_min, tuple) and not isinstance(p.u_max, tuple) and not p.u_min < p.u_max:
        yield f"u_min must be < u_max (got {p.u_min}, {p.u_max})"
    if not isinstance(p.u_init, tuple) and not isinstance(p.u_min, tuple) and not isinstance(p.u_max, tuple) \
            and not p.u_min <= p.u_init <= p.u_max:
        yield f"u_init must lie within [u_min, u_max] (got {p.u_init})"
    if p.n_steps < 2:
        yield f"n_steps must be >= 2 (got {p.n_steps})"
    k0, k1 = p.window
    if not 0 <= k0 <= k1 <= p.n_steps:
        yield f"band_window must satisfy 0 <= k_start <= k_end <= n_steps = {p.n_steps} (got [{k0}, {k1}])"
    if p.lqr_k_switch is not None and not 0 <= p.lqr_k_switch <= p.n_steps:
        yield f"lqr_k_switch must be in [0, n_steps] (got {p.lqr_k_switch})"
    t = p.target
    if isinstance(t, float) and not math.isfinite(t):
        yield f"target must be finite (got {t!r})"
    if isinstance(t, tuple) and not all(math.isfinite(v) for v in t):
        yield "target values must be finite"
    if isinstance(t, str):
        try:  # syntax and names now; values when the plant's coordinates are known
            evaluate_expression(t, {n: np.zeros(1) for n in "xyz"})
        except ProblemError as exc:
            yield str(exc)
