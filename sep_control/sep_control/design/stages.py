"""The stages of the offline design, each a function with a typed result:

    nominal_stage          -> NominalResult         open-loop nominal (mean-only, then belief space)
    identification_stage   -> IdentificationStage   TV-ERA ROM around the nominal
    gains_stage            -> GainsResult           disturbance states, TV-LQR and Kalman filter on the ROM
    field_map_stage        -> LQG                   the ROM's field map compressed for those gains

`design_pass` runs them in order (`sep_control.design.pipeline.run_design` runs passes).
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from sep_estimator.enkf import EnKFResult
from sep_estimator.ltv import LQG
from sep_plant.problem import Problem
from sep_plant.protocol import Plant, fields, nominal_states

from sep_control.design.belief import objective_of, run_belief
from sep_control.design.field_map import compressed_lqg
from sep_control.design.gains import GainsResult, design_lqg
from sep_control.design.jacobians import (AutoJacobian, Jacobian, KeptRomJacobian, RomJacobian,
                                          SensitivityJacobian)
from sep_control.design.linearization import SAME_INPUT_RTOL, same_input
from sep_control.design.noise_sketch import SKETCH_FROM, trace_std_error
from sep_control.design.optimizer import OptimizationResult, Optimizer, OptimizerOptions
from sep_control.design.runsteps import RunStepMeter
from sep_control.design.settings import DesignSettings
from sep_control.design.spotcheck import SPOT_BLOCKS, SPOT_STARTS, SPOT_TOL, spot_error
from sep_control.design.stride_check import RESOLVED_MIN, resolved_share
from sep_control.design.tvera import Identification, extend_nominal, markov_relative_error

#: Levenberg-Marquardt trials per belief-space iteration. Each is an EnKF run, and the Gauss-Newton
#: model of J_b holds the belief's spread fixed: when the first (least damped) trial raises J_b the
#: spread's own gradient, which the model misses, outweighs the mean's, and more damping does not
#: fix a missing gradient (plate 64^2: the model predicted -1.6e-5, -1.5e-5, -1.2e-5, -7e-6
#: relative for lambda 1e-3 .. 6.4e-2, the EnKF gave +1.7e-5, +1.2e-5, +5e-6, +4e-7)
BELIEF_TRIALS = 1

#: the optimizer's identifications far from the optimum only propose steps (the true objective
#: accepts them): forward impulses (about half the runs) and a field basis to 1e-6 of the largest
#: response (the forward differences' round-off stays out of it) serve as well there. Halving the
#: Hankel blocks too (p = q = 8, experiments of 16 steps) was tried: the same optimum on the slab,
#: but on the Burgers example the proposals then stalled (J 0.369 after max_iter instead of 0.00156)
PROPOSAL_ROM = {"scheme": "forward", "field_tol": 1e-6, "coarse": True}

#: experiment plan "0.9" (`DesignSettings.experiment_plan`): the mean-only optimizer's first model
#: is a coarse one (forward impulses, Hankel blocks p = q = PLAN_PQ, experiments of 2 PLAN_PQ steps,
#: field basis to 1e-6), kept while its accepted steps lower the cost by at least half of what it
#: predicts (each trial costs one rollout, not an identification); then models with the design's
#: settings (`KeptRomJacobian`). The last one is spot-checked at the final input before the design
#: reuses it (`sep_control.design.spotcheck`). Iterations are cheap then (rollouts), so the plan
#: allows PLAN_MAX_ITER of them
PLAN_PQ = 8
PLAN_MAX_ITER = 30
#: experiment plan "0.9": the mean-only optimizer stops after an accepted step of a model with the
#: design's settings that lowered the cost by less than this (relative; the step is taken). Near
#: the optimum the nominal cost is flat and every further model costs an identification; the
#: closed loop kept its cost within 0.4 % on the reference, plate and Burgers. It waits while the
#: nominal's field is out of its band (`OptimizerOptions.settle`): a 101-node reaction-diffusion
#: test plant had stopped 2.5 % above its optimum 0.056 off for a band of 0.05 (docs/benchmarks.md)
SETTLE_DECREASE = 1e-2


@dataclass
class StageContext:
    """What every stage shares: progress bars, the log, the experiments' engine, the timings."""

    show_progress: bool = True
    log: Callable[[str], None] = print
    engine: object = None                  # `sep_control.compute.engine` (None: in-process)
    timings: dict[str, float] = field(default_factory=dict)   # seconds per stage, summed over passes
    meter: RunStepMeter = field(default_factory=RunStepMeter)  # run-steps per stage, summed over passes

    def took(self, key: str, t0: float) -> None:
        """Add the time since `t0` to timings[key]."""
        self.timings[key] = self.timings.get(key, 0.0) + time.perf_counter() - t0


