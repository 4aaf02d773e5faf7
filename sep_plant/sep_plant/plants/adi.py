"""Batched tridiagonal line solves and Douglas ADI splitting for grid plants (1-D, 2-D, 3-D).

Semi-discrete system (method of lines) on a regular vertex-centred grid, a batch of M fields
T of shape (M, n_1, ..., n_d)::

    dT/dt = F(T) = sum_a A_a(T) T + g(T)

A_a(T) T is the flux-form diffusion along axis a, d/dx_a (K dT/dx_a), with the conductivity K
(a field, e.g. K(T), or a constant) evaluated at the nodes and averaged onto the faces,
K_{i+1/2} = (K_i + K_{i+1})/2. Every face of the box is either insulated (zero flux: a node on
the face and a ghost node mirroring its neighbour, T_{-1} = T_1) or held at a value (Dirichlet:
the face node is known and eliminated from the unknowns). g(T) is everything pointwise:
sources, losses, reactions.

One step (linearly implicit Euler, coefficients frozen at T_k; the slab's backward Euler)::

    (D - dt sum_a A_a(T_k)) Delta = dt F(T_k),      T_{k+1} = T_k + Delta,
    D = I + dt diag(lambda),   lambda = -dg/dT at T_k  (the implicit part of g; D > 0)

and its Douglas (delta-form) ADI factorization, solved as one line solve per axis::

    (D - dt A_1) D^-1 (D - dt A_2) D^-1 ... (D - dt A_d) Delta = dt F(T_k)
    Delta_1 = (D - dt A_1)^-1 dt F(T_k),   Delta_a = (D - dt A_a)^-1 D Delta_{a-1},   Delta = Delta_d

Why Douglas, theta = 1 (and not Peaceman-Rachford):

* It is the slab's scheme, split: in 1-D it *is* the slab's backward Euler, and for a field that
  is uniform along the other (insulated) axes A_a Delta = 0 there, so a 2-D/3-D plant reproduces
  the 1-D solution exactly (tested).
* Steady states are exact: the splitting error dt^2 A_a D^-1 A_b Delta acts on Delta, so it
  vanishes where F(T) = 0; a held target is not shifted by the split. Errors are first order
  in dt like the unsplit step (the splitting adds O(dt^2) per step).
* Unconditionally stable in 2-D and 3-D, and damping: for commuting A_a with eigenvalues
  z_a = dt mu_a <= 0 (D = I) the amplification is 1 + sum z_a / prod (1 - z_a), in (0, 1]:
  no oscillation, stiff modes are damped to 0 (L-stable like backward Euler). Peaceman-
  Rachford is second order only in 2-D with a linear operator (lost anyway with coefficients
  frozen at T_k), has no unconditionally stable 3-D form, and its stiff-mode factor tends to
  -1: grid-scale ringing at dt k0/h^2 ~ 10, which sensors and the identification would see.
* Each factor D - dt A_a is a row-diagonally dominant M-matrix (D > 0): every line solve is
  stable without pivoting; with D = I an insulated box conserves sum_i w_i T_i (quadrature
  weights w) through every stage, to round-off, since w^T A_a = 0.

Line solves, batched: every line of every run along axis a is an independent tridiagonal
system, and all of them are solved at once, with no loop over runs or lines:

* "lapack": scaled by the trapezoid weights, W (D - dt A_a) is symmetric positive definite
  (the ghost node's factor 2 is what makes A_a itself unsymmetric), so all lines go into ONE
  LAPACK dptsv call (L D L^T without pivoting; about 2x faster than the general dgtsv that
  slab.py uses) on the flattened systems, uncoupled by a zero off-diagonal at every line end:
  the result is bitwise that of the lines solved one by one. dptsv needs the line axis
  contiguous, so for every axis but the last, T and the stage right-hand side are transposed
  (np.moveaxis + copy, ~1-2 ns per node each).
* "thomas": the Thomas algorithm vectorized over all lines of all runs, in place along a
  non-contiguous axis (a Python loop over the n_a points of a line, 9 numpy operations on the
  M N / n_a other points, which are contiguous blocks; no transposes, no pivoting).
* "pcr": parallel cyclic reduction (`solve_pcr`), log2(n_a) whole-array levels, any array
  module: what a GPU state (CuPy) is solved with, since LAPACK runs on the host only ("auto" and
  "lapack" mean "pcr" there). On the CPU 2-4x slower than the default (O(n log n) work).
* "auto" (default): dptsv along the last axis, and along the others while the lines are few
  (M N / n_a < THOMAS_MIN_LINES = 2048), Thomas from there on. Measured (one core, ns per
  node-step, all-dptsv / all-Thomas): the crossover is near 1500-2000 lines (50^2 x 8 runs,
  400 lines: 76 / 116; 50^2 x 32, 1600 lines: 83 / 82; 24^3 x 4, 2304 lines: 111 / 92).
  bench/bench_plants.py --solvers (one run on a shared machine, +-15 %), auto / lapack /
  thomas: one run, auto = lapack and Thomas 1.3-4x
  slower (plate 64^2: 69 / 69 / 273); 64 runs: plate 64^2 38 / 48 / 48, plate 128^2
  58 / 71 / 76, block 24^3 82 / 101 / 93, Allen-Cahn 50^2 38 / 44 / 39.

Cost of one step per node (d axes): the explicit F(T_k) ~5 passes per axis, each factor's
coefficients 3 passes, the weighted right-hand side 1-2, the dptsv solve ~10-13 ns; no loop over
runs or over lines anywhere. Pure numpy/scipy; every function also runs on a numpy-compatible GPU
module (`backend.namespace` of the state).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy.linalg import lapack

from sep_plant.plants.backend import DeviceConstants, namespace

#: face names in axis order: axis a has faces FACES[2a] (low) and FACES[2a + 1] (high)
FACES = ("x_min", "x_max", "y_min", "y_max", "z_min", "z_max")

SOLVERS = ("auto", "lapack", "thomas", "pcr")

#: "auto": Thomas along a non-contiguous axis from this many lines (M N / n_a) on; below it,
#: numpy's per-call overhead of the n_a-step sweep costs more than dptsv's transposes
THOMAS_MIN_LINES = 2048


# ------------------------------------------------------------------------------ grid
@dataclass(frozen=True)
class Axis:
    """One axis of a vertex-centred grid: n unknown nodes on [0, length] [m].

    An insulated face has a node on it (ghost node outside); a held face's node is known
    and eliminated. So the spacing is h = length / (n - 1 + held_lo + held_hi) and the
    unknowns sit at x_i = (i + held_lo) h (the slab: insulated at 0, held at L, x_i = i L/n).
    """

    n: int
    length: float
    held_lo: bool = False
    held_hi: bool = False

    @property
    def h(self) -> float:
        return self.length / (self.n - 1 + int(self.held_lo) + int(self.held_hi))

    def nodes(self) -> np.ndarray:
        """Positions of the unknowns [m]."""
        return (np.arange(self.n) + int(self.held_lo)) * self.h

    def weights(self) -> np.ndarray:
        """Trapezoid weights (in units of h): 1/2 on an insulated face's node, else 1."""
        w = np.ones(self.n)
        if not self.held_lo:
            w[0] = 0.5
        if not self.held_hi:
            w[-1] = 0.5
        return w


