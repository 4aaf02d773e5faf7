"""Offline cost of sep: design vs Monte Carlo vs one simulator rollout, across grid sizes.

Measured in one run, printed as a table with ratios (no assertions). For each grid
n_x it times: one noise-free rollout of the N-step horizon; the whole design
(optimization + identification + gains) and its stages, with the default Jacobian ("auto":
the ROM one at N = 250) and with the sensitivity one; the Monte Carlo of each controller
(runs per controller as given; the oracle only where its n_x^2 N matrices fit comfortably);
one Gauss-Newton linearization + step by each Jacobian; and the crossover of the two over
the horizon N (`--crossover`). Also compares BLAS thread counts on the n_x = 100 design, and
reports the mean-only vs belief-space optimum.

    python bench/bench_design.py                       # n_x = 100, 400, 1600
    python bench/bench_design.py --grids 100 --runs 1000 --crossover
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.metrics import format_table
from sep_control.evaluation.montecarlo import simulate
from sep_control.design.belief import objective_of
from sep_control.design.jacobians import SensitivityJacobian
from sep_control.design.linearization import RomLinearization, SensitivityLinearization, sensitivity_normal_equations
from sep_control.design.optimizer import Optimizer, OptimizerOptions
from sep_control.design.tvera import identify
from sep_control.evaluation.oracle import oracle_lqg
from sep_plant.protocol import nominal_states
from sep_plant.scenario import reference


def timed(fn, *a, **kw):
    t0 = time.perf_counter()
    out = fn(*a, **kw)
    return out, time.perf_counter() - t0


def linearization_times(plant, problem, U: np.ndarray, p: int = 15, q: int = 15) -> tuple[float, float]:
    """Seconds for one Gauss-Newton linearization + LM step at U: (sensitivity, ROM)."""
    obj = objective_of(plant, problem)
    X = nominal_states(plant, U)
    F = plant.field(X)
    t0 = time.perf_counter()
    SensitivityLinearization(sensitivity_normal_equations(plant, U, X, obj), U.shape).step(1e-3)
    t1 = time.perf_counter()
    st = DesignSettings()                                  # the design's impulses (scheme, amplitude)
    RomLinearization(identify(plant, U, p, q, 20, impulse=st.impulse, scheme=st.impulse_scheme), obj, F,
                     U).step(1e-3)
    return t1 - t0, time.perf_counter() - t1


def prototype_table(threads: int) -> None:
    """The reference design (plans 0.8 and 0.9) against the independent numpy prototype of the
    paper's pipeline (bench/prototype_pipeline.py), run alternately in this process, and the
    ratio of their times. The prototype's nominal is the paper's gradient descent, stopped by the
    same settle rule as plan 0.9 or after 10 iterations: its nominal cost is printed beside sep's;
    a prototype run to sep's nominal cost would take longer, so the ratio is an upper bound."""
    from prototype_pipeline import prototype_design

    sim, s = reference().plant, reference().problem
    out = {}
    with threadpool_limits(threads):
        for rnd in (1, 2):
            for plan in ("0.8", "0.9"):
                d, t = timed(run_design, sim, s, DesignSettings(experiment_plan=plan), False, lambda m: None)
                out[f"sep plan {plan} #{rnd}"] = {"design_s": t, "J_nominal": d.meta["optimizer"]["mean_only_cost"],
                                                  "run_steps_k": d.meta["run_steps"]["total"] / 1e3}
            p = prototype_design(sim, s)
            out[f"prototype #{rnd}"] = {"design_s": p["total_s"], "J_nominal": p["J"], "nominal_s": p["nominal_s"],
                                        "enkf_s": p["enkf_s"], "tvera_s": p["tvera_s"], "lqg_s": p["lqg_s"],
                                        "iterations": p["iterations"]}
    for rnd in (1, 2):
        for plan in ("0.8", "0.9"):
            r = out[f"sep plan {plan} #{rnd}"]
            r["/prototype"] = r["design_s"] / out[f"prototype #{rnd}"]["design_s"]
    print("\nReference design against the numpy prototype of the paper's pipeline (same run, alternating; "
          "the ratio to the same round's prototype)")
    print(format_table(out, ["design_s", "/prototype", "J_nominal", "run_steps_k", "iterations", "nominal_s",
                             "enkf_s", "tvera_s", "lqg_s"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grids", type=int, nargs="+", default=[100, 400, 1600])
    ap.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs per controller at n_x = 100")
    ap.add_argument("--runs-large", type=int, default=200, help="runs per controller on larger grids")
    ap.add_argument("--oracle-max-nx", type=int, default=400)
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads for the main table")
    ap.add_argument("--gd-iter", type=int, default=60,
                    help="gradient-descent iterations in the GN vs GD comparison (0: skip)")
    ap.add_argument("--no-sensitivity-design", action="store_true",
                    help="skip the whole design with the sensitivity Jacobian (slow on large grids)")
    ap.add_argument("--crossover-n", type=int, nargs="+", default=[30, 60, 90, 120, 180, 250],
                    help="horizons N of the crossover table")
    ap.add_argument("--prototype-only", action="store_true",
                    help="only the design time against the numpy prototype of the paper's pipeline (n_x = 100)")
    ap.add_argument("--crossover", action="store_true",
                    help="one linearization + step by each Jacobian over the horizon N (n_x = the first grid)")
    args = ap.parse_args()
    if args.prototype_only:
        prototype_table(args.threads)
        return

    rows = {}
    for n_x in args.grids:
        scen = reference().with_plant(n_x=n_x)
        sim, s = scen.plant, scen.problem
        runs = args.runs if n_x <= 100 else args.runs_large
        with threadpool_limits(args.threads):
            U0 = s.u_start(sim.n_u)
            _, t_roll = timed(nominal_states, sim, U0)
            _, t_roll = timed(nominal_states, sim, U0)     # second call: warm
            design, t_design = timed(run_design, sim, s, DesignSettings(), False, lambda m: None)
            t_design_sens = None
            if not args.no_sensitivity_design:
                _, t_design_sens = timed(run_design, sim, s, DesignSettings(jacobian="sensitivity"), False,
                                         lambda m: None)
            mc = {}
            oracle = None
            if n_x <= args.oracle_max_nx:
                oracle, t_or = timed(oracle_lqg, design, sim)
            for c in ("open_loop", "rom_lqg", "oracle_lqg"):
                if c == "oracle_lqg" and oracle is None:
                    continue
                res, t = timed(simulate, sim, design, c, 1, runs, oracle=oracle, keep_estimates=0,
                               keep_trajectories=0)
                mc[c] = (res.metrics(), t)
            # one Gauss-Newton linearization and step at the optimum, each Jacobian
            t_ne_sens, t_ne_rom = linearization_times(sim, s, design.nominal.u)
        tm = design.meta["timings"]
        t_mc = mc["rom_lqg"][1]
        row = {
            "rollout_s": t_roll, "design_s": t_design, "design_sens_s": t_design_sens,
            "sens/auto": t_design_sens / t_design if t_design_sens else None, "optimize_s": tm["optimize_s"],
            "identify_s": tm["identify_s"], "gains_s": tm["gains_s"], "runs": runs,
            "mc_rom_s": t_mc, "mc_open_s": mc["open_loop"][1],
            "mc_oracle_s": mc["oracle_lqg"][1] if "oracle_lqg" in mc else None,
            "design/rollout": t_design / t_roll, "mc_rom/rollout": t_mc / t_roll,
            "mc_per_run/rollout": t_mc / runs / t_roll,
            "gn_sens_s": t_ne_sens, "gn_rom_s": t_ne_rom, "sens/rom": t_ne_sens / t_ne_rom,
            "in_band_rom": mc["rom_lqg"][0]["in_band"], "in_band_open": mc["open_loop"][0]["in_band"],
            "rom/oracle_cost": (mc["rom_lqg"][0]["cost_mean"] / mc["oracle_lqg"][0]["cost_mean"]
                                if "oracle_lqg" in mc else None),
            "J_mean_only": design.meta["optimizer"]["mean_only_cost"],
            "run_steps_k": design.meta["run_steps"]["total"] / 1e3,
            "nominal_k": design.meta["run_steps"]["nominal"] / 1e3,
            "belief_k": design.meta["run_steps"]["belief"] / 1e3,
            "ident_k": design.meta["run_steps"]["identification"] / 1e3,
            "J_nominal": design.meta["optimizer"]["nominal_cost"],
            "Jb_before": design.meta["optimizer"]["belief_history"][0],
            "Jb_after": design.meta["optimizer"]["belief_history"][-1],
        }
        rows[f"n_x={n_x}"] = row
        print(f"n_x = {n_x}: design {t_design:.2f} s, MC rom {t_mc:.2f} s ({runs} runs)", flush=True)

    print(f"\nTimes in seconds, BLAS threads = {args.threads}; ratios measured in this run")
    print("\nPlant run-steps of the default design per stage [thousands] (the machine-independent cost)")
    print(format_table(rows, ["run_steps_k", "nominal_k", "belief_k", "ident_k"]))
    print(format_table(rows, ["rollout_s", "design_s", "optimize_s", "identify_s", "gains_s", "design_sens_s",
                              "sens/auto", "runs", "mc_open_s", "mc_rom_s", "mc_oracle_s", "design/rollout",
                              "mc_rom/rollout", "mc_per_run/rollout"]))
    print("\nOne Gauss-Newton linearization + step: sensitivity Jacobian (dense normal equations) vs TV-ERA (ROM) "
          "Jacobian (identification + Riccati step)")
    print(format_table(rows, ["gn_sens_s", "gn_rom_s", "sens/rom"]))
    print("\nQuality at each grid")
    print(format_table(rows, ["in_band_rom", "in_band_open", "rom/oracle_cost", "J_mean_only", "J_nominal",
                              "Jb_before", "Jb_after"]))

    if args.crossover:
        n_x = args.grids[0]
        xrows = {}
        for N in args.crossover_n:
            scen = reference().with_plant(n_x=n_x).replace(n_steps=N, band_window=(int(0.6 * N), N),
                                                           lqr_k_switch=int(0.48 * N))
            with threadpool_limits(args.threads):
                t_s, t_r = linearization_times(scen.plant, scen.problem, scen.problem.u_start(scen.plant.n_u))
            xrows[f"N={N}"] = {"sensitivity_s": t_s, "rom_s": t_r, "sens/rom": t_s / t_r,
                               "auto": DesignSettings().resolved_jacobian(N)}
        print(f"\nCrossover over the horizon N at n_x = {n_x}: one linearization + step by each Jacobian")
        print(format_table(xrows, ["sensitivity_s", "rom_s", "sens/rom", "auto"]))

    if 100 in args.grids and args.gd_iter > 0:
        sim, s = reference().plant, reference().problem
        opt_rows = {}
        with threadpool_limits(args.threads):
            for method, iters in (("gn", None), ("gd", args.gd_iter)):
                opt = Optimizer(sim, s, OptimizerOptions(method=method, max_iter=iters, show_progress=False),
                                SensitivityJacobian())
                r, t = timed(opt.run)
                opt_rows[method] = {"iterations": r.iterations, "cost": r.cost, "seconds": t,
                                    "experiments": r.experiments}
        for r in opt_rows.values():
            r["cost/gn_cost"] = r["cost"] / opt_rows["gn"]["cost"]
        print("\nMean-only optimizer at n_x = 100 from u = 0.1: Gauss-Newton/LM vs gradient descent")
        print(format_table(opt_rows, ["iterations", "experiments", "cost", "cost/gn_cost", "seconds"]))

    if 100 in args.grids:
        prototype_table(args.threads)
        sim, s = reference().plant, reference().problem
        tt = {}
        for th in (1, 2):
            with threadpool_limits(th):
                d, t = timed(run_design, sim, s, DesignSettings(), False, lambda m: None)
                _, t_mc = timed(simulate, sim, d, "rom_lqg", 1, args.runs, keep_estimates=0, keep_trajectories=0)
            tt[f"threads={th}"] = {"design_s": t, "mc_rom_s": t_mc}
        base = tt["threads=1"]
        for r in tt.values():
            r["design_vs_1"] = r["design_s"] / base["design_s"]
            r["mc_vs_1"] = r["mc_rom_s"] / base["mc_rom_s"]
        print("\nBLAS threads at n_x = 100 (ratio to 1 thread)")
        print(format_table(tt, ["design_s", "design_vs_1", "mc_rom_s", "mc_vs_1"]))


if __name__ == "__main__":
    main()