@dataclass
class NominalResult:
    """The open-loop nominal: the mean-only optimum and its belief-space refinement."""

    U: np.ndarray                              # (N, n_u) the nominal input
    mean_only: OptimizationResult              # the mean-only optimizer's result
    refinement: OptimizationResult | None      # the belief-space refinement's (None: not refined)
    belief: EnKFResult | None                  # the EnKF belief at U (None: opaque states, no EnKF)
    jacobian: str                              # the mean-only optimizer's Jacobian ("sensitivity" or "rom")

    @property
    def last(self) -> OptimizationResult:
        """The result U comes from."""
        return self.refinement if self.refinement is not None else self.mean_only

    @property
    def cost(self) -> float:
        """The final objective (belief cost when refined, else the nominal cost)."""
        return self.last.cost

    @property
    def belief_history(self) -> list[float]:
        return self.refinement.history if self.refinement is not None else []

    @property
    def experiments(self) -> int:
        """Black-box runs both optimizers used."""
        return self.mean_only.experiments + (self.refinement.experiments if self.refinement is not None else 0)


@dataclass
class IdentificationStage:
    """The design's ROM: a TV-ERA identification at the nominal input."""

    identification: Identification
    reused: bool                  # the optimizer's last identification (made at this input), not a new one
    markov_rel_error: float       # `markov_relative_error` of the model on its own experiments
    spot_rel_error: float | None = None   # plan 0.9: its error at the final input (`spotcheck`), when reused from elsewhere
    stride_resolved: float | None = None  # strided impulses: the share of kept states they resolve (`stride_check`)


@dataclass
class DesignPass:
    """One pass of the stages (the limit-margin loop runs several)."""

    nominal: NominalResult
    identification: IdentificationStage
    lqg: LQG                      # the design's LQG: its gains, the compressed field map


def mean_only_jacobian(st: DesignSettings, kind: str, engine=None, problem: Problem | None = None) -> Jacobian:
    """The mean-only optimizer's strategy for the resolved Jacobian `kind`: "rom", or
    "sensitivity" (switching to the ROM near the optimum when `st.jacobian` is "auto")."""
    rom = st.rom(engine, problem)
    if st.experiment_plan == "0.8":
        proposal = replace(rom, **PROPOSAL_ROM) if st.coarse_proposals else None
        rom_jacobian = RomJacobian(rom, proposal, relinearize_rtol=st.relinearize_rtol)
    else:
        # the optimizer's models need the inputs' Markov parameters only: no impulses on the
        # plant's own noise channels (the design's model, identified after it, has them)
        rom = replace(rom, inputs_only=True)
        proposal = replace(rom, **PROPOSAL_ROM, p=min(rom.p, PLAN_PQ), q=min(rom.q, PLAN_PQ)) \
            if st.coarse_proposals else rom
        rom_jacobian = KeptRomJacobian(rom, proposal)
    if kind == "rom":
        return rom_jacobian
    if kind != "sensitivity":
        raise ValueError(f"jacobian must be 'sensitivity' or 'rom', got {kind!r}")
    sensitivity = SensitivityJacobian(st.fd_eps)
    return AutoJacobian(sensitivity, rom_jacobian) if st.jacobian == "auto" else sensitivity


