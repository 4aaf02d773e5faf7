"""How far can a controller that knows more get on a controlgym task? A reference for bench_controlgym.

`bench/bench_controlgym.py` scores sep, which knows only the env as a black box and its
noisy sensors. Where sep misses a target (for example "cost <= 0.5x the zero controller's"),
this bench measures whether a controller given white-box knowledge does any better, on the
same seeded resets, by the env's own reward:

* zero             u = 0;
* open (mean x0)   sep's optimizer's input from the mean initial state (the nominal sep designs);
* open (true x0)   the same optimizer run again from each reset's true initial state: the
                   open loop that knows the initial state. On an env without process noise (the
                   controlgym defaults) the state then follows it exactly, so this is what any
                   feedback could reach on that reset, up to the optimizer's local optimum;
* state feedback   u = -g B^+ (x - x*) on the env's true state, with B the env's actuator
                   shapes and g the best of a grid on these resets (white-box, full state).

Rewards are summed over the env's n_steps; ratios are to the zero controller's mean. No
assertions: a reference table for docs/benchmarks.md.

    OPENBLAS_NUM_THREADS=1 python bench/bench_controlgym_bounds.py --tasks allen_cahn,cahn_hilliard [--resets 5]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench_controlgym import task_setup
from sep_control.design.optimizer import Optimizer, OptimizerOptions
from sep_control.design.pipeline import DesignSettings
from sep_control.design.stages import mean_only_jacobian
from sep_plant.plants.controlgym import ControlgymPlant

#: the state-feedback gains tried (the best one's mean is reported)
GAINS = (0.3, 1.0, 3.0, 10.0, 30.0)


def rollout(env, seed: int, act) -> float:
    """The env's summed reward from ``reset(seed)`` under act(k, state) -> u."""
    _, info = env.reset(seed=seed)
    total = 0.0
    for k in range(env.n_steps):
        u = np.clip(np.asarray(act(k, info["state"]), dtype=float), -env.action_limit, env.action_limit)
        _, r, _, _, info = env.step(u)
        total += r
    return total


def optimal_open_loop(plant: ControlgymPlant, problem, x0: np.ndarray, max_iter: int) -> np.ndarray:
    """sep's mean-only optimizer (Levenberg-Marquardt, TV-ERA Jacobians) started at x0."""
    plant.initial_state = lambda batch: np.tile(x0, (int(batch), 1))   # this instance only
    st = DesignSettings(experiment_plan="0.8")
    options = OptimizerOptions(method="gn", max_iter=max_iter, show_progress=False)
    return Optimizer(plant, problem, options, mean_only_jacobian(st, "rom", None, problem)).run().U


def bounds_row(name: str, resets: int, max_iter: int) -> dict:
    plant, problem, env = task_setup(name, 8, "field")
    seeds = range(resets)
    t0 = time.perf_counter()
    mean_x0 = plant.initial_state(1)[0].copy()
    U_mean = optimal_open_loop(plant, problem, mean_x0, max_iter)
    row = {"task": name, "zero": [rollout(env, s, lambda k, x: np.zeros(plant.n_u)) for s in seeds],
           "open (mean x0)": [rollout(env, s, lambda k, x: U_mean[k]) for s in seeds], "true": []}
    x0s = plant.initial_states(list(seeds))
    for s in seeds:
        U = optimal_open_loop(plant, problem, x0s[s], max_iter)
        row["true"].append(rollout(env, s, lambda k, x: U[k]))
    pinv = np.linalg.pinv(env.control_sup)
    best = None
    for g in GAINS:
        with np.errstate(all="ignore"):
            c = [rollout(env, s, lambda k, x: -g * (pinv @ (x - env.target_state))) for s in seeds]
        if np.all(np.isfinite(c)) and (best is None or np.mean(c) > np.mean(best[1])):
            best = (g, c)
    row["feedback"] = best
    row["seconds"] = time.perf_counter() - t0
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", default="allen_cahn", help="comma-separated task names (bench_controlgym's)")
    ap.add_argument("--resets", type=int, default=5, help="seeded env resets 0..R-1")
    ap.add_argument("--max-iter", type=int, default=30, help="optimizer iterations per open loop")
    args = ap.parse_args()
    print("| task | resets | zero | open (mean x0) | open (true x0) | state feedback (g) | "
          "ratios to zero: mean x0 / true x0 / feedback | s |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.tasks.split(","):
        r = bounds_row(name.strip(), args.resets, args.max_iter)
        z = np.mean(r["zero"])
        g, fb = r["feedback"] if r["feedback"] else (None, [np.nan])
        cols = [np.mean(r["open (mean x0)"]), np.mean(r["true"]), np.mean(fb)]
        print(f"| {r['task']} | {args.resets} | {z:.1f} | {cols[0]:.1f} | {cols[1]:.1f} | {cols[2]:.1f} ({g}) | "
              + " / ".join(f"{c / z:.3f}" for c in cols) + f" | {r['seconds']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
