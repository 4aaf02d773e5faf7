"""Seeded noise sequences shared by the plant node and the offline Monte Carlo.

Run i of a batch drawn with seed s uses its own generator, ``SeedSequence(s, spawn_key=(i,))``
(the i-th child of ``SeedSequence(s)``, built directly: O(1) in i), so a plant episode with
(seed=s, run=i) sees exactly the numbers of run i of an offline Monte Carlo with seed s
(common random numbers), whichever chunk of runs that Monte Carlo draws at once.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np

from sep_plant.problem import Problem
from sep_plant.protocol import PlantInfo

#: the default noise seed of Monte Carlo runs (`evaluate --seed`) and of the plant node (parameter seed)
DEFAULT_SEED = 1


def run_generator(seed: int, run: int) -> np.random.Generator:
    """The generator of run `run` of seed `seed`."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(run),)))


def noise_sequences(problem: Problem, info: PlantInfo, seed: int,
                    runs: int | Iterable[int] = 1) -> tuple[np.ndarray, np.ndarray]:
    """Process noise w (M, N, n_w) and sensor noise v (M, N+1, n_y) of the given runs.

    `runs` is a count (runs 0..M-1) or an iterable of run indices. Per run: N n_w standard
    normals for w, then (N+1) n_y for v, scaled by w_std and v_std per channel.
    """
    idx = range(runs) if isinstance(runs, int) else list(runs)
    N, n_w, n_y = problem.n_steps, info.noise_dim, info.n_y
    w_std, v_std = problem.channels("w_std", n_w), problem.channels("v_std", n_y)
    w = np.empty((len(idx), N, n_w))
    v = np.empty((len(idx), N + 1, n_y))
    for m, i in enumerate(idx):
        rng = run_generator(seed, i)
        w[m] = rng.standard_normal((N, n_w)) * w_std
        v[m] = rng.standard_normal((N + 1, n_y)) * v_std
    return w, v
