"""`evaluate`: Monte Carlo of open loop, ROM-LQG and the full-order oracle on the nonlinear plant."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from sep_estimator.ltv import sensed_nodes

from sep_control.evaluation import figures
from sep_control.cli.common import (Formatter, add_dask, add_device, add_memory_budget, add_threads, blas_threads,
                         design_or_exit, engine_or_exit, fail, memory_budget_or_exit, plant_or_exit)
from sep_control.design.pipeline import DesignSettings, identify_rom, with_rom
from sep_control.evaluation.metrics import CONTROLLERS, format_table, write_json
from sep_control.evaluation.montecarlo import portable, simulate
from sep_control.evaluation.oracle import oracle_lqg
from sep_control.compute.progress import progress
from sep_control.design.tvera import markov_relative_error, tv_era

DESCRIPTION = """\
Monte Carlo evaluation of a design on the nonlinear plant with process and sensor noise.
Every controller sees the same random numbers (run i of seed s is the episode a plant node
started with seed=s, run=i plays). Controllers: open_loop (nominal input), rom_lqg (the
design's LQG), oracle_lqg (the same LQG on full-order finite-difference Jacobians; only where
n_x <= --oracle-max-nx, since it costs n_x^2 N memory and n_x^3 N time). Prints the docs/method.md
metrics; --json writes them, --figures the paper's figures as PNG (heat maps for grid plants);
--sweep adds the ROM-order sweep (n_r = 5, 10, 20, 40). The plant is rebuilt from the design
file's scenario.

