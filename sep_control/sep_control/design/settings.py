"""The knobs of the offline design (`DesignSettings`; defaults and flags: docs/reference/cli.md).

Pure Python/numpy: no ROS import.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from sep_estimator.disturbance import ACTING, DisturbanceError, parts, split_dims
from sep_estimator.disturbance import KINDS as DISTURBANCE_KINDS
from sep_estimator.disturbance import WALK_STD, Disturbance, choose
from sep_estimator.ltv import LTVModel
from sep_plant.problem import Problem
from sep_plant.protocol import Plant
from sep_plant.scenario import Scenario

from sep_control.compute.budget import runs_per_batch
from sep_control.design.field_map import FIELD_MAP_TOL
from sep_control.design.gains import lqr_gains
from sep_control.design.linearization import SAME_INPUT_RTOL
from sep_control.design.tvera import FIELD_TOL, SCHEMES, RomSettings

#: 'auto' Jacobian: the ROM one from N + 1 > ROM_FROM (p + q) (the measured time crossover)
ROM_FROM = 5

#: plan 0.9's field basis tolerance (`field_tol`): the optimizer's coarse models already used it
#: (`sep_control.design.stages.PROPOSAL_ROM`), and the design's field map keeps only directions
#: above 1e-5 of its spread (`field_map_tol`). Against 1e-8 (0.8's) on the six shipped scenarios
#: (design, then 300 Monte Carlo runs, docs/benchmarks.md): the same run-steps, Monte Carlo cost,
#: in band and coverage to the digits printed, nominal costs to 5e-8 (plate_anneal's optimizer
#: stopped 2.4e-4 higher), and a basis of about 0.6 the rank, whose projections are the design's
#: main work outside the plant step at large n_f (4 n_f r flops per snapshot)
PLAN_FIELD_TOL = 1e-6

#: the experiment plans (`experiment_plan`) and the settings each gives the keys left at None:
#: "0.8" is sep 0.8.0's plan (its designs bit for bit); "0.9" spends 0.13-0.27x its run-steps
#: (docs/benchmarks.md): forward impulses (one run per impulse) at every second start step (the
#: Markov parameters between them interpolated), no belief refinement (it moved J_b by 1e-6
#: relative) and 50 members for the belief statistics, and in the mean-only optimizer kept models
#: of the inputs only and a settle stop (`sep_control.design.jacobians.KeptRomJacobian`,
#: `sep_control.design.stages`), under input or rate limits the clip correction
#: (`sep_control.design.saturation`), and the field basis' Gram method (`sep_control.design.basis`;
#: set in `DesignSettings.rom`) to PLAN_FIELD_TOL
PLANS: dict[str, dict[str, Any]] = {
    "0.8": {"impulse_scheme": "central", "ensemble": 200, "belief_iter": 2, "impulse_stride": 1,
            "clip_correction": False, "field_tol": FIELD_TOL},
    "0.9": {"impulse_scheme": "forward", "ensemble": 50, "belief_iter": 0, "impulse_stride": 2,
            "clip_correction": True, "field_tol": PLAN_FIELD_TOL},
}
DEFAULT_PLAN = "0.9"

#: keys of older design files and scenario `design:` sections, and what they are called now
RENAMED = {"seed": "enkf_seed"}


@dataclass
class DesignSettings:
    """Knobs of the offline design (defaults: docs/reference/cli.md).

    Parameters
    ----------
    method : {"gn", "gd"}
        Optimizer: Levenberg-Marquardt, or the paper's gradient descent.
    jacobian : {"auto", "sensitivity", "rom"}
        Gauss-Newton Jacobian: N n_u sensitivity experiments, a TV-ERA model, or the cheaper
        (`resolved_jacobian_for`; below the crossover sensitivities until the optimum's
        neighbourhood, then one identification there).
    belief : bool
        Refine the mean-only optimum in belief space.
    max_iter : int, optional
        Optimizer iterations (None: 10 for gn, 60 for gd).
    belief_iter : int, optional
        Belief-space Gauss-Newton iterations after the mean-only optimum (None: the plan's).
    fd_eps : float
        Sensitivity experiment amplitude.
    step_size : float
        Gradient-descent step alpha.
    ensemble : int, optional
        EnKF members (even: antithetic pairs; None: the plan's).
    n_r, p, q : int
        ROM order cap, Hankel block rows (future outputs) and columns (past inputs).
    sv_tol : float
        Relative Hankel singular-value cutoff.
    impulse : float
        Impulse amplitude relative to the RMS nominal input.
    impulse_scheme : {"central", "forward"}, optional
        TV-ERA impulses: +- pairs, or one run each against an unperturbed copy (None: the plan's).
    experiment_plan : {"0.8", "0.9"}
        Which experiments the design runs (`PLANS`): "0.9" (default) spends 0.094-0.38x sep 0.8.0's
        plant run-steps (docs/benchmarks.md); "0.8" reproduces sep 0.8.0's designs bit for bit.
    field_tol : float, optional
        Field basis of the identifications: drop directions of the field responses below this
        times the largest response (None: the plan's, 1e-8 for 0.8, 1e-6 for 0.9).
    field_map_tol : float
        Field map: drop directions moving the field by less than this times its spread.
    enkf_seed : int
        Seed of the EnKF's random numbers (older files and scenarios: `seed`).
    tol : float
        Stop when an accepted step lowers the cost by less than this (relative).
    relinearize_rtol : float
        ROM Jacobian: keep the last identification while U moved less than this (relative).
    coarse_proposals : bool
        ROM Jacobian far from the optimum: forward impulses and a coarser field basis.
    memory_budget : int, optional
        Bytes for a batch of experiments (None: a quarter of the free memory).
    chunks : int
        Impulse experiments in this many chunks of start steps (tasks).
    limit_margin : float
        Keep this many closed-loop input stds inside u_min/u_max (0: none).
    margin_iterations : int
        Nominal + LQG redesigns with the tightened limits.
    clip_correction : bool, optional
        With input or rate limits: move the nominal to where the ROM predicts the lowest expected
        closed-loop cost with the limits clipping the feedback (`sep_control.design.saturation`),
        then identify and design again there; kept when the ROM predicts it cheaper (None: the
        plan's, off for 0.8, on for 0.9).
    disturbance : {"input", "output", "noise", "none", "input+noise", "noise+output", "input+output"}
        Disturbance states of the ROM filter for offset-free tracking (`sep_estimator.disturbance`):
        input biases along the detectable input directions, forcings along the noise channels'
        directions, one bias per sensor, a combination of two (stacked), or none.
    disturbance_std : float or list of float, optional
        Prior std sigma_0 of the disturbances, for all or per direction (None: the rule
        c band / sqrt(S_i S_cl,i), c = `sep_estimator.disturbance.STD0_BANDS`).
    disturbance_dims : int or [int, int], optional
        n_d, at most n_y (None: min(n_y, n_u) for input, n_y for output); a combination: n_d per
        part, n_1 + n_2 <= n_y (None: ceil(n_y / 2) for the first, the rest for the second).
    disturbance_walk_std : float or list of float
        Random-walk std of the disturbances per step (0: constant biases).
    """

    method: str = "gn"
    jacobian: str = "auto"
    belief: bool = True
    max_iter: int | None = None
    belief_iter: int | None = None
    fd_eps: float = 1e-4
    step_size: float = 1e-3
    ensemble: int | None = None
    n_r: int = 20
    p: int = 15
    q: int = 15
    sv_tol: float = 1e-10
    impulse: float = 0.01
    impulse_scheme: str | None = None
    impulse_stride: int | None = None
    experiment_plan: str = DEFAULT_PLAN
    field_tol: float | None = None
    field_map_tol: float = FIELD_MAP_TOL
    enkf_seed: int = 0
    tol: float = 1e-7
    relinearize_rtol: float = 1e-2
    coarse_proposals: bool = True
    memory_budget: int | None = None
    chunks: int = 4
    limit_margin: float = 0.0
    margin_iterations: int = 2
    clip_correction: bool | None = None
    disturbance: str = "input"
    disturbance_std: float | list[float] | None = None
    disturbance_dims: int | list[int] | None = None
    disturbance_walk_std: float | list[float] = WALK_STD

    def __post_init__(self) -> None:
        """The keys left at None take the experiment plan's values (`PLANS`)."""
        for key, value in PLANS.get(self.experiment_plan, {}).items():
            if getattr(self, key) is None:
                setattr(self, key, value)

    def check(self) -> None:
        """Raise ValueError naming the first setting out of range."""
        if self.experiment_plan not in PLANS:
            raise ValueError(f"experiment_plan must be one of {', '.join(PLANS)}, got {self.experiment_plan!r}")
        self = self.resolved()
        for name in ("field_tol", "field_map_tol", "fd_eps", "impulse", "sv_tol", "step_size", "tol",
                     "limit_margin", "relinearize_rtol"):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.number)):
                raise ValueError(f"{name} must be a number, got {v!r}")
        if self.method not in ("gn", "gd"):
            raise ValueError(f"method must be 'gn' or 'gd', got {self.method!r}")
        if self.impulse_scheme not in SCHEMES:
            raise ValueError(f"impulse_scheme must be one of {', '.join(SCHEMES)}, got {self.impulse_scheme!r}")
        if self.jacobian not in ("sensitivity", "rom", "auto"):
            raise ValueError(f"jacobian must be 'sensitivity', 'rom' or 'auto', got {self.jacobian!r}")
        if isinstance(self.impulse_stride, bool) or not isinstance(self.impulse_stride, (int, np.integer)):
            raise ValueError(f"impulse_stride must be an integer >= 1, got {self.impulse_stride!r}")
        for name in ("n_r", "p", "q", "ensemble", "chunks", "impulse_stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.ensemble % 2 or self.ensemble < 4:
            raise ValueError(f"ensemble must be even and >= 4 (antithetic pairs), got {self.ensemble}")
        if not (np.isfinite(self.limit_margin) and self.limit_margin >= 0):
            raise ValueError(f"limit_margin must be a finite number >= 0, got {self.limit_margin}")
        if not 0.0 < self.relinearize_rtol <= 0.1:
            raise ValueError(f"relinearize_rtol must be in (0, 0.1], got {self.relinearize_rtol}: a model kept "
                             "through the large early steps makes a chord method, which stops short of the optimum")
        if not isinstance(self.clip_correction, (bool, np.bool_)):
            raise ValueError(f"clip_correction must be true or false, got {self.clip_correction!r}")
        if self.margin_iterations < 0:
            raise ValueError(f"margin_iterations must be >= 0, got {self.margin_iterations}")
        for name in ("field_tol", "field_map_tol"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        for name in ("fd_eps", "impulse", "sv_tol", "step_size", "tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        self._check_disturbance()

    def _check_disturbance(self) -> None:
        """The disturbance keys on their own (`check_plant_dims` checks n_d against the plant)."""
        if self.disturbance not in DISTURBANCE_KINDS:
            raise ValueError(f"disturbance must be one of {', '.join(DISTURBANCE_KINDS)}, got {self.disturbance!r}")
        dims = self.disturbance_dims
        combined = "+" in self.disturbance
        if combined and dims is not None and not (isinstance(dims, (list, tuple)) and len(dims) == 2 and all(
                isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1 for v in dims)):
            raise ValueError(f"disturbance_dims of the combination {self.disturbance} must be two integers >= 1 "
                             f"(one per part: {', '.join(parts(self.disturbance))}), got {dims!r}")
        if not combined and dims is not None and (isinstance(dims, bool) or not isinstance(dims, (int, np.integer))
                                                  or dims < 1):
            raise ValueError(f"disturbance_dims must be an integer >= 1, got {dims!r}")
        for name in ("disturbance_std", "disturbance_walk_std"):
            v = getattr(self, name)
            if v is None:
                continue
            try:
                arr = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                arr = np.array(np.nan)
            if arr.ndim > 1 or arr.size == 0 or not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ValueError(f"{name} must be a number >= 0 or a list of them (one per direction), got {v!r}")

    def check_plant_dims(self, n_u: int, n_y: int) -> None:
        """Raise ValueError naming the key when the disturbance settings do not fit a plant with
        n_u inputs and n_y outputs: n_d > n_y (not detectable), n_d > n_u (input kind), lists of
        stds of another length than n_d."""
        if self.disturbance == "none":
            return
        if "+" in self.disturbance:
            try:
                n_c = [{"input": n_u, "output": n_y}.get(p) for p in parts(self.disturbance)]
                n_d = sum(split_dims(self.disturbance, self.disturbance_dims, n_y, n_c))
            except DisturbanceError as exc:
                raise ValueError(str(exc)) from None
            return self._check_std_lengths(n_d)
        n_max = n_y if self.disturbance == "output" else n_y if self.disturbance == "noise" else min(n_y, n_u)
        n_d = n_max if self.disturbance_dims is None else int(self.disturbance_dims)
        if n_d > n_y:
            raise ValueError(f"disturbance_dims = {n_d} > n_y = {n_y}: at most as many disturbances as sensors "
                             "are detectable; give disturbance_dims <= n_y")
        if n_d > n_max or (self.disturbance == "output" and n_d != n_y):
            raise ValueError(f"disturbance_dims = {n_d} does not fit the {self.disturbance} kind: "
                             + (f"at most n_u = {n_u} input directions" if self.disturbance == "input"
                                else f"one bias per sensor, n_d = n_y = {n_y}"))
        self._check_std_lengths(n_d)

    def _check_std_lengths(self, n_d: int) -> None:
        """ValueError when a list of disturbance stds has another length than n_d."""
        for name in ("disturbance_std", "disturbance_walk_std"):
            v = getattr(self, name)
            if v is not None and np.ndim(v) == 1 and len(v) != n_d:
                raise ValueError(f"{name} has {len(v)} values; give one number or n_d = {n_d}")

    def disturbance_for(self, rom: LTVModel, problem: Problem) -> Disturbance | None:
        """The disturbance states these settings give `rom` under `problem` (directions and prior
        std: `sep_estimator.disturbance.choose`, with the ROM's plain LQR for the closed-loop step
        gains); None for 'none'."""
        if self.disturbance == "none":
            return None
        acting = any(p in ACTING for p in parts(self.disturbance))
        K = lqr_gains(rom, problem)[0] if acting and self.disturbance_std is None else None
        w = problem.channels("w_std", rom.noise_input.shape[2]) if "noise" in parts(self.disturbance) else None
        return choose(rom, self.disturbance, float(problem.band), problem.window, dims=self.disturbance_dims,
                      std=self.disturbance_std, walk_std=self.disturbance_walk_std, K=K, noise_std=w)

    def resolved(self) -> "DesignSettings":
        """These settings with the keys left at None set by the experiment plan (`PLANS`)."""
        plan = PLANS[self.experiment_plan]
        unset = {k: v for k, v in plan.items() if getattr(self, k) is None}
        return replace(self, **unset) if unset else self

    def rom(self, engine=None, problem: Problem | None = None) -> RomSettings:
        """The TV-ERA settings of the design's identifications (experiments on `engine`; the
        problem's w_std weighs a sketch of many noise channels, `sep_control.design.noise_sketch`)."""
        self = self.resolved()
        return RomSettings(p=self.p, q=self.q, n_r=self.n_r, sv_tol=self.sv_tol, impulse=self.impulse,
                           scheme=self.impulse_scheme, memory_budget=self.memory_budget, chunks=self.chunks,
                           engine=engine, noise_std=None if problem is None else problem.w_std,
                           stride=self.impulse_stride, field_tol=self.field_tol,
                           field_basis="svd" if self.experiment_plan == "0.8" else "gram")

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
        in one batch) would not fit the memory budget, or for Gauss-Newton under plan 0.9 (its
        coarse kept models take fewer run-steps than sensitivities at every horizon)."""
        if self.jacobian == "auto" and self.method == "gn" and self.experiment_plan != "0.8":
            return "rom"
        jac = self.resolved_jacobian(n_steps)
        if self.jacobian == "auto" and jac == "sensitivity" and \
                n_steps * int(plant.n_u) > runs_per_batch(int(plant.n_x), int(plant.n_field), self.memory_budget):
            return "rom"
        return jac

    def for_plant(self, plant: Plant) -> "DesignSettings":
        """These settings as a design for `plant` uses (and records) them: a plant whose states
        are opaque (`state_is_opaque`, e.g. a Co-Simulation FMU) gets no belief refinement, since
        the EnKF does arithmetic on states; its design has the mean-only nominal and no belief
        statistics."""
        st = self.resolved()
        if st.belief and getattr(plant, "state_is_opaque", False):
            return replace(st, belief=False)
        return st

    @classmethod
    def for_scenario(cls, scenario: Scenario, **overrides: Any) -> "DesignSettings":
        """The defaults, then the scenario's `design:` section, then `overrides` (ValueError naming
        an unknown key; a renamed key, `seed` for `enkf_seed`, is read with a FutureWarning: a deprecation meant for users, shown by default)."""
        section = dict(scenario.design)
        for old, new in RENAMED.items():
            if old in section:
                if new in section:
                    raise ValueError(f"scenario design section: give `{new}` only (`{old}` is its old name)")
                warnings.warn(f"scenario design section: `{old}` is deprecated, write `{new}`",
                              FutureWarning, stacklevel=2)
                section[new] = section.pop(old)
        known = cls.__dataclass_fields__
        unknown = sorted(k for k in section if k not in known)
        if unknown:
            raise ValueError(f"scenario design section: unknown setting(s) {unknown}; known: {sorted(known)}")
        st = cls(**{**section, **overrides})
        st.check()
        return st

    @classmethod
    def from_meta(cls, meta: dict[str, Any]) -> "DesignSettings":
        """The settings recorded in a design file's metadata (unknown keys ignored; files older
        than the chunked experiments ran them as one chunk, older than `relinearize_rtol`
        identified again after every step, older than `field_map_tol` truncated the field map
        at the field basis' tolerance, older than `coarse_proposals` identified every model
        with the full settings, older than `disturbance` had no disturbance states, older than
        `experiment_plan` ran 0.8.0's plan, older than `field_tol` kept the field basis to 1e-8,
        and older ones record `enkf_seed` as `seed`)."""
        recorded = {"chunks": 1, "relinearize_rtol": SAME_INPUT_RTOL, "field_map_tol": FIELD_TOL,
                    "coarse_proposals": False, "disturbance": "none", "experiment_plan": "0.8",
                    "field_tol": FIELD_TOL}
        for key, value in meta.get("settings", {}).items():
            recorded[RENAMED.get(key, key)] = value
        return cls(**{k: v for k, v in recorded.items() if k in cls.__dataclass_fields__}).resolved()
