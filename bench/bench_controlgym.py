"""sep on controlgym's PDE environments, scored by the env's own reward, noise and reset.

For each task: sep designs from the env as a black box (plant type controlgym, the env's noise
off, its noise levels as w_std / v_std, the reward's weights as the objective's), and each
controller runs N seeded resets of the env itself (``env.reset(seed=i)``, i < N; the env's
own process and sensor noise, its own reward summed over its n_steps):

* zero         u = 0;
* sep open     sep's nominal input alone (open loop);
* sep ROM-LQG  the design as a policy (`sep_control.control.policy.DesignPolicy`, one-step-lagged
               observations: controlgym returns with step(u_k) the measurement of x_k);
* sep ROM-MPC  where the env has action limits;
* cg LQG (mean) / cg LQG (true x0)  controlgym's white-box LQG (it reads A, B, C; linear envs
               only), its filter started from the mean initial state or, as controlgym's own
               ``LQG.run`` does, from the true one; scored by the same loop as the others
               (all n_steps rewards; ``LQG.run`` drops the last one);
* PPO (quoted) the controlgym example notebook's figure for its Burgers task (-172.1 after
               50 x 32 x 100 env steps); quoted, not measured here.

Beside the rewards: the plant run-steps the design spent (every `plant.step` row, the
conformance check's included) and the design's wall time (a shared machine: indicative only).
The objective by default is the reward's (`--weighting field`): the LQR and the ROM-MPC weigh
the whole field, Q = Q_weight I summed over the state nodes (`lqr_weighting: field`,
`lqr_field_nodes: sum`, `lqr_q_early` = `lqr_q_late` = Q_weight) and R = R_weight I (`lqr_r`);
`--weighting output` is the 0.8 weighting on the sensors (Q_y = I / n_y, R = r_u I). The experiment
plan is `--plan` (default 0.9, the sample-efficient one; 0.8 is sep 0.8.0's). The disturbance
states are `--disturbance` (default none here; the product's default is input: on these tasks,
which have no persistent offset, input-bias states only turned the env's sensor noise into
input corrections, measured in docs/benchmarks.md).
Tasks: `notebook_burgers` (make("burgers", n_state=64, process_noise_cov=1e-5,
sensor_noise_cov=0.05), target 0.1 cos(2 pi x / L)) and any controlgym env at its defaults by
name. No assertions.

    OPENBLAS_NUM_THREADS=1 python bench/bench_controlgym.py [--tasks notebook_burgers,wave]
        [--resets 100] [--noise-modes 8] [--n-r 20] [--weighting field|output] [--plan 0.9|0.8]
        [--disturbance none|input|...] [--jacobian auto|sensitivity|rom]

`bench/bench_controlgym_bounds.py` measures, on the same resets, what a controller that knows the
true initial state or the whole field reaches: the reference for a missed target.
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

from sep_control.control.policy import DesignPolicy
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.plan import format_run_steps
from sep_plant.plants.controlgym import ControlgymPlant, controlgym_problem, envs_module, make_env

#: the controlgym example notebook's PPO reward on its Burgers task (quoted, not measured)
PPO_NOTEBOOK_BURGERS = -172.1
#: tasks beyond the env defaults: env, its keys, the target expression (None: the env's)
TASKS = {
    "notebook_burgers": ("burgers", {"n_state": 64, "process_noise_cov": 1e-5, "sensor_noise_cov": 0.05},
                         "0.1 * cos(2 * pi * x / 1.0)"),
    "wave_noisy": ("wave", {"process_noise_cov": 1e-5, "sensor_noise_cov": 0.05}, None),
    "burgers_1024": ("burgers", {"n_state": 1024}, None),
    "allen_cahn_1024": ("allen_cahn", {"n_state": 1024}, None),
    "burgers_4096": ("burgers", {"n_state": 4096}, None),
    "allen_cahn_4096": ("allen_cahn", {"n_state": 4096}, None),
}
LINEAR = ("convection_diffusion_reaction", "wave", "schrodinger")


def task(name: str) -> tuple[str, dict, str | None]:
    if name in TASKS:
        return TASKS[name]
    return name, {}, None


class Counting:
    """Counts the run-steps of a plant's `step` (an instance attribute: the plant's type is kept)."""

    def __init__(self, plant):
        self.n = 0
        inner = plant.step

        def step(x, u, w=None):
            self.n += int(np.atleast_2d(x).shape[0])
            return inner(x, u, w)
        plant.step = step


def white_box_lqg(env):
    """controlgym's LQG class, loaded from its file (its package __init__ imports torch)."""
    envs_module()
    path = Path(sys.modules["controlgym"].__path__[0]) / "controllers" / "lqg.py"
    spec = importlib.util.spec_from_file_location("controlgym_lqg", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.LQG(env)


def episodes(env, resets: int, act_factory) -> np.ndarray:
    """The env's summed reward over its n_steps for seeds 0..resets-1 (act_factory(obs, info) -> act)."""
    out = np.empty(resets)
    for i in range(resets):
        obs, info = env.reset(seed=i)
        act = act_factory(obs, info)
        total = 0.0
        for _ in range(env.n_steps):
            obs, r, _, _, _ = env.step(np.asarray(act(obs), dtype=float))
            total += r
        out[i] = total
    return out


def policy_factory(policy: DesignPolicy):
    def make(obs, info):
        policy.reset()
        return policy.act
    return make


def lqg_factory(lqg, x0_mean: np.ndarray | None):
    def make(obs, info):
        est = {"x": np.array(info["state"] if x0_mean is None else x0_mean, dtype=float)}
        last = {"u": None, "first": True}

        def act(o):
            if not last["first"]:                     # o measures the state before the last step
                est["x"] = lqg.evolve_state_estimate(est["x"], last["u"], o)
            last["first"] = False
            u = lqg.select_action(est["x"])
            last["u"] = u
            return u
        return act
    return make


def weighting_keys(plant: ControlgymPlant, weighting: str) -> dict:
    """The LQR/MPC weights: `field` is the reward's own (Q = Q_weight I summed over the state,
    R = R_weight I); `output` keeps `controlgym_problem`'s weights on the sensors."""
    if weighting == "output":
        return {}
    qw, rw = float(plant.env.Q[0, 0]), float(plant.env.R[0, 0])
    return {"lqr_weighting": "field", "lqr_field_nodes": "sum", "lqr_q_early": qw, "lqr_q_late": qw, "lqr_r": rw}


def task_setup(name: str, noise_modes: int | None, weighting: str):
    """(plant, problem, env) of a task: sep's plant and problem, and a scoring env with the task's target."""
    env_id, keys, target = task(name)
    plant = ControlgymPlant(env=env_id, noise_modes=noise_modes, **keys)
    overrides = weighting_keys(plant, weighting)
    if target:
        overrides["target"] = target
    problem = controlgym_problem(plant, **overrides)
    env = make_env(env_id, **keys)
    env.set_target_state(plant.env.target_state if target is None else
                         np.asarray(problem.target_field(plant.field_coordinates()), dtype=float))
    return plant, problem, env


def run_task(name: str, args, resets: int) -> dict:
    env_id = task(name)[0]
    plant, problem, env = task_setup(name, args.noise_modes, args.weighting)
    counter = Counting(plant)
    t0 = time.perf_counter()
    design = run_design(plant, problem, DesignSettings(n_r=args.n_r, experiment_plan=args.plan,
                                                       disturbance=args.disturbance, jacobian=args.jacobian),
                        show_progress=False, log=lambda m: None)
    design_s = time.perf_counter() - t0
    row = {"task": name, "resets": resets, "n_state": plant.n_x, "steps": env.n_steps, "plant_steps": counter.n, "design_s": design_s,
           "stages": format_run_steps(design.meta["run_steps"]), "prior": design.meta.get("initial_prior")}
    zero = np.zeros(plant.n_u)
    row["zero"] = episodes(env, resets, lambda o, i: (lambda obs: zero))
    row["sep open"] = episodes(env, resets, policy_factory(DesignPolicy(design, "open_loop", 1)))
    row["sep ROM-LQG"] = episodes(env, resets, policy_factory(DesignPolicy(design, "rom_lqg", 1)))
    if np.isfinite(plant.action_limit):
        row["sep ROM-MPC"] = episodes(env, resets, policy_factory(DesignPolicy(design, "rom_mpc", 1)))
    if env_id in LINEAR:
        lqg = white_box_lqg(env)
        try:
            row["cg LQG (mean)"] = episodes(env, resets, lqg_factory(lqg, plant.initial_state(1)[0]))
            row["cg LQG (true x0)"] = episodes(env, resets, lqg_factory(lqg, None))
        except ValueError as e:     # its Riccati solve failed (it logs "failed to find a finite solution")
            print(f"  {name}: controlgym's LQG could not run: {e}", flush=True)
    if name == "notebook_burgers":
        row["PPO (quoted)"] = PPO_NOTEBOOK_BURGERS
    return row


COLUMNS = ["zero", "sep open", "sep ROM-LQG", "sep ROM-MPC", "cg LQG (mean)", "cg LQG (true x0)", "PPO (quoted)"]


def fmt(v) -> str:
    if v is None:
        return "-"
    if np.isscalar(v):
        return f"{v:.1f}"
    return f"{np.mean(v):.1f} ± {np.std(v):.1f}"


def table_row(r: dict) -> str:
    """One line of the results table."""
    ratio = np.mean(r["sep ROM-LQG"]) / np.mean(r["zero"])
    return (f"| {r['task']} | {r['resets']} | " + " | ".join(fmt(r.get(c)) for c in COLUMNS)
            + f" | {ratio:.3f} | {r['plant_steps']} | {r['design_s']:.0f} |")


HEADER = "| task | resets | " + " | ".join(COLUMNS) + " | sep/zero | plant steps | design s |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", default="notebook_burgers", help="comma-separated: notebook_burgers, wave_noisy, "
                    "burgers_1024, allen_cahn_1024, burgers_4096, allen_cahn_4096 or controlgym env names at "
                    "their defaults; NAME:R scores NAME over R resets instead of --resets")
    ap.add_argument("--resets", type=int, default=100, help="seeded env resets per controller")
    ap.add_argument("--noise-modes", type=int, default=8, help="process-noise channels of the plant (Fourier modes)")
    ap.add_argument("--n-r", type=int, default=20, help="ROM order")
    ap.add_argument("--weighting", choices=("field", "output"), default="field",
                    help="LQR/MPC state weight: the reward's on the whole field, or 0.8's on the sensors")
    ap.add_argument("--plan", choices=("0.9", "0.8"), default="0.9", help="the design's experiment plan")
    ap.add_argument("--jacobian", choices=("auto", "sensitivity", "rom"), default="auto",
                    help="the nominal optimizer's Jacobian (sensitivity: N n_u experiments, exact on a linear env)")
    ap.add_argument("--disturbance", default="none",
                    help="the design's disturbance states (default none: these tasks have no offset to remove, "
                         "and the product default 'input' reads the env's sensor noise as input bias)")
    args = ap.parse_args()
    rows = []
    for spec in args.tasks.split(","):
        name, _, n = spec.strip().partition(":")
        row = run_task(name, args, int(n) if n else args.resets)
        rows.append(row)
        print(f"{row['task']}: n_state {row['n_state']}, {row['steps']} steps, design {row['plant_steps']} "
              f"plant run-steps in {row['design_s']:.0f} s; per stage {row['stages']}", flush=True)
        if row["prior"]:
            print(f"  initial state: {row['prior']['n_c']} initial-condition states on the ROM, "
                  f"{row['prior']['fit']:.1%} of the sampled free responses' deviations", flush=True)
        print("  " + table_row(row), flush=True)
    print(f"\nmean ± std of the env's summed reward over the seeded resets 0..R-1 (higher is better); "
          f"weighting {args.weighting}, plan {args.plan}, disturbance {args.disturbance}")
    print(HEADER)
    print("|" + "---|" * (len(COLUMNS) + 5))
    for r in rows:
        print(table_row(r))


if __name__ == "__main__":
    main()
