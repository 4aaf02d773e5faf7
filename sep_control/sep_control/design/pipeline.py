"""The offline design pipeline: black-box plant and problem in, design out.

1. open-loop nominal: mean-only Gauss-Newton/LM (or gradient descent), then the
   belief-space problem warm-started from it (EnKF belief along nominal observations);
2. TV-ERA reduced-order model from central-difference impulse experiments around the
   nominal (forward differences on request), with the field output map;
3. time-varying LQR (weights on the outputs) and Kalman filter on the ROM.

    design = run_design(plant, problem, DesignSettings())

The plant is checked against the plant protocol first (`sep_plant.conformance`), so a bad
plant fails in a second with a message, not after the experiments. Only the plant's
`initial_state`, `step`, `observe`, `field` and state snapshots are used.
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import platform
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sep_estimator.design_file import Design, Nominal
from sep_estimator.ltv import LTVModel
from sep_plant.conformance import check_plant
from sep_plant.plants import type_name_of
from sep_plant.problem import Problem
from sep_plant.protocol import Plant, PlantInfo, fields, outputs, rollout
from sep_plant.scenario import Scenario

from sep_control import __version__
from sep_control.compute.budget import runs_per_batch
from sep_control.design.gains import FIELD_MAP_TOL, design_lqg, input_spread
from sep_control.evaluation.metrics import nominal_cost
from sep_control.design.optimizer import SAME_INPUT_RTOL, objective_of, optimize, run_belief, same_input
from sep_control.design.tvera import FIELD_TOL, SCHEMES, Identification, extend_nominal, identify, markov_relative_error


#: 'auto' Jacobian: the ROM one from N + 1 > ROM_FROM (p + q) (the measured time crossover)
ROM_FROM = 5

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
PROPOSAL_ROM = {"scheme": "forward", "field_tol": 1e-6}


@dataclass
class DesignSettings:
    """Knobs of the offline design (defaults: docs/reference/cli.md)."""
    method: str = "gn"              # "gn" (Levenberg-Marquardt) or "gd" (paper's gradient descent)
    jacobian: str = "auto"          # "sensitivity" (N n_u experiments), "rom" (TV-ERA model), "auto": the cheaper
    belief: bool = True             # refine the mean-only optimum in belief space
    max_iter: int | None = None     # optimizer iterations (None: 10 for gn, 60 for gd)
    belief_iter: int = 2            # belief-space GN iterations after the mean-only optimum
    fd_eps: float = 1e-4            # sensitivity experiment amplitude
    step_size: float = 1e-3         # gradient-descent step alpha
    ensemble: int = 200             # EnKF members (even: antithetic pairs)
    n_r: int = 20                   # ROM order cap
    p: int = 15                     # Hankel block rows (future outputs)
    q: int = 15                     # Hankel block columns (past inputs)
    sv_tol: float = 1e-10           # relative singular-value cutoff
    impulse: float = 0.01           # impulse amplitude relative to the RMS nominal input
    impulse_scheme: str = "central"  # TV-ERA impulses: "central" (+- pairs) or "forward" (one run each)
    field_map_tol: float = FIELD_MAP_TOL  # field map: drop directions moving the field < this x its spread
    seed: int = 0                   # EnKF random numbers
    tol: float = 1e-7               # stop when an accepted step lowers the cost by less (relative)
    relinearize_rtol: float = 1e-2  # ROM Jacobian: keep the last identification while U moved less (relative)
    coarse_proposals: bool = True   # ROM Jacobian far from the optimum: forward impulses, coarser field basis
    memory_budget: int | None = None  # bytes for a batch of experiments (None: a quarter of the free memory)
    chunks: int = 4                 # impulse experiments in this many chunks of start steps (tasks)
    limit_margin: float = 0.0       # keep this many closed-loop input stds inside u_min/u_max (0: none)
    margin_iterations: int = 2      # nominal + LQG redesigns with the tightened limits

    def check(self) -> None:
        if self.method not in ("gn", "gd"):
            raise ValueError(f"method must be 'gn' or 'gd', got {self.method!r}")
        if self.impulse_scheme not in SCHEMES:
            raise ValueError(f"impulse_scheme must be one of {', '.join(SCHEMES)}, got {self.impulse_scheme!r}")
        if self.jacobian not in ("sensitivity", "rom", "auto"):
            raise ValueError(f"jacobian must be 'sensitivity', 'rom' or 'auto', got {self.jacobian!r}")
        for name in ("n_r", "p", "q", "ensemble", "chunks"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.ensemble % 2 or self.ensemble < 4:
            raise ValueError(f"ensemble must be even and >= 4 (antithetic pairs), got {self.ensemble}")
        if not (np.isfinite(self.limit_margin) and self.limit_margin >= 0):
            raise ValueError(f"limit_margin must be a finite number >= 0, got {self.limit_margin}")
        if not 0.0 < self.relinearize_rtol <= 0.1:
            raise ValueError(f"relinearize_rtol must be in (0, 0.1], got {self.relinearize_rtol}: a model kept "
                             "through the large early steps makes a chord method, which stops short of the optimum")
        if self.margin_iterations < 0:
            raise ValueError(f"margin_iterations must be >= 0, got {self.margin_iterations}")
        if not 0.0 < self.field_map_tol < 1.0:
            raise ValueError(f"field_map_tol must be in (0, 1), got {self.field_map_tol}")
        for name in ("fd_eps", "impulse", "sv_tol", "step_size", "tol", "relinearize_rtol", "field_map_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")

    def resolved_jacobian(self, n_steps: int) -> str:
        """'auto': the Jacobian whose experiments take fewer plant steps per iteration. The
        sensitivity one runs N n_u experiments of N/2 steps on average, N (N+1) n_u / 2
        run-steps (and forms a dense (N n_u)^2 normal matrix from N n_f rows, O(N^3) work); the
        ROM one 2 N n_u experiments of p + q steps, 2 N n_u (p + q) run-steps, and solves the step
        on the ROM in O(N n_r^3). In plant steps the ROM one is cheaper from N + 1 > 4 (p + q);
        its own work (POD updates, Hankel SVDs) moves the measured time crossover to N ~ 145
        (slab at n_x = 100 and 1600, Allen-Cahn at 2500: bench/bench_design.py --crossover),
        hence the ROM one from N + 1 > ROM_FROM (p + q) (N >= 150 with the default p = q = 15).
        Forward impulses (`impulse_scheme`) halve the ROM one's experiments and move the
        crossover lower (measured N ~ 110 at n_x = 1600); the rule stays the central one's."""
        if self.jacobian != "auto":
            return self.jacobian
        return "rom" if n_steps + 1 > ROM_FROM * (self.p + self.q) else "sensitivity"

    def resolved_jacobian_for(self, plant: Plant, n_steps: int) -> str:
        """`resolved_jacobian`, and the ROM one also when the sensitivity experiments (N n_u runs
        in one batch) would not fit the memory budget."""
        jac = self.resolved_jacobian(n_steps)
        if self.jacobian == "auto" and jac == "sensitivity" and \
                n_steps * int(plant.n_u) > runs_per_batch(int(plant.n_x), int(plant.n_field), self.memory_budget):
            return "rom"
        return jac

    @classmethod
    def for_scenario(cls, scenario: Scenario, **overrides: Any) -> "DesignSettings":
        """The defaults, then the scenario's `design:` section, then `overrides` (ValueError naming
        an unknown key)."""
        known = cls.__dataclass_fields__
        unknown = sorted(k for k in scenario.design if k not in known)
        if unknown:
            raise ValueError(f"scenario design section: unknown setting(s) {unknown}; known: {sorted(known)}")
        st = cls(**{**dict(scenario.design), **overrides})
        st.check()
        return st

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> "DesignSettings":
        """The settings recorded in a design file's metadata (unknown keys ignored; files older
        than the chunked experiments ran them as one chunk, older than `relinearize_rtol`
        identified again after every step, older than `field_map_tol` truncated the field map
        at the field basis' tolerance, and older than `coarse_proposals` identified every model
        with the full settings)."""
        recorded = {"chunks": 1, "relinearize_rtol": SAME_INPUT_RTOL, "field_map_tol": FIELD_TOL,
                    "coarse_proposals": False,
                    **meta.get("settings", {})}
        return cls(**{k: v for k, v in recorded.items() if k in cls.__dataclass_fields__})