Example:  evaluate --design out/design.npz --runs 1000 --figures out/figures --sweep
"""

TABLE_KEYS = ["cost_mean", "cost_std", "in_band", "rms", "mean_dev_start", "mean_dev_end", "coverage_2sigma",
              "n_runs", "seconds"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="evaluate", description=DESCRIPTION, formatter_class=Formatter)
    p.add_argument("--design", metavar="DESIGN_FILE", required=True, help="design file from `design`")
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs per controller")
    p.add_argument("--seed", type=int, default=1, help="base seed of the noise (common random numbers)")
    p.add_argument("--controllers", nargs="+", choices=CONTROLLERS, default=None,
                   help="default: open_loop rom_lqg oracle_lqg, and rom_mpc when the scenario has input limits")
    p.add_argument("--mpc-horizon", type=int, default=20, help="rom_mpc: horizon H in steps")
    p.add_argument("--mpc-budget", type=float, default=None,
                   help="rom_mpc: seconds a QP may take before the step falls back to the clipped LQR "
                        "(default: no budget offline, so the numbers do not depend on the machine's load; "
                        "the online node's default is 0.02)")
    p.add_argument("--oracle-max-nx", type=int, default=500,
                   help="skip the full-order oracle above this many states (n_x^2 N memory)")
    p.add_argument("--json", metavar="PATH", help="write metrics as JSON (one object per controller)")
    p.add_argument("--figures", metavar="DIR", help="write the PNG figures here")
    p.add_argument("--sweep", action="store_true", help="ROM-order sweep (re-identifies at each n_r)")
    p.add_argument("--sweep-orders", type=int, nargs="+", default=[5, 10, 20, 40])
    p.add_argument("--sweep-runs", type=int, default=200, help="Monte Carlo runs per sweep point")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_threads(p)
    add_memory_budget(p)
    add_dask(p)
    add_device(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.runs < 1:
        fail(f"--runs must be >= 1, got {args.runs}")
    budget = memory_budget_or_exit(args.memory_budget)
    design = design_or_exit(args.design)
    plant = plant_or_exit(design.scenario, f"{args.design} (its scenario)", device=args.device)
    lo, hi = design.problem.limits(design.info.n_u)
    limited = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
    controllers = list(args.controllers) if args.controllers else \
        [c for c in CONTROLLERS if c != "rom_mpc" or limited]
    if args.mpc_horizon < 1 or (args.mpc_budget is not None and not args.mpc_budget > 0):
        fail("--mpc-horizon must be >= 1 and --mpc-budget > 0")
    oracle_fits = design.info.n_x <= args.oracle_max_nx
    if "oracle_lqg" in controllers and not oracle_fits:
        print(f"oracle_lqg skipped: n_x = {design.info.n_x} > --oracle-max-nx = {args.oracle_max_nx}")
        controllers.remove("oracle_lqg")
    rows: dict[str, dict] = {}
    results = {}
    with blas_threads(args.threads), engine_or_exit(args.dask, log=print) as engine:
        oracle, oracle_s = None, 0.0
        if "oracle_lqg" in controllers or (args.sweep and oracle_fits):
            t0 = time.perf_counter()
            oracle = oracle_lqg(design, plant)
            oracle_s = time.perf_counter() - t0
        for name in progress(controllers, desc="Monte Carlo", enabled=not args.quiet):
            t0 = time.perf_counter()
            res = simulate(plant, design, name, args.seed, args.runs, oracle=oracle, keep_estimates=1,
                           keep_trajectories=1, memory_budget=budget, engine=engine,
                           mpc={"horizon": args.mpc_horizon, "time_budget_s": args.mpc_budget})
            rows[name] = res.metrics()
            rows[name]["seconds"] = time.perf_counter() - t0
            results[name] = res
        print(f"{args.runs} runs per controller, seed {args.seed}, plant {design.scenario.plant_type}, "
              f"n_x = {design.info.n_x}, n_r = {design.n_r}")
        print(format_table(rows, TABLE_KEYS))
        if "rom_lqg" in rows and "oracle_lqg" in rows:
            ratio = rows["rom_lqg"]["cost_mean"] / rows["oracle_lqg"]["cost_mean"]
            print(f"ROM-LQG / oracle mean cost: {ratio:.5f}  (oracle design {oracle_s:.2f} s)")
        sweep_rows = rom_sweep(plant, design, oracle, args, engine) if args.sweep else None
    if args.json:
        write_json(args.json, rows)
        print(f"metrics written to {args.json}")
    if args.figures:
        written = write_figures(Path(args.figures), design, results, sweep_rows)
        print(f"figures written to {args.figures}: " + ", ".join(p.name for p in written))
    return 0


def rom_sweep(plant, design, oracle, args, engine=None) -> list[dict]:
    """Re-identify the ROM at each order cap; Markov error and closed-loop cost vs the oracle.
    The impulse experiments run once (at the largest order) on `engine`; each sweep point
    (realization at n_r and its Monte Carlo) is one task."""
    from sep_control.compute.engine import InProcess

    engine = engine or InProcess()
    settings = DesignSettings.from_meta(design.meta)
    settings.n_r = max(args.sweep_orders)
    ident = identify_rom(plant, design.nominal.u, settings, engine=engine)
    oracle_cost = None
    if oracle is not None:
        oracle_cost = simulate(plant, design, "oracle_lqg", args.seed, args.sweep_runs, oracle=oracle,
                               keep_estimates=0, keep_trajectories=0, engine=engine).metrics()["cost_mean"]
    shared = dict(plant=engine.ship(plant), data=ident.data, design=design if engine.local else portable(design),
                  p=settings.p, q=settings.q, sv_tol=settings.sv_tol, seed=args.seed, runs=args.sweep_runs)
    points = engine.map(sweep_point, list(args.sweep_orders), shared,
                        [f"plant {design.scenario.plant_type}: ROM sweep point n_r = {n}" for n in args.sweep_orders],
                        "ROM sweep", show_progress=not args.quiet)
    rows = [{**pt, "cost_oracle": oracle_cost} for pt in points]
    print(f"\nROM-order sweep ({args.sweep_runs} runs each, relative singular-value cutoff {settings.sv_tol:g}):")
    table = {f"n_r={r['n_r']}": {"n_r_used": r["n_r_used"], "markov_rel_error": r["markov_rel_error"],
                                 "cost_mean": r["cost_mean"],
                                 "cost/oracle": r["cost_mean"] / r["cost_oracle"] if r["cost_oracle"] else None,
                                 "in_band": r["in_band"]} for r in rows}
    print(format_table(table, ["n_r_used", "markov_rel_error", "cost_mean", "cost/oracle", "in_band"]))
    return rows


def sweep_point(n_r: int, plant, data, design, p: int, q: int, sv_tol: float, seed: int, runs: int) -> dict:
    """One sweep point: TV-ERA at order cap n_r from the shared Markov data, then `runs` runs."""
    from sep_control.compute.engine import local_plant

    plant = local_plant(plant)
    model, _ = tv_era(data, design.n_steps, p, q, n_r, sv_tol)
    m = simulate(plant, with_rom(design, model), "rom_lqg", seed, runs, keep_estimates=0,
                 keep_trajectories=0).metrics()
    return {"n_r": n_r, "n_r_used": int(model.dims.max()), "markov_rel_error": markov_relative_error(model, data.Y),
            "cost_mean": m["cost_mean"], "in_band": m["in_band"]}


def write_figures(out: Path, design, results, sweep_rows) -> list[Path]:
    info, xyz, obj, nom = design.info, design.field_xyz, design.objective, design.nominal
    paths = [figures.nominal_belief_figure(out / "nominal_belief_and_control.png", info, xyz, obj.target, obj.band,
                                           nom.belief_mean, nom.belief_std, nom.u, obj.window)]
    means = {name: r.F_mean for name, r in results.items()}
    if means:
        paths.append(figures.mc_mean_vs_nominal_figure(out / "closed_loop_mean_vs_nominal.png", info, xyz,
                                                       obj.target, obj.band, nom.field, means, obj.window))
    closed = results.get("rom_lqg") or results.get("oracle_lqg")
    if closed is not None:
        ol = results["open_loop"].F[0] if "open_loop" in results else None
        paths.append(figures.mc_estimation_figure(out / "estimation_error_2sigma.png", info, xyz, nom.field,
                                                  closed.F[0], closed.F_hat[0], closed.F_std, ol, obj.window,
                                                  sensed=sensed_nodes(design.rom, P=design.lqg.kf.P_prior[-1])))
        paths.append(figures.mc_std_map_figure(out / "estimation_std.png", info, xyz, closed.F_std, obj.window))
    if sweep_rows:
        paths.append(figures.rom_sweep_figure(out / "rom_order_sweep.png", design.hankel_sv,
                                              min(obj.window[0], design.n_steps), sweep_rows))
    return paths


if __name__ == "__main__":
    sys.exit(main())
