"""A Gymnasium environment as a black-box sep plant.

sep needs a simulator it can restart from any state. A Gymnasium env is one when it can be
reset to a given state and reports its state, as controlgym's envs do::

    obs, info = env.reset(state=x)             # info["state"] is x
    obs, r, term, trunc, info = env.step(u)     # info["state"] is the next state

`GymPlant` wraps such an env (built from a factory ``"package.module:callable"`` and its
keyword arguments) as a plant of `sep_plant.protocol`, one run at a time:

    step(x, u, w):  env.reset(state=x_m); env.step(u_m); x_{m,next} = info["state"] + Phi w_m
    observe(x):     the observation env.reset(state=x_m) returns
    field(x):       x (the state is the field)

Noise. The env used for the experiments is built with `noise_off` merged over `env_kwargs`
(its own noise switched off, e.g. ``{process_noise_cov: 0, sensor_noise_cov: 0}``), so every
step is deterministic; sep adds the noise itself. The process noise is taken to be additive on
the state after the step (controlgym's model): `noise_modes` None gives one noise channel per
state entry (Phi = I, n_w = n_x); an integer k keeps the k slowest real Fourier modes of the
state vector as the channels (Phi = the first k columns of an orthonormal real Fourier basis:
white noise of std s per entry projected on those modes is exactly s per channel, and the
dropped fast modes are the ones a diffusive PDE damps before any sensor sees them). That keeps
the design's noise-channel experiments at k instead of n_x (`docs/plants.md`).

Initial states. `initial_states(seeds)` (the optional protocol method) draws one initial state
per seed from the env's own reset, ``env.reset(seed=s)``; `initial_state(batch)` is their mean
over `mean_samples` fixed seeds (0..mean_samples-1): the design's nominal starts there.

The env's step is one run per call (tens of ms for controlgym's PDEs): a subclass may give a
batched fast path (`sep_plant.plants.controlgym`), checked against the env's step by a test.
Numpy only here; gymnasium is needed by the env itself.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np

from sep_plant.plants.keys import PlantConfigError, integer, positive

__all__ = ["GymPlant", "fourier_noise_basis", "load_factory"]


def load_factory(target: str) -> Callable[..., Any]:
    """The env factory named ``"package.module:callable"``."""
    from sep_plant.plants import import_target    # the registry's own resolution (a plant error here)

    if not isinstance(target, str):
        raise PlantConfigError(f"env must be 'package.module:callable', got {target!r}")
    return import_target(target, "env", PlantConfigError)


def fourier_noise_basis(n: int, k: int) -> np.ndarray:
    """Phi (n, k): the k lowest-wavenumber columns of an orthonormal real Fourier basis of R^n
    (the constant, then cos and sin of wavenumber 1, 2, ...)."""
    i = np.arange(n)
    cols = [np.full(n, 1.0 / np.sqrt(n))]
    m = 1
    while len(cols) < k:
        c = np.cos(2 * np.pi * m * i / n)
        cols.append(c / np.linalg.norm(c))
        if len(cols) < k:
            s = np.sin(2 * np.pi * m * i / n)
            norm = np.linalg.norm(s)
            if norm > 1e-12:
                cols.append(s / norm)
        m += 1
    return np.stack(cols[:k], axis=1)


class GymPlant:
    """A resettable Gymnasium env (``reset(state=x)``, ``info["state"]``) as a sep plant.

    Parameters
    ----------
    env : str
        The env factory, ``"package.module:callable"``, called with `env_kwargs` | `noise_off`.
    env_kwargs : dict
        The env's own keyword arguments (plain JSON data).
    noise_off : dict
        Keyword arguments that switch the env's own noise off (they override `env_kwargs` for
        the env sep steps).
    dt : float
        The env's step [s] (the env's ``sample_time`` when it has one and dt is None).
    noise_modes : int or None
        Process-noise channels: None, one per state entry; k, the k slowest Fourier modes.
    mean_samples : int
        Seeded resets averaged into the nominal initial state.
    """

    field_name = "state"
    field_unit = ""
    field_is_state = True
    noise_on_inputs = False

    def __init__(self, env: str, env_kwargs: Mapping[str, Any] | None = None,
                 noise_off: Mapping[str, Any] | None = None, dt: float | None = None,
                 noise_modes: int | None = None, mean_samples: int = 1000):
        self.env_target = env
        self.env_kwargs = dict(env_kwargs or {})
        self.noise_off = dict(noise_off or {})
        self.env = self._build_env({**self.env_kwargs, **self.noise_off})
        obs, info = self.env.reset(seed=0)
        x0 = self._state_of(info)
        self.n_x = int(x0.size)
        self.n_y = int(np.asarray(obs).size)
        self.n_u = int(np.prod(self.env.action_space.shape))
        self.dt = positive("dt", dt if dt is not None else getattr(self.env, "sample_time", 1.0))
        self.noise_modes = None if noise_modes is None else integer("noise_modes", noise_modes, lo=1, hi=self.n_x)
        self.n_w = self.n_x if self.noise_modes is None else self.noise_modes
        self.noise_basis = None if self.noise_modes is None else fourier_noise_basis(self.n_x, self.noise_modes)
        self.mean_samples = integer("mean_samples", mean_samples, lo=1)
        self.n_field = self.n_x
        self.input_names = tuple(f"u{i}" for i in range(self.n_u))
        self.output_names = tuple(f"y{i}" for i in range(self.n_y))
        self._x0_mean = self.initial_states(np.arange(self.mean_samples)).mean(axis=0)

    # ------------------------------------------------------------ building
    def _build_env(self, kwargs: Mapping[str, Any]):
        return load_factory(self.env_target)(**kwargs)

    @staticmethod
    def _state_of(info: Mapping[str, Any]) -> np.ndarray:
        if not isinstance(info, Mapping) or "state" not in info:
            raise PlantConfigError("the env does not report its state: reset() and step() must return "
                                   "info['state'] (and reset must accept state=)")
        x = np.asarray(info["state"])
        if np.iscomplexobj(x):
            raise PlantConfigError("the env's state is complex: sep's states are real float64 arrays")
        return np.asarray(x, dtype=float).ravel()

    def config(self) -> dict[str, Any]:
        return {"env": self.env_target, "env_kwargs": dict(self.env_kwargs), "noise_off": dict(self.noise_off),
                "dt": self.dt, "noise_modes": self.noise_modes, "mean_samples": self.mean_samples}

    # ------------------------------------------------------- initial states
    def initial_state(self, batch: int) -> np.ndarray:
        """The nominal initial state: the mean of the env's reset over `mean_samples` seeds."""
        return np.tile(self._x0_mean, (int(batch), 1))

    def initial_states(self, seeds) -> np.ndarray:
        """(M, n_x): one initial state per seed from the env's own reset, ``reset(seed=s)``."""
        seeds = np.atleast_1d(np.asarray(seeds, dtype=np.int64))
        out = np.empty((seeds.size, self.n_x))
        for m, s in enumerate(seeds):
            _, info = self.env.reset(seed=int(s))
            out[m] = self._state_of(info)
        return out

    # -------------------------------------------------------------- dynamics
    def _reset_to(self, x: np.ndarray):
        obs, _ = self.env.reset(state=np.array(x, dtype=float))
        return obs

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        X = np.atleast_2d(np.asarray(x, dtype=float))
        U = np.broadcast_to(np.asarray(u, dtype=float), (X.shape[0], self.n_u))
        out = self._step_batch(X, U)
        return self._add_noise(out, w)

    def _step_batch(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """The env's own step, one run at a time (subclasses may batch it)."""
        out = np.empty_like(X)
        for m in range(X.shape[0]):
            self._reset_to(X[m])
            info = self.env.step(np.array(U[m]))[4]
            out[m] = self._state_of(info)
        return out

    def _add_noise(self, X: np.ndarray, w: np.ndarray | None) -> np.ndarray:
        if w is None:
            return X
        W = np.broadcast_to(np.asarray(w, dtype=float), (X.shape[0], self.n_w))
        return X + (W if self.noise_basis is None else W @ self.noise_basis.T)

    def observe(self, x: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(np.asarray(x, dtype=float))
        return np.stack([np.asarray(self._reset_to(X[m]), dtype=float).ravel() for m in range(X.shape[0])])

    def field(self, x: np.ndarray) -> np.ndarray:
        return np.atleast_2d(np.asarray(x, dtype=float)).copy()

    def field_coordinates(self) -> np.ndarray:
        xyz = np.zeros((self.n_field, 3))
        xyz[:, 0] = np.arange(self.n_field, dtype=float)
        return xyz
