"""A tiny conforming plant and deliberately broken variants of it, one defect each, for the
plant-protocol tests (importable as ``broken_plants:Name`` with tests/ on the path).

`ToyPlant`: a stable linear diffusion on a ring of n_x nodes (no sep import: a user's plant is
structural), two Gaussian actuators, two point sensors.
"""
from __future__ import annotations

import numpy as np


class ToyPlant:
    dt = 0.5
    field_name = "level"
    field_unit = "m"

    def __init__(self, n_x: int = 6, decay: float = 0.1):
        if n_x < 4:
            raise ValueError(f"n_x must be >= 4, got {n_x}")
        self.n_x, self.decay = int(n_x), float(decay)
        self.n_u = self.n_y = 2
        self.n_field = self.n_x
        self.input_names = ("pump_a", "pump_b")
        self.output_names = ("gauge_a", "gauge_b")
        x = np.arange(self.n_x)
        self._B = np.stack([np.exp(-0.5 * ((x - c) / 1.0) ** 2) for c in (1, self.n_x - 2)], axis=1)
        L = -2 * np.eye(self.n_x) + np.roll(np.eye(self.n_x), 1, 0) + np.roll(np.eye(self.n_x), -1, 0)
        self._A = np.eye(self.n_x) + 0.2 * L - self.decay * np.eye(self.n_x)
        self._sensors = [1, self.n_x - 2]

    def config(self) -> dict:
        return {"n_x": self.n_x, "decay": self.decay}

    def initial_state(self, batch: int) -> np.ndarray:
        return np.zeros((batch, self.n_x))

    def step(self, x, u, w=None):
        U = np.atleast_2d(u) + (0.0 if w is None else np.atleast_2d(w))
        return x @ self._A.T + U @ self._B.T

    def observe(self, x):
        return x[:, self._sensors]

    def field(self, x):
        return x

    def field_coordinates(self):
        xyz = np.zeros((self.n_x, 3))
        xyz[:, 0] = np.arange(self.n_x) * 0.1
        return xyz


class MissingObserve(ToyPlant):
    observe = None


class WrongStepShape(ToyPlant):
    def step(self, x, u, w=None):
        return super().step(x, u, w)[:, :-1]


class NonFiniteObserve(ToyPlant):
    def observe(self, x):
        y = super().observe(x).copy()
        y[:, 0] = np.nan
        return y


class NotDeterministic(ToyPlant):
    def step(self, x, u, w=None):
        return super().step(x, u, w) + 1e-6 * np.random.standard_normal(x.shape)


class RunsInteract(ToyPlant):
    def step(self, x, u, w=None):
        out = super().step(x, u, w)
        return out + 0.01 * out.mean(axis=0)


class ModifiesState(ToyPlant):
    def step(self, x, u, w=None):
        out = super().step(x, u, w)
        x += 1.0
        return out


class NoiseNotOnInputs(ToyPlant):
    """Declares (by default) that the noise enters the inputs, but ignores w."""

    def step(self, x, u, w=None):
        return super().step(x, u, None)


class BadConfig(ToyPlant):
    def config(self) -> dict:
        return {"n_x": self.n_x, "decay": self.decay, "colour": "blue"}


class WrongNames(ToyPlant):
    def __init__(self, n_x: int = 6, decay: float = 0.1):
        super().__init__(n_x, decay)
        self.output_names = ("gauge_a",)


class BadGrid(ToyPlant):
    grid_shape = (2, 2)


class NoisePlant(ToyPlant):
    """Conforming plant whose process noise is NOT on the inputs: two disturbance channels with
    their own spatial profiles (noise_on_inputs = False, n_w = 2)."""

    noise_on_inputs = False
    n_w = 2

    def __init__(self, n_x: int = 6, decay: float = 0.1):
        super().__init__(n_x, decay)
        x = np.arange(self.n_x)
        self._D = np.stack([np.cos(2 * np.pi * x / self.n_x), np.sin(2 * np.pi * x / self.n_x)], axis=1)

    def step(self, x, u, w=None):
        out = x @ self._A.T + np.atleast_2d(u) @ self._B.T
        return out if w is None else out + np.atleast_2d(w) @ self._D.T
