"""The offline design pipeline: black-box plant and problem in, design out.

1. open-loop nominal: mean-only Gauss-Newton/LM (or gradient descent), then the
   belief-space problem warm-started from it (EnKF belief along nominal observations);
2. TV-ERA reduced-order model from central-difference impulse experiments around the
   nominal (forward differences on request), with the field output map;
3. disturbance states for offset-free tracking (`sep_estimator.disturbance`), time-varying LQR
   (weights on the outputs) and Kalman filter on the ROM augmented with them;
4. the field map compressed to the directions the ROM state reaches with those gains (kept as
   identified when the LQR weighs the field);
5. a plant with an uncertain initial state: initial-condition states appended to the ROM from the
   free responses of sampled initial states, the filter's prior P_0 = blockdiag(0, cov(c)), and
   steps 3-4 again on it (`sep_control.design.initial_prior`).

    design = run_design(plant, problem, DesignSettings())

Each step is a stage with a typed result (`sep_control.design.stages`); with input limits and
a limit margin the stages run again inside tightened limits. The plant is checked against the
plant protocol first (`sep_plant.conformance`), so a bad plant fails in a second with a message,
not after the experiments. Only the plant's `initial_state`, `step`, `observe`, `field` and
state snapshots are used.
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import platform
import time
from dataclasses import asdict, replace
from typing import Any, Callable

import numpy as np

from sep_estimator.design import Design, Nominal
from sep_estimator.design_file import disturbance_meta
from sep_estimator.ltv import LTVModel
from sep_plant.conformance import check_plant
from sep_plant.plants import type_name_of
from sep_plant.problem import Objective, Problem
from sep_plant.protocol import Plant, PlantInfo, fields, outputs
from sep_plant.scenario import Scenario

from sep_control import __version__
from sep_control.design.belief import objective_of
from sep_control.design.gains import design_lqg, input_spread
from sep_control.design.settings import DesignSettings
from sep_control.design.plan import clip_correction_pass, format_run_steps, log_plan, margin_redesigns
from sep_control.design.runsteps import RunStepMeter, metered
from sep_control.design.saturation import ClosedLoopRom, RomClosedLoop, correct_nominal
from sep_control.design.stages import DesignPass, NominalResult, StageContext, design_pass, fixed_nominal_pass
from sep_control.design.tvera import Identification

__all__ = ["DesignSettings", "run_design", "identify_rom", "with_rom", "tightened_limits", "scenario_of"]


def scenario_of(plant: Plant, problem: Problem) -> Scenario:
    """The plain-data scenario (type string, complete plant keys, problem) of a plant object."""
    return Scenario(type_name_of(plant), dict(plant.config()), problem.resolved())


def run_design(plant: Plant, problem: Problem, settings: DesignSettings | None = None,
               show_progress: bool = True, log: Callable[[str], None] = print, engine=None) -> Design:
    """Run the whole offline design for `plant` and `problem` and return the `Design`.

    With input limits and `settings.limit_margin` = c > 0 the nominal is re-optimized
    `margin_iterations` times inside the limits tightened by c times the designed LQG's
    closed-loop input std (`gains.input_spread`): lo + c sigma_u,k <= ubar_k <= hi - c sigma_u,k,
    so that the feedback has room to act on both sides (each time the ROM and the gains are
    redesigned around the new nominal).

    Parameters
    ----------
    plant : Plant
        The black-box plant (checked against the plant protocol first).
    problem : Problem
        Horizon, objective, noise, limits and LQG weights.
    settings : DesignSettings, optional
        The design's knobs (None: the defaults).
    show_progress : bool
        Draw progress bars.
    log : callable
        Receives one line per stage.
    engine : optional
        `sep_control.compute.engine` that runs the impulse experiments (None: in-process). The
        result does not depend on it (the chunk plan is `settings.chunks`).

    Returns
    -------
    Design
        Scenario, plant info, objective, nominal and belief, the ROM's LQG, the Hankel singular
        values and the metadata (settings, provenance, timings, optimizer, validation; "belief":
        "ensemble", or "absent" for a plant whose states are opaque: its nominal is the mean-only
        one and no EnKF runs, `DesignSettings.for_plant`).
    """
    given = settings or DesignSettings()
    given.check()
    given.check_plant_dims(int(plant.n_u), int(plant.n_y))
    check_plant(plant, problem.channels("u_init", int(plant.n_u)))
    meter = RunStepMeter()
    st = given.for_plant(plant)
    if st.belief != given.belief:
        log("the plant's states are opaque (state_is_opaque): mean-only nominal, no EnKF belief "
            "(the belief refinement and the belief statistics need arithmetic on states)")
    scenario = scenario_of(plant, problem)
    problem = scenario.problem
    ctx = StageContext(show_progress, log, engine, meter=meter)
    log_plan(plant, problem, st, log)
    t_all = time.perf_counter()
    counted = metered(plant, meter)
    optimized, margins, experiments = _with_limit_margin(counted, problem, st, ctx,
                                                         design_pass(counted, problem, st, ctx))
    final, correction = _with_clip_correction(counted, problem, st, ctx, optimized)
    ctx.timings["total_s"] = time.perf_counter() - t_all
    log(f"run-steps: {format_run_steps(meter.as_dict())}")

    obj = objective_of(plant, problem)
    ident = final.identification.identification
    U, belief = final.nominal.U, final.nominal.belief
    X_nom = ident.X_ext[: problem.n_steps + 1]
    F_nom = fields(plant, X_nom)
    nominal = Nominal(U, outputs(plant, X_nom), F_nom, *((belief.mean, belief.std) if belief is not None else ()))
    meta = {**_meta(st, ctx.timings, final, obj, F_nom, margins, experiments, optimized.nominal),
            "belief": nominal.belief_kind}
    if correction is not None:
        meta["clip_correction"] = correction
    with meter.stage("identification"):            # the free responses of sampled initial states
        lqg = _initial_prior_hook(counted, final, problem, st, nominal, meta, log)
    meta["run_steps"] = meter.as_dict()
    return Design(scenario, PlantInfo.of(plant), obj, np.asarray(plant.field_coordinates(), dtype=float), nominal,
                  lqg, ident.hankel_sv, meta)


def _initial_prior_hook(plant: Plant, final: DesignPass, problem: Problem, st: DesignSettings, nominal: Nominal,
                        meta: dict[str, Any], log: Callable[[str], None]):
    """The design's LQG on the ROM with initial-condition states (`sep_control.design.initial_prior`:
    the free responses of sampled initial states, P_0 = blockdiag(0, cov(c))): the gains and
    the field map redesigned on it with the final pass's disturbance states; the final pass's
    LQG itself, bit for bit, for a plant whose initial state is known."""
    from sep_control.design.field_map import compressed_lqg
    from sep_control.design.initial_prior import fit_initial_prior, with_initial_states

    prior = fit_initial_prior(plant, nominal.u, nominal.y, nominal.field)
    if prior is None:
        return final.lqg
    meta["initial_prior"] = {"n_c": prior.n_c, "fit": prior.fit, "run_steps": prior.run_steps,
                             "trace": float(np.trace(prior.cov))}
    log(f"initial state uncertain: {prior.n_c} initial-condition states on the ROM from {prior.run_steps} "
        f"free-response run-steps (they hold {prior.fit:.1%} of the sampled deviations)")
    rom = with_initial_states(final.identification.identification.model, prior)
    return compressed_lqg(design_lqg(rom, problem, final.lqg.disturbance), st.field_map_tol)


#: the limit-margin loop warns when its nominal's objective ends above this many times the
#: unmargined one's: the tightened limits then hold the targets out of reach (the FMU rod at
#: margin 1: 1.18 -> 461.6, no run in band), which a user asked for the margin should be told
MARGIN_COST_WARN = 2.0


def _with_limit_margin(plant: Plant, problem: Problem, st: DesignSettings, ctx: StageContext,
                       first: DesignPass) -> tuple[DesignPass, list[dict[str, Any]], int]:
    """The limit-margin loop on top of the stages: the last pass, one record per redesign, and
    the experiments of the passes before the last."""
    lo, hi = problem.limits(int(plant.n_u))
    current, margins, experiments = first, [], 0
    kind = "belief" if st.belief else "nominal"
    for it in range(margin_redesigns(problem, st)):
        sigma = input_spread(current.lqg)
        bounds = tightened_limits(lo, hi, sigma, st.limit_margin)
        experiments += current.nominal.experiments
        current = design_pass(plant, problem, st, ctx, U0=current.nominal.U, bounds=bounds)
        margins.append({"iteration": it + 1, "sigma_u_max": float(sigma.max()),
                        "sigma_u_mean": float(sigma.mean()), "objective": current.nominal.cost,
                        "objective_kind": kind})
        ctx.log(f"limit margin {st.limit_margin:g} sigma_u (iteration {it + 1}): input std up to "
                f"{sigma.max():.3g}, {kind} J = {current.nominal.cost:.6g}")
    ratio = current.nominal.cost / first.nominal.cost if margins and first.nominal.cost > 0 else 1.0
    if ratio > MARGIN_COST_WARN:
        ctx.log(f"warning: the limit margin raised the {kind} objective {ratio:.3g}x "
                f"({first.nominal.cost:.6g} -> {current.nominal.cost:.6g}): inside limits tightened by "
                f"{st.limit_margin:g} closed-loop input stds the nominal cannot reach its targets; "
                f"a smaller --limit-margin (limit_margin) keeps them in reach")
    return current, margins, experiments


#: the clip correction runs when the limits' clipping adds more than this share to the closed-loop
#: cost the ROM predicts (below it the feedback rarely reaches a limit and there is nothing to gain)
CLIP_LOSS_MIN = 0.01
#: the ROM Monte Carlo's random numbers: one stream to optimize on, a fresh one to judge by
CLIP_SEEDS = (0, 1)


def _closed_loop(plant: Plant, problem: Problem, p: DesignPass) -> ClosedLoopRom:
    """Pass p's closed loop on its ROM (its LQG, nominal input and the nominal's field)."""
    X = p.identification.identification.X_ext[: problem.n_steps + 1]
    return ClosedLoopRom.of(p.lqg, p.nominal.U, fields(plant, X), objective_of(plant, problem), problem)


def _nominal_cost(cl: ClosedLoopRom) -> float:
    """J of the nominal (its rollout's field and inputs)."""
    return float(cl.objective.cost(cl.f_nom, cl.u_nom))


def _with_clip_correction(plant: Plant, problem: Problem, st: DesignSettings, ctx: StageContext,
                          current: DesignPass) -> tuple[DesignPass, dict[str, Any] | None]:
    """The nominal moved to where the ROM predicts the lowest closed-loop cost under the limits'
    clipping (`sep_control.design.saturation`), the stages again around it, and the pass the
    ROM Monte Carlo of fresh random numbers predicts cheaper; the record for the design file."""
    if not clip_correction_pass(problem, st.resolved()):
        if st.resolved().clip_correction and margin_redesigns(problem, st):
            ctx.log(f"clip correction: not run (limit_margin {st.limit_margin:g}: the nominal stays inside the "
                    f"tightened limits)")
        return current, None
    t0 = time.perf_counter()
    cl = _closed_loop(plant, problem, current)
    mc, zero = RomClosedLoop(cl, seed=CLIP_SEEDS[0]), np.zeros_like(cl.u_nom)
    clipped, free = mc.cost(zero), mc.cost(zero, limits=False)
    record: dict[str, Any] = {"predicted_cost": clipped, "predicted_cost_unclipped": free}
    if clipped - free <= CLIP_LOSS_MIN * clipped:
        ctx.log(f"clip correction: the limits add {clipped - free:.3g} to the predicted closed-loop cost "
                f"{clipped:.6g} (ROM Monte Carlo), under {CLIP_LOSS_MIN:.0%}: nominal kept")
        record["kept"] = "optimized"
        return current, record
    fix = correct_nominal(mc, clipped)
    if np.array_equal(fix.U, current.nominal.U):
        ctx.log(f"clip correction: the limits add {clipped - free:.3g} to the predicted closed-loop cost "
                f"{clipped:.6g} (ROM Monte Carlo), and no move inside them lowers it: nominal kept")
        record.update({"iterations": fix.iterations, "kept": "optimized"})
        return current, record
    ctx.log(f"clip correction: the limits clip the feedback; ROM Monte Carlo closed-loop cost {clipped:.6g} "
            f"(without limits {free:.6g}), moved nominal {fix.predicted:.6g} ({fix.iterations} L-BFGS-B "
            f"iterations, {time.perf_counter() - t0:.1f} s); identifying again there")
    moved = fixed_nominal_pass(plant, problem, st, ctx, fix.U, "moved by the clip correction")
    cl_moved = _closed_loop(plant, problem, moved)
    before = RomClosedLoop(cl, seed=CLIP_SEEDS[1]).cost(zero)
    after = RomClosedLoop(cl_moved, seed=CLIP_SEEDS[1]).cost(zero)
    keep = after < before
    J0, J1 = _nominal_cost(cl), _nominal_cost(cl_moved)
    record.update({"moved_predicted_cost": fix.predicted, "iterations": fix.iterations,
                   "check_optimized": before, "check_moved": after, "kept": "moved" if keep else "optimized",
                   "nominal_cost_optimized": J0, "nominal_cost_moved": J1})
    ctx.log(f"clip correction: predicted closed-loop cost (fresh random numbers, each on its own ROM) "
            f"{before:.6g} optimized -> {after:.6g} moved (nominal J {J0:.6g} -> {J1:.6g}): "
            f"{'moved nominal kept' if keep else 'optimized nominal kept'}")
    ctx.took("clip_correction_s", t0)
    return (moved if keep else current), record


def _meta(st: DesignSettings, timings: dict[str, float], final: DesignPass, obj: Objective, F_nom: np.ndarray,
          margins: list[dict[str, Any]], experiments: int, optimized: NominalResult) -> dict[str, Any]:
    """The design file's metadata (docs/reference/design-file.md); `optimized`: the nominal of
    the optimizer's last pass (the final pass's unless the clip correction moved it)."""
    nom, ident = optimized, final.identification
    opt = nom.mean_only
    k0, k1 = obj.window
    return {
        "settings": asdict(st),
        "provenance": {"tool": "sep design", "version": __version__, "python": platform.python_version(),
                       "numpy": np.__version__, "created_unix": time.time(), "seed": st.enkf_seed},
        "timings": timings,
        "optimizer": {"method": st.method, "jacobian": nom.jacobian, "mean_only_cost": opt.cost,
                      "mean_only_history": opt.history, "belief_history": nom.belief_history,
                      "iterations": opt.iterations, "experiments": opt.experiments,
                      "linearizations": opt.linearizations, "stop": opt.stop,
                      "belief_experiments": nom.refinement.experiments if nom.refinement is not None else 0,
                      "identification_reused": ident.reused, "nominal_cost": float(obj.cost(F_nom, nom.U)),
                      "limit_margins": margins, "experiments_before_last_margin_pass": experiments},
        "validation": {"markov_rel_error": ident.markov_rel_error, "impulse_amplitude": ident.identification.delta,
                       **({} if ident.spot_rel_error is None else {"spot_markov_rel_error": ident.spot_rel_error}),
                       **({} if ident.stride_resolved is None else {"stride_resolved_share": ident.stride_resolved}),
                       "max_dev_in_band_window": float(np.max(np.abs(F_nom[k0:k1 + 1] - obj.targets(k0, k1)))),
                       **({} if obj.holds is None else {"max_dev_per_hold": [
                           float(np.max(np.abs(F_nom[a:b + 1] - obj.targets(a, b)))) for a, b, _ in obj.holds]})},
        "disturbance": disturbance_meta(final.lqg.disturbance),
    }


def tightened_limits(lo: np.ndarray, hi: np.ndarray, sigma: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, n_u) bounds lo + c sigma, hi - c sigma; where they would cross, both at the middle."""
    LO, HI = lo + c * sigma, hi - c * sigma
    with np.errstate(invalid="ignore"):      # channels without limits: inf - inf, never crossing
        mid = 0.5 * (np.where(np.isfinite(lo), lo, HI) + np.where(np.isfinite(hi), hi, LO))
        cross = LO > HI
    return np.where(cross, mid, LO), np.where(cross, mid, HI)


def identify_rom(plant: Plant, U: np.ndarray, st: DesignSettings, show_progress: bool = False,
                 engine=None, problem: Problem | None = None) -> Identification:
    """`tvera.identify` with the design's settings (and the problem's w_std, the weights of a
    sketch of many noise channels)."""
    return st.rom(engine, problem).identify(plant, U, show_progress)


def with_rom(design: Design, model: LTVModel, hankel_sv: np.ndarray | None = None) -> Design:
    """`design` with its ROM replaced by `model` and the LQG gains redesigned (same nominal; the
    field map is `model`'s as it is; the disturbance states chosen again on `model` with the
    design's settings, `DesignSettings.disturbance_for`)."""
    dist = DesignSettings.from_meta(design.meta).disturbance_for(model, design.problem)
    meta = {**design.meta, "disturbance": disturbance_meta(dist)}
    return replace(design, lqg=design_lqg(model, design.problem, dist).lqg(), meta=meta,
                   hankel_sv=design.hankel_sv if hankel_sv is None else hankel_sv)
