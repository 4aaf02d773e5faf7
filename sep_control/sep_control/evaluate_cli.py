"""`evaluate`: Monte Carlo of open loop, ROM-LQG and the full-order oracle on the nonlinear plant."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from sep_plant.slab import SlabSimulator

from . import figures
from .cli_common import Formatter, add_threads, blas_threads, design_or_exit, fail
from .design import DesignSettings, identify_rom, markov_relative_error, with_rom
from .metrics import CONTROLLERS, format_table, write_json
from .montecarlo import simulate
from .oracle import oracle_lqg
from .progress import progress

DESCRIPTION = """\
Monte Carlo evaluation of a design on the nonlinear simulator with process and sensor
noise. Every controller sees the same random numbers (run i of seed s is the episode a
plant node started with seed=s, run=i plays). Controllers: open_loop (nominal input),
rom_lqg (the design's LQG), oracle_lqg (the same LQG on full-order finite-difference
Jacobians). Prints the DESIGN.md §3 metrics; --json writes them, --figures the paper's
figures as PNG; --sweep adds the ROM-order sweep (n_r = 5, 10, 20, 40).

Example:  evaluate --design out/design.npz --runs 1000 --figures out/figures --sweep
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="evaluate", description=DESCRIPTION, formatter_class=Formatter)
    p.add_argument("--design", metavar="DESIGN_FILE", required=True, help="design file from `design`")
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs per controller")
    p.add_argument("--seed", type=int, default=1, help="base seed of the noise (common random numbers)")
    p.add_argument("--controllers", nargs="+", choices=CONTROLLERS, default=list(CONTROLLERS))
    p.add_argument("--json", metavar="PATH", help="write metrics as JSON (one object per controller)")
    p.add_argument("--figures", metavar="DIR", help="write the PNG figures here")
    p.add_argument("--sweep", action="store_true", help="ROM-order sweep (re-identifies at each n_r)")
    p.add_argument("--sweep-orders", type=int, nargs="+", default=[5, 10, 20, 40])
    p.add_argument("--sweep-runs", type=int, default=200, help="Monte Carlo runs per sweep point")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_threads(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.runs < 1:
        fail(f"--runs must be >= 1, got {args.runs}")
    design = design_or_exit(args.design)
    s = design.scenario
    sim = SlabSimulator(s)
    rows: dict[str, dict] = {}
    results = {}
    with blas_threads(args.threads):
        oracle = None
        if "oracle_lqg" in args.controllers or args.sweep:
            t0 = time.perf_counter()
            oracle = oracle_lqg(design, sim)
            oracle_s = time.perf_counter() - t0
        for name in progress(args.controllers, desc="Monte Carlo", enabled=not args.quiet):
            t0 = time.perf_counter()
            res = simulate(design, name, args.seed, args.runs, oracle=oracle, keep_estimates=1, sim=sim,
                           keep_trajectories=1)
            rows[name] = res.metrics(design)
            rows[name]["seconds"] = time.perf_counter() - t0
            results[name] = res
        print(f"{args.runs} runs per controller, seed {args.seed}, n_x = {s.n_x}, n_r = {design.n_r}")
        print(format_table(rows, ["cost_mean", "cost_std", "in_band", "rms", "mean_dev_37_5", "mean_dev_62_5",
                                  "coverage_2sigma", "n_runs", "seconds"]))
        if "rom_lqg" in rows and "oracle_lqg" in rows:
            ratio = rows["rom_lqg"]["cost_mean"] / rows["oracle_lqg"]["cost_mean"]
            print(f"ROM-LQG / oracle mean cost: {ratio:.5f}  (oracle design {oracle_s:.2f} s)")
        sweep_rows = rom_sweep(design, sim, oracle, args) if args.sweep else None
    if args.json:
        write_json(args.json, rows)
        print(f"metrics written to {args.json}")
    if args.figures:
        written = write_figures(Path(args.figures), design, results, sweep_rows)
        print(f"figures written to {args.figures}: " + ", ".join(p.name for p in written))
    return 0


def rom_sweep(design, sim, oracle, args) -> list[dict]:
    """Re-identify the ROM at each order cap; Markov error and closed-loop cost vs the oracle."""
    settings = DesignSettings(**{k: v for k, v in design.meta.get("settings", {}).items()
                                 if k in DesignSettings.__dataclass_fields__})
    settings.n_r = max(args.sweep_orders)
    _, data, _, _ = identify_rom(sim, design.u_nom, settings)
    from .tvera import tv_era

    oracle_cost = simulate(design, "oracle_lqg", args.seed, args.sweep_runs, oracle=oracle, keep_estimates=0,
                           sim=sim, keep_trajectories=0).metrics()["cost_mean"]
    rows = []
    for n_r in progress(args.sweep_orders, desc="ROM sweep", enabled=not args.quiet):
        real = tv_era(data, design.n_steps, settings.p, settings.q, n_r, settings.sv_tol)
        d = with_rom(design, real)
        m = simulate(d, "rom_lqg", args.seed, args.sweep_runs, keep_estimates=0, sim=sim,
                     keep_trajectories=0).metrics()
        rows.append({"n_r": n_r, "n_r_used": int(real.dims.max()),
                     "markov_rel_error": markov_relative_error(real, data.Y),
                     "cost_mean": m["cost_mean"], "cost_oracle": oracle_cost, "in_band": m["in_band"]})
    print(f"\nROM-order sweep ({args.sweep_runs} runs each, relative singular-value cutoff {settings.sv_tol:g}):")
    table = {f"n_r={r['n_r']}": {"n_r_used": r["n_r_used"], "markov_rel_error": r["markov_rel_error"],
                                 "cost_mean": r["cost_mean"], "cost/oracle": r["cost_mean"] / r["cost_oracle"],
                                 "in_band": r["in_band"]} for r in rows}
    print(format_table(table, ["n_r_used", "markov_rel_error", "cost_mean", "cost/oracle", "in_band"]))
    return rows


def write_figures(out: Path, design, results, sweep_rows) -> list[Path]:
    s = design.scenario
    paths = [figures.fig_nominal(out / "nominal_belief_and_control.png", s, design.belief_mean,
                                 design.belief_std, design.u_nom)]
    means = {name: r.T_mean for name, r in results.items()}
    if means:
        paths.append(figures.fig_mean_vs_nominal(out / "closed_loop_mean_vs_nominal.png", s, design.T_nom, means))
    closed = results.get("rom_lqg") or results.get("oracle_lqg")
    if closed is not None and "open_loop" in results:
        paths.append(figures.fig_estimation(out / "estimation_error_2sigma.png", s, design.T_nom, closed.T[0],
                                            closed.T_hat[0], closed.T_std, results["open_loop"].T[0]))
    if sweep_rows:
        paths.append(figures.fig_rom_sweep(out / "rom_order_sweep.png", design.hankel_sv,
                                           min(s.k_band, s.n_steps), sweep_rows))
    return paths


if __name__ == "__main__":
    sys.exit(main())
