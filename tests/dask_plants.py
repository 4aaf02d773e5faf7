"""Plants that fail only on a Dask worker, for the engine's fault tests (importable as
``dask_plants:Name`` with tests/ on the path, which LocalCluster workers inherit).

In this process (the conformance check, the in-process reference run) they are `ToyPlant`.
"""
from __future__ import annotations

import os

from broken_plants import ToyPlant


def on_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


class KillsWorkerOnce(ToyPlant):
    """The first step taken on any worker kills that worker's process (as a crash or the OOM
    killer would); `marker` records that it happened, so the rerun succeeds."""

    def __init__(self, n_x: int = 6, decay: float = 0.1, marker: str = ""):
        super().__init__(n_x, decay)
        self.marker = str(marker)

    def config(self) -> dict:
        return {**super().config(), "marker": self.marker}

    def step(self, x, u, w=None):
        if self.marker and on_worker() and not os.path.exists(self.marker):
            with open(self.marker, "w") as fh:
                fh.write(f"killed worker pid {os.getpid()}\n")
            os._exit(1)
        return super().step(x, u, w)


class RaisesOnWorker(ToyPlant):
    """A simulator that fails on the cluster (a solver that diverges there)."""

    def step(self, x, u, w=None):
        if on_worker():
            raise RuntimeError("solver diverged (injected on the worker)")
        return super().step(x, u, w)
