"""Trajectory optimization: sensitivity normal equations vs brute force, GN vs GD, optimality."""
import numpy as np
import pytest

from core_helpers import coarse_scenario, flat
from core_helpers import one_blas_thread  # noqa: F401  (fixture)
from sep_control.evaluation.metrics import nominal_cost
from sep_control.design.belief import belief_cost, objective_of, run_belief
from sep_control.design.jacobians import SensitivityJacobian
from sep_control.design.linearization import sensitivity_normal_equations
from sep_control.design.optimizer import Optimizer, OptimizerOptions
from sep_plant.protocol import nominal_states

# A tiny, strongly nonlinear problem: long steps and large inputs move the field by tens of
# degrees within the horizon, so K(T) changes and the sensitivities depend on U; every step
# has weight (q_early not negligible) so every row of the Jacobian matters.
TINY_SCENARIO = flat(n_x=12, n_steps=6, dt=5.0, k_band=3, lqr_k_switch=3, q_early=0.3, heater_sigma=0.08,
                     heater_centers=(0.2, 0.6), sensor_positions=(0.2, 0.6), r_u=0.1)
TINY, PROB = TINY_SCENARIO.plant, TINY_SCENARIO.problem
OBJ = objective_of(TINY, PROB)

pytestmark = pytest.mark.usefixtures("one_blas_thread")


def optimize(plant, problem, U0=None, **options):
    """One `Optimizer` run with the sensitivity Jacobian, no progress bar."""
    return Optimizer(plant, problem, OptimizerOptions(show_progress=False, **options), SensitivityJacobian()).run(U0)


def tiny_U(seed=0):
    return 3.0 + np.random.default_rng(seed).standard_normal((PROB.n_steps, TINY.n_u))


def residual(sim, p, U):
    """r(U) with J = |r|^2 (the optimizer's documented least-squares form), written out."""
    T = nominal_states(sim, U)
    q = p.q_weights()
    rows = [np.sqrt(q[k] / sim.n_x) * (T[k] - 150.0) for k in range(1, p.n_steps + 1)]
    return np.concatenate(rows + [np.sqrt(p.r_u) * U.ravel()])


def fd_jacobian(fun, U, h=1e-5):
    cols = []
    for i in range(U.size):
        E = np.zeros(U.size)
        E[i] = h
        cols.append((fun(U + E.reshape(U.shape)) - fun(U - E.reshape(U.shape))) / (2 * h))
    return np.array(cols).T


def test_residual_form_is_the_nominal_cost():
    sim = TINY
    U = tiny_U()
    assert np.sum(residual(sim, PROB, U) ** 2) == pytest.approx(
        float(nominal_cost(nominal_states(sim, U), U, OBJ)), rel=1e-12)
    # and the cost formula itself, written out from docs/method.md
    T = nominal_states(sim, U)
    q = PROB.q_weights()
    J = sum(q[k] * np.mean((T[k] - 150.0) ** 2) for k in range(1, PROB.n_steps + 1)) + 0.1 * np.sum(U**2)
    assert float(nominal_cost(T, U, OBJ)) == pytest.approx(J, rel=1e-12)
    # the evaluation's nominal_cost is the objective's own cost, bit for bit
    assert OBJ.cost(T, U) == nominal_cost(T, U, OBJ)


def test_gradient_equals_brute_force_finite_differences():
    sim = TINY
    U = tiny_U()
    X = nominal_states(sim, U)
    J = lambda V: float(nominal_cost(nominal_states(sim, V), V, OBJ))
    grad = fd_jacobian(lambda V: np.array([J(V)]), U)[0]
    ne = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6)
    assert np.linalg.norm(grad) > 1.0                       # (a real, non-trivial gradient)
    np.testing.assert_allclose(ne.Jtr, grad / 2, rtol=1e-4, atol=1e-4 * np.abs(grad).max())
    # gradient-only mode gives the same J'r
    ne_g = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6, gram=False)
    np.testing.assert_allclose(ne_g.Jtr, ne.Jtr, rtol=1e-12)
    # experiment accounting: N n_u runs, n_u (k+1) active runs at step k
    N, n_u = U.shape
    assert ne.experiments == N * n_u
    assert ne.run_steps == n_u * N * (N + 1) // 2


