"""controlgym's PDE environments as sep plants (``plant: {type: controlgym, env: burgers, ...}``).

controlgym (Zhang et al., arXiv 2311.18736; PyPI ``controlgym`` 1.0.0, MIT) is the shared
benchmark suite of large-scale control: ten PDE envs (allen_cahn, burgers, cahn_hilliard,
convection_diffusion_reaction, fisher, ginzburg_landau, korteweg_de_vries, kuramoto_sivashinsky,
schrodinger, wave) with n_state nodes, n_observation point sensors, n_action distributed
actuators, additive Gaussian process noise on the state (covariance process_noise_cov I) and
sensor noise (sensor_noise_cov I), reward -[(x - x*)' Q (x - x*) + u' R u] per step.

`ControlgymPlant` is a `sep_plant.plants.gym.GymPlant` on ``controlgym.envs.make(env, **keys)``:
every other key is the env's own constructor key (n_state, n_observation, n_action,
process_noise_cov, sensor_noise_cov, Q_weight, R_weight, target_state, n_steps, seed ...), passed
through unchanged. The env sep steps is built with both noise covariances 0; the env's noise
levels become the problem's w_std = sqrt(process_noise_cov) and v_std = sqrt(sensor_noise_cov)
(`controlgym_problem`). With `fast` (the default) a batch is stepped by
`sep_plant.plants.controlgym_fast.FastStep` from the env's own operators, one vectorized call
instead of one ``env.step`` per run; `observe` is C x with the env's own C.

Install (optional extra, `make venv` does it): controlgym 1.0.0 pins numpy < 2 and gymnasium
0.29.1, and its package ``__init__`` imports torch (for its PPO); its envs need only numpy,
scipy and gymnasium and run under numpy 2. So: ``pip install gymnasium`` then
``pip install --no-deps controlgym==1.0.0``; `envs_module` imports ``controlgym.envs`` without
running the package's ``__init__`` (no torch). No controlgym code is copied here.
"""
from __future__ import annotations

import importlib
import importlib.util
import math
import sys
import types
from typing import Any

import numpy as np

from sep_plant.plants.controlgym_fast import COVERED, FastStep
from sep_plant.plants.gym import GymPlant
from sep_plant.plants.keys import PlantConfigError

__all__ = ["ControlgymPlant", "ENV_IDS", "controlgym_problem", "envs_module", "make_env"]

ENV_IDS = ("allen_cahn", "burgers", "cahn_hilliard", "convection_diffusion_reaction", "fisher",
           "ginzburg_landau", "korteweg_de_vries", "kuramoto_sivashinsky", "schrodinger", "wave")
#: the env's keys that switch its noise off for sep's experiments
NOISE_OFF = {"process_noise_cov": 0.0, "sensor_noise_cov": 0.0}


def envs_module():
    """``controlgym.envs``, imported without running ``controlgym/__init__.py`` (which imports
    torch). Raises ImportError with the install line when controlgym is missing."""
    if "controlgym.envs" in sys.modules:
        return sys.modules["controlgym.envs"]
    spec = importlib.util.find_spec("controlgym")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("controlgym is not installed: pip install gymnasium && "
                          "pip install --no-deps controlgym==1.0.0 (docs/plants.md)")
    if "controlgym" not in sys.modules:
        stub = types.ModuleType("controlgym")
        stub.__path__ = list(spec.submodule_search_locations)
        stub.__spec__ = spec
        sys.modules["controlgym"] = stub
    return importlib.import_module("controlgym.envs")


def _env_value(key: str, value: Any) -> Any:
    """A plain-data key as the env takes it (lists become arrays)."""
    return np.asarray(value, dtype=float) if key == "target_state" and value is not None else value


def make_env(env: str, **keys: Any):
    """``controlgym.envs.make(env, **keys)`` (lists converted to the arrays it expects)."""
    if env not in ENV_IDS:
        raise PlantConfigError(f"env must be one of {', '.join(ENV_IDS)}, got {env!r}")
    try:
        return envs_module().make(env, **{k: _env_value(k, v) for k, v in keys.items()})
    except ImportError as exc:
        raise PlantConfigError(str(exc)) from None
    except (TypeError, AssertionError) as exc:
        raise PlantConfigError(f"controlgym env {env!r}: {exc}") from None


