"""Whether a design may run on a given plant: the check of the design-driven nodes, with the
sim-to-real rehearsal's exception (docs/robustness.md).

A design is made on a simulator, "the model". By default a node refuses a design made for other
plant keys than the plant it runs with (`sep_estimator.design_file.check_matches`). Asked with
``allow_model_mismatch``, it runs a design on a plant that differs only where a real plant
differs from its simulator:

* plant keys (``plant.t_right: 150.0 -> 147.0``) and
* a perturbation of the actuators and sensors (``input_gain: 0.8``, `sep_plant.perturb`),

and still refuses what no design can run on: another plant type, another horizon, other problem
keys (target, band, weights; the `RUN_TIME_KEYS` excepted), another interface (inputs, outputs,
noise channels, field nodes). The differences use the words of `sep_plant.truth.plant_differences`,
the same as `sep evaluate --truth` and `sep analyze`.
Pure Python: no ROS import.
"""
from __future__ import annotations

from typing import Any, Mapping

from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario
from sep_plant.truth import interface_differences, plant_differences

from sep_estimator.design_file import DesignFileError, check_matches, problem_mismatches

#: the hint a refusal gives for the rehearsal's way out
ALLOW_HINT = ("; to run this design on this plant anyway (a model-mismatch rehearsal), set "
              "allow_model_mismatch:=true")


def model_mismatch(design: Any, plant: Scenario, info: PlantInfo | None = None,
                   perturbation: Mapping[str, Any] | None = None, allow: bool = False,
                   where: str = "design file") -> list[str]:
    """How the plant differs from the design's model; raises where the design may not run on it.

    Parameters
    ----------
    design : Design
        The loaded design (its scenario's plant is the model).
    plant : Scenario
        The plant's scenario (from a scenario file or the plant's scenario topic).
    info : PlantInfo, optional
        The plant's description (its interface is then checked too).
    perturbation : mapping, optional
        The plant's actuator/sensor perturbation (input_gain, input_offset, sensor_bias).
    allow : bool
        Whether plant keys and a perturbation may differ (``allow_model_mismatch``).
    where : str
        What the design is called in messages.

    Returns
    -------
    list of str
        The differences (``"plant.t_right: 150.0 -> 147.0"``, ``"input_gain: 0.8"``); empty when
        the plant is the model.

    Raises
    ------
    DesignFileError
        The plant differs and `allow` is False (the message names every difference), or it
        differs where no design can follow (type, horizon, problem keys, interface).
    """
    diffs = plant_differences(design.scenario, plant, perturbation)
    if not allow:
        try:
            check_matches(design, plant, where)
        except DesignFileError as exc:
            raise DesignFileError(f"{exc}{ALLOW_HINT if _only_model(design, plant, info) else ''}") from None
        if diffs:      # only the perturbation differs
            raise DesignFileError(f"{where} was designed for the unperturbed plant; this plant is perturbed: "
                                  + "; ".join(diffs) + ALLOW_HINT)
        return []
    hard = _hard_differences(design, plant, info)
    if hard:
        raise DesignFileError(f"{where} cannot run on this plant even with allow_model_mismatch: "
                              + "; ".join(hard) + ". A design runs only on a plant of its type, horizon, "
                              "problem and interface; re-run `sep design` for this one")
    return diffs


def _hard_differences(design: Any, plant: Scenario, info: PlantInfo | None) -> list[str]:
    """What no design can follow: plant type, horizon, problem keys, interface."""
    model = design.scenario
    if model.plant_type != plant.plant_type:
        return [f"plant type: {model.plant_type!r} != {plant.plant_type!r}"]
    out = []
    if model.problem.n_steps != plant.problem.n_steps:
        out.append(f"n_steps: {model.problem.n_steps} != {plant.problem.n_steps}")
    out += problem_mismatches(design.problem, plant.problem)
    if info is not None:
        out += interface_differences(design.info, info)
    return out


def _only_model(design: Any, plant: Scenario, info: PlantInfo | None) -> bool:
    return not _hard_differences(design, plant, info)


__all__ = ["ALLOW_HINT", "model_mismatch"]
