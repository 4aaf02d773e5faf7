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
coordinates x, y, z [m] and the time t = k dt [s] (e.g. "150 + 5 * sin(2 * pi * x)" or
"100 + 50 * minimum(t / 20, 1)"), evaluated by a small whitelisting parser (no Python eval).
Vectors (w_std, v_std, u_min, u_max, u_init, du_max) are a number for every channel or a list
with one entry per channel.

Recipes (`recipe`: a list of `Segment`s, times in seconds): segment s covers the steps
k_s0..k_s1 with k dt in [start, end] (a step two segments share belongs to the earlier one);
there f*_k is its target (constant, per node, or an expression in x, y, z, t), q_k its weight;
a segment with a band is a hold (in band: |f_{k,i} - f*_{k,i}| <= band_s for every node i and
every k of EVERY hold), one without a band a ramp, tracked by its weight only. Steps outside
every segment weigh q_outside and take the next segment's target at its first step (after the
last segment: the last one's at its last step). The band window and band of a recipe's
`Objective` are then the span of the holds and the narrowest hold band (rms and mean
deviations are over that span). Input rate limits: |u_k - u_{k-1}| <= du_max per channel
for k >= 1 (u_{-1} is free: the first input is limited by the box only).
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
    # recipes and rate limits (None / inf: none; not written by `to_dict` then)
    recipe: "tuple[Segment, ...] | None" = None  # segments of a time-varying objective (seconds)
    du_max: Vector = math.inf                    # |u_k - u_{k-1}| <= du_max per channel

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

    def q_weights(self, dt: float | None = None) -> np.ndarray:
        """q_k for k = 0..N of the nominal cost (q_0 is unused: the initial state is fixed); a
        recipe's segment weights need the plant's time step dt [s]."""
        k = np.arange(self.n_steps + 1)
        if self.recipe is not None:
            q = np.full(self.n_steps + 1, self.q_outside)
            for seg, (k0, k1) in zip(self.recipe, self.segment_steps(dt)):
                q[k0:k1 + 1] = seg.weight
            return q
        k0, k1 = self.window
        return np.where((k >= k0) & (k <= k1), self.q_window, self.q_outside)

    @property
    def time_varying(self) -> bool:
        """Whether f* depends on the step: a recipe, or a target expression in t."""
        return self.recipe is not None or (isinstance(self.target, str) and uses_time(self.target))

    @property
    def input_limited(self) -> bool:
        """Whether any channel has a finite u_min or u_max."""
        return any(math.isfinite(v) for key in (self.u_min, self.u_max)
                   for v in (key if isinstance(key, tuple) else (key,)))

    @property
    def rate_limited(self) -> bool:
        """Whether any channel has a finite du_max."""
        d = self.du_max if isinstance(self.du_max, tuple) else (self.du_max,)
        return any(math.isfinite(v) for v in d)

    def segment_steps(self, dt: float | None) -> list[tuple[int, int]]:
        """(k_s0, k_s1) of every recipe segment: the steps k with k dt in [start, end], a step
        shared with the previous segment left to it. Raises ProblemError when a segment has no
        step of its own or ends past N."""
        if self.recipe is None:
            return []
        if dt is None or not dt > 0:
            raise ProblemError("a recipe needs the plant's time step dt")
        out: list[tuple[int, int]] = []
        for i, seg in enumerate(self.recipe):
            k0 = int(math.ceil(seg.start / dt - 1e-9))
            k1 = int(math.floor(seg.end / dt + 1e-9))
            if out and k0 <= out[-1][1]:
                k0 = out[-1][1] + 1
            if k0 > k1:
                raise ProblemError(f"recipe segment {i} ({seg.start:g}..{seg.end:g} s) holds no step of "
                                   f"its own at dt = {dt:g} s")
            if k1 > self.n_steps:
                raise ProblemError(f"recipe segment {i} ends at {seg.end:g} s, past the horizon "
                                   f"N dt = {self.n_steps * dt:g} s")
            out.append((k0, k1))
        return out

    def target_steps(self, coords: np.ndarray, dt: float | None = None) -> np.ndarray:
        """f*: (n_field,) for a constant-in-time target (`target_field`), else (N+1, n_field),
        f*_k at t = k dt (a target expression in t, or a recipe: the module docstring)."""
        if not self.time_varying:
            return self.target_field(coords)
        if dt is None or not dt > 0:
            raise ProblemError("a time-varying target needs the plant's time step dt")
        N, n = self.n_steps, coords.shape[0]
        t = np.arange(N + 1) * float(dt)
        if self.recipe is None:
            return _target_values(self.target, coords, t, "target")
        out = np.full((N + 1, n), np.nan)
        steps = self.segment_steps(dt)
        for i, (seg, (k0, k1)) in enumerate(zip(self.recipe, steps)):
            out[k0:k1 + 1] = _target_values(seg.target, coords, t[k0:k1 + 1], f"recipe segment {i} target")
        owned = np.zeros(N + 1, dtype=bool)
        for k0, k1 in steps:
            owned[k0:k1 + 1] = True
        firsts = np.array([k0 for k0, _ in steps])
        for k in np.flatnonzero(~owned):           # gaps: the next segment's first target
            nxt = np.searchsorted(firsts, k)
            out[k] = out[firsts[nxt]] if nxt < len(firsts) else out[steps[-1][1]]
        return out

    def hold_steps(self, dt: float | None) -> list[tuple[int, int, float]]:
        """(k_s0, k_s1, band_s) of every hold segment of a recipe (segments with a band)."""
        return [(k0, k1, float(seg.band)) for seg, (k0, k1) in zip(self.recipe or (), self.segment_steps(dt))
                if seg.band is not None]

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
        """f* at every field node, (n_field,), from the node coordinates (n_field, 3) [m] (a
        target constant in time; `target_steps` for any)."""
        n = coords.shape[0]
        t = self.target
        if self.time_varying:
            raise ProblemError("the target varies in time (a recipe or an expression in t): use target_steps")
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

    def check_dims(self, n_u: int, n_y: int, n_w: int, coords: np.ndarray, dt: float = 1.0) -> None:
        """Raise ProblemError if a vector key or the target (a recipe: at the time step dt)
        does not fit the plant."""
        problems = []
        for key, n in (("w_std", n_w), ("v_std", n_y), ("u_min", n_u), ("u_max", n_u), ("u_init", n_u),
                       ("du_max", n_u)):
            try:
                self.channels(key, n)
            except ProblemError as exc:
                problems.append(str(exc))
        try:
            target = self.target_steps(coords, dt)
            if not np.all(np.isfinite(target)):
                problems.append(f"target {self.target!r} is not finite at every node and step")
            if self.recipe is not None and not self.hold_steps(dt):
                problems.append("a recipe needs at least one hold segment (a segment with a band)")
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
        out = {f.name: _encode(getattr(self, f.name)) for f in fields(self)
               if not (f.name in CHOICES and getattr(self, f.name) == CHOICES[f.name][0])}
        if self.recipe is None:
            del out["recipe"]
        else:
            out["recipe"] = [seg.to_dict() for seg in self.recipe]
        if not self.rate_limited:
            del out["du_max"]
        return out

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
    # a recipe's hold segments (k_s0, k_s1, band_s); None: one hold, the band window with `band`
    holds: tuple[tuple[int, int, float], ...] | None = None

    @classmethod
    def of(cls, problem: Problem, coords: np.ndarray, dt: float | None = None) -> "Objective":
        """The objective on nodes `coords` (n_field, 3); a time-varying target needs dt [s]."""
        return cls.with_target(problem, problem.target_steps(coords, dt), dt)

    @classmethod
    def with_target(cls, problem: Problem, target: np.ndarray, dt: float | None = None) -> "Objective":
        """The objective of a problem with its resolved target f* (n_field,) or (N+1, n_field)
        (as a design file stores it)."""
        if problem.recipe is None:
            return cls(target, problem.q_weights(), float(problem.band), problem.window, float(problem.r_u))
        holds = tuple(problem.hold_steps(dt))
        if not holds:
            raise ProblemError("a recipe needs at least one hold segment (a segment with a band)")
        return cls(target, problem.q_weights(dt), min(b for _, _, b in holds), (holds[0][0], holds[-1][1]),
                   float(problem.r_u), holds)

    @property
    def segments(self) -> tuple[tuple[int, int, float], ...]:
        """The holds (k_s0, k_s1, band_s) whose band test makes 'in band' (one without a recipe)."""
        return self.holds if self.holds is not None else ((self.window[0], self.window[1], float(self.band)),)

    def target_at(self, k: int) -> np.ndarray:
        """f*_k, (n_field,)."""
        return self.target if np.ndim(self.target) <= 1 else self.target[k]

    def targets(self, k0: int, k1: int) -> np.ndarray:
        """f* over steps k0..k1: (n_field,) (constant in time) or (k1 - k0 + 1, n_field)."""
        return self.target if np.ndim(self.target) <= 1 else self.target[k0:k1 + 1]

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
        if np.ndim(self.target) <= 1:
            e = self.squared_error(F[..., 1:, :])
        else:
            e = np.mean((F[..., 1:, :] - self.target[1:]) ** 2, axis=-1)
        field = np.einsum("k,...k->...", self.q[1:], e)
        return field + self.r_u * np.sum(U**2, axis=(-2, -1))

    # the same J one step at a time (a streaming sum: `sep_control.evaluation.metrics.MetricsAccumulator`)
    def squared_error(self, f: np.ndarray, k: int | None = None) -> np.ndarray:
        """e = mean_i (f_i - f*_i)^2 of fields f (..., n_field) of step k (any step for a target
        constant in time): the field term of J before q_k."""
        return np.mean((f - (self.target if k is None else self.target_at(k))) ** 2, axis=-1)

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
                           f"(numbers, x, y, z, t, pi, e, + - * / ** %, comparisons and "
                           f"{', '.join(sorted(_FUNCS))})")

    with np.errstate(all="ignore"):
        return ev(tree)


