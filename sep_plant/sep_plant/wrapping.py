"""A plant wrapped by another object that adds to its `step` and forwards everything else.

`PlantWrapper` is the base of the wrappers the design and the device path put around a plant
(`sep_plant.device.DevicePlant`, which steps it on a GPU; the design's run-step meter,
`sep_control.design.runsteps.MeteredPlant`): the wrapper's own names (`_OWN`, and the methods and
properties of its class) stay on the wrapper; reading any other attribute reads the plant's, and
setting one sets the plant's (`solver`, `block_nodes`, ...). Pure Python: no ROS import.
"""
from __future__ import annotations

from typing import Any

__all__ = ["PlantWrapper"]


class PlantWrapper:
    """Forwards every attribute but its own (`_OWN`, its class's) to the wrapped plant `plant`."""

    _OWN: tuple[str, ...] = ("_plant",)

    def __init__(self, plant: Any):
        object.__setattr__(self, "_plant", plant)

    @property
    def plant(self) -> Any:
        """The wrapped plant."""
        return self._plant

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in self._OWN:
            raise AttributeError(name)
        return getattr(self._plant, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self._OWN or hasattr(type(self), name):
            object.__setattr__(self, name, value)
        else:
            setattr(self._plant, name, value)