class Grid:
    """A box of 1-3 axes (C order: the last axis varies fastest)."""

    def __init__(self, axes: Sequence[Axis]):
        if not 1 <= len(axes) <= 3 or any(a.n < 2 for a in axes):
            raise ValueError(f"a grid has 1-3 axes of >= 2 nodes, got {axes!r}")
        self.axes = tuple(axes)
        self.ndim = len(self.axes)
        self.shape = tuple(a.n for a in self.axes)
        self.size = int(np.prod(self.shape))
        self.h = tuple(a.h for a in self.axes)
        self.cell_volume = float(np.prod(self.h))      # h_1 ... h_d [m^d]
        self.device = DeviceConstants()                  # the axes' weights on a GPU module

    def weights(self) -> np.ndarray:
        """Quadrature weights w (shape): sum_i w_i f_i * cell_volume ~ integral of f over the box
        (exact for the discrete heat balance of an insulated box)."""
        w = np.ones(())
        for a in self.axes:
            w = np.multiply.outer(w, a.weights())
        return w

    def node_axes(self) -> tuple[np.ndarray, ...]:
        return tuple(a.nodes() for a in self.axes)

    def coordinates(self) -> np.ndarray:
        """(size, 3) x, y, z of every unknown in C order [m] (missing axes are 0)."""
        mesh = np.meshgrid(*self.node_axes(), indexing="ij")
        xyz = np.zeros((self.size, 3))
        for i, m in enumerate(mesh):
            xyz[:, i] = m.ravel()
        return xyz

    def nearest_nodes(self, fractions: Sequence[Sequence[float]]) -> np.ndarray:
        """Flat index of the unknown nearest each point (coordinates as fractions of the sides)."""
        out = []
        for p in fractions:
            idx = tuple(int(np.argmin(np.abs(ax.nodes() - f * ax.length))) for f, ax in zip(p, self.axes))
            out.append(int(np.ravel_multi_index(idx, self.shape)))
        return np.array(out, dtype=int)

    def gaussians(self, centers: Sequence[Sequence[float]], sigma: float) -> np.ndarray:
        """exp(-|x - c_j|^2 / 2 s^2) per axis (c_j and s as fractions of each side), (size, n_c);
        unnormalized (1 at the centre point)."""
        cols = []
        for c in centers:
            g = np.ones(())
            for f, ax in zip(c, self.axes):
                s = sigma * ax.length
                g = np.multiply.outer(g, np.exp(-0.5 * ((ax.nodes() - f * ax.length) / s) ** 2))
            cols.append(g.ravel())
        return np.stack(cols, axis=1)


