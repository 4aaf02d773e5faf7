"""Oracle: finite-difference full-order Jacobians vs the analytic Jacobians of the scheme."""
import numpy as np
import pytest

from core_helpers import (Slab, cached_design, cached_oracle, coarse_scenario, conductivity, d2_matrix,  # noqa: F401
                          dense_jacobians, dense_step, one_blas_thread)
from sep_control.evaluation.oracle import full_order_model, rom_lqg
from sep_estimator.ltv import IdentityFieldMap
from sep_plant.protocol import nominal_states as nominal_rollout

N_STEPS = 8

pytestmark = pytest.mark.usefixtures("one_blas_thread")


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.mark.parametrize("changes", [
    dict(),                                         # reference physics
    dict(beta=2.0, gamma=1.0, dt=2.0),              # strongly T- and x-dependent K, long steps
])
def test_full_order_jacobians_equal_the_analytic_ones(changes):
    s = sim = Slab(n_x=10, **changes)
    rng = np.random.default_rng(0)
    U = 2.0 + rng.standard_normal((N_STEPS, s.n_u))
    X = nominal_rollout(sim, U)
    # (the test's dense model is the simulator: same trajectory)
    for k in range(N_STEPS):
        np.testing.assert_allclose(dense_step(s, X[k], U[k]), X[k + 1], rtol=1e-12)
    m = full_order_model(sim, X, U)
    A, B = m.A, m.B
    assert A.shape == (N_STEPS, s.n_x, s.n_x) and B.shape == (N_STEPS, s.n_x, s.n_u)
    assert m.C.shape == (N_STEPS + 1, s.n_y, s.n_x) and m.Bw is None
    assert isinstance(m.G, IdentityFieldMap)              # the slab's field is its state
    for k in range(N_STEPS):
        A_ex, B_ex = dense_jacobians(s, X[k], U[k])
        assert rel(A[k], A_ex) < 1e-6
        assert rel(B[k], B_ex) < 1e-6
    # C selects the sensor nodes
    C_ex = np.zeros((s.n_y, s.n_x))
    C_ex[np.arange(s.n_y), s.sensor_nodes()] = 1.0
    for k in range(N_STEPS + 1):
        np.testing.assert_allclose(m.C[k], C_ex, atol=1e-9)


def test_the_analytic_jacobian_check_is_sensitive():
    """(control) the Jacobian without the dK/dT term (K evaluated at the actual temperatures but
    treated as a constant) is far outside the tolerance used above, so that comparison really
    checks the temperature dependence of the discretized equations."""
    s = sim = Slab(n_x=10)
    U = np.full((N_STEPS, s.n_u), 3.0)
    X = nominal_rollout(sim, U)
    A = full_order_model(sim, X, U).A
    k = N_STEPS - 1
    M = (1 + s.dt * s.eta) * np.eye(s.n_x) - s.dt * conductivity(s, X[k])[:, None] * d2_matrix(s.n_x, s.h)
    assert rel(A[k], np.linalg.inv(M)) > 1e-4
    assert rel(A[k], dense_jacobians(s, X[k], U[k])[0]) < 1e-6


def test_oracle_lqg_shapes_and_field_map():
    # plan 0.8's design (central impulses at every start step: the ROM the oracle is checked against
    # to 1e-5; plan 0.9's forward, strided impulses are ~1e-3 off by design)
    s = coarse_scenario()
    d = cached_design(s, experiment_plan="0.8")
    lqg = cached_oracle(s, experiment_plan="0.8")
    orc = lqg.model
    N, nx, nu, ny = s.problem.n_steps, s.plant.n_x, s.plant.n_u, s.plant.n_y
    assert lqg.name == "oracle_lqg"
    # the design's LQG on the full-order model: its disturbance states (the same directions) too
    nz = nx + lqg.n_d
    assert lqg.n_d == d.lqg.n_d and lqg.rom.A.shape == (N, nx, nx)
    np.testing.assert_array_equal(lqg.disturbance.map, d.disturbance.map)
    assert orc.A.shape == (N, nz, nz) and lqg.K.shape == (N, nu, nz) and lqg.kf.L.shape == (N + 1, nz, ny)
    np.testing.assert_array_equal(orc.G.matrix(3), np.eye(nx, nz))
    np.testing.assert_allclose(lqg.field_std, np.sqrt(np.einsum("kii->ki", lqg.kf.P_post[:, :nx, :nx])), rtol=1e-12)
    # identical input-output behaviour: ROM and full-order Markov parameters agree
    rom, orc = rom_lqg(d).rom, lqg.rom
    for j, k in [(0, 1), (0, 10), (5, 30), (20, 40), (30, 80)]:
        Mr, Mo = rom.B[j], orc.B[j]
        for i in range(j + 1, k):
            Mr, Mo = rom.A[i] @ Mr, orc.A[i] @ Mo
        np.testing.assert_allclose(rom.C[k] @ Mr, orc.C[k] @ Mo, rtol=0, atol=1e-5 * np.abs(orc.C[k] @ Mo).max())
    # and the ROM's field map reproduces the full-order field responses (the whole field), to the
    # design's field map tolerance (it drops what moves the field by < 1e-5 of the state's spread)
    for j, k in [(0, 1), (3, 20), (40, 79)]:
        Mr, Mo = rom.B[j], orc.B[j]
        for i in range(j + 1, k):
            Mr, Mo = rom.A[i] @ Mr, orc.A[i] @ Mo
        np.testing.assert_allclose(rom.G.matrix(k) @ Mr, Mo, rtol=0, atol=1e-4 * np.abs(Mo).max())