def uses_time(text: str) -> bool:
    """Whether an expression names t (a syntax error: False; `evaluate_expression` reports it)."""
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError:
        return False
    return any(isinstance(n, ast.Name) and n.id == "t" for n in ast.walk(tree))


def _target_values(spec: float | tuple[float, ...] | str, coords: np.ndarray, t: np.ndarray | None,
                   what: str) -> np.ndarray:
    """A target spec (constant, per-node tuple, expression in x, y, z, t) on nodes `coords`:
    (n,) when t is None, else (len(t), n) at the times t [s]."""
    n = coords.shape[0]
    shape = (n,) if t is None else (t.shape[0], n)
    if isinstance(spec, str):
        names = {"x": coords[:, 0], "y": coords[:, 1], "z": coords[:, 2]}
        if t is not None:
            names = {**{k: v[None, :] for k, v in names.items()}, "t": t[:, None]}
        values = evaluate_expression(spec, names)
        out = np.broadcast_to(np.asarray(values, dtype=float), shape).copy()
    elif isinstance(spec, tuple):
        if len(spec) != n:
            raise ProblemError(f"{what} has {len(spec)} values, the plant's field has {n} nodes")
        out = np.broadcast_to(np.asarray(spec, dtype=float), shape).copy()
    else:
        out = np.full(shape, float(spec))
    if not np.all(np.isfinite(out)):
        raise ProblemError(f"{what} {spec!r} is not finite at every node")
    return out


