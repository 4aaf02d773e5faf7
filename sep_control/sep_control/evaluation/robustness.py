"""Model-mismatch evaluation: a design run on a truth plant, and the robustness sweep
(`sep evaluate --truth/--truth-scenario/--perturb/--robustness`, docs/robustness.md).

A design is made on its scenario's plant, "the model"; `sep_plant.truth.truth_plant` builds the
plant it is run on, "the truth" (other plant keys, another scenario's plant of the same type, a
perturbation of actuators and sensors), and refuses what no design can run on. Here:

* `make_truth`: the truth of the command line's options (None when none is given);
* `oracle_on`: the full-order oracle on a truth (`sep_control.evaluation.oracle.truth_oracle`:
  linearized along the design's nominal with the truth's offsets as affine terms; the model's
  own oracle when the truth is the model);
* `parse_sweep` / `sweep_truths`: ``KEY=LO:HI:N``, one truth-plant key (a dotted key for an
  entry of a mapping-valued key: ``boundary_temperatures.x_max``) or a perturbation key over N
  evenly spaced values;
* `evaluate_truth`: every controller on one truth, the same seeds for all (common random numbers);
* `plants_record`: both plants as plain data for the JSON outputs.

Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from sep_plant.perturb import PERTURBATIONS
from sep_plant.scenario import Scenario
from sep_plant.truth import Truth, TruthError, parse_assignments, truth_plant

from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.oracle import Oracle, OracleUnavailable, oracle_lqg, truth_oracle


def make_truth(model: Scenario, truth: Sequence[str] | None = None, perturb: Sequence[str] | None = None,
               scenario: Scenario | None = None) -> Truth | None:
    """The truth plant of ``--truth KEY=VALUE ...``, ``--perturb KEY=VALUE ...`` and
    ``--truth-scenario`` (already loaded); None when none of them is given.

    Raises
    ------
    TruthError
        An item is not KEY=VALUE, a key is unknown, a value does not fit, or the truth has another
        interface than the model (the message names it).
    """
    if not truth and not perturb and scenario is None:
        return None
    keys = parse_assignments(truth or [], "--truth")
    pert = parse_assignments(perturb or [], "--perturb")
    return truth_plant(model, keys, pert, scenario)


def oracle_on(design: Any, truth: Truth | None, plant: Any, model: Any | None = None) -> Oracle | Any:
    """The full-order oracle on the plant the controllers run on.

    Parameters
    ----------
    design : Design
        The design.
    truth : Truth or None
        The truth (None, or the model itself: the model's oracle, `oracle_lqg`, as without a truth).
    plant : Plant
        The plant object the Monte Carlo steps (the truth's, possibly on a device).
    model : Plant, optional
        The design's plant (its nominal states); the design scenario's (cached) plant when None.

    Returns
    -------
    LQG or Oracle
        `oracle_lqg` on the model; `truth_oracle` (affine terms) on another truth.

    Raises
    ------
    OracleUnavailable
        The truth's state dimension differs from the model's.
    """
    if truth is None or truth.is_model:
        return oracle_lqg(design, plant)
    return truth_oracle(design, plant, model)


@dataclass(frozen=True)
class Sweep:
    """A robustness sweep: `key` over `values` (a plant key, dotted for a mapping's entry, or a
    perturbation key)."""

    key: str
    values: tuple[float, ...]

    @property
    def is_perturbation(self) -> bool:
        return self.key in PERTURBATIONS

    def label(self, value: float) -> str:
        return f"{self.key}={value:g}"


def parse_sweep(text: str) -> Sweep:
    """``KEY=LO:HI:N`` as a `Sweep` of N evenly spaced values from LO to HI (N >= 2).

    Raises
    ------
    TruthError
        Not of that form, LO/HI not numbers, N not an integer >= 2 (the message names it).
    """
    key, sep, rng = str(text).partition("=")
    key = key.strip()
    parts = rng.split(":")
    if not sep or not key or len(parts) != 3:
        raise TruthError(f"--robustness: expected KEY=LO:HI:N (e.g. t_right=146:150:5), got {text!r}")
    try:
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        raise TruthError(f"--robustness {key}: LO and HI must be numbers, got {parts[0]!r} and {parts[1]!r}") from None
    try:
        n = int(parts[2])
    except ValueError:
        raise TruthError(f"--robustness {key}: N must be an integer >= 2, got {parts[2]!r}") from None
    if n < 2:
        raise TruthError(f"--robustness {key}: N must be >= 2 (a sweep needs two values at least), got {n}")
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise TruthError(f"--robustness {key}: LO and HI must be finite, got {lo:g} and {hi:g}")
    return Sweep(key, tuple(float(v) for v in np.linspace(lo, hi, n)))


def sweep_truths(model: Scenario, sweep: Sweep, truth: Sequence[str] | None = None,
                 perturb: Sequence[str] | None = None, scenario: Scenario | None = None) -> list[Truth]:
    """One truth per sweep value: the ``--truth``/``--perturb``/``--truth-scenario`` truth with the
    swept key set to the value (TruthError naming an unknown key or a value that does not fit)."""
    keys = parse_assignments(truth or [], "--truth")
    pert = parse_assignments(perturb or [], "--perturb")
    base = dict((scenario if scenario is not None else model).canonical().plant_config)
    out = []
    for v in sweep.values:
        k, p = dict(keys), dict(pert)
        if sweep.is_perturbation:
            p[sweep.key] = v
        else:
            name, value = _plant_value(sweep.key, v, base, keys, model.plant_type)
            k[name] = value
        out.append(truth_plant(model, k, p, scenario))
    return out


def _plant_value(key: str, value: float, base: Mapping[str, Any], given: Mapping[str, Any],
                 plant_type: str) -> tuple[str, Any]:
    """(plant key, its value) for a swept key: ``name`` or ``name.entry`` of a mapping-valued key."""
    name, dot, entry = key.partition(".")
    if name not in base:
        raise TruthError(f"--robustness: unknown key {name!r}: neither a perturbation key ({', '.join(PERTURBATIONS)}) "
                         f"nor a key of plant {plant_type!r} ({', '.join(sorted(base))})")
    current = given.get(name, base[name])
    if dot:
        if not isinstance(current, Mapping):
            raise TruthError(f"--robustness {key}: plant key {name!r} is not a mapping (its value: {current!r}); "
                             f"sweep {name} itself")
        return name, {**dict(current), entry: value}
    if isinstance(current, Mapping) or isinstance(current, (list, tuple)):
        raise TruthError(f"--robustness {key}: plant key {name!r} holds {current!r}, not a number; sweep one entry "
                         f"of it (KEY.ENTRY=LO:HI:N) or set it with --truth")
    if isinstance(current, int) and not isinstance(current, bool) and float(value).is_integer():
        return name, int(value)
    return name, value


def evaluate_truth(plant: Any, design: Any, controllers: Sequence[str], seed: int, runs: int,
                   oracle: Any = None, on_done: Callable[[str, dict], None] | None = None,
                   **simulate_kw: Any) -> dict[str, dict[str, Any]]:
    """The metrics of every controller on `plant` (the same seeds for all; `simulate`'s keywords
    pass through). 'oracle_lqg' needs `oracle` (`oracle_on`) and is left out when it is None.

    Returns
    -------
    dict
        Controller name -> its metrics (docs/method.md).
    """
    rows: dict[str, dict[str, Any]] = {}
    for name in controllers:
        if name == "oracle_lqg" and oracle is None:
            continue
        res = simulate(plant, design, name, seed, runs, oracle=oracle, keep_estimates=0, keep_trajectories=0,
                       **simulate_kw)
        rows[name] = res.metrics()
        if on_done is not None:
            on_done(name, rows[name])
    return rows


def plants_record(design: Any, truth: Truth | None) -> dict[str, Any]:
    """Both plants as plain data: the model (the design's plant) and the truth (`Truth.record`,
    with what differs)."""
    sc = design.scenario
    model = {"type": sc.plant_type, **dict(sc.plant_config)}
    return {"model": model, "truth": truth.record() if truth is not None else
            {"plant": model, "differences": [], "perturbation": {}}}


__all__ = ["OracleUnavailable", "Sweep", "evaluate_truth", "make_truth", "oracle_on", "parse_sweep",
           "plants_record", "sweep_truths"]
