"""Where a design's time goes outside the plant's step: a partial design under cProfile.

Runs the design of one `bench_scale.py` row until it has simulated `--run-steps` plant
run-steps (then stops it), timing every plant step from outside, and prints the design's
time, its plant-step time, the rest per node-step ((design - plant steps) / (run-steps n_x))
and the cProfile table of the functions that took the most time (a time includes what it
calls). Prints a table, asserts nothing.

    OPENBLAS_NUM_THREADS=1 python bench/profile_design.py --row plate:256 --run-steps 3000
    python bench/profile_design.py --row block:60 --run-steps 2000 --device cuda
    PYTHONPATH=/tmp/sep-0.8/sep_plant:... python bench/profile_design.py ...   # another checkout

`--stage sensitivity|impulse|belief` profiles one stage's experiments alone at u_init (the
sensitivity normal equations, the TV-ERA impulse experiments, the EnKF belief), each cut at
`--run-steps`, instead of the design from its start. `--sort tottime` orders the table by each
function's own time (what to shorten) instead of the time with its callees.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "bench"))


class Enough(Exception):
    """The run-step budget is spent."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--row", default="plate:256", help="a bench_scale.py row (default plate:256)")
    ap.add_argument("--nodes", type=int, nargs="+", help="grid nodes instead of the row's (e.g. 60 60 60)")
    ap.add_argument("--run-steps", type=int, default=3000, help="stop after this many plant run-steps")
    ap.add_argument("--stage", choices=["design", "sensitivity", "impulse", "belief"], default="design")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--memory-budget", help="the design's memory budget (e.g. 8G: at plate 256^2 the "
                    "sensitivity Jacobian, as on a large host; default: this machine's)")
    ap.add_argument("--top", type=int, default=18, help="cProfile rows to print")
    ap.add_argument("--sort", choices=["cumulative", "tottime"], default="cumulative",
                    help="order of the cProfile table: time with callees (default) or a function's own")
    args = ap.parse_args()

    from threadpoolctl import threadpool_limits

    from bench_scale import ROWS
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_plant.device import on_device
    from sep_plant.protocol import nominal_states
    from sep_plant.scenario import load_scenario

    file, changes = ROWS[args.row]
    if args.nodes:
        changes = {**changes, "nodes": list(args.nodes)}
    scen = load_scenario(REPO / "sep_plant" / "scenarios" / file if file else None).with_plant(**changes)
    plant = on_device(scen.plant, args.device)
    problem = scen.problem
    st = DesignSettings.for_scenario(scen)
    if args.memory_budget:
        from dataclasses import replace

        from sep_control.compute.budget import parse_budget
        st = replace(st, memory_budget=parse_budget(args.memory_budget))
    spent = [0.0, 0]
    step = plant.step

    def timed_step(X, *a, **kw):
        if spent[1] >= args.run_steps:
            raise Enough()
        t0 = time.perf_counter()
        out = step(X, *a, **kw)
        spent[0] += time.perf_counter() - t0
        spent[1] += X.shape[0] if X.ndim > 1 else 1
        return out

    def work():
        U = problem.u_start(plant.n_u)
        if args.stage == "design":
            run_design(plant, problem, st, show_progress=False, log=lambda m: None)
        elif args.stage == "sensitivity":
            from sep_control.design.belief import objective_of
            from sep_control.design.linearization import sensitivity_normal_equations
            sensitivity_normal_equations(plant, U, nominal_states(plant, U), objective_of(plant, problem), st.fd_eps)
        elif args.stage == "impulse":
            st.rom(None).identify(plant, U, False)
        else:
            from sep_control.design.belief import run_belief
            run_belief(plant, U, problem, st.ensemble, st.enkf_seed, st.memory_budget)

    with threadpool_limits(1):
        plant.step = timed_step
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        try:
            work()
            stopped = "finished"
        except Exception as exc:               # an engine re-raises it as the cause of its own
            cause = exc
            while cause is not None and not isinstance(cause, Enough):
                cause = cause.__cause__
            if cause is None:
                raise
            stopped = f"stopped at {args.run_steps} run-steps"
        prof.disable()
        total = time.perf_counter() - t0
    plant_s, run_steps = spent
    rest = total - plant_s
    print(f"{args.row}{' ' + str(args.nodes) if args.nodes else ''} {args.stage} on {args.device}: {stopped}; "
          f"n_x = {plant.n_x}, run-steps = {run_steps}, Jacobian {st.resolved_jacobian_for(plant, problem.n_steps)}")
    print(f"time {total:.2f} s, plant steps {plant_s:.2f} s ({1e9 * plant_s / max(1, run_steps * plant.n_x):.1f} "
          f"ns/node-step), rest {rest:.2f} s = {1e9 * rest / max(1, run_steps * plant.n_x):.2f} ns/node-step")
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats(args.sort).print_stats(args.top)
    print("\n".join(line for line in s.getvalue().splitlines() if line.strip())[-6000:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