# ------------------------------------------------------------------- recipes
@dataclass(frozen=True)
class Segment:
    """One recipe segment: steps with k dt in [start, end] [s] track `target` (a number, n_field
    values, or an expression in x, y, z, t) with weight q_k = `weight`; with a `band` it is a hold
    (the band test applies over it), without one a ramp (tracked by weight only)."""

    start: float
    end: float
    target: float | tuple[float, ...] | str
    band: float | None = None
    weight: float = 1.0

    KEYS = ("start", "end", "target", "band", "weight")

    def to_dict(self) -> dict[str, Any]:
        out = {"start": self.start, "end": self.end, "target": _encode(self.target), "weight": self.weight}
        if self.band is not None:
            out["band"] = self.band
        return out

    @classmethod
    def from_dict(cls, d: Any, source: str) -> "Segment":
        if isinstance(d, Segment):
            return d
        if not isinstance(d, Mapping):
            raise ProblemError(f"{source} must be a mapping of {', '.join(cls.KEYS)}, got {d!r}")
        unknown = sorted(str(k) for k in d if k not in cls.KEYS)
        if unknown:
            raise ProblemError(f"{source}: unknown key(s) {unknown}; segment keys: {list(cls.KEYS)}")
        for key in ("start", "end", "target"):
            if key not in d:
                raise ProblemError(f"{source}: missing key {key!r}")
        target = d["target"]
        if isinstance(target, str):
            try:
                evaluate_expression(target, {n: np.zeros(1) for n in "xyzt"})
            except ProblemError as exc:
                raise ProblemError(f"{source}: {exc}") from None
        elif isinstance(target, (list, tuple)):
            if not target:
                raise ProblemError(f"{source}: target must be a number, a non-empty list or an expression")
            target = tuple(_num(f"target[{i}]", x, source) for i, x in enumerate(target))
        else:
            target = _num("target", target, source)
        band = None if d.get("band") is None else _num("band", d["band"], source)
        seg = cls(_num("start", d["start"], source), _num("end", d["end"], source), target, band,
                  _num("weight", d.get("weight", 1.0), source))
        if not (math.isfinite(seg.start) and math.isfinite(seg.end) and 0 <= seg.start <= seg.end):
            raise ProblemError(f"{source}: need 0 <= start <= end (finite seconds), got {seg.start}, {seg.end}")
        if band is not None and not (math.isfinite(band) and band > 0):
            raise ProblemError(f"{source}: band must be a finite number > 0 (or absent: a ramp), got {band}")
        if not (math.isfinite(seg.weight) and seg.weight >= 0):
            raise ProblemError(f"{source}: weight must be a finite number >= 0, got {seg.weight}")
        if isinstance(target, (float, tuple)) and not all(math.isfinite(v) for v in np.atleast_1d(target)):
            raise ProblemError(f"{source}: target must be finite")
        return seg


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


