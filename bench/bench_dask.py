"""In-process vs a Dask LocalCluster, side by side in one run (no assertions).

The same work twice, once in this process and once on `--dask local:N` (default N = 2, the
cores of this machine), with the same chunk plan, so the answers must agree (the "max rel diff"
column: ≤ 1e-12 expected). Rows:

* TV-ERA impulse experiments alone (reference problem, slab at several n_x, 4 chunks): where
  the cluster's overhead (scheduling, shipping nominal snapshots and field bases) starts to pay;
* a whole design (default: the reference problem on the slab at n_x = 1600, whose Gauss-Newton
  uses the ROM Jacobian: each identification of the optimizer runs in 4 chunks on the cluster; the
  EnKF belief and the Riccati passes stay in the client);
* a 1000-run Monte Carlo of ROM-LQG (the reference design and that design).

The cluster's start-up (a few seconds) is reported once and not charged to any row.

    OPENBLAS_NUM_THREADS=1 python bench/bench_dask.py [--workers 2] [--grids 100 1600 6400]
        [--design-nx 1600] [--runs 1000] [--quick]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.compute.engine import open_engine
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.montecarlo import simulate
from sep_control.design.tvera import impulse_experiments, extend_nominal
from sep_plant.protocol import rollout
from sep_plant.scenario import reference

COLUMNS = ["in_process_s", "dask_s", "speed-up", "max_rel_diff", "note"]


def timed(fn, *a, **kw):
    t0 = time.perf_counter()
    out = fn(*a, **kw)
    return out, time.perf_counter() - t0


def rel(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def row(name, t_here, t_there, diff, note="") -> tuple[str, dict]:
    return name, {"in_process_s": t_here, "dask_s": t_there, "speed-up": t_here / t_there,
                  "max_rel_diff": diff, "note": note}


def experiments_rows(engine, grids):
    for n_x in grids:
        scen = reference().with_plant(n_x=n_x)
        plant, N = scen.plant, scen.problem.n_steps
        U = np.full((N, int(plant.n_u)), 0.3)
        X = rollout(plant, plant.initial_state(1), extend_nominal(U, 30))[0]
        kw = dict(Xbar_ext=X, chunks=4)
        a, t_a = timed(impulse_experiments, plant, U, 30, 15, 3e-3, **kw)
        b, t_b = timed(impulse_experiments, plant, U, 30, 15, 3e-3, engine=engine, **kw)
        yield row(f"TV-ERA experiments, slab n_x={n_x}", t_a, t_b, max(rel(b.Y, a.Y), rel(b.Yf, a.Yf)),
                  f"{a.experiments} experiments")


def design_rows(engine, n_x, runs):
    scen = reference().with_plant(n_x=n_x)
    plant, problem = scen.plant, scen.problem
    st = DesignSettings.for_scenario(scen)
    a, t_a = timed(run_design, plant, problem, st, show_progress=False, log=lambda m: None)
    b, t_b = timed(run_design, plant, problem, DesignSettings.for_scenario(scen), show_progress=False,
                   log=lambda m: None, engine=engine)
    diff = max(rel(b.lqg.K, a.lqg.K), rel(b.nominal.u, a.nominal.u), rel(b.rom.C, a.rom.C))
    name = f"slab {n_x}"
    yield row(f"design, reference problem, {name}", t_a, t_b, diff, f"chunks {st.chunks}")
    for label, sc, d in (("reference", reference(), None), (name, scen, a)):
        if label == name and n_x == 100:
            continue
        if d is None:
            d = run_design(sc.plant, sc.problem, DesignSettings.for_scenario(sc), show_progress=False,
                           log=lambda m: None)
        here, t_h = timed(simulate, sc.plant, d, "rom_lqg", 1, runs, keep_estimates=1, keep_trajectories=1)
        there, t_t = timed(simulate, sc.plant, d, "rom_lqg", 1, runs, keep_estimates=1, keep_trajectories=1,
                           engine=engine)
        # per-run inputs and the mean field (the metrics follow from them)
        diff = max(rel(there.U, here.U), rel(there.F_mean, here.F_mean),
                   abs(there.summary["cost_mean"] - here.summary["cost_mean"]) / here.summary["cost_mean"])
        yield row(f"Monte Carlo {runs} runs, {label} (n_x={sc.plant.n_x})", t_h, t_t, diff,
                  f"in band {here.summary['in_band']:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--grids", type=int, nargs="+", default=[100, 1600, 6400])
    ap.add_argument("--design-nx", type=int, default=1600, help="slab grid of the design row")
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--quick", action="store_true", help="slab 100 and 1600 only, design at n_x = 100, 200 runs")
    args = ap.parse_args()
    if args.quick:
        args.grids, args.design_nx, args.runs = [100, 1600], 100, 200
    rows = {}
    with threadpool_limits(1):
        (engine, t_start) = timed(open_engine, f"local:{args.workers}")
        with engine:
            print(f"{engine.describe()}; cluster start-up {t_start:.1f} s (not in the rows)")
            for name, r in experiments_rows(engine, args.grids):
                rows[name] = r
                print(format_table({name: r}, COLUMNS), flush=True)
            for name, r in design_rows(engine, args.design_nx, args.runs):
                rows[name] = r
                print(format_table({name: r}, COLUMNS), flush=True)
    print(f"\nin-process vs dask local:{args.workers} (one BLAS thread everywhere; speed-up = in-process / dask):")
    print(format_table(rows, COLUMNS))


if __name__ == "__main__":
    main()
