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
    """The first `kills` steps taken on workers each kill their worker's process (as a crash or
    the OOM killer would); marker files record that it happened (`marker`, `marker.1`, ...), so
    the reruns succeed."""

    def __init__(self, n_x: int = 6, decay: float = 0.1, marker: str = "", kills: int = 1):
        super().__init__(n_x, decay)
        self.marker, self.kills = str(marker), int(kills)

    def config(self) -> dict:
        return {**super().config(), "marker": self.marker, "kills": self.kills}

    def step(self, x, u, w=None):
        if self.marker and on_worker():
            for j in range(self.kills):
                try:   # atomic: of two workers stepping at once, exactly one takes marker j
                    fd = os.open(self.marker if j == 0 else f"{self.marker}.{j}",
                                 os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    continue
                os.write(fd, f"killed worker pid {os.getpid()}\n".encode())
                os.close(fd)
                os._exit(1)
        return super().step(x, u, w)


class RaisesOnWorker(ToyPlant):
    """A simulator that fails on the cluster (a solver that diverges there)."""

    def step(self, x, u, w=None):
        if on_worker():
            raise RuntimeError("solver diverged (injected on the worker)")
        return super().step(x, u, w)
