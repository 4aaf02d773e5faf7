"""`sep evaluate`: Monte Carlo of open loop, ROM-LQG, ROM-MPC and the full-order oracle on the
nonlinear plant."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from sep_estimator.disturbance import summary as disturbance_summary
from sep_estimator.ltv import sensed_nodes
from sep_plant.noise import DEFAULT_SEED
from sep_plant.scenario import json_default

from sep_control.cli.common import (add_compute_options, add_deprecated, blas_threads, controller_name,
                                    design_or_exit, engine_or_exit, fail, groups, legacy_main,
                                    memory_budget_or_exit, plant_or_exit)
from sep_control.cli import truth as truth_cli
from sep_control.compute.progress import RunSteps, bars_wanted
from sep_control.evaluation import figures
from sep_control.control.controllers import CONTROLLER_NAMES as CONTROLLERS
from sep_control.evaluation.metrics import format_table, write_metrics_json
from sep_control.evaluation.robustness import plants_record
from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.sweep import rom_sweep, sweep_run_steps

HELP = "Monte Carlo of the controllers on the nonlinear plant, metrics and figures"
DESCRIPTION = """\
Monte Carlo evaluation of a design on the nonlinear plant with process and sensor noise.
Every controller sees the same random numbers (run i of seed s is the episode a plant node
started with seed=s, run=i plays). Controllers: open_loop (nominal input), rom_lqg (the
design's LQG), rom_mpc (box-constrained MPC on the ROM), oracle_lqg (the same LQG on full-order
finite-difference Jacobians; only where n_x <= --oracle-max-nx, since it costs n_x^2 N memory
and n_x^3 N time). Prints the docs/method.md metrics; --json writes them, --figures the paper's
figures as PNG (heat maps for grid plants); --sweep adds the ROM-order sweep (n_r = 5, 10, 20,
40). The plant is rebuilt from the design file's scenario.

Model mismatch (docs/robustness.md): --truth KEY=VALUE, --truth-scenario FILE and --perturb
KEY=VALUE run every controller on a truth plant that differs from the design's (the oracle is
then the truth's full-order LQG along the design's nominal); --robustness KEY=LO:HI:N sweeps one
truth key or perturbation key.

Example:  sep evaluate --design out/design.npz --runs 1000 --figures out/figures --sweep
          sep evaluate --design out/design.npz --truth t_right=147 --perturb input_gain=0.8
          sep evaluate --design out/design.npz --robustness t_right=146:150:5 --figures out/rob
