"""The LQR/MPC state weight on the outputs (lqr_weighting: output) against the weight on the
reconstructed field (lqr_weighting: field), on the shipped scenarios (no assertions; both columns
with the same Monte Carlo seeds, seed 1, runs 0..R-1, in one run).

For each scenario: a design per weighting (`run_design` with the problem key changed; the
nominal and the ROM are the same, the gains differ), then ROM-LQG (and, with --mpc, ROM-MPC)
on the model, and the full-order oracle with the same objective where n_x <= 500. Columns: in
band, mean cost, and the field design against the output design (in band difference, cost
ratio), ROM/oracle.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=sep_plant:sep_estimator:sep_control:examples/burgers \\
        python bench/bench_field_weighting.py [--cases reference burgers rod plate block allen_cahn]
        [--runs 1000] [--mpc rod] [--weightings output field]

The rod needs examples/fmu_rod/rod.fmu (python examples/fmu_rod/build_fmu.py).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.oracle import oracle_lqg
from sep_plant.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = {"reference": REPO / "sep_plant/scenarios/reference.yaml",
             "burgers": REPO / "examples/burgers/scenario.yaml",
             "rod": REPO / "examples/fmu_rod/scenario.yaml",
             "plate": REPO / "sep_plant/scenarios/plate.yaml",
             "block": REPO / "sep_plant/scenarios/block.yaml",
             "allen_cahn": REPO / "sep_plant/scenarios/allen_cahn.yaml"}
COLUMNS = ["in_band", "cost_mean", "d_in_band", "cost/output", "rom/oracle", "design_s"]
ORACLE_MAX_NX = 500
WEIGHTINGS = ("output", "field")


def run_case(case: str, runs: int, controllers: list[str], weightings=WEIGHTINGS) -> dict[str, dict]:
    scen = load_scenario(SCENARIOS[case])
    st = DesignSettings.for_scenario(scen)
    rows: dict[str, dict] = {}
    for w in weightings:
        t0 = time.perf_counter()
        d = run_design(scen.plant, scen.problem.replace(lqr_weighting=w), st, show_progress=False,
                       log=lambda m: None)
        took = time.perf_counter() - t0
        orc = None
        if scen.info.n_x <= ORACLE_MAX_NX and not getattr(scen.plant, "state_is_opaque", False):
            orc = simulate(scen.plant, d, "oracle_lqg", 1, runs, oracle=oracle_lqg(d, scen.plant),
                           keep_estimates=0, keep_trajectories=0).metrics()
        for c in controllers:
            m = simulate(scen.plant, d, c, 1, runs, keep_estimates=0, keep_trajectories=0).metrics()
            m["design_s"] = took
            if orc is not None:
                m["rom/oracle"] = m["cost_mean"] / orc["cost_mean"]
            rows[f"{case} | {c} | {w}"] = m
        if orc is not None:
            rows[f"{case} | oracle_lqg | {w}"] = orc
        print(f"{case}: {w} design {took:.1f} s", flush=True)
    for name, r in rows.items():
        ref = rows.get(name.rsplit("|", 1)[0] + "| output", r)
        r["d_in_band"] = r["in_band"] - ref["in_band"]
        r["cost/output"] = r["cost_mean"] / ref["cost_mean"]
    print(format_table(rows, COLUMNS), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", choices=list(SCENARIOS), default=list(SCENARIOS))
    ap.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs per column (seed 1, runs 0..R-1)")
    ap.add_argument("--mpc", nargs="*", default=["rod"], help="cases that also run rom_mpc")
    ap.add_argument("--weightings", nargs="+", choices=WEIGHTINGS, default=list(WEIGHTINGS),
                    help="the weightings to design with (the same seeds: columns of separate runs compare)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    table: dict[str, dict] = {}
    with threadpool_limits(1):
        for case in args.cases:
            table.update(run_case(case, args.runs, ["rom_lqg"] + (["rom_mpc"] if case in args.mpc else []),
                                  args.weightings))
    print(f"\n{args.runs} runs per row (seed 1); d_in_band and cost/output against the output weighting:")
    print(format_table(table, COLUMNS))
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
