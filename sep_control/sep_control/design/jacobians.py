"""Which Gauss-Newton model the optimizer uses at each iterate: the linearization strategies.

* `SensitivityJacobian`: N n_u impulse-sensitivity experiments at every iterate
  (`SensitivityLinearization`).
* `RomJacobian`: a TV-ERA model identified at the iterates (`RomLinearization`). It keeps its
  last identification while U moved less than `relinearize_rtol` (relative), or for every
  iteration as a chord (`chord`); far from the optimum its identifications may use coarser
  `proposal` settings, since they only propose steps that the true objective accepts.
* `AutoJacobian`: sensitivities until an accepted step reaches the optimum's neighbourhood
  (it moves U by at most `NEAR_OPTIMUM` or lowers the objective by at most `NEAR_DECREASE`),
  then one TV-ERA identification there, which the belief refinement and the design reuse.

A strategy holds the state of one optimization (the kept identification, whether the last
step was near the optimum): make a new one per `Optimizer.run`.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import NamedTuple, Protocol

from sep_plant.problem import Objective
from sep_plant.protocol import Plant

from sep_control.design.linearization import (SAME_INPUT_RTOL, Linearization, Point, RomLinearization,
                                              SensitivityLinearization, same_input,
                                              sensitivity_normal_equations)
from sep_control.design.tvera import Identification, RomSettings

#: an accepted step that moved U by at most NEAR_OPTIMUM (max |dU| / max |U|) or lowered the cost
#: by at most NEAR_DECREASE (relative) marks the optimum's neighbourhood: the Gauss-Newton steps
#: after it move U by 1e-3 and less, or lower the cost by 1e-5 and less (every shipped scenario;
#: Allen-Cahn's weakly weighted inputs, r_u = 1e-5, still move by percents there), so a model
#: identified there is the one the belief refinement and the design go on with
NEAR_OPTIMUM = 1e-2
NEAR_DECREASE = 1e-3


def near_optimum(moved: float, decrease: float) -> bool:
    """Whether an accepted step that moved U by `moved` (max |dU| / max |U|) and lowered the
    objective by `decrease` (relative) was made in the optimum's neighbourhood."""
    return moved <= NEAR_OPTIMUM or decrease <= NEAR_DECREASE


class Linearized(NamedTuple):
    """A linearization and what it cost."""

    lin: Linearization
    kind: str           # "sensitivity", "rom", "rom (proposal)" or "rom (kept)"
    experiments: int    # simulator runs made for it (0: a kept identification)


class Jacobian(Protocol):
    """A linearization strategy (see the module docstring)."""

    def linearize(self, plant: Plant, obj: Objective, at: Point, gram: bool = True) -> Linearized:
        """The Gauss-Newton model at `at` (`gram` False: the gradient is enough)."""

    def relinearize(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                    gram: bool = True) -> Linearized | None:
        """After every trial step of `lin` failed: a model made at `at` to try again, or None."""

    def accepted(self, moved: float, decrease: float) -> None:
        """An accepted step moved U by `moved` and lowered the objective by `decrease` (relative)."""


class SensitivityJacobian:
    """N n_u impulse-sensitivity experiments of amplitude `eps` at every iterate."""

    def __init__(self, eps: float = 1e-4):
        self.eps = eps

    def linearize(self, plant: Plant, obj: Objective, at: Point, gram: bool = True) -> Linearized:
        ne = sensitivity_normal_equations(plant, at.U, at.X, obj, self.eps, at.residual_field, gram=gram)
        return Linearized(SensitivityLinearization(ne, at.U.shape), "sensitivity", ne.experiments)

    def relinearize(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                    gram: bool = True) -> Linearized | None:
        return None         # already made at `at`

    def accepted(self, moved: float, decrease: float) -> None:
        pass