class ControlgymPlant(GymPlant):
    """A controlgym PDE env as a plant; see the module docstring.

    Parameters
    ----------
    env : str
        The env's name (`ENV_IDS`).
    fast : bool
        Step batches with the env's operators (`FastStep`) instead of ``env.step`` per run.
    noise_modes : int or None
        Process-noise channels (`GymPlant`): None, one per node; k, the k slowest Fourier modes.
    mean_samples : int
        Seeded resets averaged into the nominal initial state.
    **env_keys
        The env's own constructor keys (plain data: target_state as a list).
    """

    def __init__(self, env: str = "burgers", fast: bool = True, noise_modes: int | None = None,
                 mean_samples: int = 1000, **env_keys: Any):
        self.env_id = env
        if not isinstance(fast, bool):
            raise PlantConfigError(f"fast must be true or false, got {fast!r}")
        self.fast = fast and env in COVERED
        keys = {k: (list(map(float, v)) if isinstance(v, (list, tuple, np.ndarray)) else v)
                for k, v in env_keys.items()}
        super().__init__(env="sep_plant.plants.controlgym:make_env", env_kwargs={"env": env, **keys},
                         noise_off=NOISE_OFF, dt=None, noise_modes=noise_modes, mean_samples=mean_samples)
        self.env_keys = keys
        self._fast = FastStep(env, self.env) if self.fast else None
        self.C = np.asarray(self.env.C, dtype=float)

    def config(self) -> dict[str, Any]:
        return {"env": self.env_id, "fast": self.fast, "noise_modes": self.noise_modes,
                "mean_samples": self.mean_samples, **self.env_keys}

    def _step_batch(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        if self._fast is None:
            return super()._step_batch(X, U)
        return self._fast(X, U)

    def observe(self, x: np.ndarray) -> np.ndarray:
        if self._fast is None:
            return super().observe(x)
        return np.atleast_2d(np.asarray(x, dtype=float)) @ self.C.T

    def field_coordinates(self) -> np.ndarray:
        """x of every node (the env's grid; a two-field state, u then v, repeats it, with y = 1
        for the second field)."""
        grid = np.asarray(self.env.domain_coordinates, dtype=float)
        xyz = np.zeros((self.n_field, 3))
        reps = self.n_field // grid.size
        xyz[:, 0] = np.tile(grid, reps)[: self.n_field]
        xyz[:, 1] = np.repeat(np.arange(reps, dtype=float), grid.size)[: self.n_field]
        return xyz

    # ----------------------------------------------------------- the task
    @property
    def action_limit(self) -> float:
        return float(self.env.action_limit)

    def noise_levels(self) -> tuple[float, float]:
        """(w_std, v_std) of the env's own noise: sqrt(process_noise_cov), sqrt(sensor_noise_cov)."""
        ref = make_env(self.env_id, **{k: v for k, v in self.env_keys.items()})
        return math.sqrt(float(ref.process_noise_cov)), math.sqrt(float(ref.sensor_noise_cov))


def controlgym_problem(plant: ControlgymPlant, **overrides: Any):
    """The sep problem of the env's own task: horizon n_steps, the env's target, its noise, its
    action limit, and the reward's weights as the nominal cost's (q_k = 1 on every step,
    r_u = R_weight / (Q_weight n_state), since Q_w sum_i e_i^2 = Q_w n mean_i e_i^2) and the
    LQR's (Q_y = I / n_y, R = r_u I). `overrides` replace any problem key."""
    from sep_plant.problem import Problem

    env = plant.env
    w_std, v_std = plant.noise_levels()
    N = int(env.n_steps)
    Qw = float(env.Q[0, 0])
    Rw = float(env.R[0, 0])
    r_u = Rw / (Qw * plant.n_x)
    target = np.asarray(env.target_state, dtype=float)
    lim = float(env.action_limit)
    keys = dict(n_steps=N, target=0.0 if not np.any(target) else tuple(target.tolist()),
                band=1.0, band_window=(1, N), q_window=1.0, q_outside=1.0, r_u=r_u,
                w_std=w_std, v_std=v_std, u_min=-lim, u_max=lim, lqr_k_switch=0,
                lqr_q_late=1.0, lqr_q_early=1.0, lqr_r=r_u, u_init=0.0)
    keys.update(overrides)
    return Problem(**keys)