_VECTORS = ("w_std", "v_std", "u_min", "u_max", "u_init", "du_max")
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
    if key == "recipe":
        if v is None:
            return None
        if not isinstance(v, (list, tuple)) or not v:
            raise ProblemError(f"{source}: recipe must be a non-empty list of segments, got {v!r}")
        return tuple(Segment.from_dict(seg, f"{source}: recipe segment {i}") for i, seg in enumerate(v))
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
            evaluate_expression(t, {n: np.zeros(1) for n in "xyzt"})
        except ProblemError as exc:
            yield str(exc)
    dm = p.du_max if isinstance(p.du_max, tuple) else (p.du_max,)
    if any(math.isnan(v) or not v > 0 for v in dm):
        yield f"du_max must be > 0 (inf: no rate limit; got {p.du_max!r})"
    if p.recipe is not None:
        for i in range(1, len(p.recipe)):
            if p.recipe[i].start < p.recipe[i - 1].end - 1e-12 * max(1.0, abs(p.recipe[i - 1].end)):
                yield (f"recipe segments must be in time order without overlap (segment {i} starts at "
                       f"{p.recipe[i].start:g} s, before segment {i - 1} ends at {p.recipe[i - 1].end:g} s)")
        if all(seg.band is None for seg in p.recipe):
            yield "a recipe needs at least one hold segment (a segment with a band)"
        if p.lqr_weighting == "field" and p.lqr_field_time == "objective":
            yield ("lqr_field_time: objective is not available with a recipe (its weights are in seconds, "
                   "the LQR's schedule in steps); use lqr_field_time: lqr")
