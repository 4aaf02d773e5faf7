"""The paper's plant: the nonlinear 1-D heat slab as a batched black-box simulator.

    dT/dt = K(x,T) T_xx - eta T + sum_j b_j(x) (u_j + w_j) + s,
    K(x,T) = k0 (1 + beta (T - t_ref)/t_scale)(1 + gamma x/L),
    dT/dx(0) = 0 (insulated), T(L) = t_right, T(x, 0) = t_init;   y = T(sensor nodes) + v.

Backward Euler with K frozen at T_k:
    T_{k+1} - T_k = dt [ K(x, T_k) D2 T_{k+1} - eta T_{k+1} + B (u_k + w_k) ]
D2 is the second difference with an insulated left end (ghost node T_{-1} = T_1) and the
Dirichlet right end T(L) = t_right eliminated. One step is one tridiagonal solve; a batch of
M runs is one tridiagonal solve of size M n_x (LAPACK gtsv, blocks uncoupled), which costs
tens of nanoseconds per node-step instead of tens of microseconds per run-step.

Nodes x_i = i L / n_x (i = 0..n_x-1) in metres; five Gaussian heaters (each integrating to 1
over the slab) and five sensors at the nodes nearest their positions, by default.

Optional keys (off by default, the reference unchanged): `source` s, a constant heat source
spread uniformly over the slab [F/s] (a truth key: an unmodelled distributed forcing), and
`noise_centers` (with `noise_sigma`), process noise through channels of its own: n_w Gaussian
profiles e_l(x) (each integrating to 1) instead of the heaters,
    ... + sum_j b_j(x) u_j + sum_l e_l(x) w_l + s        (noise_on_inputs false, n_w channels).
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy.linalg import lapack

from sep_plant.plants import adi, blocks, keys
from sep_plant.initial import offset_states, spread_key
from sep_plant.plants.backend import DeviceConstants, namespace


class SlabPlant:
    """The heat slab of docs/method.md (the plant protocol of `sep_plant.protocol`)."""

    field_name = "temperature"
    field_unit = "F"
    field_is_state = True
    noise_on_inputs = True
    #: step() accepts CuPy arrays and steps them on their GPU (`sep_plant.device`)
    device_capable = True
    #: a batch is stepped in blocks of at most this many nodes (`blocks.step_in_blocks`)
    block_nodes = blocks.BLOCK_NODES

    def __init__(self, n_x: int = 100, length: float = 1.0, k0: float = 0.01, beta: float = 0.5,
                 gamma: float = 0.2, t_ref: float = 100.0, t_scale: float = 50.0, eta: float = 0.002,
                 t_right: float = 150.0, t_init: float = 100.0,
                 heater_centers: Sequence[float] = (0.1, 0.3, 0.5, 0.7, 0.9), heater_sigma: float = 0.02,
                 sensor_positions: Sequence[float] = (0.1, 0.3, 0.5, 0.7, 0.9), dt: float = 0.25,
                 initial_spread: float = 0.0, source: float = 0.0,
                 noise_centers: Sequence[float] | None = None, noise_sigma: float | None = None):
        self.n_x = keys.integer("n_x", n_x, lo=4)
        self.length = keys.positive("length", length)
        self.k0 = keys.positive("k0", k0)
        self.beta = keys.number("beta", beta)
        self.gamma = keys.number("gamma", gamma)
        self.t_ref = keys.number("t_ref", t_ref)
        self.t_scale = keys.positive("t_scale", t_scale)
        self.eta = keys.number("eta", eta, lo=0.0)
        self.t_right = keys.number("t_right", t_right)
        self.t_init = keys.number("t_init", t_init)
        self.heater_centers = keys.numbers("heater_centers", heater_centers, lo=0.0, hi=1.0)
        self.heater_sigma = keys.positive("heater_sigma", heater_sigma)
        self.sensor_positions = keys.numbers("sensor_positions", sensor_positions, lo=0.0, hi=1.0)
        self.dt = keys.positive("dt", dt)
        self.initial_spread = keys.number("initial_spread", initial_spread, lo=0.0)
        self.source = keys.number("source", source)
        self.noise_centers = None if noise_centers is None else keys.numbers("noise_centers", noise_centers,
                                                                             lo=0.0, hi=1.0)
        self.noise_sigma = None if noise_sigma is None else keys.positive("noise_sigma", noise_sigma)
        for temp in (self.t_init, self.t_right):
            if 1 + self.beta * (temp - self.t_ref) / self.t_scale <= 0 or 1 + self.gamma <= 0:
                raise keys.PlantConfigError(f"K(x,T) is not positive at T = {temp:g}: check "
                                            "beta/gamma/t_ref/t_scale")
        self.n_u = len(self.heater_centers)
        self.n_y = len(self.sensor_positions)
        self.n_field = self.n_x
        self.input_names = tuple(f"heater_{j}" for j in range(self.n_u))
        self.output_names = tuple(f"sensor_{j}" for j in range(self.n_y))
        self.h = self.length / self.n_x
        x = np.arange(self.n_x) * self.h
        self._x = x
        self._sensors = np.array([int(np.argmin(np.abs(x - p * self.length))) for p in self.sensor_positions])
        keys.distinct("sensor_positions", list(self._sensors))
        self._space = 1.0 + self.gamma * x / self.length                 # (1 + gamma x/L)
        self._b_dt = self.dt * self.heater_profiles()                     # dt b_j(x_i), (n_x, n_u)
        if self.noise_centers is not None:                                # own noise channels: U = [u, w]
            self.noise_on_inputs = False
            self.n_w = len(self.noise_centers)
            sig = self.heater_sigma if self.noise_sigma is None else self.noise_sigma
            self._b_dt = np.concatenate([self._b_dt, self.dt * self._gaussians(self.noise_centers, sig)], axis=1)
        self._src_dt = self.dt * self.source
        self._c_scale = self.dt * self.k0 / self.h**2                     # dt k0 / h^2
        self._diag0 = 1.0 + self.dt * self.eta
        self._device = DeviceConstants()

    # ------------------------------------------------------------- description
    def config(self) -> dict[str, Any]:
        return {"n_x": self.n_x, "length": self.length, "k0": self.k0, "beta": self.beta,
                "gamma": self.gamma, "t_ref": self.t_ref, "t_scale": self.t_scale, "eta": self.eta,
                "t_right": self.t_right, "t_init": self.t_init, "heater_centers": list(self.heater_centers),
                "heater_sigma": self.heater_sigma, "sensor_positions": list(self.sensor_positions),
                "dt": self.dt, **spread_key(self.initial_spread), **self._optional_config()}

    def _optional_config(self) -> dict[str, Any]:
        """The optional keys that are set (absent at their defaults: the reference's config as before;
        `source` always with noise channels of their own, so that it is a truth key of that variant)."""
        out: dict[str, Any] = {}
        if self.source != 0.0 or self.noise_centers is not None:
            out["source"] = self.source
        if self.noise_centers is not None:
            out["noise_centers"] = list(self.noise_centers)
        if self.noise_sigma is not None:
            out["noise_sigma"] = self.noise_sigma
        return out

    def grid(self) -> np.ndarray:
        """Node positions x_i = i L / n_x (the Dirichlet node x = L is eliminated)."""
        return self._x.copy()

    def field_coordinates(self) -> np.ndarray:
        xyz = np.zeros((self.n_x, 3))
        xyz[:, 0] = self._x
        return xyz

    def sensor_nodes(self) -> np.ndarray:
        """Index of the node nearest each sensor position."""
        return self._sensors.copy()

    def heater_profiles(self) -> np.ndarray:
        """b_j(x_i), shape (n_x, n_u): Gaussians integrating to 1 over the slab."""
        return self._gaussians(self.heater_centers, self.heater_sigma)

    def noise_profiles(self) -> np.ndarray:
        """e_l(x_i), shape (n_x, n_w): the noise channels' Gaussians (the heaters' with noise on the inputs)."""
        if self.noise_centers is None:
            return self.heater_profiles()
        return self._gaussians(self.noise_centers, self.heater_sigma if self.noise_sigma is None else self.noise_sigma)

    def _gaussians(self, centers: Sequence[float], sigma: float) -> np.ndarray:
        x = self._x[:, None]
        c = np.asarray(centers)[None, :] * self.length
        s = sigma * self.length
        return np.exp(-0.5 * ((x - c) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))

    # -------------------------------------------------------------------- API
    def initial_state(self, batch: int = 1) -> np.ndarray:
        """T(x, 0) = t_init everywhere: (batch, n_x)."""
        return np.full((batch, self.n_x), self.t_init)

    def initial_states(self, seeds) -> np.ndarray:
        """(M, n_x): one initial state per seed, the known one plus a uniform offset of std
        `initial_spread` (`sep_plant.initial.offset_states`; 0: the known state exactly)."""
        return offset_states(self.initial_state(1)[0], self.initial_spread, seeds)

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """Advance one step: x_{k+1} = f(x_k, u_k + w_k) for every run of the batch."""
        xp = namespace(x, u, w)
        single = np.ndim(x) == 1
        X = xp.atleast_2d(xp.asarray(x))
        U = xp.atleast_2d(xp.asarray(u))
        own = self.noise_centers is not None
        if w is not None and not own:
            U = U + xp.atleast_2d(xp.asarray(w))
        M, n = X.shape
        if n != self.n_x or U.shape[-1] != self.n_u:
            raise ValueError(f"step: expected states (*, {self.n_x}) and inputs (*, {self.n_u}), "
                             f"got {X.shape} and {U.shape}")
        if U.shape[0] != M:
            U = xp.broadcast_to(U, (M, self.n_u))
        if own:                       # the noise channels as extra columns of U (and of b_dt)
            W = xp.zeros((M, self.n_w)) if w is None else xp.broadcast_to(xp.atleast_2d(xp.asarray(w)), (M, self.n_w))
            U = xp.concatenate([U, W], axis=1)
        out = blocks.step_in_blocks(self._step, X, U, self.block_nodes)
        return out[0] if single else out

    def _step(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """One backward-Euler step of the runs X (M, n_x) under inputs U (M, n_u): one gtsv call
        (numpy), or parallel cyclic reduction on another array module (`adi.solve_pcr`)."""
        xp = namespace(X)
        M, n = X.shape
        space = self._device.get(xp, "space", lambda: self._space)
        b_dt = self._device.get(xp, "b_dt", lambda: self._b_dt)
        # c_i = dt K(x_i, T_i) / h^2
        c = self._c_scale * (1.0 + self.beta * (X - self.t_ref) / self.t_scale) * space
        d = self._diag0 + 2.0 * c
        du = -c.copy()
        du[:, 0] *= 2.0               # ghost node: row 0 is (2 T_1 - 2 T_0) / h^2
        du[:, -1] = 0.0               # no coupling between runs
        rhs = X + U @ b_dt.T
        if self._src_dt != 0.0:
            rhs += self._src_dt
        rhs[:, -1] += c[:, -1] * self.t_right
        if xp is not np:
            return adi.solve_pcr(-c, d, du, rhs)           # row i: -c_i T_{i-1} + d_i T_i + du_i T_{i+1}
        dl = np.empty_like(c)
        dl[:, :-1] = -c[:, 1:]
        dl[:, -1] = 0.0
        _, _, _, sol, info = lapack.dgtsv(dl.ravel()[:-1], d.ravel(), du.ravel()[:-1], rhs.ravel(),
                                          overwrite_dl=1, overwrite_d=1, overwrite_du=1, overwrite_b=1)
        if info != 0:
            raise FloatingPointError(f"tridiagonal solve failed (LAPACK info {info}): "
                                     "non-finite state or input?")
        return sol.reshape(M, n)

    def observe(self, x: np.ndarray) -> np.ndarray:
        """Noise-free sensor outputs h(x): temperatures at the sensor nodes."""
        return x[..., self._sensors]

    def field(self, x: np.ndarray) -> np.ndarray:
        """The temperature field is the state."""
        return x