class RomJacobian:
    """A TV-ERA model identified at the iterates (`RomLinearization`).

    Parameters
    ----------
    rom : RomSettings
        The identification's settings (those near the optimum, which a later stage reuses).
    proposal : RomSettings, optional
        Settings of the identifications made far from the optimum (the first, and those after
        an accepted step outside the optimum's neighbourhood), e.g. forward impulses and a
        coarser field basis: they only propose steps. None: `rom` everywhere.
    relinearize_rtol : float
        Keep the last identification while U stays within this of where it was made
        (`same_input`; the default identifies again after every step).
    chord : bool
        Keep the first identification for every iteration (a chord method).
    start : Identification, optional
        An identification handed over by an earlier stage, kept as if made here.
    settled_rtol : float
        `relinearize` offers no new model when the kept one has the full settings and was made
        within this of the input (0: only when made at the input itself).
    """

    def __init__(self, rom: RomSettings, proposal: RomSettings | None = None,
                 relinearize_rtol: float = SAME_INPUT_RTOL, chord: bool = False,
                 start: Identification | None = None, settled_rtol: float = 0.0):
        self.rom, self.proposal = rom, proposal
        self.relinearize_rtol, self.chord = relinearize_rtol, chord
        self.settled_rtol = settled_rtol
        self.kept = start          # the newest identification (each holds the nominal states and a basis)
        self.settled = False       # the last accepted step was in the optimum's neighbourhood

    def linearize(self, plant: Plant, obj: Objective, at: Point, gram: bool = True,
                  rtol: float | None = None) -> Linearized:
        rtol = self.relinearize_rtol if rtol is None else rtol
        if self.kept is not None and (self.chord or same_input(self.kept.U, at.U, rtol)):
            return Linearized(self._on(self.kept, obj, at), "rom (kept)", 0)
        far = self.proposal is not None and not self.settled
        self.kept = (self.proposal if far else self.rom).identify(plant, at.U)
        coarse = far and self.proposal != self.rom      # without coarse proposals the first model is a full one
        return Linearized(self._on(self.kept, obj, at), "rom (proposal)" if coarse else "rom",
                          self.kept.data.experiments)

    def relinearize(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                    gram: bool = True) -> Linearized | None:
        """A model kept from an earlier input whose trials all failed: once more on one made at
        `at`, with the full settings (None for a chord, or when `lin` was made at `at`)."""
        ident = lin.identification
        if ident is None or self.chord or same_input(ident.U, at.U):
            return None
        if self.settled_rtol > 0 and same_input(ident.U, at.U, self.settled_rtol) and \
                ident.made_with(self.rom.scheme, self.rom.field_tol, self.rom.p, self.rom.q):
            return None     # a model with the full settings made within settled_rtol: at the optimum
        self.settled = True
        return self.linearize(plant, obj, at, gram, SAME_INPUT_RTOL)

    def accepted(self, moved: float, decrease: float) -> None:
        self.settled = near_optimum(moved, decrease)

    def _on(self, ident: Identification, obj: Objective, at: Point) -> RomLinearization:
        # plan 0.8 (the "svd" field basis) keeps 0.8.0's step-by-step projections, bit for bit
        return RomLinearization(ident, obj, at.residual_field, at.U, one_pass=self.rom.field_basis != "svd")


class AutoJacobian:
    """`sensitivity` until an accepted step reaches the optimum's neighbourhood (`near_optimum`),
    `rom` from there on: one TV-ERA identification near the optimum instead of N n_u more
    sensitivity runs per iteration."""

    def __init__(self, sensitivity: SensitivityJacobian, rom: RomJacobian):
        self.sensitivity, self.rom = sensitivity, rom
        self.current: SensitivityJacobian | RomJacobian = sensitivity

    def linearize(self, plant: Plant, obj: Objective, at: Point, gram: bool = True) -> Linearized:
        return self.current.linearize(plant, obj, at, gram)

    def relinearize(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                    gram: bool = True) -> Linearized | None:
        return self.current.relinearize(plant, obj, at, lin, gram)

    def accepted(self, moved: float, decrease: float) -> None:
        self.rom.accepted(moved, decrease)
        if self.current is self.sensitivity and self.rom.settled:
            self.current = self.rom


class KeptRomJacobian(RomJacobian):
    """Experiment plan 0.9's ROM Jacobian: few identifications, each kept while it pays.

    The first model is a coarse `proposal` one. A model is kept for every step while its
    accepted steps lower the objective by at least half of what it predicts; when one does not
    (`refresh`, a stale model) a new one is made there, with the design's settings
    when the last step was in the optimum's neighbourhood (`near_optimum`); once a coarse model
    stopped predicting, every later model has the design's settings. When the kept coarse
    model's steps stall or fail (`relinearize`: its fixed point J_kept' r = 0 is not the optimum)
    a model with the design's settings is made there; when such a model's steps stall or fail,
    the optimizer stops.
    """

    def __init__(self, rom: RomSettings, proposal: RomSettings):
        super().__init__(rom, proposal, relinearize_rtol=float("inf"))

    def _full(self, ident: Identification) -> bool:
        return ident.made_with(self.rom.scheme, self.rom.field_tol, self.rom.p, self.rom.q, noise=False)

    def full_model(self, lin: Linearization) -> bool:
        """Whether `lin` is a model with the design's settings (not a coarse proposal one): a
        settle stop (`OptimizerOptions.settle`) applies to its steps only, since a coarse
        model's small decrease says that model is poor, not that the optimum is near."""
        return lin.identification is not None and self._full(lin.identification)

    def relinearize(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                    gram: bool = True) -> Linearized | None:
        ident = lin.identification
        if ident is None or self._full(ident) or same_input(ident.U, at.U):
            return None
        self.settled = True
        return self.linearize(plant, obj, at, gram, SAME_INPUT_RTOL)

    def refresh(self, plant: Plant, obj: Objective, at: Point, lin: Linearization,
                gram: bool = True) -> Linearized | None:
        """A kept model whose last step paid less than half its prediction: a new one at `at`,
        with the design's settings (a coarse model that stopped predicting is not tried again:
        on such a plant the coarse Hankel blocks miss the dynamics)."""
        ident = lin.identification
        if ident is None or same_input(ident.U, at.U):
            return None
        self.settled = True
        self.coarse_failed = True
        return self.linearize(plant, obj, at, gram, SAME_INPUT_RTOL)

    def accepted(self, moved: float, decrease: float) -> None:
        self.settled = getattr(self, "coarse_failed", False) or near_optimum(moved, decrease)
