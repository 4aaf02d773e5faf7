"""TV-ERA impulse schemes side by side: central differences (the default) vs forward (no assertions).

Central impulses run a +-delta pair per (step, channel); forward ones one +delta run, differenced
against an unperturbed copy of the nominal stepped in the same batch: about half the plant steps
for a bias of O(delta) in the Markov parameters, and at small delta the round-off of the plant's
own step, divided by delta, shows up as extra directions of the field basis (r_f). For each case
(the reference problem on the slab at several n_x, by default 100 and 1600) this measures, in one
run and with one BLAS thread, for each variant (scheme, amplitude):

* one identification at the central design's optimized nominal: seconds, experiments, field
  basis rank r_f, and the relative difference of its Markov parameters from central differences
  at 1e-2 (whose own O(delta^2) error is below 1e-8 here);
* the whole design with that variant (everything else default): seconds, the relative
  difference of the optimized input from the central design's, the nominal cost;
* a Monte Carlo of each design's ROM-LQG (common random numbers) and, where n_x is small, the
  oracle: in band, cost, ROM / oracle.

    OPENBLAS_NUM_THREADS=1 python bench/bench_impulse.py [--grids 100 1600] [--runs 200]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.oracle import oracle_lqg
from sep_control.design.tvera import identify
from sep_plant.scenario import reference

VARIANTS = {"central 1e-2": ("central", 1e-2), "forward 1e-2": ("forward", 1e-2),
            "forward 1e-3": ("forward", 1e-3)}
COLUMNS = ["n_x", "design_s", "design/central", "identify_s", "identify/central", "experiments", "r_f",
           "markov_vs_central", "u_rel_diff", "nominal_cost", "in_band", "cost_mean", "rom/oracle"]


def timed(fn, *a, **kw):
    t0 = time.perf_counter()
    out = fn(*a, **kw)
    return out, time.perf_counter() - t0


def case(n_x: int, runs: int, oracle_max_nx: int) -> dict[str, dict]:
    scen = reference().with_plant(n_x=n_x)
    plant, problem = scen.plant, scen.problem
    designs, rows = {}, {}
    for name, (scheme, amp) in VARIANTS.items():
        st = DesignSettings(impulse_scheme=scheme, impulse=amp)
        designs[name], t = timed(run_design, plant, problem, st, show_progress=False, log=lambda m: None)
        rows[name] = {"n_x": n_x, "design_s": t}
    U = designs["central 1e-2"].nominal.u
    truth = None
    oracle = oracle_lqg(designs["central 1e-2"], plant) if n_x <= oracle_max_nx else None
    o_cost = None
    if oracle is not None:
        o_cost = simulate(plant, designs["central 1e-2"], "oracle_lqg", 1, runs, oracle=oracle, keep_estimates=0,
                          keep_trajectories=0).summary["cost_mean"]
    for name, (scheme, amp) in VARIANTS.items():
        ident, t = timed(identify, plant, U, 15, 15, 20, 1e-10, amp, scheme=scheme)
        truth = ident.data.Y if truth is None else truth          # the first variant: central 1e-2
        d = designs[name]
        mc = simulate(plant, d, "rom_lqg", 1, runs, keep_estimates=0, keep_trajectories=0).summary
        rows[name].update({
            "identify_s": t, "experiments": ident.data.experiments, "r_f": int(d.rom.G.rank),
            "markov_vs_central": float(np.linalg.norm(ident.data.Y - truth) / np.linalg.norm(truth)),
            "u_rel_diff": float(np.linalg.norm(d.nominal.u - U) / np.linalg.norm(U)),
            "nominal_cost": d.meta["optimizer"]["nominal_cost"], "in_band": mc["in_band"],
            "cost_mean": mc["cost_mean"], "rom/oracle": None if o_cost is None else mc["cost_mean"] / o_cost})
    base = rows["central 1e-2"]
    for r in rows.values():
        r["design/central"] = r["design_s"] / base["design_s"]
        r["identify/central"] = r["identify_s"] / base["identify_s"]
    return {f"slab:{n_x} {name}": r for name, r in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=[100, 1600])
    ap.add_argument("--runs", type=int, default=200, help="Monte Carlo runs per design")
    ap.add_argument("--oracle-max-nx", type=int, default=400)
    args = ap.parse_args()
    rows: dict[str, dict] = {}
    with threadpool_limits(1):
        for n_x in args.grids:
            rows.update(case(n_x, args.runs, args.oracle_max_nx))
            print(f"slab:{n_x} done", flush=True)
    print("\nImpulse schemes, one run, one BLAS thread; ratios to central 1e-2 (the default) from the same run")
    print(format_table(rows, COLUMNS))


if __name__ == "__main__":
    main()