# ------------------------------------------------------------------------------ boundary data
@dataclass(frozen=True)
class Held:
    """A held (Dirichlet) face: its value and the conductivity there (K at the value)."""

    value: float
    conductivity: float


def held_faces(grid: Grid, held: Mapping[str, Held]) -> list[tuple[Held | None, Held | None]]:
    """Per axis (low, high) held data, checked against the grid's axes."""
    out = []
    for a, ax in enumerate(grid.axes):
        lo, hi = held.get(FACES[2 * a]), held.get(FACES[2 * a + 1])
        if (lo is not None) != ax.held_lo or (hi is not None) != ax.held_hi:
            raise ValueError(f"held faces {sorted(held)} do not match axis {a} of the grid")
        out.append((lo, hi))
    return out


# ------------------------------------------------------------------------------ one axis
def _lines(x: np.ndarray | float, axis: int, contiguous: bool) -> np.ndarray | float:
    """View (or contiguous copy) of a batch field (M, *shape) with grid axis `axis` last."""
    if np.ndim(x) == 0:
        return x
    xp = namespace(x)
    v = xp.moveaxis(x, axis + 1, -1)
    return xp.ascontiguousarray(v) if contiguous else v


def _unlines(x: np.ndarray, axis: int) -> np.ndarray:
    return namespace(x).moveaxis(x, -1, axis + 1)


