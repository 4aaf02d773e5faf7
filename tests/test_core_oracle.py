"""Oracle: finite-difference full-order Jacobians vs the analytic Jacobians of the scheme."""
import numpy as np
import pytest

from core_helpers import (cached_design, cached_oracle, coarse_scenario, conductivity, d2_matrix,  # noqa: F401
                          dense_jacobians, dense_step, one_blas_thread)
from sep_control.oracle import full_order_jacobians, rom_lqg
from sep_control.optimize import nominal_rollout
from sep_plant.scenario import Scenario
from sep_plant.slab import SlabSimulator

pytestmark = pytest.mark.usefixtures("one_blas_thread")


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.mark.parametrize("changes", [
    dict(),                                         # reference physics
    dict(beta=2.0, gamma=1.0, dt=2.0),              # strongly T- and x-dependent K, long steps
])
def test_full_order_jacobians_equal_the_analytic_ones(changes):
    s = Scenario(n_x=10, n_steps=8, k_band=4, lqr_k_switch=4, **changes)
    sim = SlabSimulator(s)
    rng = np.random.default_rng(0)
    U = 2.0 + rng.standard_normal((s.n_steps, s.n_u))
    X = nominal_rollout(sim, U)
    # (the test's dense model is the simulator: same trajectory)
    for k in range(s.n_steps):
        np.testing.assert_allclose(dense_step(s, X[k], U[k]), X[k + 1], rtol=1e-12)
    A, B, C = full_order_jacobians(sim, X, U)
    assert A.shape == (s.n_steps, s.n_x, s.n_x) and B.shape == (s.n_steps, s.n_x, s.n_u)
    assert C.shape == (s.n_y, s.n_x)
    for k in range(s.n_steps):
        A_ex, B_ex = dense_jacobians(s, X[k], U[k])
        assert rel(A[k], A_ex) < 1e-6
        assert rel(B[k], B_ex) < 1e-6
    # C selects the sensor nodes
    C_ex = np.zeros((s.n_y, s.n_x))
    C_ex[np.arange(s.n_y), s.sensor_nodes()] = 1.0
    np.testing.assert_allclose(C, C_ex, atol=1e-9)


def test_the_analytic_jacobian_check_is_sensitive():
    """(control) the Jacobian without the dK/dT term (K evaluated at the actual temperatures but
    treated as a constant) is far outside the tolerance used above, so that comparison really
    checks the temperature dependence of the discretized equations."""
    s = Scenario(n_x=10, n_steps=8, k_band=4, lqr_k_switch=4)
    sim = SlabSimulator(s)
    U = np.full((s.n_steps, s.n_u), 3.0)
    X = nominal_rollout(sim, U)
    A, _, _ = full_order_jacobians(sim, X, U)
    k = s.n_steps - 1
    M = (1 + s.dt * s.eta) * np.eye(s.n_x) - s.dt * conductivity(s, X[k])[:, None] * d2_matrix(s.n_x, s.h)
    assert rel(A[k], np.linalg.inv(M)) > 1e-4
    assert rel(A[k], dense_jacobians(s, X[k], U[k])[0]) < 1e-6


def test_oracle_lqg_shapes_and_field_map():
    s = coarse_scenario()                   # the end-to-end test's design (computed once)
    d = cached_design(s)
    orc = cached_oracle(s)
    N, nx = s.n_steps, s.n_x
    assert orc.name == "oracle_lqg"
    assert orc.A.shape == (N, nx, nx) and orc.K.shape == (N, s.n_u, nx) and orc.L.shape == (N + 1, nx, s.n_y)
    np.testing.assert_array_equal(orc.G[3], np.eye(nx))
    np.testing.assert_allclose(orc.field_std, np.sqrt(np.einsum("kii->ki", orc.P_post)), rtol=1e-12)
    # identical input-output behaviour: ROM and full-order Markov parameters agree
    rom = rom_lqg(d)
    for j, k in [(0, 1), (0, 10), (5, 30), (20, 40), (30, 80)]:
        Mr, Mo = rom.B[j], orc.B[j]
        for i in range(j + 1, k):
            Mr, Mo = rom.A[i] @ Mr, orc.A[i] @ Mo
        np.testing.assert_allclose(rom.C[k] @ Mr, orc.C[k] @ Mo, rtol=0, atol=1e-5 * np.abs(orc.C[k] @ Mo).max())
    # and the ROM's field map reproduces the full-order field responses (the whole field)
    for j, k in [(0, 1), (3, 20), (40, 79)]:
        Mr, Mo = rom.B[j], orc.B[j]
        for i in range(j + 1, k):
            Mr, Mo = rom.A[i] @ Mr, orc.A[i] @ Mo
        np.testing.assert_allclose(rom.G[k] @ Mr, Mo, rtol=0, atol=1e-5 * np.abs(Mo).max())
