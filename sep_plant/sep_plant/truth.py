"""The truth plant of a model-mismatch evaluation: the plant a design runs on when it is not the
plant the design was made for.

A design is made on a simulator (its scenario's plant, "the model"); the plant it runs on always
differs. `truth_plant` builds that other plant from the model's scenario and

* plant keys that differ (``t_right=147``, ``boundary_temperatures={x_max: 147}``: values are YAML),
* or another scenario file's plant of the same type (``--truth-scenario``),
* and a generic perturbation of actuators and sensors (`sep_plant.perturb.PerturbedPlant`:
  input_gain, input_offset, sensor_bias), which keeps the design file valid.

It refuses, naming what to fix, an unknown plant key, an unknown perturbation key, and a truth
plant whose interface differs from the model's (inputs, outputs, noise channels, field nodes):
a design's filter and gains only fit a plant with the same interface. The state dimension n_x may
differ (the oracle is then built on the truth's own states). Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from sep_plant.perturb import NEUTRAL, PerturbationError, PerturbedPlant, check_perturbation
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario, ScenarioError, load_yaml


class TruthError(ValueError):
    """The truth plant cannot be built or does not fit the design (the message names why)."""


@dataclass(frozen=True)
class Truth:
    """A truth plant and how it differs from the model."""

    plant: Any
    scenario: Scenario                     # the truth's own scenario (plant keys), canonical
    differences: tuple[str, ...]           # "plant.t_right: 150.0 -> 147.0", "input_gain: 0.8", ...
    perturbation: Mapping[str, list] = field(default_factory=dict)

    @property
    def is_model(self) -> bool:
        """Whether the truth is the model itself (no difference)."""
        return not self.differences

    def describe(self) -> str:
        return "the model itself" if self.is_model else "; ".join(self.differences)

    def record(self) -> dict[str, Any]:
        """Plain data for JSON outputs and bags: the truth's plant and what differs."""
        return {"plant": {"type": self.scenario.plant_type, **dict(self.scenario.plant_config)},
                "differences": list(self.differences), "perturbation": dict(self.perturbation)}


def parse_assignments(items: Sequence[str], what: str = "--truth") -> dict[str, Any]:
    """``KEY=VALUE`` strings as a dict, each VALUE read as YAML (``147``, ``[147, 150]``,
    ``{x_max: 147}``); TruthError naming the item that is not of that form."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = str(item).partition("=")
        key = key.strip()
        if not sep or not key:
            raise TruthError(f"{what}: expected KEY=VALUE, got {item!r}")
        try:
            out[key] = load_yaml(text) if text.strip() else None
        except yaml.YAMLError as exc:
            raise TruthError(f"{what}: {key}: not a YAML value: {text!r} ({exc})") from None
    return out


def truth_plant(model: Scenario, keys: Mapping[str, Any] | None = None,
                perturbation: Mapping[str, Any] | None = None, scenario: Scenario | None = None) -> Truth:
    """The truth plant for a design made on `model`'s plant.

    Parameters
    ----------
    model : Scenario
        The design's scenario (its plant is the model).
    keys : mapping, optional
        Plant keys of the truth that differ from the model's (or from `scenario`'s plant).
    perturbation : mapping, optional
        input_gain, input_offset, sensor_bias (`sep_plant.perturb`).
    scenario : Scenario, optional
        Another scenario whose plant (of the same type) is the truth's starting point.

    Returns
    -------
    Truth
        The plant (a `PerturbedPlant` when a perturbation is given), its scenario and the list of
        differences from the model.
    """
    base = scenario if scenario is not None else model
    if base.plant_type != model.plant_type:
        raise TruthError(f"the truth scenario's plant is of type {base.plant_type!r}, the design's "
                         f"{model.plant_type!r}: a truth plant must be of the design's type")
    known = dict(base.plant_config) if scenario is None else dict(base.canonical().plant_config)
    keys = dict(keys or {})
    unknown = sorted(k for k in keys if k not in known)
    if unknown:
        raise TruthError(f"unknown truth key(s) {unknown} for plant {model.plant_type!r}; its keys: "
                         f"{', '.join(sorted(known))}")
    try:
        truth_scn = base.with_plant(**keys) if keys else base.canonical()
        inner = truth_scn.plant
    except ScenarioError as exc:
        raise TruthError(f"truth plant: {exc}") from None
    _check_interface(model.info, PlantInfo.of(inner))
    plant, pert = inner, {}
    if perturbation:
        try:
            values = check_perturbation(perturbation, int(inner.n_u), int(inner.n_y))
            plant = PerturbedPlant.around(inner, **{k: v.tolist() for k, v in values.items()})
        except PerturbationError as exc:
            raise TruthError(f"--perturb: {exc}") from None
        pert = plant.perturbation()
    return Truth(plant, truth_scn, tuple(plant_differences(model, truth_scn, pert)), pert)


def plant_differences(model: Scenario, plant: Scenario, perturbation: Mapping[str, Any] | None = None) -> list[str]:
    """How `plant` (and a perturbation of it) differs from the design's plant `model`, one entry
    per key: "plant.t_right: 150.0 -> 147.0", "input_gain: 0.8" (empty: the model itself).

    The vocabulary of `Truth.differences`, of the nodes' ``model_mismatch`` and of `sep analyze`.
    The horizon is not compared (a problem key, not the plant's); neutral perturbation values
    are left out.
    """
    diffs = [d.replace(" != ", " -> ") for d in model.plant_mismatches(plant) if not d.startswith("n_steps")]
    neutral = {k: v for k, v in (perturbation or {}).items()
               if not np.all(np.asarray(v, dtype=float) == NEUTRAL.get(k, np.nan))}
    return diffs + [f"{k}: {_short(v)}" for k, v in neutral.items()]


def interface_differences(model: PlantInfo, truth: PlantInfo) -> list[str]:
    """Where the truth's interface (inputs, outputs, noise channels, field nodes) differs from the
    model's, each naming both values (empty: a design of the model fits the truth)."""
    problems = []
    for attr in ("n_u", "n_y", "n_field", "noise_dim"):
        a, b = getattr(model, attr), getattr(truth, attr)
        if a != b:
            problems.append(f"{attr} {b} (the design's plant has {a})")
    for attr, count in (("input_names", "n_u"), ("output_names", "n_y")):   # names, where the counts agree
        if getattr(model, attr) != getattr(truth, attr) and getattr(model, count) == getattr(truth, count):
            problems.append(f"{attr} {list(getattr(truth, attr))} (the design's: {list(getattr(model, attr))})")
    return problems


def _check_interface(model: PlantInfo, truth: PlantInfo) -> None:
    problems = interface_differences(model, truth)
    if problems:
        raise TruthError("the truth plant has another interface than the design's plant: " + "; ".join(problems)
                         + ". A design runs only on plants with its inputs, outputs and field nodes")


def _short(values: list) -> str:
    arr = np.asarray(values)
    return f"{arr[0]:g}" if arr.size and np.all(arr == arr[0]) else "[" + ", ".join(f"{v:g}" for v in arr) + "]"


__all__ = ["Truth", "TruthError", "interface_differences", "parse_assignments", "plant_differences",
           "truth_plant"]
