"""The nonlinear heat slab as a batched black-box simulator.

    T_{k+1} - T_k = dt [ K(x, T_k) D2 T_{k+1} - eta T_{k+1} + B (u_k + w_k) ]   (backward Euler,
                                                                                K frozen at T_k)
    y_k = T_k[sensor nodes] + v_k

D2 is the second difference with an insulated left end (ghost node T_{-1} = T_1) and the
Dirichlet right end T(L) = T_right eliminated. One step is one tridiagonal solve; a batch
of M runs is one tridiagonal solve of size M n_x (LAPACK gtsv, blocks uncoupled), which
costs tens of nanoseconds per node-step instead of tens of microseconds per run-step.

The offline design only calls `initial_state`, `step`, `observe` (and reads the state
as a field snapshot): it never sees K, D2 or B. Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .scenario import Scenario


class SlabSimulator:
    """Batched simulator of one `Scenario`.

    States are arrays (M, n_x) (a single state (n_x,) is accepted and returned as such);
    inputs (M, n_u); outputs (M, n_y).
    """

    def __init__(self, scenario: Scenario):
        self.scenario = s = scenario
        self.n_x, self.n_u, self.n_y, self.dt = s.n_x, s.n_u, s.n_y, s.dt
        self._x = s.grid()
        self._space = 1.0 + s.gamma * self._x / s.length          # (1 + gamma x/L)
        self._b_dt = s.dt * s.heater_profiles()                    # dt b_j(x_i), (n_x, n_u)
        self._sensors = s.sensor_nodes()
        self._c_scale = s.dt * s.k0 / s.h**2                       # dt k0 / h^2
        self._diag0 = 1.0 + s.dt * s.eta
        self._bc = s.t_right

    # ------------------------------------------------------------------ API
    def initial_state(self, batch: int | None = None) -> np.ndarray:
        """T(x, 0) = t_init everywhere; (n_x,) or (batch, n_x)."""
        x0 = np.full(self.n_x, self.scenario.t_init)
        return x0 if batch is None else np.tile(x0, (batch, 1))

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Advance one step: x_{k+1} = f(x_k, u_k + w_k) for every run of the batch."""
        single = x.ndim == 1
        X = np.atleast_2d(x)
        U = np.atleast_2d(u)
        if w is not None:
            U = U + np.atleast_2d(w)
        M, n = X.shape
        if n != self.n_x or U.shape[-1] != self.n_u:
            raise ValueError(f"step: expected states (*, {self.n_x}) and inputs (*, {self.n_u}), "
                             f"got {X.shape} and {U.shape}")
        if U.shape[0] != M:
            U = np.broadcast_to(U, (M, self.n_u))
        s = self.scenario
        # c_i = dt K(x_i, T_i) / h^2
        c = self._c_scale * (1.0 + s.beta * (X - s.t_ref) / s.t_scale) * self._space
        d = self._diag0 + 2.0 * c
        du = -c.copy()
        du[:, 0] *= 2.0               # ghost node: row 0 is (2 T_1 - 2 T_0) / h^2
        du[:, -1] = 0.0               # no coupling between runs
        dl = np.empty_like(c)
        dl[:, :-1] = -c[:, 1:]
        dl[:, -1] = 0.0
        rhs = X + U @ self._b_dt.T
        rhs[:, -1] += c[:, -1] * self._bc
        _, _, _, sol, info = lapack.dgtsv(dl.ravel()[:-1], d.ravel(), du.ravel()[:-1], rhs.ravel(),
                                          overwrite_dl=1, overwrite_d=1, overwrite_du=1, overwrite_b=1)
        if info != 0:
            raise FloatingPointError(f"tridiagonal solve failed (LAPACK info {info}): "
                                     "non-finite state or input?")
        out = sol.reshape(M, n)
        return out[0] if single else out

    def observe(self, x: np.ndarray) -> np.ndarray:
        """Noise-free sensor outputs h(x): temperatures at the sensor nodes."""
        return x[..., self._sensors]

    def rollout(self, x0: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Simulate T steps for a batch: x0 (M, n_x), u (M, T, n_u) or (T, n_u) -> (M, T+1, n_x)."""
        X0 = np.atleast_2d(x0)
        M = X0.shape[0]
        U = np.broadcast_to(u, (M,) + u.shape[-2:]) if u.ndim == 2 else u
        T = U.shape[1]
        out = np.empty((M, T + 1, self.n_x))
        out[:, 0] = X0
        for k in range(T):
            out[:, k + 1] = self.step(out[:, k], U[:, k], None if w is None else w[:, k])
        return out


def clip_inputs(u: np.ndarray, scenario: Scenario) -> np.ndarray:
    """Heater limits [u_min, u_max] (a no-op at the reference's infinite limits)."""
    if np.isinf(scenario.u_min) and np.isinf(scenario.u_max):
        return u
    return np.clip(u, scenario.u_min, scenario.u_max)
