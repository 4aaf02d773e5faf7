"""Model Exchange FMUs stepped by sep: classical RK4 over a batch, one FMU instance for all runs.

The state of run m is the FMU's continuous-state vector x_m (float64). One plant step holds the
inputs v_m over dt and takes `substeps` classical RK4 steps of size tau = dt / substeps:

    k1 = f(x, v),  k2 = f(x + (tau/2) k1, v),  k3 = f(x + (tau/2) k2, v),  k4 = f(x + tau k3, v),
    x <- x + (tau/6) (k1 + 2 k2 + 2 k3 + k4),

where f(x, v) is the FMU's derivative function. A stage is a sweep over the runs with the ONE
instance: for run m, set its continuous states and inputs, get its derivatives (three C calls;
two when every run has the same inputs, which are then set once per step). The stage
arithmetic is numpy over the whole batch, in the same order of operations as the C code of the
example rod's Co-Simulation doStep, so both give the same numbers. The model must not depend on
time explicitly: sep's step is time-invariant, and the FMU's time stays at the start time.

Buffers and the per-run ctypes arguments (pointers into their rows) are built once per batch
size (`Workspace`), so a sweep allocates nothing. Pure numpy/ctypes: no ROS import.
"""
from __future__ import annotations

from collections import OrderedDict
from ctypes import c_size_t, c_void_p

import numpy as np

from sep_plant.plants.fmu.binding import WARNING, Binding, refs_array

#: workspaces (batch sizes) kept per stepper
KEEP_WORKSPACES = 4


def row_pointers(A: np.ndarray) -> list[c_void_p]:
    """A c_void_p to each row of a C-contiguous 2-D array."""
    base, stride = A.ctypes.data, A.strides[0]
    return [c_void_p(base + i * stride) for i in range(A.shape[0])]


class Workspace:
    """Stage buffers of a batch of M runs and the C arguments that point into them."""

    def __init__(self, b: Binding, M: int, n: int, n_in: int, in_refs) -> None:
        self.T, self.Y, self.acc = np.empty((M, n)), np.empty((M, n)), np.empty((M, n))
        self.K = [np.empty((M, n)) for _ in range(4)]
        self.V = np.empty((M, max(n_in, 1)))
        nc = c_size_t(n)
        self.on_T = [(b.c, p, nc) for p in row_pointers(self.T)]
        self.on_Y = [(b.c, p, nc) for p in row_pointers(self.Y)]
        self.into_K = [[(b.c, p, nc) for p in row_pointers(K)] for K in self.K]
        self.inputs = [b.values_args(in_refs, n_in, n_in, p) for p in row_pointers(self.V)]


class ExchangeStepper:
    """Batched fixed-step RK4 of a Model Exchange FMU (see the module docstring).

    Parameters
    ----------
    binding : the instance (in continuous-time mode).
    n_x : number of continuous states.
    input_refs : value references of the inputs set each step, in the columns' order of `V`.
    dt : plant step [s].
    substeps : RK4 steps per plant step.
    completed_step : call fmi2/3CompletedIntegratorStep after each RK4 step (the FMU asks for it).
    """

    def __init__(self, binding: Binding, n_x: int, input_refs: list[int], dt: float, substeps: int,
                 completed_step: bool) -> None:
        self.b = binding
        self.n_x = int(n_x)
        self.n_in = len(input_refs)
        self._in_refs = refs_array(input_refs)
        self.dt = float(dt)
        self.substeps = int(substeps)
        self.completed_step = bool(completed_step)
        self._spaces: OrderedDict[int, Workspace] = OrderedDict()

    def workspace(self, M: int) -> Workspace:
        ws = self._spaces.pop(M, None)
        if ws is None:
            ws = Workspace(self.b, M, self.n_x, self.n_in, self._in_refs)
        self._spaces[M] = ws
        while len(self._spaces) > KEEP_WORKSPACES:
            self._spaces.popitem(last=False)
        return ws

    def step(self, X: np.ndarray, V: np.ndarray) -> np.ndarray:
        """x_{k+1} of every run: X (M, n_x), V (M, n_in) or (1, n_in) held over dt -> (M, n_x)."""
        M = X.shape[0]
        ws = self.workspace(M)
        T, Y, acc, (K1, K2, K3, K4) = ws.T, ws.Y, ws.acc, ws.K
        T[...] = X
        shared = V.shape[0] == 1
        if shared:
            ws.V[0] = V[0]
            st = self.b.set_reals(*ws.inputs[0])
            if st > WARNING:
                raise self.b.fail("setting the inputs", st)
        else:
            ws.V[...] = V
        tau = self.dt / self.substeps
        half, sixth = 0.5 * tau, tau / 6.0
        for _ in range(self.substeps):
            self._sweep(ws.on_T, ws.into_K[0], ws.inputs, shared)
            np.multiply(K1, half, out=Y)
            Y += T
            self._sweep(ws.on_Y, ws.into_K[1], ws.inputs, shared)
            np.multiply(K2, half, out=Y)
            Y += T
            self._sweep(ws.on_Y, ws.into_K[2], ws.inputs, shared)
            np.multiply(K3, tau, out=Y)
            Y += T
            self._sweep(ws.on_Y, ws.into_K[3], ws.inputs, shared)
            np.multiply(K2, 2.0, out=acc)                 # (((k1 + 2 k2) + 2 k3) + k4) tau/6, as in C
            acc += K1
            np.multiply(K3, 2.0, out=Y)
            acc += Y
            acc += K4
            acc *= sixth
            T += acc
            if self.completed_step:
                self.b.completed_step()
        return T.copy()           # non-finite (an unstable substep) like any plant's: callers judge

    def _sweep(self, states, into, inputs, shared: bool) -> None:
        """One RK4 stage: derivatives of every run (the hot loop: C calls only)."""
        set_x, get_dx, set_v = self.b.set_states, self.b.get_derivatives, self.b.set_reals
        st = 0
        if shared:
            for a, d in zip(states, into):
                st |= set_x(*a) | get_dx(*d)
        else:
            for a, v, d in zip(states, inputs, into):
                st |= set_x(*a) | set_v(*v) | get_dx(*d)
        if st > WARNING:            # statuses OR-ed: above 1 only when some call returned >= discard
            raise self.b.fail("computing derivatives (set states / set inputs / get derivatives)", st)

    def read(self, X: np.ndarray, refs: list[int], n_values: int) -> np.ndarray:
        """Variables `refs` at the states X (M, n_x) -> (M, n_values): set states, get reals."""
        X = np.ascontiguousarray(X, dtype=float)
        out = np.empty((X.shape[0], n_values))
        refs_c = refs_array(refs)
        nc = c_size_t(self.n_x)
        set_x, get = self.b.set_states, self.b.get_reals
        st = 0
        for px, po in zip(row_pointers(X), row_pointers(out)):
            st |= set_x(self.b.c, px, nc) | get(*self.b.values_args(refs_c, len(refs), n_values, po))
        if st > WARNING:
            raise self.b.fail("reading outputs (set states / get reals)", st)
        return out


__all__ = ["ExchangeStepper", "Workspace", "row_pointers"]