class AxisOperator:
    """A_a in line-last layout (..., n): face coefficients c_{i+1/2} = K_{i+1/2} / h^2 of the
    n - 1 inner faces (stored as c[..., i], with c[..., n-1] = 0) and of the held end faces.

        (A_a T)_i = c_{i+1/2} (T_{i+1} - T_i) - c_{i-1/2} (T_i - T_{i-1})

    Insulated end: the ghost node doubles the inner face, e.g. (A T)_0 = 2 c_{1/2} (T_1 - T_0).
    Held end: T_{-1} is the held value, c_{-1/2} = (K_0 + K_held)/2 / h^2.
    `like` fixes shape and memory layout of every array built (contiguous lines for dptsv,
    a moveaxis view's layout for Thomas).
    """

    def __init__(self, K: np.ndarray | float, like: np.ndarray, h: float, lo: Held | None, hi: Held | None):
        half = 0.5 / (h * h)
        xp = self.xp = namespace(like)
        c = xp.empty_like(like)
        if np.ndim(K) == 0:
            c[..., :-1] = 2.0 * half * float(K)
        else:
            xp.add(K[..., 1:], K[..., :-1], out=c[..., :-1])
            c[..., :-1] *= half
        c[..., -1] = 0.0
        self.c = c
        self.lo, self.hi = lo, hi
        self.c_lo = None if lo is None else half * (K[..., 0] + lo.conductivity if np.ndim(K) else
                                                    float(K) + lo.conductivity)
        self.c_hi = None if hi is None else half * (K[..., -1] + hi.conductivity if np.ndim(K) else
                                                    float(K) + hi.conductivity)

    def apply(self, T: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """out += A_a T (..., n), held values included; a new array when out is None. 4 passes."""
        q = self.xp.subtract(T[..., 1:], T[..., :-1])
        q *= self.c[..., :-1]                                             # c_{i+1/2} (T_{i+1} - T_i)
        if out is None:
            out = self.xp.zeros_like(self.c)
        out[..., :-1] += q
        out[..., 1:] -= q
        if self.lo is None:
            out[..., 0] += q[..., 0]                                      # ghost node
        else:
            out[..., 0] += self.c_lo * (self.lo.value - T[..., 0])
        if self.hi is None:
            out[..., -1] -= q[..., -1]
        else:
            out[..., -1] += self.c_hi * (self.hi.value - T[..., -1])
        return out

    def system(self, D: np.ndarray | float, dt: float, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """W (D - dt A_a) as a symmetric tridiagonal (diag, off), laid out like the coefficients
        (..., n); off[..., i] couples nodes i and i+1, off[..., -1] = 0 (lines uncoupled).

        W = diag(w), the trapezoid weights of the axis (1/2 on an insulated end's node): the
        ghost node makes A_a itself unsymmetric (row 0 is 2 c (T_1 - T_0)), W A_a is symmetric,
        and W (D - dt A_a) is symmetric positive definite (D > 0, diagonally dominant): the
        right-hand side is multiplied by w and the solve needs no pivoting. 3 passes.
        """
        xp = self.xp
        off = xp.multiply(self.c, -dt)                                    # -dt c_{i+1/2}
        diag = xp.subtract(w * D, off, out=xp.empty_like(off))
        diag[..., 1:] -= off[..., :-1]                                   # w D + dt (c_{i-1/2} + c_{i+1/2})
        if self.lo is not None:
            diag[..., 0] += dt * self.c_lo
        if self.hi is not None:
            diag[..., -1] += dt * self.c_hi
        return diag, off


# ------------------------------------------------------------------------------ line solvers
def solve_lapack(diag: np.ndarray, off: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """All symmetric positive definite tridiagonal systems along the last axis in one LAPACK
    call (dptsv: L D L^T, no pivoting; inputs consumed). Arrays (..., n), C-contiguous,
    off[..., -1] = 0 so that no line couples to the next: the result is bitwise that of the
    lines solved one by one. About 2x faster than the general dgtsv (bench_plants.py)."""
    shape = rhs.shape
    _, _, x, info = lapack.dptsv(diag.reshape(-1), off.reshape(-1)[:-1], rhs.reshape(-1),
                                 overwrite_d=1, overwrite_e=1, overwrite_b=1)
    if info != 0:
        raise FloatingPointError(f"tridiagonal line solve failed (LAPACK dptsv info {info}): "
                                 "non-finite state or input, or a non-positive conductivity?")
    return x.reshape(shape)


def solve_thomas(diag: np.ndarray, off: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The same systems by the Thomas algorithm, vectorized over the leading axes (any strides:
    a moveaxis view of a C array, whose slices [..., i] are contiguous blocks, is the fast
    case). No pivoting (positive definite). Cost: 9 numpy operations per point of a line."""
    xp = namespace(rhs)
    n = rhs.shape[-1]
    cp = xp.empty_like(rhs)                               # rhs's memory layout: slices [..., i] stay blocks
    dp = xp.empty_like(rhs)
    m = xp.empty(cp.shape[:-1])
    t = xp.empty_like(m)
    xp.divide(1.0, diag[..., 0], out=m)
    xp.multiply(off[..., 0], m, out=cp[..., 0])
    xp.multiply(rhs[..., 0], m, out=dp[..., 0])
    for i in range(1, n):
        a = off[..., i - 1]
        xp.multiply(a, cp[..., i - 1], out=t)            # m = 1 / (b_i - a_i c'_{i-1})
        xp.subtract(diag[..., i], t, out=t)
        xp.divide(1.0, t, out=m)
        xp.multiply(off[..., i], m, out=cp[..., i])       # c'_i = c_i m
        xp.multiply(a, dp[..., i - 1], out=t)             # d'_i = (d_i - a_i d'_{i-1}) m
        xp.subtract(rhs[..., i], t, out=t)
        xp.multiply(t, m, out=dp[..., i])
    for i in range(n - 2, -1, -1):                        # x_i = d'_i - c'_i x_{i+1}
        xp.multiply(cp[..., i], dp[..., i + 1], out=t)
        xp.subtract(dp[..., i], t, out=dp[..., i])
    _check_finite(xp, dp[..., 0])
    return dp


def solve_pcr(sub: np.ndarray, diag: np.ndarray, sup: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Tridiagonal systems along the last axis by parallel cyclic reduction, on any array module.

    Row i of each line: sub_i x_{i-1} + diag_i x_i + sup_i x_{i+1} = rhs_i (sub[..., 0] and
    sup[..., -1] are ignored: the lines are uncoupled). Level s = 1, 2, 4, ... eliminates the
    couplings at distance s from every row at once::

        alpha_i = -a_i / b_{i-s},  gamma_i = -c_i / b_{i+s}      (0 where i -+ s is off the line)
        a_i <- alpha_i a_{i-s},  c_i <- gamma_i c_{i+s}
        b_i <- b_i + alpha_i c_{i-s} + gamma_i a_{i+s},  d_i <- d_i + alpha_i d_{i-s} + gamma_i d_{i+s}

    until s >= n, where every row is decoupled: x = d / b. ceil(log2 n) levels of ~14 whole-array
    operations: O(n log n) work, but no loop over the points of a line, which is what a GPU
    needs (Thomas makes n dependent passes; LAPACK runs on the host only). No pivoting: the
    plants' systems are diagonally dominant, which every level preserves. Inputs are not
    modified; any strides.
    """
    xp = namespace(rhs, diag)
    n = rhs.shape[-1]
    a = xp.array(sub, copy=True)
    c = xp.array(sup, copy=True)
    a[..., 0] = 0.0
    c[..., -1] = 0.0
    b = xp.array(diag, copy=True)
    d = xp.array(rhs, copy=True)
    s = 1
    while s < n:
        alpha = -a[..., s:] / b[..., :-s]                  # rows s..n-1 against row i - s
        gamma = -c[..., :-s] / b[..., s:]                  # rows 0..n-s-1 against row i + s
        a2 = xp.zeros_like(a)
        c2 = xp.zeros_like(c)
        a2[..., s:] = alpha * a[..., :-s]
        c2[..., :-s] = gamma * c[..., s:]
        b[..., s:] += alpha * c[..., :-s]                  # old c, a: a2, c2 are new arrays
        b[..., :-s] += gamma * a[..., s:]
        d2 = xp.array(d, copy=True)
        d2[..., s:] += alpha * d[..., :-s]
        d2[..., :-s] += gamma * d[..., s:]
        a, c, d = a2, c2, d2
        s *= 2
    x = d / b
    _check_finite(xp, x[..., 0])
    return x


def _check_finite(xp, x) -> None:
    """A numpy solve is checked here; a device one is not: the check is a host synchronization
    per line solve (on an H200, a third of the plant's step time), so a device state is checked
    once per step or per reduced result instead (`sep_plant.device.check_finite`)."""
    if xp is not np:
        return
    if not bool(xp.all(xp.isfinite(x))):
        raise FloatingPointError("tridiagonal line solve gave non-finite values: non-finite state "
                                 "or input, or a non-positive conductivity?")


def _solve_symmetric_pcr(diag: np.ndarray, off: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """The symmetric systems of `AxisOperator.system` (off[..., i] couples i and i+1) by PCR."""
    sub = namespace(off).empty_like(off)
    sub[..., 1:] = off[..., :-1]
    return solve_pcr(sub, diag, off, rhs)


def _use_lapack(solver: str, axis: int, grid: Grid, batch: int) -> bool:
    """dptsv along `axis`? ("auto": on the contiguous last axis, or when the lines are few)."""
    if solver != "auto":
        return solver == "lapack"
    return axis == grid.ndim - 1 or batch * grid.size // grid.shape[axis] < THOMAS_MIN_LINES


def _line_solver(solver: str, xp) -> str:
    """The solver a step uses: as asked on numpy; off the host (no LAPACK) "thomas" as asked,
    everything else parallel cyclic reduction."""
    if xp is np:
        return solver
    return "thomas" if solver == "thomas" else "pcr"


# ------------------------------------------------------------------------------ steps
#: conductivity at the nodes at T_k: a constant, an array broadcastable to the batch
#: (M or 1, *shape) (any spatial variation, e.g. K(x, T_k)), or a callable K(T) (pointwise; it
#: is evaluated on each axis's line layout of T, which spares the transposes of K)
Conductivity = Callable[[np.ndarray], np.ndarray] | np.ndarray | float


def _conductivity(K: Conductivity, T: np.ndarray, Tl: np.ndarray, axis: int,
                  contiguous: bool) -> np.ndarray | float:
    """K in the line layout of `axis` (Tl: T in that layout)."""
    if callable(K):
        return K(Tl)
    if np.ndim(K) == 0:
        return float(K)
    xp = namespace(T)
    return _lines(xp.broadcast_to(K if xp is np else xp.asarray(K), T.shape), axis, contiguous)


def diffusion(grid: Grid, T: np.ndarray, K: Conductivity, held: Mapping[str, Held]) -> np.ndarray:
    """sum_a A_a(T) T for a batch T (M, *shape): the flux-form diffusion (K: see Conductivity)."""
    faces = held_faces(grid, held)
    out = namespace(T).zeros_like(T, dtype=float)
    for a in range(grid.ndim):
        Tl = _lines(T, a, contiguous=False)
        op = AxisOperator(_conductivity(K, T, Tl, a, False), Tl, grid.h[a], *faces[a])
        out += _unlines(op.apply(Tl), a)
    return out


def douglas_step(grid: Grid, T: np.ndarray, K: Conductivity, held: Mapping[str, Held],
                 g: np.ndarray | float, lam: np.ndarray | float, dt: float,
                 solver: str = "auto") -> np.ndarray:
    """T_{k+1} for a batch T (M, *shape) by the Douglas ADI step of the module docstring.

    K: the conductivity (see Conductivity: constant, array or K(T)); held: {face: Held};
    g: the pointwise part of dT/dt at T_k, (M, *shape) or scalar; lam = -dg/dT at T_k (the
    implicit part), D = 1 + dt lam must be > 0. Returns a new array.

    Cost per node and axis: about 12 passes over the field plus the line solve ("lapack": the
    axis's transposes of T and of the stage right-hand side, 2 more, unless it is the last).
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
    xp = namespace(T)
    solver = _line_solver(solver, xp)
    faces = held_faces(grid, held)
    D = 1.0 + dt * lam if np.ndim(lam) else 1.0 + dt * float(lam)
    use_lapack = [_use_lapack(solver, a, grid, T.shape[0]) for a in range(grid.ndim)]
    ops = []
    rhs = xp.zeros_like(T, dtype=float)
    rhs += g                                                              # F(T_k) = g + sum_a A_a T
    for a in range(grid.ndim):
        Tl = _lines(T, a, contiguous=use_lapack[a])
        op = AxisOperator(_conductivity(K, T, Tl, a, use_lapack[a]), Tl, grid.h[a], *faces[a])
        op.apply(Tl, out=_lines(rhs, a, contiguous=False))
        ops.append(op)
    rhs *= dt
    delta = rhs
    for a, op in enumerate(ops):
        w = grid.device.get(xp, f"w{a}", grid.axes[a].weights)
        rl = _lines(delta, a, contiguous=use_lapack[a])          # our own array (or a copy): scaled in place
        if a > 0:                                          # W D Delta_{a-1}; a = 0: W dt F(T_k)
            rl *= _lines(D, a, contiguous=False) if np.ndim(D) else D
        rl *= w
        diag, off = op.system(_lines(D, a, contiguous=False), dt, w)
        solve = (solve_lapack if use_lapack[a] else
                 _solve_symmetric_pcr if solver == "pcr" else solve_thomas)
        delta = _unlines(solve(diag, off, rl), a)
    return T + delta


def axes_for(shape: Sequence[int], lengths: Sequence[float], held: Mapping[str, object]) -> Grid:
    """The grid whose faces named in `held` are held (Dirichlet), all others insulated."""
    return Grid([Axis(int(n), float(L), FACES[2 * a] in held, FACES[2 * a + 1] in held)
                 for a, (n, L) in enumerate(zip(shape, lengths))])


__all__ = ["Axis", "AxisOperator", "FACES", "Grid", "Held", "SOLVERS", "axes_for", "diffusion",
           "douglas_step", "held_faces", "solve_lapack", "solve_pcr", "solve_thomas"]


def rk4(rhs, x: np.ndarray, u: np.ndarray, horizon: float, h: float) -> np.ndarray:
    """Reference integrator for checking the schemes: classical RK4 of the semi-discrete system
    dx/dt = rhs(x, u) over `horizon` with steps of at most h (independent of the ADI split)."""
    n = int(np.ceil(horizon / h))
    h = horizon / n
    for _ in range(n):
        k1 = rhs(x, u)
        k2 = rhs(x + 0.5 * h * k1, u)
        k3 = rhs(x + 0.5 * h * k2, u)
        k4 = rhs(x + h * k3, u)
        x = x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return x