def scenario_of(plant: Plant, problem: Problem) -> Scenario:
    """The plain-data scenario (type string, complete plant keys, problem) of a plant object."""
    return Scenario(type_name_of(plant), dict(plant.config()), problem.resolved())


def run_design(plant: Plant, problem: Problem, settings: DesignSettings | None = None,
               show_progress: bool = True, log=print, engine=None) -> Design:
    """Run the whole offline design for `plant` and `problem` and return the `Design`.

    `engine` (`sep_control.compute.engine`; in-process by default) runs the impulse experiments; the
    result does not depend on it (the chunk plan is `settings.chunks`).
    With input limits and `settings.limit_margin` = c > 0 the nominal is re-optimized
    `margin_iterations` times inside the limits tightened by c times the designed LQG's
    closed-loop input std (`lqr.input_spread`): lo + c sigma_u,k <= ubar_k <= hi - c sigma_u,k,
    so that the feedback has room to act on both sides (each time the ROM and the gains are
    redesigned around the new nominal)."""
    st = settings or DesignSettings()
    st.check()
    check_plant(plant, problem.channels("u_init", int(plant.n_u)))
    scenario = scenario_of(plant, problem)
    problem = scenario.problem
    info = PlantInfo.of(plant)
    obj = objective_of(plant, problem)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    lo, hi = problem.limits(int(plant.n_u))
    limited = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))

    nom = _nominal(plant, problem, st, show_progress, log, engine, timings)
    ident, lqg = _rom_and_gains(plant, problem, st, nom, show_progress, log, engine, timings)
    margins: list[dict[str, Any]] = []
    experiments = 0       # of the passes before the last (the margin loop's redesigns)
    if limited and st.limit_margin > 0:
        for it in range(st.margin_iterations):
            sigma = input_spread(lqg)
            LO, HI = tightened_limits(lo, hi, sigma, st.limit_margin)
            experiments += nom["opt"].experiments + (nom["last"].experiments if st.belief else 0)
            nom = _nominal(plant, problem, st, show_progress, log, engine, timings, U0=nom["U"], bounds=(LO, HI))
            ident, lqg = _rom_and_gains(plant, problem, st, nom, show_progress, log, engine, timings)
            margins.append({"iteration": it + 1, "sigma_u_max": float(sigma.max()),
                            "sigma_u_mean": float(sigma.mean()), "objective": nom["cost"],
                            "objective_kind": "belief" if st.belief else "nominal"})
            log(f"limit margin {st.limit_margin:g} sigma_u (iteration {it + 1}): input std up to "
                f"{sigma.max():.3g}, {'belief' if st.belief else 'nominal'} J = {nom['cost']:.6g}")
    timings["total_s"] = time.perf_counter() - t_all

    U, opt, last = nom["U"], nom["opt"], nom["last"]
    N = problem.n_steps
    X_nom = ident.X_ext[: N + 1]
    F_nom = fields(plant, X_nom)
    k0, k1 = obj.window
    markov_err = nom["markov_rel_error"]
    meta: dict[str, Any] = {
        "settings": asdict(st),
        "provenance": {"tool": "sep design", "version": __version__, "python": platform.python_version(),
                       "numpy": np.__version__, "created_unix": time.time(), "seed": st.seed},
        "timings": timings,
        "optimizer": {"method": st.method, "jacobian": nom["jacobian"], "mean_only_cost": nom["mean_only_cost"],
                      "mean_only_history": opt.history, "belief_history": nom["belief_history"],
                      "iterations": opt.iterations, "experiments": opt.experiments,
                      "linearizations": opt.linearizations, "stop": opt.stop,
                      "belief_experiments": last.experiments if st.belief else 0,
                      "identification_reused": nom["reused"], "nominal_cost": float(nominal_cost(F_nom, U, obj)),
                      "limit_margins": margins, "experiments_before_last_margin_pass": experiments},
        "validation": {"markov_rel_error": markov_err, "impulse_amplitude": ident.delta,
                       "max_dev_in_band_window": float(np.max(np.abs(F_nom[k0:k1 + 1] - obj.target)))},
    }
    belief = nom["belief"]
    nominal = Nominal(U, outputs(plant, X_nom), F_nom, belief.mean, belief.std)
    return Design(scenario, info, obj, np.asarray(plant.field_coordinates(), dtype=float), nominal, lqg,
                  ident.hankel_sv, meta)