"""

TABLE_KEYS = ["cost_mean", "cost_std", "in_band", "rms", "mean_dev_start", "mean_dev_end", "coverage_2sigma",
              "n_runs", "seconds"]


def configure(parser: argparse.ArgumentParser) -> None:
    """The options of `sep evaluate`."""
    basic, advanced = groups(parser)
    basic.add_argument("--design", metavar="DESIGN_FILE", required=True, help="design file from `sep design`")
    basic.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs per controller")
    basic.add_argument("--seed", type=int, default=DEFAULT_SEED,
                       help="base seed of the noise (common random numbers)")
    basic.add_argument("--controllers", nargs="+", choices=CONTROLLERS, type=controller_name, default=None,
                       metavar="NAME",
                       help=f"controllers to run, of {', '.join(CONTROLLERS)} (default: open_loop rom_lqg "
                            "oracle_lqg, and rom_mpc when the scenario has input limits)")
    basic.add_argument("--json", metavar="PATH", help="write metrics as JSON (one object per controller)")
    basic.add_argument("--figures", metavar="DIR", help="write the PNG figures here")
    basic.add_argument("--sweep", action="store_true", help="ROM-order sweep (re-identifies at each n_r)")
    basic.add_argument("--quiet", action="store_true",
                       help="no progress bar (drawn in run-steps only when stderr is a terminal)")
    advanced.add_argument("--mpc-horizon", type=int, default=20, help="rom_mpc: horizon H in steps")
    advanced.add_argument("--mpc-time-budget", type=float, default=None, metavar="SECONDS",
                          help="rom_mpc: seconds a QP may take before the step falls back to the clipped LQR "
                               "(default: no budget offline, so the numbers do not depend on the machine's load; "
                               "the online node's default is 0.02)")
    add_deprecated(advanced, "--mpc-budget", "--mpc-time-budget", "mpc_time_budget", type=float)
    advanced.add_argument("--oracle-max-nx", type=int, default=500,
                          help="skip the full-order oracle above this many states (n_x^2 N memory)")
    advanced.add_argument("--sweep-orders", type=int, nargs="+", default=[5, 10, 20, 40], metavar="N_R",
                          help="order caps of the sweep")
    advanced.add_argument("--sweep-runs", type=int, default=200, help="Monte Carlo runs per sweep point")
    add_compute_options(advanced)
    truth_cli.add_truth_options(parser)


def run(args: argparse.Namespace) -> int:
    if args.runs < 1:
        fail(f"--runs must be >= 1, got {args.runs}")
    if args.mpc_horizon < 1 or (args.mpc_time_budget is not None and not args.mpc_time_budget > 0):
        fail("--mpc-horizon must be >= 1 and --mpc-time-budget > 0")
    if args.sweep and truth_cli.wants_truth(args):
        fail("--sweep re-identifies the ROM on the design's own plant: run it without --truth, --truth-scenario, "
             "--perturb and --robustness")
    budget = memory_budget_or_exit(args.memory_budget)
    design = design_or_exit(args.design)
    if args.robustness:
        return run_sweep(args, design, budget)
    truth = truth_cli.truth_or_exit(args, design)
    plant = plant_or_exit(design.scenario, f"{args.design} (its scenario)", device=args.device) if truth is None \
        else truth_cli.truth_plant_or_exit(truth, args.device)
    controllers = chosen_controllers(args, design)
    oracle_fits = oracle_skip_reason(design, args.oracle_max_nx) is None
    N = design.n_steps
    total = len(controllers) * args.runs * N + \
        (sweep_run_steps(plant, design, args.sweep_orders, args.sweep_runs, oracle_fits) if args.sweep else 0)
    rows: dict[str, dict] = {}
    results = {}
    with blas_threads(args.threads), engine_or_exit(args.dask, log=print) as engine, \
            RunSteps(total, "Monte Carlo (run-steps)", bars_wanted(args.quiet)) as bar:
        oracle, oracle_s = None, 0.0
        if "oracle_lqg" in controllers or (args.sweep and oracle_fits):
            t0 = time.perf_counter()
            oracle = truth_cli.oracle_or_none(design, truth, plant)
            oracle_s = time.perf_counter() - t0
            if oracle is None:
                controllers.remove("oracle_lqg")
        for name in controllers:
            t0 = time.perf_counter()
            res = simulate(plant, design, name, args.seed, args.runs, oracle=oracle, keep_estimates=1,
                           keep_trajectories=1, memory_budget=budget, engine=engine,
                           mpc=truth_cli.mpc_options(args))
            bar.add(args.runs, N)
            rows[name] = {**res.metrics(), "seconds": time.perf_counter() - t0, "run_steps": args.runs * N}
            if name in ("rom_lqg", "rom_mpc"):
                rows[name]["disturbance"] = disturbance_summary(design.disturbance)
            results[name] = res
        print(f"{args.runs} runs per controller, seed {args.seed}, plant {design.scenario.plant_type}, "
              f"n_x = {design.info.n_x}, n_r = {design.n_r}, disturbance states "
              f"{disturbance_summary(design.disturbance)} (rom_lqg, rom_mpc); plant run-steps {args.runs * N:,} per "
              f"controller, {len(controllers) * args.runs * N:,} in all")
        if truth is not None:
            print(truth_cli.describe(design, truth))
        print(format_table(rows, TABLE_KEYS))
        print_recipe(rows, design)
        if "rom_lqg" in rows and "oracle_lqg" in rows:
            ratio = rows["rom_lqg"]["cost_mean"] / rows["oracle_lqg"]["cost_mean"]
            print(f"ROM-LQG / oracle mean cost: {ratio:.5f}  (oracle design {oracle_s:.2f} s)")
        sweep_rows = None
        if args.sweep:
            sweep_rows = rom_sweep(plant, design, oracle, args.sweep_orders,
                                   args.sweep_runs, args.seed, engine, progress=bar)
    write_outputs(args, design, truth, rows, results, sweep_rows)
    return 0


def write_outputs(args: argparse.Namespace, design, truth, rows: dict, results: dict, sweep_rows) -> None:
    """The ROM-order sweep's table, --json (with both plants when a truth is given) and --figures."""
    if sweep_rows is not None:
        print_sweep(sweep_rows, args.sweep_runs, design)
    if args.json:
        plants = plants_record(design, truth) if truth is not None else {}
        write_metrics_json(args.json, {name: {**row, **plants} for name, row in rows.items()})
        print(f"metrics written to {args.json}")
    if args.figures:
        written = write_figures(Path(args.figures), design, results, sweep_rows)
        print(f"figures written to {args.figures}: " + ", ".join(p.name for p in written))


def run_sweep(args: argparse.Namespace, design, budget) -> int:
    """`--robustness KEY=LO:HI:N`: every controller on N truth plants; table, --json, --figures."""
    sweep, truths = truth_cli.sweep_or_exit(args, design)
    controllers = chosen_controllers(args, design)
    total = len(controllers) * args.runs * design.n_steps * len(truths)
    with blas_threads(args.threads), engine_or_exit(args.dask, log=print) as engine, \
            RunSteps(total, "Monte Carlo (run-steps)", bars_wanted(args.quiet)) as bar:
        result = truth_cli.run_robustness(args, design, controllers, sweep, truths, budget, engine, bar)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2, default=json_default) + "\n")
        print(f"robustness sweep written to {args.json}")
    if args.figures:
        path = truth_cli.robustness_figure(Path(args.figures), design, result)
        print(f"figure written to {path}")
    return 0


