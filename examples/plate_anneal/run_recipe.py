#!/usr/bin/env python3
"""A recipe end to end with sep's Python API: design the plate-anneal scenario (optionally on a
coarser grid), run a short Monte Carlo of every controller, and print the results per hold.

    python examples/plate_anneal/run_recipe.py --nodes 12 --runs 50      # about 2 min on one core
    python examples/plate_anneal/run_recipe.py --runs 1000               # the shipped 24 x 24 grid

The scenario is sep_plant/scenarios/plate_anneal.yaml (its header says how its numbers were
chosen); `sep design` / `sep evaluate` on it give the same numbers for the same grid.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.metrics import segment_max_dev
from sep_control.evaluation.montecarlo import simulate
from sep_plant.protocol import rate_feasible
from sep_plant.scenario import load_scenario

SCENARIO = Path(__file__).resolve().parents[2] / "sep_plant" / "scenarios" / "plate_anneal.yaml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=None, help="grid nodes per side (default: the scenario's 24)")
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    sc = load_scenario(SCENARIO)
    if args.nodes:
        sc = sc.with_plant(nodes=[args.nodes, args.nodes])
    with threadpool_limits(1):
        d = run_design(sc.plant, sc.problem, DesignSettings.for_scenario(sc), show_progress=False, log=lambda m: None)
        obj = d.objective
        du = d.problem.channels("du_max", d.info.n_u)
        nom = segment_max_dev(d.nominal.field[None], obj)[:, 0]
        print(f"nominal cost {obj.cost(d.nominal.field, d.nominal.u):.4g}, rate-feasible "
              f"{bool(rate_feasible(d.nominal.u, du))}, worst |f - f*| per hold: "
              + ", ".join(f"{v:.2f} (band {b:g})" for v, (_, _, b) in zip(nom, obj.holds)))
        for name in ("open_loop", "rom_lqg", "rom_mpc"):
            s = simulate(sc.plant, d, name, args.seed, args.runs, mpc={"horizon": 5}).summary   # H as in docs
            holds = ", ".join(f"{h['in_band']:.3f} in band (max {h['max_dev']:.2f})" for h in s["segments"])
            print(f"{name:10s} cost {s['cost_mean']:.4g}, in band {s['in_band']:.3f}; per hold: {holds}; "
                  f"rate clips {s['rate_clips']}, plant clips {s['rate_violations']}")


if __name__ == "__main__":
    main()
