"""Memory budgets: how many runs of a plant fit in a batch.

Experiments and Monte Carlo runs are batches in arrays; on a large grid a batch of every run
does not fit. A batch costs about `RUN_COPIES` state vectors per run (the state, the plant's
temporaries in `step`, the field and its estimate), so the budget in bytes sets the batch size.
The default budget is a quarter of the memory available when the tool starts (at least 256 MB).
n_x is a state row's real length, so plants whose states are not the physics' vector count
right too: an opaque state (a Co-Simulation FMU's serialized state, `sep_plant.plants.fmu`) is
its row of n_x float64, and an FMU plant steps a whole batch with one FMU instance per process,
whose memory does not grow with the runs (its steps hold about 4 rows (CS) or 9 (ME) per run).
Pure Python: no ROS import.
"""
from __future__ import annotations

import os

#: state-sized arrays alive per run while a batch steps, for a plant that steps a batch in one
#: piece (measured on the built-in plants stepped so: the ADI step's coefficient and right-hand-side
#: arrays dominate). The built-in plants now step in cache-sized blocks (`sep_plant.plants.blocks`),
#: whose temporaries are a block's, not the batch's; for them the budget is an upper bound (the
#: plate 256^2 design peaks at 2.39 GB instead of 3.33 GB, README)
RUN_COPIES = 12
MIN_BUDGET = 256 << 20


def default_budget() -> int:
    """A quarter of the memory available now (bytes), at least MIN_BUDGET."""
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        avail = 4 << 30
    return max(MIN_BUDGET, avail // 4)


def runs_per_batch(n_x: int, n_field: int, budget: int | None = None, minimum: int = 1) -> int:
    """How many runs of an n_x-state plant (n_field field nodes) a batch may hold."""
    budget = default_budget() if budget is None else int(budget)
    per_run = 8 * (RUN_COPIES * n_x + 4 * n_field)
    return max(minimum, budget // per_run)


def parse_budget(text: str) -> int:
    """'2G', '512M', '1.5g' or a number of bytes -> bytes (ValueError naming the problem)."""
    t = str(text).strip().lower()
    scale = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}.get(t[-1:], 1)
    num = t[:-1] if t[-1:] in "kmg" else t
    try:
        value = float(num) * scale
    except ValueError:
        raise ValueError(f"memory budget must be a size like 2G or 512M, got {text!r}") from None
    if not value >= MIN_BUDGET:
        raise ValueError(f"memory budget must be at least {MIN_BUDGET >> 20} MB, got {text!r}")
    return int(value)


def worker_budget(engine) -> int | None:
    """A quarter of the smallest worker memory limit of a cluster engine (`sep_control.compute.engine`),
    at least 64 MB; None when the engine reports no limit (in-process, unlimited workers)."""
    limit = engine.memory_limit()
    return None if limit is None else max(limit // 4, 1 << 26)