def test_gauss_newton_matrix_equals_explicit_jacobian():
    sim = TINY
    U = tiny_U(1)
    X = nominal_states(sim, U)
    Jac = fd_jacobian(lambda V: residual(sim, PROB, V), U)     # (N n_x + N n_u, N n_u)
    r = residual(sim, PROB, U)
    ne = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6)
    JtJ = Jac.T @ Jac
    assert ne.JtJ.shape == JtJ.shape == (U.size, U.size)
    np.testing.assert_allclose(ne.JtJ, JtJ, rtol=1e-4, atol=1e-6 * np.abs(JtJ).max())
    np.testing.assert_allclose(ne.Jtr, Jac.T @ r, rtol=1e-4, atol=1e-6 * np.abs(Jac.T @ r).max())
    # causality: the response at step k does not depend on inputs at steps >= k, so the
    # explicit Jacobian is block lower triangular and the sensitivity runs need not run early
    n_u, n_x = TINY.n_u, TINY.n_x
    for k in range(1, PROB.n_steps + 1):
        rows = Jac[(k - 1) * n_x:k * n_x]
        assert np.all(np.abs(rows[:, k * n_u:]) < 1e-9)


def test_residual_field_replaces_the_trajectory_in_Jtr():
    """Belief-space variant: J'r with the residual of another field (the belief mean)."""
    sim = TINY
    U = tiny_U(2)
    X = nominal_states(sim, U)
    other = X + np.random.default_rng(3).standard_normal(X.shape)
    ne = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6, residual_field=other)
    Jac = fd_jacobian(lambda V: residual(sim, PROB, V), U)
    q = PROB.q_weights()
    r_other = np.concatenate([np.sqrt(q[k] / TINY.n_x) * (other[k] - 150.0)
                              for k in range(1, PROB.n_steps + 1)] + [np.sqrt(PROB.r_u) * U.ravel()])
    np.testing.assert_allclose(ne.Jtr, Jac.T @ r_other, rtol=1e-4, atol=1e-5 * np.abs(Jac.T @ r_other).max())


@pytest.fixture(scope="module")
def small():
    s = coarse_scenario(20, 40)
    return s.problem, s.plant


def test_gauss_newton_beats_gradient_descent(small):
    s, sim = small
    gn = optimize(sim, s, method="gn", max_iter=4)
    gd = optimize(sim, s, method="gd", max_iter=4)
    obj = objective_of(sim, s)
    assert gn.history[0] == gd.history[0]                      # same start (constant u_init)
    # GN converges: its 4th step lowers the cost by less than tol and is not taken
    assert gn.iterations == 3 and gn.stop == "the step lowered the objective by less than tol (not taken)"
    assert gd.iterations == 4 and gd.stop == "max_iter = 4"
    assert gn.cost < 0.1 * gd.cost
    # both descend monotonically (accept/reject on the true cost)
    assert all(b < a for a, b in zip(gn.history, gn.history[1:]))
    assert all(b < a for a, b in zip(gd.history, gd.history[1:]))
    assert gn.experiments == 4 * s.n_steps * sim.n_u
    np.testing.assert_allclose(gn.cost, float(nominal_cost(nominal_states(sim, gn.U), gn.U, obj)), rtol=1e-12)


def test_optimum_has_a_small_gradient(small):
    s, sim = small
    U0 = np.full((s.n_steps, sim.n_u), s.u_init)
    obj = objective_of(sim, s)
    res = optimize(sim, s, method="gn", max_iter=30, tol=1e-14)
    grad = lambda U: 2 * sensitivity_normal_equations(sim, U, nominal_states(sim, U), obj, eps=1e-6,
                                                      gram=False).Jtr
    g0, g = grad(U0), grad(res.U)
    assert np.linalg.norm(g) < 1e-6 * np.linalg.norm(g0)
    # and it is a minimum: random small perturbations do not lower the cost
    J = lambda U: float(nominal_cost(nominal_states(sim, U), U, obj))
    rng = np.random.default_rng(0)
    for _ in range(5):
        assert J(res.U + 1e-3 * rng.standard_normal(res.U.shape)) > res.cost
    # the optimized nominal is in the band over the band window (the design problem is feasible)
    T = nominal_states(sim, res.U)
    assert np.max(np.abs(T[s.window[0]:] - 150.0)) < s.band