def nominal_stage(plant: Plant, problem: Problem, st: DesignSettings, ctx: StageContext,
                  U0: np.ndarray | None = None, bounds: tuple[np.ndarray, np.ndarray] | None = None) -> NominalResult:
    """Stage 1: the open-loop nominal (mean-only optimum, then the belief-space refinement),
    from U0 (None: u_init) inside `bounds` (None: the problem's limits)."""
    t0 = time.perf_counter()
    kind = st.resolved_jacobian_for(plant, problem.n_steps)     # plan 0.9 + gn + auto: "rom"
    planned = st.experiment_plan != "0.8" and st.method == "gn" and kind == "rom"
    max_iter = PLAN_MAX_ITER if planned and st.max_iter is None else st.max_iter
    options = OptimizerOptions(method=st.method, max_iter=max_iter, tol=st.tol, step_size=st.step_size,
                               bounds=bounds, show_progress=ctx.show_progress, refresh_on_stall=planned,
                               settle=SETTLE_DECREASE if planned else 0.0)
    with ctx.meter.stage("nominal"):
        opt = Optimizer(plant, problem, options, mean_only_jacobian(st, kind, ctx.engine, problem)).run(U0)
    ctx.log(f"mean-only {st.method} ({', '.join(opt.linearizations)} Jacobians): J = {opt.cost:.6g} after "
            f"{opt.iterations} iterations ({opt.experiments} experiments, {opt.seconds:.2f} s; stopped: {opt.stop})")
    refined = None
    if st.belief:
        # the belief refinement moves U by ~1e-4 relative and its Jacobian is the nominal's to first
        # order: a chord on one ROM, the mean-only optimizer's last one when it used the ROM
        # Jacobian (identified at its optimum or within relinearize_rtol of it), else one
        # identified at the mean-only optimum
        options = OptimizerOptions(objective="belief", max_iter=st.belief_iter, tol=st.tol, members=st.ensemble,
                                   enkf_seed=st.enkf_seed, max_trials=BELIEF_TRIALS, bounds=bounds,
                                   memory_budget=st.memory_budget, show_progress=ctx.show_progress)
        chord = RomJacobian(st.rom(ctx.engine, problem), chord=True, start=opt.identification)
        with ctx.meter.stage("belief"):
            refined = Optimizer(plant, problem, options, chord).run(opt.U)
        ctx.log(f"belief-space gn: J_b = {refined.history[0]:.8g} -> {refined.cost:.8g} "
                f"({refined.iterations} iterations, {refined.seconds:.2f} s; stopped: {refined.stop})")
    ctx.took("optimize_s", t0)
    last = refined if refined is not None else opt
    belief = last.belief if last.belief is not None else _belief_statistics(plant, last.U, problem, st, ctx)
    return NominalResult(last.U, opt, refined, belief, kind)


def _belief_statistics(plant: Plant, U: np.ndarray, problem: Problem, st: DesignSettings,
                       ctx: StageContext) -> EnKFResult | None:
    """The EnKF belief along U (`st.ensemble` members) for the design file's statistics; None for
    a plant whose states are opaque (the EnKF adds and scales states)."""
    if getattr(plant, "state_is_opaque", False):
        return None
    with ctx.meter.stage("belief"):
        return run_belief(plant, U, problem, st.ensemble, st.enkf_seed, st.memory_budget)


def identification_stage(plant: Plant, st: DesignSettings, nominal: NominalResult,
                         ctx: StageContext, problem: Problem | None = None) -> IdentificationStage:
    """Stage 2: TV-ERA around the nominal; the optimizer's last identification when it was made
    at this very input with the design's own settings (not a coarse proposal model)."""
    with ctx.meter.stage("identification"):
        return _identification_stage(plant, st, nominal, ctx, problem)


