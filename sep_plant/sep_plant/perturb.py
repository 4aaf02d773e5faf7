"""A plant whose actuators and sensors differ from the model's: the generic model mismatch.

`PerturbedPlant` wraps any plant of the protocol and changes only what crosses its boundary:

    u_applied = g * (u + w) + b          (noise on the inputs; g * u + b with its own noise channels)
    y         = h(x) + s                 (observe)

g (`input_gain`), b (`input_offset`, in input units) and s (`sensor_bias`, in output units) are a
scalar for every channel or one value per channel. It is a wrapper rather than new plant keys, so a
design file made for the plant stays valid for it: `evaluate --perturb ...` and the plant node's
perturbation parameters run the same design against it (docs/robustness.md).

With the noise on the inputs the gain scales the noise too (the noise is part of what the
actuator receives), so the wrapper keeps the protocol's rule step(x, u, w) == step(x, u + w).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from sep_plant.plants import make_plant, resolve, type_name_of

#: perturbation keys and the plant dimension each one's per-channel values follow
PERTURBATIONS = {"input_gain": "n_u", "input_offset": "n_u", "sensor_bias": "n_y"}
#: values that leave the plant as it is
NEUTRAL = {"input_gain": 1.0, "input_offset": 0.0, "sensor_bias": 0.0}


class PerturbationError(ValueError):
    """A perturbation key is unknown or its value does not fit the plant."""


def channel_values(name: str, value: Any, n: int) -> np.ndarray:
    """A perturbation value as an (n,) array: a number for every channel or a list of n numbers
    (PerturbationError naming the key otherwise)."""
    arr = np.asarray(value, dtype=float) if not isinstance(value, (str, bytes, bool)) else None
    if arr is None or arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
        raise PerturbationError(f"{name} must be a number or a list of {n} numbers (one per channel), "
                                f"got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise PerturbationError(f"{name} must be finite, got {value!r}")
    return np.broadcast_to(arr, (n,)).astype(float)


def check_perturbation(values: Mapping[str, Any], n_u: int, n_y: int) -> dict[str, np.ndarray]:
    """The perturbation as (n,) arrays per key; unknown keys are refused, naming the known ones."""
    unknown = sorted(set(values) - set(PERTURBATIONS))
    if unknown:
        raise PerturbationError(f"unknown perturbation key(s) {unknown}; known: {sorted(PERTURBATIONS)}")
    dims = {"n_u": n_u, "n_y": n_y}
    return {k: channel_values(k, values.get(k, NEUTRAL[k]), dims[PERTURBATIONS[k]]) for k in PERTURBATIONS}


class PerturbedPlant:
    """`plant` with actuator gain and offset and sensor bias (module docstring).

    Parameters
    ----------
    plant : dict
        The wrapped plant as scenario data, ``{"type": ..., **its keys}`` (so that `config()`
        rebuilds the wrapper, on a Dask worker too).
    input_gain, input_offset, sensor_bias : float or list of float
        g, b (n_u values) and s (n_y values); a number applies to every channel.
    inner : plant, optional
        The plant object `plant` describes, when the caller has it (not built again).
    """

    def __init__(self, plant: Mapping[str, Any], input_gain: Any = 1.0, input_offset: Any = 0.0,
                 sensor_bias: Any = 0.0, *, inner: Any = None):
        if not isinstance(plant, Mapping) or not isinstance(plant.get("type"), str):
            raise PerturbationError(f"plant must be a mapping with 'type' and the plant's keys, got {plant!r}")
        spec = dict(plant)
        self._type = spec.pop("type")
        self.inner = make_plant(self._type, spec) if inner is None else inner
        p = check_perturbation({"input_gain": input_gain, "input_offset": input_offset,
                                "sensor_bias": sensor_bias}, int(self.inner.n_u), int(self.inner.n_y))
        self.gain, self.offset, self.bias = p["input_gain"], p["input_offset"], p["sensor_bias"]
        self._noise_on_inputs = bool(getattr(self.inner, "noise_on_inputs", True))

    @classmethod
    def around(cls, plant: Any, **perturbation: Any) -> "PerturbedPlant":
        """The wrapper of an existing plant object (the object itself, described by its type and
        `config()`)."""
        return cls({"type": type_name_of(plant), **plant.config()}, inner=plant, **perturbation)

    @classmethod
    def rebuild(cls, config: Mapping[str, Any], files: Mapping[str, bytes]) -> "PerturbedPlant":
        """The wrapper of `config` (`config()`) whose wrapped plant reads files, from their bytes
        (on a cluster worker: the wrapped class's own ``rebuild(config, files)``, e.g. an FMU's)."""
        spec = dict(config["plant"])
        kind = spec.pop("type")
        rebuild = getattr(resolve(kind), "rebuild", None)
        inner = rebuild(spec, files) if rebuild is not None else make_plant(kind, spec)
        return cls(config["plant"], **{k: v for k, v in config.items() if k != "plant"}, inner=inner)

    def __getattr__(self, name: str) -> Any:
        # the description (dt, n_x, names, grid_shape, field_is_state, ...) is the wrapped plant's
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def config(self) -> dict[str, Any]:
        return {"plant": {"type": self._type, **self.inner.config()}, "input_gain": self.gain.tolist(),
                "input_offset": self.offset.tolist(), "sensor_bias": self.bias.tolist()}

    def perturbation(self) -> dict[str, list[float]]:
        """The non-neutral perturbation values, per key (what reports name)."""
        out = {"input_gain": self.gain, "input_offset": self.offset, "sensor_bias": self.bias}
        return {k: v.tolist() for k, v in out.items() if np.any(v != NEUTRAL[k])}

    def initial_state(self, batch: int) -> np.ndarray:
        return self.inner.initial_state(batch)

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        if self._noise_on_inputs:
            total = u if w is None else u + w
            return self.inner.step(x, self.gain * total + self.offset)
        return self.inner.step(x, self.gain * u + self.offset, w)

    def observe(self, x: np.ndarray) -> np.ndarray:
        return self.inner.observe(x) + self.bias

    def field(self, x: np.ndarray) -> np.ndarray:
        return self.inner.field(x)

    def field_coordinates(self) -> np.ndarray:
        return self.inner.field_coordinates()

    def __repr__(self) -> str:
        return f"PerturbedPlant({self._type}, {self.perturbation()})"


__all__ = ["NEUTRAL", "PERTURBATIONS", "PerturbationError", "PerturbedPlant", "channel_values",
           "check_perturbation"]
