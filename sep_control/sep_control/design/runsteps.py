"""Plant run-steps spent by a design, per stage: the machine-independent cost of a design.

A run-step is one run stepped once (`plant.step` on a batch of M runs is M run-steps). For a
simulator whose step costs milliseconds to seconds (an FMU, a CFD code, a gymnasium env) the
run-steps decide what a design costs; they do not depend on the machine.

    meter = RunStepMeter()
    plant = metered(plant, meter)          # counts every step of the design's experiments
    with meter.stage("nominal"):
        ...                                # run-steps land in meter.counts["nominal"]

Stages of a design (`STAGES`; the plant protocol's conformance check before them, a few dozen
run-steps, is not counted): "nominal" (the
mean-only optimizer: rollouts and its Jacobian experiments), "belief" (the belief-space
refinement and the EnKF belief of the nominal), "identification" (the design's TV-ERA
experiments and the nominal rollout they extend), "validation" (rollouts made to check and
record the result). Experiments run by a non-local engine (dask workers) are added by their
exact count (`impulse_run_steps`), since the workers step their own copies of the plant.
Pure Python: no ROS import.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np

from sep_plant.wrapping import PlantWrapper

#: the stages a design's run-steps are reported by (docs/reference/design-file.md)
STAGES = ("nominal", "belief", "identification", "validation")


class RunStepMeter:
    """Run-steps counted per stage (`counts`), the current stage set by `stage`."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {s: 0 for s in STAGES}
        self.current = "nominal"

    def add(self, n: int) -> None:
        """Count `n` run-steps to the current stage."""
        self.counts[self.current] = self.counts.get(self.current, 0) + int(n)

    @contextmanager
    def stage(self, name: str) -> Iterator["RunStepMeter"]:
        """Count to stage `name` inside the block (the previous stage afterwards)."""
        before, self.current = self.current, name
        try:
            yield self
        finally:
            self.current = before

    @property
    def total(self) -> int:
        return int(sum(self.counts.values()))

    def as_dict(self) -> dict[str, int]:
        """{stage: run-steps, ..., "total": all of them} (for the log, --json and the design file)."""
        return {**{k: int(v) for k, v in self.counts.items()}, "total": self.total}


class MeteredPlant(PlantWrapper):
    """A plant whose `step` counts its runs on a `RunStepMeter`; every other attribute is the
    wrapped plant's (its `plant`)."""

    _OWN = ("_plant", "meter")

    def __init__(self, plant: Any, meter: RunStepMeter):
        super().__init__(plant)
        object.__setattr__(self, "meter", meter)

    def step(self, x: Any, u: Any, w: Any = None) -> Any:
        """The plant's step of the runs x (one run for a 1-D x), counted."""
        self.meter.add(1 if np.ndim(x) == 1 else int(np.shape(x)[0]))
        return self._plant.step(x, u) if w is None else self._plant.step(x, u, w)

    @property
    def device_plant(self) -> Any:
        """The wrapped plant, for `sep_plant.device`: a `DevicePlant` keeps its batches resident
        through the meter (`step_resident`)."""
        return self._plant

    def step_resident(self, X: Any, u: Any, w: Any = None) -> Any:
        """The wrapped `DevicePlant`'s resident step of the runs X (device arrays), counted."""
        self.meter.add(1 if X.ndim == 1 else int(X.shape[0]))
        return self._plant.step_resident(X, u) if w is None else self._plant.step_resident(X, u, w)

    def __repr__(self) -> str:
        return f"MeteredPlant({self._plant!r})"


def metered(plant: Any, meter: RunStepMeter) -> MeteredPlant:
    """`plant` with its steps counted on `meter`."""
    return MeteredPlant(unmetered(plant), meter)


def unmetered(plant: Any) -> Any:
    """The plant a `MeteredPlant` wraps (the plant itself otherwise)."""
    return plant.plant if isinstance(plant, MeteredPlant) else plant


def meter_of(plant: Any) -> RunStepMeter | None:
    """The meter counting `plant`'s steps (None: not metered)."""
    return plant.meter if isinstance(plant, MeteredPlant) else None