def _identification_stage(plant: Plant, st: DesignSettings, nominal: NominalResult,
                          ctx: StageContext, problem: Problem | None = None) -> IdentificationStage:
    U, t0 = nominal.U, time.perf_counter()
    ident = nominal.last.identification
    # plan 0.9: the model made at the mean-only optimum also serves the belief-refined nominal,
    # which moved by ~1e-4 relative (within relinearize_rtol): the Markov parameters move by that
    # much, far below the forward impulses' own O(delta) error
    rtol = SAME_INPUT_RTOL if st.experiment_plan == "0.8" else st.relinearize_rtol
    full = ident is not None and ident.made_with(st.impulse_scheme, st.field_tol, p=st.p, q=st.q)
    # the stride check first (no plant steps): a model the strided data do not resolve is neither
    # reused nor spot-checked, and its stride is not tried again at the final input
    resolved = resolved_share(ident) if full and ident.stride > 1 else None
    unresolved = resolved is not None and resolved < RESOLVED_MIN
    reused = full and not unresolved and same_input(ident.U, U, rtol)
    spot = None
    if not reused and not unresolved and st.experiment_plan != "0.8" and full:
        with ctx.meter.stage("validation"):
            spot = spot_error(plant, ident, U)
        reused = spot <= SPOT_TOL
        ctx.log(f"TV-ERA: the optimizer's last model, checked at the final input by impulses at "
                f"{SPOT_BLOCKS} x {SPOT_STARTS} start steps: Markov relative error {spot:.2e} "
                f"({'<=' if reused else '>'} {SPOT_TOL:g}: {'reused' if reused else 'identified again'})")
    if not reused and not unresolved:
        ident = st.rom(ctx.engine, problem).identify(plant, U, ctx.show_progress)
        resolved = resolved_share(ident) if ident.stride > 1 else None
        unresolved = resolved is not None and resolved < RESOLVED_MIN
    if unresolved:
        # the filter's model keeps states below the interpolation's error: impulse every start step
        ctx.log(f"TV-ERA: the strided impulses (impulse_stride {st.impulse_stride}) resolve {resolved:.0%} of the "
                f"kept ROM states (< {RESOLVED_MIN:.0%}: the interpolation's error sets the rest, by Weyl's "
                f"bound); identifying again with impulses at every start step")
        ident = replace(st.rom(ctx.engine, problem), stride=1).identify(plant, U, ctx.show_progress)
    elif reused and not np.array_equal(ident.U, U):
        ident = replace(ident, X_ext=nominal_states(plant, extend_nominal(U, st.p + st.q)),
                        U=U.copy())     # the same linear model; the nominal of the final input
    ctx.took("identify_s", t0)
    err = markov_relative_error(ident.model, ident.data.Y, ident.data.noise)
    if ident.data.noise is not None:
        ctx.log(describe_sketch(ident))
    ctx.log(f"TV-ERA: n_r = {int(ident.model.dims.max())} (cap {st.n_r}), {ident.data.experiments} impulse "
            f"experiments{_stride_note(ident.stride)}{_reuse_note(ident.U, U) if reused else ''}, Markov relative "
            f"error {err:.2e}")
    return IdentificationStage(ident, reused, err, spot if reused else None, resolved)


def describe_sketch(ident: Identification) -> str:
    """One log line: the noise channels identified on random combinations (`noise_sketch`)."""
    sk, m, q = ident.data.noise, ident.model, ident.q
    n_u, n_y = m.B.shape[2], m.C.shape[1]
    err = trace_std_error(sk.sketched(m.Bw), sk)
    return (f"TV-ERA: {sk.n_w} process-noise channels (> {SKETCH_FROM}) identified on {sk.rank} random "
            f"combinations per start step (B_w W B_w' estimated without bias); Hankel matrices "
            f"{ident.p * n_y} x {q * (n_u + sk.rank)} instead of {ident.p * n_y} x {q * (n_u + sk.n_w)}; "
            f"the ROM noise covariance's trace has a relative standard error of {err:.1%} per step "
            f"(median), averaged over the steps by the filter")


def _stride_note(stride: int) -> str:
    """The log's note on strided impulses (`impulse_stride`): accuracy traded for run-steps."""
    if stride == 1:
        return ""
    return (f" at one start step in {stride} (impulse_stride; the Markov parameters between interpolated "
            f"linearly: about 1/{stride} of the run-steps, the interpolation's error is in the Markov error below)")


def _reuse_note(U_ident: np.ndarray, U: np.ndarray) -> str:
    """The log's note on a reused identification (how far the nominal moved since it was made)."""
    moved = float(np.max(np.abs(U - U_ident))) / max(float(np.max(np.abs(U_ident))), 1e-12)
    return (" (the optimizer’s last identification, reused" +
            (f"; made where the nominal input was {moved:.1e} relative away" if moved > 0 else "") + ")")