def test_input_limits_are_respected(small):
    s, sim = small
    s2 = s.replace(u_min=0.0, u_max=0.6)
    res = optimize(sim, s2, method="gn", max_iter=3)
    assert res.U.min() >= 0.0 and res.U.max() <= 0.6
    assert res.cost < res.history[0]


def test_mean_only_problem_is_a_noise_free_belief(small):
    """With no process noise the EnKF belief along the nominal observations is the nominal
    itself (zero spread, zero gain), and the belief cost is the nominal cost."""
    s, sim = small
    s0 = s.replace(w_std=0.0)
    U = np.full((s.n_steps, sim.n_u), 0.3)
    obj = objective_of(sim, s)
    b = run_belief(sim, U, s0, members=2, seed=0)
    X = nominal_states(sim, U)
    np.testing.assert_allclose(b.mean, X, rtol=1e-13)
    assert np.all(b.std == 0)
    assert belief_cost(b, U, obj) == pytest.approx(float(nominal_cost(X, U, obj)), rel=1e-13)
    # with noise the spread is penalized on top of the mean's cost; deterministic in the seed
    b1, b2 = run_belief(sim, U, s, 20, 3), run_belief(sim, U, s, 20, 3)
    np.testing.assert_array_equal(b1.mean, b2.mean)
    assert belief_cost(b1, U, obj) > float(nominal_cost(b1.mean, U, obj))


def test_belief_objective_optimizes_the_belief_cost(small):
    s, sim = small
    start = optimize(sim, s, method="gn", max_iter=3)
    res = optimize(sim, s, U0=start.U, method="gn", objective="belief", max_iter=2, members=20, enkf_seed=1)
    assert res.objective == "belief"
    assert res.cost <= res.history[0]
    assert res.cost == pytest.approx(belief_cost(run_belief(sim, res.U, s, 20, 1), res.U, objective_of(sim, s)),
                                     rel=1e-12)


def test_bad_arguments(small):
    s, sim = small
    with pytest.raises(ValueError, match="method"):
        optimize(sim, s, method="newton")
    with pytest.raises(ValueError, match="objective"):
        optimize(sim, s, objective="robust")


def test_belief_members_stepped_in_memory_batches_equal_one_batch(small):
    """The EnKF's forecast steps go in batches that fit the memory budget: the same belief."""
    from unittest import mock

    from sep_control.design import belief as belief_mod

    s, sim = small
    U = np.full((s.n_steps, sim.n_u), 0.3)
    whole = run_belief(sim, U, s, 20, 3)
    calls = []
    step = sim.step

    def counting_step(X, *a):
        calls.append(X.shape[0])
        return step(X, *a)

    with mock.patch.object(belief_mod, "runs_per_batch", return_value=6), mock.patch.object(sim, "step", counting_step):
        split = run_belief(sim, U, s, 20, 3)
    assert max(calls) == 6 and 2 in calls          # 20 members as 6 + 6 + 6 + 2
    np.testing.assert_allclose(split.mean, whole.mean, rtol=0, atol=1e-12 * np.abs(whole.mean).max())
    np.testing.assert_allclose(split.std, whole.std, rtol=0, atol=1e-12 * np.abs(whole.std).max())


def test_gram_matrix_one_step_per_chunk_equals_the_chunked_one(monkeypatch):
    """At large n_field the Gram update runs one step per chunk (no zeroing of the rows between
    steps: the next step overwrites every row it reads); it equals the chunked accumulation."""
    import sep_control.design.linearization as lin

    sim = TINY
    U = tiny_U(2)
    X = nominal_states(sim, U)
    chunked = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6)
    init = lin._ChunkedGram.__init__

    def one_step_chunks(self, n, n_f, N, xp=np):
        init(self, n, n_f, N, xp)
        self.chunk = 1
    monkeypatch.setattr(lin._ChunkedGram, "__init__", one_step_chunks)
    single = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-6)
    np.testing.assert_allclose(single.JtJ, chunked.JtJ, rtol=1e-12, atol=1e-12 * np.abs(chunked.JtJ).max())
    assert np.array_equal(single.Jtr, chunked.Jtr)