def tightened_limits(lo: np.ndarray, hi: np.ndarray, sigma: np.ndarray, c: float) -> tuple[np.ndarray, np.ndarray]:
    """(N, n_u) bounds lo + c sigma, hi - c sigma; where they would cross, both at the middle."""
    LO, HI = lo + c * sigma, hi - c * sigma
    with np.errstate(invalid="ignore"):      # channels without limits: inf - inf, never crossing
        mid = 0.5 * (np.where(np.isfinite(lo), lo, HI) + np.where(np.isfinite(hi), hi, LO))
        cross = LO > HI
    return np.where(cross, mid, LO), np.where(cross, mid, HI)


def _nominal(plant: Plant, problem: Problem, st: DesignSettings, show_progress: bool, log, engine,
             timings: dict, U0: np.ndarray | None = None, bounds=None) -> dict[str, Any]:
    """Stage 1: the open-loop nominal (mean-only optimum, then the belief-space refinement)."""
    t0 = time.perf_counter()
    rom = {"p": st.p, "q": st.q, "n_r": st.n_r, "sv_tol": st.sv_tol, "impulse": st.impulse,
           "memory_budget": st.memory_budget, "scheme": st.impulse_scheme, "chunks": st.chunks, "engine": engine}
    jacobian = st.resolved_jacobian_for(plant, problem.n_steps)
    opt = optimize(plant, problem, U0=U0, method=st.method, objective="nominal", max_iter=st.max_iter, tol=st.tol,
                   eps=st.fd_eps, step_size=st.step_size, show_progress=show_progress,
                   jacobian=jacobian, rom=rom, bounds=bounds, relinearize_rtol=st.relinearize_rtol,
                   rom_near_optimum=st.jacobian == "auto",
                   rom_proposal=PROPOSAL_ROM if st.coarse_proposals else None)
    log(f"mean-only {st.method} ({', '.join(opt.linearizations)} Jacobians): J = {opt.cost:.6g} after "
        f"{opt.iterations} iterations ({opt.experiments} experiments, {opt.seconds:.2f} s; stopped: {opt.stop})")
    U, belief_hist, last = opt.U, [], opt
    if st.belief:
        # the belief refinement moves U by ~1e-4 relative and its Jacobian is the nominal's to first
        # order: a chord on one ROM, the mean-only optimizer's last one when it used the ROM
        # Jacobian (identified at its optimum or within relinearize_rtol of it), else one
        # identified at the mean-only optimum
        bopt = optimize(plant, problem, U0=U, method="gn", objective="belief", max_iter=st.belief_iter,
                        tol=st.tol, eps=st.fd_eps, members=st.ensemble, seed=st.seed, show_progress=show_progress,
                        jacobian="rom", rom=rom, reuse=opt, chord=True, max_trials=BELIEF_TRIALS, bounds=bounds)
        log(f"belief-space gn: J_b = {bopt.history[0]:.8g} -> {bopt.cost:.8g} "
            f"({bopt.iterations} iterations, {bopt.seconds:.2f} s; stopped: {bopt.stop})")
        U, belief_hist, last = bopt.U, bopt.history, bopt
    timings["optimize_s"] = timings.get("optimize_s", 0.0) + time.perf_counter() - t0
    belief = last.belief if last.belief is not None else run_belief(plant, U, problem, st.ensemble, st.seed,
                                                                    st.memory_budget)
    return {"U": U, "opt": opt, "last": last, "belief": belief, "belief_history": belief_hist,
            "mean_only_cost": opt.cost, "cost": last.cost, "jacobian": jacobian, "reused": False}


