"""Open-loop nominal trajectory optimization from black-box experiments only.

Minimizes the nominal cost J(U) or the belief-space cost J_b(U) (`sep_control.design.belief`),
both sums of squares |r(U)|^2 whose Gauss-Newton models come from a linearization strategy
(`sep_control.design.jacobians`: impulse sensitivities, an identified ROM, or the switch
between them).

Methods:
* ``gn`` (default): Levenberg-Marquardt on (J'J + lambda diag(J'J)) dU = -J'r with
  accept/reject on the true cost; converges in a few iterations.
* ``gd``: the paper's gradient descent U <- U - alpha grad J (grad J = 2 J'r) with
  backtracking; slow, kept for comparison.

The belief-space Gauss-Newton step uses the nominal-trajectory sensitivities (d mu / dU =
d xbar / dU to first order, since the filter follows observations that move with the nominal),
and each step is accepted on the true J_b.

    result = Optimizer(plant, problem, OptimizerOptions(), SensitivityJacobian()).run()
Pure numpy: no ROS import.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from sep_estimator.enkf import EnKFResult
from sep_plant.problem import Problem
from sep_plant.protocol import Plant, fields, nominal_states, rate_clip_sequence

from sep_control.compute.progress import progress
from sep_control.design.belief import belief_cost, objective_of, run_belief
from sep_control.design.jacobians import Jacobian, Linearized
from sep_control.design.linearization import Linearization, Point
from sep_control.design.tvera import Identification
from sep_control.evaluation.metrics import in_band

METHODS = ("gn", "gd")
#: `refresh_on_stall`: an accepted step that lowers the objective by less than this share of what
#: a kept model predicted makes the strategy offer a model made at the new input (trust-region
#: ratio rho < 1/2: the kept model no longer describes the plant there)
POOR_MODEL = 0.5
OBJECTIVES = ("nominal", "belief")


@dataclass(frozen=True)
class OptimizerOptions:
    """Options of one `Optimizer` run (the linearization's own are its strategy's)."""

    method: str = "gn"              # "gn" (Levenberg-Marquardt) or "gd" (gradient descent)
    objective: str = "nominal"      # "nominal" (J) or "belief" (J_b)
    max_iter: int | None = None     # iterations (None: 10 for gn, 60 for gd)
    tol: float = 1e-7               # stop when an accepted trial lowers the objective by less (relative)
    step_size: float = 1e-3         # gradient-descent step alpha
    max_trials: int = 12            # damped trials per iteration (lambda x 4, alpha / 2 after each)
    members: int = 200              # belief objective: EnKF members (even)
    enkf_seed: int = 0              # belief objective: seed of the EnKF's random numbers
    memory_budget: int | None = None  # belief objective: bytes for a batch of member steps
    # input box: (lo, hi), each broadcastable to (N, n_u); None: the problem's u_min/u_max
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    show_progress: bool = True
    # a step lowering the objective by less than tol on a model made elsewhere (a kept one): make
    # one at this input (`Jacobian.relinearize`) and go on, instead of stopping there (a kept
    # model's fixed point is not the optimum: J_kept' r = 0, not J' r = 0)
    refresh_on_stall: bool = False
    # settle stop (0: none): an accepted step that lowers the objective by less than this (relative)
    # is taken and ends the run, when the strategy's model has its full settings
    # (`KeptRomJacobian.full_model`; any model for a strategy without that test) and the nominal's
    # field is within every hold's band (a nominal out of its band has not settled on what matters:
    # a 101-node reaction-diffusion plant settled at 0.056 off for a band of 0.05, no run in band)
    settle: float = 0.0

    def check(self) -> None:
        """Raise ValueError naming a bad method or objective."""
        if self.method not in METHODS:
            raise ValueError(f"method must be 'gn' or 'gd', got {self.method!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be 'nominal' or 'belief', got {self.objective!r}")

    @property
    def iterations(self) -> int:
        """`max_iter`, resolved."""
        return self.max_iter if self.max_iter is not None else (10 if self.method == "gn" else 60)


@dataclass
class OptimizationResult:
    U: np.ndarray                          # (N, n_u) optimized nominal input
    cost: float                            # final objective (nominal or belief cost)
    history: list[float] = field(default_factory=list)   # objective after each iteration
    iterations: int = 0
    experiments: int = 0                   # black-box runs used for linearizations
    seconds: float = 0.0
    method: str = "gn"
    objective: str = "nominal"
    identification: Identification | None = None  # ROM path: the last TV-ERA model (at or near the final U)
    belief: EnKFResult | None = None       # belief objective: the belief at the final U
    linearizations: list[str] = field(default_factory=list)  # "sensitivity", "rom", "rom (proposal)", "rom (kept)"
    stop: str = ""                         # why it stopped


class Attempt(NamedTuple):
    """The outcome of up to max_trials damped steps from one iterate."""

    outcome: str                # "accepted", "converged" (the model predicts < tol) or "rejected"
    lam: float                  # the damping after the trials
    alpha: float                # the gradient step after the trials
    point: Point | None = None  # the accepted trial


def active_bounds(U: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Inputs at a bound whose descent direction leaves the box (projected-gradient active set):
    u <= lo with dJ/du > 0, or u >= hi with dJ/du < 0. Those are held in the next step, so that
    the step of the free inputs is not spent against a bound and then clipped away."""
    span = np.maximum(np.abs(hi - lo), 1.0)
    span = np.where(np.isfinite(span), span, 1.0)
    eps = 1e-9 * span
    return ((U <= lo + eps) & (grad > 0)) | ((U >= hi - eps) & (grad < 0))