def oracle_skip_reason(design, max_nx: int) -> str | None:
    """Why the full-order oracle cannot be built for this design's plant (None: it can)."""
    if design.info.state_is_opaque:
        return ("the plant's states are opaque (state_is_opaque, e.g. a Co-Simulation FMU's serialized state): "
                "the full-order oracle differentiates the step with respect to the state")
    if design.info.n_x > max_nx:
        return f"n_x = {design.info.n_x} > --oracle-max-nx = {max_nx}"
    return None


def chosen_controllers(args: argparse.Namespace, design) -> list[str]:
    """--controllers, or the defaults (rom_mpc only with input limits); oracle_lqg left out (with
    a line saying so) above --oracle-max-nx."""
    controllers = list(dict.fromkeys(args.controllers)) if args.controllers else \
        [c for c in CONTROLLERS if c != "rom_mpc" or design.problem.input_limited]
    why = oracle_skip_reason(design, args.oracle_max_nx) if "oracle_lqg" in controllers else None
    if why is not None:
        print(f"oracle_lqg skipped: {why}")
        controllers.remove("oracle_lqg")
    if not controllers:
        fail("no controller left to evaluate (oracle_lqg skipped, see above); name others with --controllers")
    return controllers


def print_recipe(rows: dict, design) -> None:
    """A recipe's per-hold results (in band, max |f - f*| and its 99 % quantile over the runs,
    the nominal's max) and the rate-limit counts, when the problem has them."""
    obj, p = design.objective, design.problem
    if obj.holds is not None:
        from sep_control.evaluation.metrics import segment_max_dev

        nom = segment_max_dev(design.nominal.field[None], obj)[:, 0]
        print("\nper hold segment (in band / max |f - f*| / its 99 % quantile over the runs):")
        table = {"nominal": {f"hold {j + 1} [{k0},{k1}] ±{b:g}": f"max {d:.3g}"
                             for j, ((k0, k1, b), d) in enumerate(zip(obj.holds, nom))}}
        for name, r in rows.items():
            table[name] = {f"hold {j + 1} [{s['k_start']},{s['k_end']}] ±{s['band']:g}":
                           f"{s['in_band']:.3f} / {s['max_dev']:.3g} / {s['max_dev_p99']:.3g}"
                           for j, s in enumerate(r.get("segments") or [])}
        print(format_table(table, list(table["nominal"])))
    if p.rate_limited:
        print("\nrate limits (channel-steps): " + "; ".join(
            f"{name}: {r.get('rate_clips', 0):,} clipped by the law, {r.get('rate_violations', 0):,} by the plant, "
            f"{r.get('rate_at_limit', 0.0):.3f} at the limit" for name, r in rows.items()))


def print_sweep(rows: list[dict], runs: int, design) -> None:
    from sep_control.design.pipeline import DesignSettings

    sv_tol = DesignSettings.from_meta(design.meta).sv_tol
    print(f"\nROM-order sweep ({runs} runs each, relative singular-value cutoff {sv_tol:g}):")
    table = {f"n_r={r['n_r']}": {"n_r_used": r["n_r_used"], "markov_rel_error": r["markov_rel_error"],
                                 "cost_mean": r["cost_mean"],
                                 "cost/oracle": r["cost_mean"] / r["cost_oracle"] if r["cost_oracle"] else None,
                                 "in_band": r["in_band"]} for r in rows}
    print(format_table(table, ["n_r_used", "markov_rel_error", "cost_mean", "cost/oracle", "in_band"]))


def write_figures(out: Path, design, results, sweep_rows) -> list[Path]:
    info, xyz, obj, nom = design.info, design.field_xyz, design.objective, design.nominal
    mean = nom.belief_mean if nom.belief_mean is not None else nom.field      # no belief: the nominal field
    target = obj.target_at(obj.window[1])             # a time-varying target: at the band window's end
    paths = [figures.nominal_belief_figure(out / "nominal_belief_and_control.png", info, xyz, target, obj.band,
                                           mean, nom.belief_std, nom.u, obj.window)]
    means = {name: r.F_mean for name, r in results.items()}
    if means:
        paths.append(figures.mc_mean_vs_nominal_figure(out / "closed_loop_mean_vs_nominal.png", info, xyz,
                                                       target, obj.band, nom.field, means, obj.window))
    if np.ndim(obj.target) > 1:                       # the target drawn over time (a recipe)
        paths.append(figures.recipe_figure(out / "recipe.png", info, obj, nom.field,
                                           {name: r.F for name, r in results.items()}))
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


def main(argv: list[str] | None = None) -> int:
    """The old `evaluate` command: `sep evaluate` with a deprecation line."""
    return legacy_main("evaluate", argv)


if __name__ == "__main__":
    sys.exit(main())
