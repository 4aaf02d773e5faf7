"""A design in memory: the nominal, the ROM LQG and everything the online nodes and the evaluation need.

`Design` and `Nominal` are the objects; how they are stored on disk is the design file's
business (`sep_estimator.design_file`: `save_design`, `load_design`, docs/reference/design-file.md).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sep_plant.problem import Objective, Problem
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario

from sep_estimator.disturbance import Disturbance
from sep_estimator.ltv import LQG, LTVModel


@dataclass
class Nominal:
    """The optimized open-loop nominal and its belief (k = 0..N).

    Attributes
    ----------
    u : ndarray, shape (N, n_u)
        ubar_k, the nominal inputs.
    y : ndarray, shape (N+1, n_y)
        ybar_k, the noise-free nominal outputs.
    field : ndarray, shape (N+1, n_field)
        fbar_k, the nominal field.
    belief_mean, belief_std : ndarray, shape (N+1, n_field), or None
        The EnKF belief mean along the nominal observations and its per-node std; None when
        absent (opaque-state plants: no EnKF runs on their states).
    """

    u: np.ndarray
    y: np.ndarray
    field: np.ndarray
    belief_mean: np.ndarray | None = None
    belief_std: np.ndarray | None = None

    @property
    def belief_kind(self) -> str:
        """meta["belief"] of a design file: "ensemble" when the statistics are there, else "absent"."""
        return "absent" if self.belief_mean is None else "ensemble"


@dataclass
class Design:
    """Everything the online nodes and the evaluation need.

    Attributes
    ----------
    scenario : Scenario
        Plant spec and problem (plain data).
    info : PlantInfo
        Dimensions, names, dt, field description.
    objective : Objective
        Resolved target, weights, band window.
    field_xyz : ndarray, shape (n_field, 3)
        Node coordinates [m].
    nominal : Nominal
        ubar, ybar, fbar and the belief along them.
    lqg : LQG
        The ROM LQG: ``lqg.model`` the ROM with its disturbance states, ``lqg.rom`` the ROM.
    hankel_sv : ndarray, shape (N+1, n_sv)
        Hankel singular values of the identification.
    meta : dict
        Settings, validation, provenance (the design file's ``meta``).
    """

    scenario: Scenario
    info: PlantInfo
    objective: Objective
    field_xyz: np.ndarray
    nominal: Nominal
    lqg: LQG
    hankel_sv: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def rom(self) -> LTVModel:
        """The identified ROM (n_r states), without disturbance states."""
        return self.lqg.rom

    @property
    def disturbance(self) -> Disturbance | None:
        """The filter's disturbance states (None: none)."""
        return self.lqg.disturbance

    @property
    def problem(self) -> Problem:
        """The scenario's problem."""
        return self.scenario.problem

    @property
    def n_r(self) -> int:
        """The ROM order n_r."""
        return self.rom.n

    @property
    def n_steps(self) -> int:
        """The horizon N."""
        return int(self.nominal.u.shape[0])


__all__ = ["Design", "Nominal"]