def _rom_and_gains(plant: Plant, problem: Problem, st: DesignSettings, nom: dict, show_progress: bool, log,
                   engine, timings: dict):
    """Stages 2 and 3: TV-ERA around the nominal (the optimizer's last identification when it is
    at this input already) and the LQG on the ROM."""
    U, last = nom["U"], nom["last"]
    t0 = time.perf_counter()
    # the optimizer's last identification is the design's ROM only when made at this very input
    # with the design's own settings (not a coarse proposal model)
    reused = last.identification is not None and same_input(last.identification.U, U) \
        and last.identification.made_with(st.impulse_scheme, p=st.p, q=st.q)
    ident = last.identification if reused else identify_rom(plant, U, st, show_progress, engine)
    if reused and not np.array_equal(ident.U, U):
        ident = replace(ident, X_ext=rollout(plant, plant.initial_state(1), extend_nominal(U, st.p + st.q))[0],
                        U=U.copy())     # the same linear model; the nominal of the final input
    nom["reused"] = reused
    timings["identify_s"] = timings.get("identify_s", 0.0) + time.perf_counter() - t0
    nom["markov_rel_error"] = markov_relative_error(ident.model, ident.data.Y)
    log(f"TV-ERA: n_r = {int(ident.model.dims.max())} (cap {st.n_r}), {ident.data.experiments} impulse "
        f"experiments{' (the optimizer’s last identification, reused)' if reused else ''}, Markov relative "
        f"error {nom['markov_rel_error']:.2e}")
    t0 = time.perf_counter()
    lqg = design_lqg(ident.model, problem, map_tol=st.field_map_tol)
    timings["gains_s"] = timings.get("gains_s", 0.0) + time.perf_counter() - t0
    return ident, lqg


def identify_rom(plant: Plant, U: np.ndarray, st: DesignSettings, show_progress: bool = False,
                 engine=None) -> Identification:
    """`tvera.identify` with the design's settings."""
    return identify(plant, U, st.p, st.q, st.n_r, st.sv_tol, st.impulse, show_progress,
                    memory_budget=st.memory_budget, scheme=st.impulse_scheme, chunks=st.chunks, engine=engine)


def with_rom(design: Design, model: LTVModel, hankel_sv: np.ndarray | None = None) -> Design:
    """`design` with its ROM replaced by `model` and the LQG gains redesigned (same nominal)."""
    return replace(design, lqg=design_lqg(model, design.problem),
                   hankel_sv=design.hankel_sv if hankel_sv is None else hankel_sv)
