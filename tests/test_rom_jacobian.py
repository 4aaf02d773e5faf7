"""Gauss-Newton with the TV-ERA (ROM) Jacobian reaches the sensitivity-Jacobian optimum."""
import numpy as np
import pytest

from core_helpers import flat
from sep_control.optimize import (objective_of, optimize, rom_normal_equations,
                                  sensitivity_normal_equations)
from sep_plant.protocol import nominal_states as nominal_rollout

SC = flat(n_x=24, n_steps=60, k_band=36, lqr_k_switch=29)
P, S = SC.plant, SC.problem
OBJ = objective_of(P, S)
N_U = P.n_u
ROM = {"p": 8, "q": 8, "n_r": 16}


def test_rom_normal_equations_match_the_sensitivity_ones():
    sim = P
    U = np.full((S.n_steps, N_U), 0.2) + 0.02 * np.random.default_rng(1).standard_normal((S.n_steps, N_U))
    X = nominal_rollout(sim, U)
    a = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-5)
    b = rom_normal_equations(sim, U, OBJ, X, **ROM)
    # the one-sided eps = 1e-5 differences carry an O(eps) bias; the ROM's are central differences
    assert np.linalg.norm(b.Jtr - a.Jtr) / np.linalg.norm(a.Jtr) < 1e-4
    assert np.linalg.norm(b.JtJ - a.JtJ) / np.linalg.norm(a.JtJ) < 1e-4
    # 2 N n_u runs of p+q steps (central differences) instead of N n_u runs of N/2 steps on average
    assert b.experiments == 2 * S.n_steps * N_U
    assert b.run_steps == b.experiments * (ROM["p"] + ROM["q"])
    assert a.run_steps == N_U * S.n_steps * (S.n_steps + 1) // 2


def test_rom_gauss_newton_converges_to_the_same_optimum():
    sim = P
    ref = optimize(sim, S, show_progress=False)
    rom = optimize(sim, S, show_progress=False, jacobian="rom", rom=ROM)
    assert rom.iterations <= ref.iterations + 1
    assert rom.cost == pytest.approx(ref.cost, rel=1e-6)
    np.testing.assert_allclose(rom.U, ref.U, atol=1e-4 * np.abs(ref.U).max())


def test_unknown_jacobian_refused():
    with pytest.raises(ValueError, match="jacobian"):
        optimize(P, S, jacobian="adjoint", show_progress=False)
