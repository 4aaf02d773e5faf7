"""Uncertain initial states: draws from a plant's initial-state distribution, per run.

A plant may define the optional protocol method ``initial_states(seeds) -> (M, n_x)``: one
initial state per integer seed, drawn from its initial-state distribution (deterministic in the
seed). ``initial_state(batch)`` stays the known (nominal) initial state the design starts from,
the distribution's mean or another state the plant documents. A plant without the method
starts every run at ``initial_state``.

Run `run` of a Monte Carlo or plant episode with noise seed `seed` draws its initial state with
the seed `initial_seed(seed, run)` (a child of ``SeedSequence(seed)`` apart from the run's noise
stream), so the plant node's episode (seed, run) starts where run `run` of the offline Monte
Carlo does, whichever chunk that run is in.

The built-in plants take the key ``initial_spread`` (default 0): the initial field plus a
uniform offset of std initial_spread per run (`offset_states`). With 0 every draw is the known
initial state, bit for bit, and nothing about a design or a Monte Carlo changes.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Iterable

import numpy as np

#: the spawn-key entry that separates a run's initial-state stream from its noise stream
INITIAL_STREAM = 1


def initial_seed(seed: int, run: int) -> int:
    """The integer seed of run `run`'s initial state under noise seed `seed` (< 2^32)."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(int(run), INITIAL_STREAM))
    return int(ss.generate_state(1, dtype=np.uint32)[0])


def has_initial_distribution(plant: Any) -> bool:
    """Whether the plant draws initial states (the optional method `initial_states`)."""
    return callable(getattr(plant, "initial_states", None))


def initial_states(plant: Any, seed: int, runs: int | Iterable[int]) -> np.ndarray:
    """(M, n_x): the initial states of runs `runs` (a count or run indices) under seed `seed`.

    Parameters
    ----------
    plant : Plant
        The plant; without `initial_states` every run starts at ``initial_state``.
    seed : int
        The noise seed of the Monte Carlo or episode.
    runs : int or iterable of int
        Runs 0..M-1, or the run indices.

    Returns
    -------
    ndarray, shape (M, n_x)
    """
    idx = list(range(runs)) if isinstance(runs, int) else [int(r) for r in runs]
    if not has_initial_distribution(plant):
        return plant.initial_state(len(idx))
    X = np.asarray(plant.initial_states(np.array([initial_seed(seed, r) for r in idx], dtype=np.int64)))
    if X.shape != (len(idx), int(plant.n_x)):
        raise ValueError(f"initial_states returned shape {X.shape}, expected {(len(idx), int(plant.n_x))}")
    return X


def sample_initial_states(plant: Any, samples: int, seed: int = 0) -> np.ndarray | None:
    """(samples, n_x) draws for the design (seeds of runs 0..samples-1 under `seed`), or None when
    the plant has no initial-state distribution or every draw is its known initial state."""
    if not has_initial_distribution(plant):
        return None
    X = initial_states(plant, seed, samples)
    if np.array_equal(X, np.asarray(plant.initial_state(samples))):
        return None
    return X


def spread_key(spread: float) -> dict[str, float]:
    """The ``initial_spread`` entry of a built-in plant's config(): absent at 0 (the default), so
    that a plant without spread has the same keys, scenarios and design files as before the key."""
    return {} if spread == 0 else {"initial_spread": float(spread)}


def offset_states(x0: np.ndarray, spread: float, seeds: Iterable[int]) -> np.ndarray:
    """(M, n_x): x0 + spread xi_m with xi_m ~ N(0, 1) from ``default_rng(seed_m)``, one scalar per
    run (a uniform offset of the whole initial field); spread 0 gives x0 exactly."""
    seeds = [int(s) for s in np.atleast_1d(np.asarray(seeds))]
    X = np.tile(np.asarray(x0, dtype=float), (len(seeds), 1))
    if spread == 0:
        return X
    xi = np.array([np.random.default_rng(s).standard_normal() for s in seeds])
    return X + spread * xi[:, None]
