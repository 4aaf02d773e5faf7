"""A design with process noise on every node against the same plant with a few noise channels.

The plant: `tests/rd_plant.py`, 1-D reaction-diffusion of `--nodes` nodes, 3 actuators, 5 point
sensors, process noise additive on the state (`noise_on_inputs` False). Rows, one after the
other in this process (a shared machine: compare the times within one run only):

* modes 8             noise on the 8 slowest cosine modes (n_w = 8: identified channel by channel);
* every node          n_w = n_x, the noise channels sketched on SKETCH_PROBES random combinations
                      per start step (`sep_control.design.noise_sketch`, the default above
                      SKETCH_FROM channels);
* every node, exact   (``--exact``) n_w = n_x identified channel by channel (the sketch switched
                      off for this row): the reference the sketch is measured against.

Per row: the design's run-steps, its time, the identification's Hankel width q (n_u + n_w
identified), the Markov relative error, and a `--runs`-run closed-loop Monte Carlo of the
ROM-LQG (seed 1) on the plant with its own noise: cost, in band, 2 sigma coverage. No assertions.

    OPENBLAS_NUM_THREADS=1 python bench/bench_noise_channels.py [--nodes 201] [--steps 150]
        [--runs 200] [--w-std 0.003] [--exact] [--plan 0.9] [--probes 32]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from unittest import mock

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rd_plant import ReactionDiffusionPlant  # noqa: E402

from sep_control.design import noise_sketch  # noqa: E402
from sep_control.design.pipeline import DesignSettings, run_design  # noqa: E402
from sep_control.evaluation.montecarlo import simulate  # noqa: E402
from sep_plant.problem import Problem  # noqa: E402


def row(name: str, plant, problem: Problem, st: DesignSettings, runs: int) -> dict:
    """Design, then a Monte Carlo of its ROM-LQG: one table row."""
    t0 = time.perf_counter()
    d = run_design(plant, problem, st, show_progress=False, log=lambda m: None)
    seconds = time.perf_counter() - t0
    n_id = plant.n_w if noise_sketch.sketch_for(plant.n_w, problem.w_std) is None else noise_sketch.SKETCH_PROBES
    m = simulate(plant, d, "rom_lqg", 1, runs, keep_estimates=0, keep_trajectories=0).metrics()
    return {"row": name, "n_w": plant.n_w, "hankel_cols": st.q * (plant.n_u + n_id),
            "run_steps": d.meta["run_steps"]["total"], "design_s": seconds,
            "markov": d.meta["validation"]["markov_rel_error"], "cost": m["cost_mean"],
            "in_band": m["in_band"], "cov2": m["coverage_2sigma"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=201)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--plan", default="0.9", choices=["0.8", "0.9"])
    ap.add_argument("--w-std", type=float, default=0.003, help="process-noise std per channel")
    ap.add_argument("--probes", type=int, default=noise_sketch.SKETCH_PROBES)
    ap.add_argument("--exact", action="store_true", help="also the every-node plant identified channel by channel")
    args = ap.parse_args()
    problem = Problem(n_steps=args.steps, target=0.3, band=0.05, w_std=args.w_std, v_std=0.02, u_init=0.2, r_u=0.01)
    st = DesignSettings(experiment_plan=args.plan)
    keys = ["row", "n_w", "hankel_cols", "run_steps", "design_s", "markov", "cost", "in_band", "cov2"]
    print(f"reaction-diffusion, {args.nodes} nodes, N = {args.steps}, w_std {args.w_std:g}, plan {args.plan}, "
          f"{args.runs} runs (seed 1)")
    print(" | ".join(keys), flush=True)
    rows = []

    def add(r: dict) -> None:
        rows.append(r)
        print(" | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else f"{r[k]:,}" if isinstance(r[k], int)
                         else str(r[k]) for k in keys), flush=True)

    add(row("modes 8", ReactionDiffusionPlant(args.nodes, noise_modes=8), problem, st, args.runs))
    every = ReactionDiffusionPlant(args.nodes)
    with mock.patch.object(noise_sketch, "SKETCH_PROBES", args.probes):
        add(row(f"every node, sketch {args.probes}", every, problem, st, args.runs))
    if args.exact:
        with mock.patch.object(noise_sketch, "SKETCH_FROM", 10**9):
            add(row("every node, exact", every, problem, st, args.runs))
    base = rows[0]
    for r in rows[1:]:
        print(f"{r['row']} / modes 8: run-steps {r['run_steps'] / base['run_steps']:.2f}x, "
              f"time {r['design_s'] / base['design_s']:.2f}x")


if __name__ == "__main__":
    main()
