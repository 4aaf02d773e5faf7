"""Cache-sized blocks of a batch: the built-in plants step a large batch a block of runs at a time.

A batched step streams a dozen state-sized arrays (coefficients, right-hand sides, line-solve
work) through memory. While one block's arrays stay in the caches (a few MB each), a step costs
20-60 ns per node; a batch of hundreds of large-grid runs in one piece spills every array to main
memory and costs 1.4-2.3x as much per node (measured with `bench/bench_plants.py --blocks`).
So `step_in_blocks` cuts the batch into blocks of at most `BLOCK_NODES` nodes (runs x n_x) and
steps them one after another into one output array. Runs are independent, so the result is that
of the whole batch in one piece to round-off (bitwise where the line solver is the same).
On a GPU (a CuPy batch) the blocks are the device plant's (`sep_plant.device`, 2^24 nodes): there
a step's cost is kernel launches, not caches. Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from sep_plant.plants.backend import namespace

#: nodes (runs x n_x) per block; see the module docstring and bench/bench_plants.py --blocks
BLOCK_NODES = 1 << 17


def runs_per_block(n_x: int, block_nodes: int | None = None) -> int:
    """How many runs of an n_x-node plant one block holds (at least one)."""
    return max(1, int(BLOCK_NODES if block_nodes is None else block_nodes) // max(1, int(n_x)))


def step_in_blocks(step: Callable[[np.ndarray, np.ndarray], np.ndarray], X: np.ndarray, S: np.ndarray,
                   block_nodes: int | None = None) -> np.ndarray:
    """`step(X[i:j], S[i:j])` for consecutive blocks of runs, gathered into one (M, ...) array.

    X (M, ...) are the runs' states, S (M or broadcast, ...) what each run is stepped with (its
    input or source); a batch that fits one block is passed through whole, with no copy."""
    M = X.shape[0]
    b = runs_per_block(int(np.prod(X.shape[1:], dtype=np.int64)), block_nodes)
    if M <= b:
        return step(X, S)
    first = step(X[:b], S[:b])
    out = namespace(first).empty((M,) + first.shape[1:], dtype=first.dtype)
    out[:b] = first
    for i in range(b, M, b):
        out[i:i + b] = step(X[i:i + b], S[i:i + b])
    return out


__all__ = ["BLOCK_NODES", "runs_per_block", "step_in_blocks"]