class Optimizer:
    """Projected Levenberg-Marquardt (or gradient descent) on the nominal or belief cost.

    Every step is accepted on the true objective, whichever model proposed it. Input limits:
    the problem's u_min/u_max or `options.bounds`; inputs at an active bound (`active_bounds`)
    are held, the others step, and the trial point is projected onto the box before the true
    objective accepts it. Rate limits (du_max): the projected trial is then clipped forward in
    time to |u_k - u_{k-1}| <= du_max (a feasible point, not the exact projection).

    A run stops after `max_iter` iterations, when an accepted trial lowers the objective by less
    than `tol` relative (such a step is not taken: it keeps the last linearization at the final
    input), with a settle stop (`settle` > 0) after an accepted step that lowered it by less than
    `settle` on a full model with the nominal's field within its bands (that step is taken; the
    last linearization was made before it),
    when no trial of `max_trials` lowers it, or, for the belief objective (gn), when the
    Gauss-Newton model predicts a decrease below `tol` relative for the next step (that trial,
    an EnKF run, is not evaluated); the result's `stop` says which. With a ROM strategy the
    result carries the last identification, made at the final input or within the strategy's
    `relinearize_rtol` of it (the ROM path linearizes after the last step too: a later stage
    reuses it).
    """

    def __init__(self, plant: Plant, problem: Problem, options: OptimizerOptions, strategy: Jacobian):
        options.check()
        self.plant, self.problem, self.options, self.strategy = plant, problem, options, strategy
        self.obj = objective_of(plant, problem)
        # belief objective: a trial the Gauss-Newton model predicts to lower J_b by less than tol is
        # not evaluated (an EnKF run). The nominal objective evaluates every trial (one rollout): an
        # inexact model (a ROM Jacobian, Burgers: Markov error 2.5e-4) can predict less than tol
        # where the true cost still falls by more (stopping there left Burgers' optimum 2e-5 higher)
        self.predict_stop = options.method == "gn" and options.objective == "belief"

    def run(self, U0: np.ndarray | None = None) -> OptimizationResult:
        """Minimize from U0 (stopping rules: the class docstring).

        Parameters
        ----------
        U0 : ndarray, shape (N, n_u), optional
            Start input (None: the problem's u_init held over the horizon); clipped into the box.

        Returns
        -------
        OptimizationResult
            The optimized input and objective, the objective's history, the experiments and
            linearizations used, and why it stopped.
        """
        o, t0 = self.options, time.perf_counter()
        U = self.problem.u_start(int(self.plant.n_u)) if U0 is None else np.array(U0, dtype=float)
        self._box(U.shape)
        at = self._evaluate(self._project(U))
        result = OptimizationResult(at.U, at.J, [at.J], method=o.method, objective=o.objective)
        lin = self._linearize(self.strategy.linearize(self.plant, self.obj, at, self._gram), result)
        lam, alpha, last = 1e-3, o.step_size, o.iterations - 1
        bar = progress(range(o.iterations), desc=f"optimize[{o.method},{o.objective}]", enabled=o.show_progress)
        for it in bar:
            attempt, lin = self._iteration(lin, at, lam, alpha, result)
            lam, alpha = attempt.lam, attempt.alpha
            if attempt.outcome != "accepted":
                result.stop = ("the model predicts a decrease below tol" if attempt.outcome == "converged"
                               else f"no trial of {o.max_trials} lowered the objective")
                break
            new = attempt.point
            rel = (at.J - new.J) / max(at.J, 1e-300)
            if rel < o.tol and o.refresh_on_stall:
                fresh = self.strategy.relinearize(self.plant, self.obj, at, lin, self._gram)
                if fresh is not None:
                    lin = self._linearize(fresh, result)
                    continue
            if rel < o.tol:
                # a decrease below tol is no real improvement (for the belief an ensemble estimate's),
                # and staying at U keeps the linearization made here (an identification the belief
                # refinement and the design reuse) at the final input
                result.stop = "the step lowered the objective by less than tol (not taken)"
                break
            poor = o.refresh_on_stall and self._poor_model(lin, at, new)
            self.strategy.accepted(float(np.max(np.abs(new.U - at.U))) / max(float(np.max(np.abs(at.U))), 1e-12),
                                   rel)
            at, lam, alpha = new, max(lam / 3.0, 1e-9), alpha * 1.2
            result.history.append(at.J)
            result.iterations = it + 1
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(J=f"{at.J:.6g}")
            if rel < o.settle and getattr(self.strategy, "full_model", lambda _: True)(lin) and bool(in_band(at.residual_field, self.obj)):
                result.stop = f"settled: the step lowered the objective by less than {o.settle:g} (taken)"
                break
            if it == last and lin.identification is None:
                result.stop = f"max_iter = {o.iterations}"
                break
            fresh = self.strategy.refresh(self.plant, self.obj, at, lin, self._gram) if poor else None
            lin = self._linearize(fresh or self.strategy.linearize(self.plant, self.obj, at, self._gram), result)
            if it == last:
                result.stop = f"max_iter = {o.iterations}"
        result.identification, result.belief = lin.identification, at.belief
        result.U, result.cost, result.seconds = at.U, at.J, time.perf_counter() - t0
        return result

    # ------------------------------------------------------------ internals
    @staticmethod
    def _poor_model(lin: Linearization, at: Point, new: Point) -> bool:
        """Whether the accepted step from `at` to `new` lowered the objective by less than
        POOR_MODEL times what the model `lin` predicted (a kept model gone stale)."""
        predicted = -lin.predicted_change(new.U - at.U)
        return not predicted > 0 or (at.J - new.J) < POOR_MODEL * predicted

    @property
    def _gram(self) -> bool:
        return self.options.method == "gn"         # gradient descent needs J'r only

    def _box(self, shape: tuple[int, int]) -> None:
        bounds = self.options.bounds
        lo, hi = self.problem.limits(int(self.plant.n_u)) if bounds is None else bounds
        self.lo = np.broadcast_to(np.asarray(lo, dtype=float), shape)
        self.hi = np.broadcast_to(np.asarray(hi, dtype=float), shape)
        self.bounded = bool(np.any(np.isfinite(self.lo)) or np.any(np.isfinite(self.hi)))
        self.du_max = self.problem.channels("du_max", int(self.plant.n_u))

    def _project(self, U: np.ndarray) -> np.ndarray:
        """U clipped into the box, then made rate-feasible forward in time (u_k = clip(u_k,
        u_{k-1} -+ du_max), k = 1..N-1; `sep_plant.protocol.rate_clip_sequence`): every trial
        the true objective accepts is a feasible nominal."""
        return rate_clip_sequence(np.clip(U, self.lo, self.hi), self.du_max)

    def _evaluate(self, U: np.ndarray) -> Point:
        """The objective at U (a rollout, and for the belief objective an EnKF run)."""
        X = nominal_states(self.plant, U)
        if self.options.objective == "nominal":
            F = fields(self.plant, X)
            return Point(U, float(self.obj.cost(F, U)), X, F)
        o = self.options
        b = run_belief(self.plant, U, self.problem, o.members, o.enkf_seed, o.memory_budget, X=X)
        return Point(U, belief_cost(b, U, self.obj), X, b.mean, b)

    @staticmethod
    def _linearize(made: Linearized, result: OptimizationResult) -> Linearization:
        result.experiments += made.experiments
        result.linearizations.append(made.kind)
        return made.lin

    def _iteration(self, lin: Linearization, at: Point, lam: float, alpha: float,
                   result: OptimizationResult) -> tuple[Attempt, Linearization]:
        """The trials of one iteration; when every trial of a kept model fails, the strategy may
        offer one made at this input, and its trials start from the same damping."""
        attempt = self._attempt(lin, at, lam, alpha)
        if attempt.outcome == "rejected":
            fresh = self.strategy.relinearize(self.plant, self.obj, at, lin, self._gram)
            if fresh is not None:
                lin = self._linearize(fresh, result)
                attempt = self._attempt(lin, at, lam, alpha)
        return attempt, lin

    def _attempt(self, lin: Linearization, at: Point, lam: float, alpha: float) -> Attempt:
        """Up to max_trials damped steps from `at`: the first that the true objective accepts,
        "converged" when `predict_stop` and the model predicts a decrease below tol relative
        (that trial is not evaluated), else "rejected"."""
        o = self.options
        grad = lin.gradient()
        frozen = active_bounds(at.U, grad, self.lo, self.hi) if self.bounded else None
        for _ in range(o.max_trials):
            if o.method == "gn":
                dU = lin.step(lam, frozen)
            else:
                dU = -alpha * grad
                if frozen is not None:
                    dU[frozen] = 0.0
            U_try = self._project(at.U + dU)
            if self.predict_stop and 0.0 <= -lin.predicted_change(U_try - at.U) < o.tol * at.J:
                return Attempt("converged", lam, alpha)
            trial = self._evaluate(U_try)
            if np.isfinite(trial.J) and trial.J < at.J:
                return Attempt("accepted", lam, alpha, trial)
            lam, alpha = lam * 4.0, alpha * 0.5
        return Attempt("rejected", lam, alpha)
