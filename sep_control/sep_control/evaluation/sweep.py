"""The ROM-order sweep of `sep evaluate --sweep`: how the closed loop degrades with the order cap.

At each order cap n_r the ROM is realized again by TV-ERA from one set of Markov parameters
(the impulse experiments run once, at the largest cap), the LQG is redesigned on it (same
nominal), and a Monte Carlo measures its cost against the full-order oracle's.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Sequence

from sep_control.compute.progress import RunSteps
from sep_control.design.noise_sketch import identified_noise_channels
from sep_control.design.pipeline import DesignSettings, identify_rom, with_rom
from sep_control.design.tvera import FIELD_TOL, markov_relative_error, tv_era
from sep_control.evaluation.montecarlo import portable, simulate
from sep_control.evaluation.validation import impulse_run_steps


def sweep_run_steps(plant, design, orders: Sequence[int], runs: int, oracle: bool) -> int:
    """Run-steps of `rom_sweep`: the identification's experiments, the oracle's runs (if any)
    and `runs` runs per order, each of N steps."""
    st = DesignSettings.from_meta(design.meta)
    N = design.n_steps
    n_w = identified_noise_channels(plant, design.problem.w_std)
    return impulse_run_steps(plant, N, st.p + st.q, st.impulse_scheme, n_w) + (len(orders) + bool(oracle)) * runs * N


def rom_sweep(plant, design, oracle, orders: Sequence[int], runs: int, seed: int, engine=None,
              show_progress: bool = False, progress=None) -> list[dict[str, Any]]:
    """Closed-loop cost and Markov error of the ROM-LQG at each order cap.

    Parameters
    ----------
    plant : Plant
        The nonlinear plant.
    design : Design
        The design whose nominal, settings (p, q, sv_tol, impulse scheme; impulses at every start
        step) and problem are used.
    oracle : LQG or None
        The full-order oracle LQG (`sep_control.evaluation.oracle.oracle_lqg`); None: no
        ``cost_oracle`` (rows carry None).
    orders : sequence of int
        The order caps n_r; the experiments are identified once at max(orders).
    runs : int
        Monte Carlo runs per point (and for the oracle), seed `seed` (common random numbers).
    engine : engine, optional
        Where the experiments and the points run (`sep_control.compute.engine`): each point
        (realization at n_r and its Monte Carlo) is one task.
    show_progress : bool
        A bar over the points (the engine's).
    progress : RunSteps, optional
        Advanced by the run-steps done (`sweep_run_steps` in all).

    Returns
    -------
    list of dict
        One row per order: n_r, n_r_used (the realized order), markov_rel_error, cost_mean,
        in_band, cost_oracle.
    """
    from sep_control.compute.engine import InProcess

    engine, progress = engine or InProcess(), progress or RunSteps(0, "", enabled=False)
    settings = DesignSettings.from_meta(design.meta)
    settings.n_r = max(orders)
    # impulses at every start step: strided ones leave the higher orders' states to the
    # interpolation's error (`sep_control.design.stride_check`), which the sweep would then compare
    settings.impulse_stride = 1
    N = design.n_steps
    ident = identify_rom(plant, design.nominal.u, settings, engine=engine, problem=design.problem)
    progress.add(impulse_run_steps(plant, N, settings.p + settings.q, settings.impulse_scheme,
                                   identified_noise_channels(plant, design.problem.w_std)))
    oracle_cost = None
    if oracle is not None:
        oracle_cost = simulate(plant, design, "oracle_lqg", seed, runs, oracle=oracle, keep_estimates=0,
                               keep_trajectories=0, engine=engine).metrics()["cost_mean"]
        progress.add(runs * N)
    shared = dict(plant=engine.ship(plant), data=ident.data, design=design if engine.local else portable(design),
                  p=settings.p, q=settings.q, sv_tol=settings.sv_tol, seed=seed, runs=runs,
                  field_tol=settings.field_tol)
    points = engine.map(sweep_point, list(orders), shared,
                        [f"plant {design.scenario.plant_type}: ROM sweep point n_r = {n}" for n in orders],
                        "ROM sweep", show_progress=show_progress)
    progress.add(len(orders) * runs * N)
    return [{**pt, "cost_oracle": oracle_cost} for pt in points]


def sweep_point(n_r: int, plant, data, design, p: int, q: int, sv_tol: float, seed: int, runs: int,
                field_tol: float = FIELD_TOL) -> dict[str, Any]:
    """One sweep point: TV-ERA at order cap n_r from the shared Markov data, then `runs` runs.

    Parameters
    ----------
    n_r : int
        The order cap.
    plant : Plant or its shipped form
        (`engine.ship`: rebuilt once per worker process).
    data : MarkovData
        The shared impulse experiments.
    design : Design
        The design whose nominal and problem the redesigned LQG keeps.
    p, q : int
        Hankel block rows and columns.
    sv_tol : float
        Relative singular-value cutoff.
    seed, runs : int
        The Monte Carlo's seed and runs.
    field_tol : float
        The field map's truncation (the identification's field basis tolerance).

    Returns
    -------
    dict
        n_r, n_r_used, markov_rel_error, cost_mean, in_band.
    """
    from sep_control.compute.engine import local_plant

    plant = local_plant(plant)
    model, _ = tv_era(data, design.n_steps, p, q, n_r, sv_tol, field_tol=field_tol)
    m = simulate(plant, with_rom(design, model), "rom_lqg", seed, runs, keep_estimates=0,
                 keep_trajectories=0).metrics()
    return {"n_r": n_r, "n_r_used": int(model.dims.max()),
            "markov_rel_error": markov_relative_error(model, data.Y, data.noise),
            "cost_mean": m["cost_mean"], "in_band": m["in_band"]}

