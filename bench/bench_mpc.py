"""Input limits: LQG with the clipped command vs the ROM-MPC, side by side (no assertions).

On the reference problem (or --scenario), one design without limits and one with
u in [--u-min, --u-max] (default [0, 0.6], the limits a new user tried), each evaluated with
common random numbers:

* Monte Carlo table (--runs, default 1000): open loop, ROM-LQG (command clipped) and ROM-MPC
  (horizon --horizon), without and with limits; cost ratios MPC / LQG; the MPC's QP share,
  fallbacks and QP solve time p50/p99;
* the limit margin of the nominal (`design --limit-margin c`, c in --margins): nominal cost and
  ROM-LQG / ROM-MPC in band (--margin-runs each);
* a figure (--figures DIR, default out/bench_mpc): each input of run 0 against its limits,
  for LQG+clip and MPC.

    OPENBLAS_NUM_THREADS=1 python bench/bench_mpc.py [--runs 1000] [--horizon 20] [--quick]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from threadpoolctl import threadpool_limits

from sep_control.control.controllers import MpcOptions
from sep_control.evaluation import figures
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.montecarlo import simulate
from sep_plant.scenario import load_scenario

COLUMNS = ["cost_mean", "in_band", "mean_dev_end", "cost/LQG", "mpc_qp_share", "mpc_fallbacks", "mpc_qp_p50_s",
           "mpc_qp_p99_s", "seconds"]


def design(scen, **settings):
    st = DesignSettings.for_scenario(scen, **settings)
    t0 = time.perf_counter()
    d = run_design(scen.plant, scen.problem, st, show_progress=False, log=lambda m: None)
    return d, time.perf_counter() - t0


def evaluate(scen, d, runs, horizon, label, rows, keep=None):
    lqg_cost = None
    for ctl in ("open_loop", "rom_lqg", "rom_mpc"):
        t0 = time.perf_counter()
        r = simulate(scen.plant, d, ctl, 1, runs, keep_estimates=0, keep_trajectories=1, mpc=MpcOptions(horizon))
        m = dict(r.summary, seconds=time.perf_counter() - t0)
        if ctl == "rom_lqg":
            lqg_cost = m["cost_mean"]
        if ctl == "rom_mpc":
            m["cost/LQG"] = m["cost_mean"] / lqg_cost
            steps = m["mpc_qp_steps"] + m["mpc_unconstrained_steps"] + m["mpc_fallbacks"]
            m["mpc_qp_share"] = m["mpc_qp_steps"] / max(1, steps)
        rows[f"{label}: {ctl}"] = m
        print(format_table({f"{label}: {ctl}": m}, COLUMNS), flush=True)
        if keep is not None:
            keep[ctl] = r.U[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", help="scenario file (default: the reference)")
    ap.add_argument("--u-min", type=float, default=0.0)
    ap.add_argument("--u-max", type=float, default=0.6)
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--horizon", type=int, default=20)
    ap.add_argument("--margins", type=float, nargs="*", default=[0.25, 1.0])
    ap.add_argument("--margin-runs", type=int, default=200)
    ap.add_argument("--figures", default="out/bench_mpc")
    ap.add_argument("--quick", action="store_true", help="200 runs, one margin")
    args = ap.parse_args()
    if args.quick:
        args.runs, args.margins, args.margin_runs = 200, [1.0], 100
    base = load_scenario(args.scenario)
    lim = base.replace(u_min=args.u_min, u_max=args.u_max)
    rows: dict[str, dict] = {}
    with threadpool_limits(1):
        d_free, t_free = design(base)
        d_lim, t_lim = design(lim)
        print(f"designs: no limits {t_free:.1f} s, u in [{args.u_min:g}, {args.u_max:g}] {t_lim:.1f} s")
        evaluate(base, d_free, args.runs, args.horizon, "no limits", rows)
        U_run0: dict = {}
        evaluate(lim, d_lim, args.runs, args.horizon, f"u in [{args.u_min:g}, {args.u_max:g}]", rows, U_run0)
        lo, hi = lim.problem.limits(d_lim.info.n_u)
        path = figures.inputs_vs_limits_figure(Path(args.figures) / "inputs_vs_limits.png", d_lim.info,
                                               d_lim.nominal.u,
                                               {"LQG + clip": U_run0["rom_lqg"], "ROM-MPC": U_run0["rom_mpc"]}, lo, hi,
                                               d_lim.objective.window)
        margin_rows = {}
        for c in args.margins:
            d_m, t_m = design(lim, limit_margin=c)
            row = {"nominal_cost": d_m.meta["optimizer"]["nominal_cost"], "design_s": t_m}
            for ctl in ("rom_lqg", "rom_mpc"):
                m = simulate(lim.plant, d_m, ctl, 1, args.margin_runs, keep_estimates=0, keep_trajectories=0,
                             mpc=MpcOptions(args.horizon)).summary
                row[f"{ctl}_in_band"], row[f"{ctl}_cost"] = m["in_band"], m["cost_mean"]
            margin_rows[f"margin {c:g} sigma_u"] = row
    print(f"\nMonte Carlo, {args.runs} runs per row (seed 1, common random numbers), MPC horizon {args.horizon}:")
    print(format_table(rows, COLUMNS))
    print(f"\nnominal with a limit margin (u in [{args.u_min:g}, {args.u_max:g}], {args.margin_runs} runs each; "
          f"no margin: nominal cost {d_lim.meta['optimizer']['nominal_cost']:.4g}):")
    print(format_table(margin_rows, ["nominal_cost", "rom_lqg_in_band", "rom_mpc_in_band", "rom_lqg_cost",
                                     "rom_mpc_cost", "design_s"]))
    print(f"\nfigure: {path}")


if __name__ == "__main__":
    main()
