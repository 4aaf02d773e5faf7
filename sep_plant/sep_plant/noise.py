"""Seeded noise sequences shared by the plant node and the offline Monte Carlo.

Run i of a batch drawn with seed s uses its own generator, spawned from
``SeedSequence(s)`` as child i, so a plant episode with (seed=s, run=i) sees exactly
the numbers of run i of an offline Monte Carlo with seed s (common random numbers).
"""
from __future__ import annotations

import numpy as np

from .scenario import Scenario


def noise_sequences(s: Scenario, seed: int, runs: int | range = 1) -> tuple[np.ndarray, np.ndarray]:
    """Process noise w (M, N, n_u) on the heater inputs and sensor noise v (M, N+1, n_y).

    `runs` is a count (runs 0..M-1) or a range of run indices.
    """
    idx = range(runs) if isinstance(runs, int) else runs
    children = np.random.SeedSequence(seed).spawn(max(idx) + 1 if len(idx) else 0)
    w = np.empty((len(idx), s.n_steps, s.n_u))
    v = np.empty((len(idx), s.n_steps + 1, s.n_y))
    for m, i in enumerate(idx):
        rng = np.random.default_rng(children[i])
        w[m] = rng.standard_normal((s.n_steps, s.n_u)) * s.w_std
        v[m] = rng.standard_normal((s.n_steps + 1, s.n_y)) * s.v_std
    return w, v
