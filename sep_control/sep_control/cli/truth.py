"""The model-mismatch options of `sep evaluate`: --truth, --truth-scenario, --perturb and the
--robustness sweep (the logic: `sep_control.evaluation.robustness`; docs/robustness.md).

Bad values exit 2 naming them (`TruthError`'s message): an item that is not KEY=VALUE, an
unknown truth or perturbation key, a value that does not fit, a truth plant with another
interface than the design's, a sweep that is not KEY=LO:HI:N with N >= 2.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from sep_plant.perturb import NEUTRAL
from sep_plant.truth import Truth, TruthError

from sep_control.cli.common import fail, plant_or_exit, scenario_or_exit
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.robustness import (OracleUnavailable, Sweep, evaluate_truth, make_truth, oracle_on,
                                             parse_sweep, plants_record, sweep_truths)

SWEEP_KEYS = ["in_band", "cost_mean", "mean_dev_end", "cost/oracle"]


def add_truth_options(parser: argparse.ArgumentParser) -> None:
    """The "Model mismatch" option group of `sep evaluate`."""
    g = parser.add_argument_group("Model mismatch (docs/robustness.md)")
    g.add_argument("--truth", nargs="+", metavar="KEY=VALUE", default=None,
                   help="run the controllers on a truth plant: the design's plant with these plant keys changed; "
                        "values are YAML (t_right=147, boundary_temperatures={x_max: 147}, viscosity=0.012)")
    g.add_argument("--truth-scenario", metavar="FILE", default=None,
                   help="the truth plant is this scenario's plant (same type and interface as the design's); "
                        "--truth changes keys of it")
    g.add_argument("--perturb", nargs="+", metavar="KEY=VALUE", default=None,
                   help="perturb the truth's actuators and sensors: input_gain=G input_offset=B sensor_bias=S "
                        "(a number for every channel or a list, one per channel): u -> G u + B, y -> y + S")
    g.add_argument("--robustness", metavar="KEY=LO:HI:N", default=None,
                   help="sweep one truth-plant key (KEY.ENTRY for a mapping's entry, e.g. "
                        "boundary_temperatures.x_max) or perturbation key over N >= 2 values from LO to HI: "
                        "a table, --json and --figures (in band and cost against the key)")


def wants_truth(args: argparse.Namespace) -> bool:
    return bool(args.truth or args.perturb or args.truth_scenario or args.robustness)


def truth_or_exit(args: argparse.Namespace, design) -> Truth | None:
    """The truth plant of the options (None without any); exit 2 naming a bad value."""
    scenario = scenario_or_exit(args.truth_scenario) if args.truth_scenario else None
    try:
        return make_truth(design.scenario, args.truth, args.perturb, scenario)
    except TruthError as exc:
        fail(str(exc))


def sweep_or_exit(args: argparse.Namespace, design) -> tuple[Sweep, list[Truth]]:
    """The --robustness sweep and its truth plants; exit 2 naming a bad value."""
    scenario = scenario_or_exit(args.truth_scenario) if args.truth_scenario else None
    try:
        sweep = parse_sweep(args.robustness)
        return sweep, sweep_truths(design.scenario, sweep, args.truth, args.perturb, scenario)
    except TruthError as exc:
        fail(str(exc))


def truth_plant_or_exit(truth: Truth, device: str):
    """The truth's plant, checked against the plant protocol and placed on `device` (exit 2)."""
    return plant_or_exit(truth.scenario, f"truth plant ({truth.describe()})", device=device, plant=truth.plant)


def oracle_or_none(design, truth: Truth | None, plant):
    """The oracle on the truth (`oracle_on`), or None with a line saying why it cannot be built."""
    try:
        return oracle_on(design, truth, plant)
    except OracleUnavailable as exc:
        print(f"oracle_lqg skipped: {exc}")
        return None


def describe(design, truth: Truth | None) -> str:
    """The line naming both plants."""
    return (f"model: the design's plant ({design.scenario.plant_type}); truth: "
            + (truth.describe() if truth is not None else "the model itself"))


def run_robustness(args: argparse.Namespace, design, controllers: list[str], sweep: Sweep, truths: list[Truth],
                   budget, engine, bar) -> dict[str, Any]:
    """Every controller on every truth of the sweep (same seeds); prints the table; returns the
    JSON object (`robustness_figure` draws it)."""
    points = []
    for value, truth in zip(sweep.values, truths):
        plant = truth_plant_or_exit(truth, args.device)
        oracle = oracle_or_none(design, truth, plant) if "oracle_lqg" in controllers else None
        t0 = time.perf_counter()
        rows = evaluate_truth(plant, design, controllers, args.seed, args.runs, oracle=oracle,
                              on_done=lambda name, row: bar.add(args.runs, design.n_steps),
                              memory_budget=budget, engine=engine, mpc=mpc_options(args))
        points.append({"value": value, "truth": truth.record(), "controllers": rows,
                       "seconds": time.perf_counter() - t0})
    print(f"robustness of the design against the truth plant's {sweep.key}: {args.runs} runs per controller "
          f"and value, seed {args.seed}; {describe(design, truths[0])} (at the first value)")
    print(format_table(sweep_table(sweep, points), SWEEP_KEYS))
    return {"sweep": {"key": sweep.key, "values": list(sweep.values)}, "model": plants_record(design, None)["model"],
            "runs": args.runs, "seed": args.seed, "points": points}


def sweep_table(sweep: Sweep, points: list[dict]) -> dict[str, dict]:
    """Table rows "KEY=VALUE controller" with in band, cost, deviation at the window end and the
    cost relative to the oracle at that value."""
    table = {}
    for pt in points:
        rows = pt["controllers"]
        oracle = rows.get("oracle_lqg", {}).get("cost_mean")
        for name, r in rows.items():
            table[f"{sweep.label(pt['value'])} {name}"] = {
                **r, "cost/oracle": r["cost_mean"] / oracle if oracle else None}
    return table


def robustness_figure(out: Path, design, result: dict) -> Path:
    """figures.robustness_figure of a `run_robustness` result."""
    from sep_control.evaluation import figures

    key, values = result["sweep"]["key"], result["sweep"]["values"]
    names = list(dict.fromkeys(n for pt in result["points"] for n in pt["controllers"]))
    rows = {n: [pt["controllers"].get(n) for pt in result["points"]] for n in names}
    name, _, entry = key.partition(".")
    own = NEUTRAL.get(key, design.scenario.plant_config.get(name))       # the model's own value
    own = own.get(entry) if entry and isinstance(own, dict) else own
    return figures.robustness_figure(out / "robustness.png", key, values, rows,
                                     own if isinstance(own, (int, float)) and not isinstance(own, bool) else None)


def mpc_options(args: argparse.Namespace) -> dict:
    return {"horizon": args.mpc_horizon, "time_budget_s": args.mpc_time_budget}
