"""A test plant with process noise on every node: 1-D reaction-diffusion (pure numpy, batched).

    x_{k+1} = S(x_k, u_k) + Phi w_k,   S: m explicit Euler substeps of dt/m of
    dx/dt = D L x + a x - b x^3 + B u

(m the fewest that keep D dt / (m h^2) <= 0.4) on n_x nodes of a rod of length 1 (L: the
second difference, zero-flux ends), n_u Gaussian actuators, n_y point sensors, the field the
state itself. The process noise is additive on the state, not on the inputs (`noise_on_inputs`
False): `noise_modes` None puts one channel on every node (Phi = I, n_w = n_x); an integer k
keeps the k slowest cosine modes of the rod (Phi = their orthonormal columns, n_w = k), the
plant with a few channels.
"""
from __future__ import annotations

import numpy as np


class ReactionDiffusionPlant:
    """1-D reaction-diffusion with process noise on every node or on a few modes."""

    noise_on_inputs = False
    field_is_state = True
    field_name, field_unit = "concentration", "1"

    def __init__(self, n_x: int = 201, n_u: int = 3, n_y: int = 5, noise_modes: int | None = None,
                 dt: float = 0.1, diffusion: float = 0.005, a: float = -0.2, b: float = 0.5):
        self.n_x, self.n_u, self.n_y, self.noise_modes = int(n_x), int(n_u), int(n_y), noise_modes
        self.dt, self.diffusion, self.a, self.b = float(dt), float(diffusion), float(a), float(b)
        self.n_field = self.n_x
        self.z = np.linspace(0.0, 1.0, self.n_x)
        h = self.z[1] - self.z[0]
        self.substeps = max(1, int(np.ceil(self.dt * self.diffusion / h**2 / 0.4)))
        centres = (np.arange(self.n_u) + 0.5) / self.n_u
        self.B = np.exp(-0.5 * ((self.z[:, None] - centres[None, :]) / 0.1) ** 2)    # (n_x, n_u)
        self.sensors = np.round(np.linspace(0.1, 0.9, self.n_y) * (self.n_x - 1)).astype(int)
        if noise_modes is None:
            self.Phi, self.n_w = None, self.n_x
        else:
            k = np.arange(int(noise_modes))
            P = np.cos(np.pi * k[None, :] * self.z[:, None])
            self.Phi, self.n_w = P / np.linalg.norm(P, axis=0), int(noise_modes)
        self.input_names = [f"u{i}" for i in range(self.n_u)]
        self.output_names = [f"y{i}" for i in range(self.n_y)]

    def config(self) -> dict:
        return {"n_x": self.n_x, "n_u": self.n_u, "n_y": self.n_y, "noise_modes": self.noise_modes,
                "dt": self.dt, "diffusion": self.diffusion, "a": self.a, "b": self.b}

    def initial_state(self, batch: int = 1) -> np.ndarray:
        return np.zeros((batch, self.n_x))

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        out = np.array(np.atleast_2d(x), dtype=float)
        u = np.broadcast_to(np.asarray(u, dtype=float), (out.shape[0], self.n_u))
        force = u @ self.B.T
        h = self.dt / self.substeps
        kd = self.diffusion / (self.z[1] - self.z[0]) ** 2
        lap = np.empty_like(out)
        for _ in range(self.substeps):
            lap[:, 1:-1] = out[:, 2:] - 2 * out[:, 1:-1] + out[:, :-2]
            lap[:, 0] = 2 * (out[:, 1] - out[:, 0])
            lap[:, -1] = 2 * (out[:, -2] - out[:, -1])
            out += h * (kd * lap + self.a * out - self.b * out**3 + force)
        if w is not None:
            w = np.broadcast_to(np.asarray(w, dtype=float), (x.shape[0], self.n_w))
            out += w if self.Phi is None else w @ self.Phi.T
        return out

    def observe(self, x: np.ndarray) -> np.ndarray:
        return np.atleast_2d(x)[:, self.sensors].copy()

    def field(self, x: np.ndarray) -> np.ndarray:
        return np.atleast_2d(x).copy()

    def field_coordinates(self) -> np.ndarray:
        return np.column_stack([self.z, np.zeros(self.n_x), np.zeros(self.n_x)])
