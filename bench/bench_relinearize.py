"""Identifying again after every Gauss-Newton step vs keeping the last identification while the
input moved by less than `relinearize_rtol` (the design default, 1e-2), side by side in one run
(no assertions).

With the ROM Jacobian every Gauss-Newton iterate used to get its own TV-ERA identification
(2 N n_u impulse experiments of p + q steps), the most plant steps of the design. Near the
optimum the steps move U by 1e-3 and less, and a model identified one step earlier proposes
them as well (every step is accepted on the true objective). The design's own ROM is always
identified at the final input. For each row this measures both settings, alternating, in one
process with one BLAS thread:

* design time, identifications (impulse experiments / 2 N n_u: the central scheme, noise on the
  inputs), counting the design's final one;
* the mean-only optimum J and the final nominal cost, their relative difference, max |dU| /
  max |U| between the two nominals, the final ROM's Markov relative error;
* a Monte Carlo of ROM-LQG (cost, in band) and, where the full-order oracle fits (n_x <= 400),
  ROM-LQG / oracle cost.

    OPENBLAS_NUM_THREADS=1 python bench/bench_relinearize.py                  # slab 100 and 1600
    python bench/bench_relinearize.py --rows slab:10000 --runs 200
    python bench/bench_relinearize.py --rows slab:100 allen_cahn --repeats 3
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.montecarlo import simulate
from sep_control.design.linearization import SAME_INPUT_RTOL
from sep_control.evaluation.oracle import oracle_lqg
from sep_plant.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
SETTINGS = {"every step": SAME_INPUT_RTOL, "default": DesignSettings.relinearize_rtol}


def scenario_of(row: str):
    """'slab:N' (the reference problem at n_x = N) or a shipped scenario's name."""
    if row.startswith("slab:"):
        return load_scenario(None).with_plant(n_x=int(row.split(":")[1]))
    return load_scenario(REPO / "sep_plant" / "scenarios" / f"{row}.yaml")


def measure(row: str, repeats: int, runs: int) -> list[dict]:
    scen = scenario_of(row)
    plant, problem = scen.plant, scen.problem
    designs, times = {}, {name: [] for name in SETTINGS}
    for _ in range(repeats):
        for name, rtol in SETTINGS.items():      # alternating: load drifts hit both alike
            st = DesignSettings.for_scenario(scen, relinearize_rtol=rtol)
            t0 = time.perf_counter()
            designs[name] = run_design(plant, problem, st, show_progress=False, log=lambda m: None)
            times[name].append(time.perf_counter() - t0)
    per_ident = 2 * problem.n_steps * plant.n_u
    oracle = oracle_lqg(designs["every step"], plant) if plant.n_x <= 400 else None
    out = []
    base = designs["every step"]
    for name, d in designs.items():
        opt = d.meta["optimizer"]
        mc = simulate(plant, d, "rom_lqg", 1, runs, keep_estimates=0, keep_trajectories=0).summary
        row_out = {
            "row": row, "setting": name, "rtol": SETTINGS[name], "design_s": float(np.median(times[name])),
            "idents": (opt["experiments"] + opt["belief_experiments"]) / per_ident
            + (0 if opt["identification_reused"] else 1),
            "J_mean_only": opt["mean_only_cost"], "J_nominal": opt["nominal_cost"],
            "dJ_rel": abs(opt["nominal_cost"] - base.meta["optimizer"]["nominal_cost"]) / base.meta["optimizer"]["nominal_cost"],
            "dU_rel": float(np.max(np.abs(d.nominal.u - base.nominal.u)) / np.max(np.abs(base.nominal.u))),
            "markov": d.meta["validation"]["markov_rel_error"],
            "mc_cost": mc["cost_mean"], "in_band": mc["in_band"],
        }
        if oracle is not None:
            orc = simulate(plant, d, "oracle_lqg", 1, runs, oracle=oracle_lqg(d, plant), keep_estimates=0,
                           keep_trajectories=0).summary
            row_out["rom/oracle"] = mc["cost_mean"] / orc["cost_mean"]
        out.append(row_out)
    out[1]["time ratio"] = out[1]["design_s"] / out[0]["design_s"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", nargs="+", default=["slab:100", "slab:1600"],
                    help="slab:N (reference problem at n_x = N) or a shipped scenario name (plate, allen_cahn, ...)")
    ap.add_argument("--repeats", type=int, default=1, help="designs per setting (median time)")
    ap.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs of ROM-LQG per design")
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads")
    args = ap.parse_args()
    cols = ["row", "setting", "rtol", "design_s", "time ratio", "idents", "J_mean_only", "J_nominal", "dJ_rel",
            "dU_rel", "markov", "mc_cost", "in_band", "rom/oracle"]
    fmt = lambda v: "-" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)
    print(" | ".join(cols))
    print(" | ".join("---" for _ in cols))
    with threadpool_limits(args.threads):
        for row in args.rows:
            for r in measure(row, args.repeats, args.runs):
                cells = [fmt(r.get(c)) for c in cols]
                cells[cols.index("J_mean_only")] = f"{r['J_mean_only']:.10g}"
                cells[cols.index("J_nominal")] = f"{r['J_nominal']:.10g}"
                print(" | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