def gains_stage(identified: IdentificationStage, problem: Problem, st: DesignSettings,
                ctx: StageContext) -> GainsResult:
    """Stage 3: the disturbance states the settings ask for (`DesignSettings.disturbance_for`),
    then the TV-LQR and Kalman gains on the identified ROM with them (`design_lqg`)."""
    t0 = time.perf_counter()
    rom = identified.identification.model
    dist = st.disturbance_for(rom, problem)
    ctx.log(describe_disturbance(dist))
    gains = design_lqg(rom, problem, dist)
    ctx.took("gains_s", t0)
    return gains


def describe_disturbance(dist) -> str:
    """One log line: the disturbance model, its directions and covariance, and how they were chosen
    (a combination: each part's directions, and whether the stacked step gain has full rank)."""
    if dist is None:
        return "disturbance states: none (no offset-free tracking)"
    d = dist.directions
    if len(dist.part_dims) > 1:
        where = "; ".join(f"{p}: {_where(p, r)}" for p, r in zip(dist.kind.split("+"), d.get("parts", [{}, {}])))
        where += f"; detectable together {'yes' if d.get('detectable') else 'NO'}"
    else:
        where = _where(dist.kind, d)
    std0 = ", ".join(f"{v:.3g}" for v in dist.std0)
    walk = ", ".join(f"{v:.3g}" for v in dist.walk_std) if np.any(dist.walk_std) else "0 (constant)"
    return (f"disturbance states: {dist.kind}, n_d = {dist.n_d}; {where}; prior std {std0} "
            f"({dist.std0_rule}); random-walk std {walk}")


def _where(kind: str, d: dict) -> str:
    """How a single kind's directions were chosen, for `describe_disturbance`."""
    if kind not in ("input", "noise"):
        return d.get("rule", "F = I (one bias per sensor)")
    sv = ", ".join(f"{v:.3g}" for v in d.get("singular_values", []))
    return (f"input directions E: right singular vectors of the band-window step gain (singular values {sv}); "
            f"kept {d.get('kept')} of {d.get('asked')}, detectable {'yes' if d.get('detectable') else 'NO'}")


def field_map_stage(gains: GainsResult, st: DesignSettings, ctx: StageContext) -> LQG:
    """Stage 4: the design's LQG, its field map compressed at `st.field_map_tol` against the
    spread the gains give the ROM state (`sep_control.design.field_map.compressed_lqg`)."""
    t0 = time.perf_counter()
    lqg = compressed_lqg(gains, st.field_map_tol)
    ctx.took("gains_s", t0)
    return lqg


def design_pass(plant: Plant, problem: Problem, st: DesignSettings, ctx: StageContext,
                U0: np.ndarray | None = None, bounds: tuple[np.ndarray, np.ndarray] | None = None) -> DesignPass:
    """The four stages in order: nominal, identification, gains, field map."""
    nominal = nominal_stage(plant, problem, st, ctx, U0, bounds)
    identified = identification_stage(plant, st, nominal, ctx, problem)
    gains = gains_stage(identified, problem, st, ctx)
    return DesignPass(nominal, identified, field_map_stage(gains, st, ctx))


def fixed_nominal_pass(plant: Plant, problem: Problem, st: DesignSettings, ctx: StageContext, U: np.ndarray,
                       why: str) -> DesignPass:
    """The stages around a given nominal U, not optimized (`why` says where it came from): one
    rollout for its cost, the belief statistics (EnKF, `st.ensemble` members), the identification
    at U, the gains and the field map."""
    t0 = time.perf_counter()
    with ctx.meter.stage("nominal"):
        J = float(objective_of(plant, problem).cost(fields(plant, nominal_states(plant, U)), U))
    opt = OptimizationResult(np.array(U, dtype=float), J, [J], method=st.method, stop=why)
    belief = _belief_statistics(plant, opt.U, problem, st, ctx)
    ctx.took("optimize_s", t0)
    nominal = NominalResult(opt.U, opt, None, belief, "given")
    identified = identification_stage(plant, st, nominal, ctx, problem)
    gains = gains_stage(identified, problem, st, ctx)
    return DesignPass(nominal, identified, field_map_stage(gains, st, ctx))
