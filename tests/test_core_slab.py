"""The slab plant: the discrete equations, steady state, boundaries, batching, inputs, noise."""
import math

import numpy as np
import pytest

from core_helpers import Slab, dense_step, flat, heater_matrix, spatial_operator
from sep_plant.noise import noise_sequences
from sep_plant.protocol import clip_inputs, rollout


def steady_state(s: Slab, tol: float = 1e-11, max_steps: int = 5000) -> np.ndarray:
    """Step with u = 0 until the field stops changing (large dt: backward Euler is stable)."""
    sim = s
    x = sim.initial_state(1)[0]
    u = np.zeros(s.n_u)
    for _ in range(max_steps):
        x_new = sim.step(x, u)
        if np.max(np.abs(x_new - x)) < tol:
            return x_new
        x = x_new
    raise AssertionError("no steady state reached")


@pytest.mark.parametrize("n_x", [20, 50])
def test_step_matches_the_discretized_equations(n_x):
    """One step is the backward-Euler step of docs/method.md with K frozen at T_k (dense solve)."""
    s = Slab(n_x=n_x)
    sim = s
    rng = np.random.default_rng(1)
    for _ in range(3):
        T = 100.0 + 60.0 * rng.random(n_x)
        u = rng.standard_normal(s.n_u)
        np.testing.assert_allclose(sim.step(T, u), dense_step(s, T, u), rtol=1e-12, atol=0)


def test_steady_state_solves_the_discrete_steady_equation():
    s = Slab(n_x=40, dt=200.0)
    T = steady_state(s)
    # K(T) (D2 T + bc) - eta T = 0, operator built independently in core_helpers
    res = spatial_operator(s, T, T)
    scale = s.eta * np.max(np.abs(T))
    assert np.max(np.abs(res)) < 1e-8 * scale
    # heat flows in from the right end and leaks out everywhere: monotone, below T_right
    assert np.all(np.diff(T) > 0)
    assert T[-1] < s.t_right and T[0] > s.t_init


def test_steady_state_is_second_order_accurate_for_constant_conductivity():
    """beta = gamma = 0: T(x) = T_right cosh(m x) / cosh(m L), m = sqrt(eta / k0); the
    ghost-node / eliminated-Dirichlet scheme converges at O(h^2)."""
    errs = []
    for n_x in (20, 40, 80):
        s = Slab(n_x=n_x, dt=200.0, beta=0.0, gamma=0.0, sensor_positions=(0.5,))
        T = steady_state(s)
        m = math.sqrt(s.eta / s.k0)
        exact = s.t_right * np.cosh(m * s.grid()) / math.cosh(m * s.length)
        errs.append(np.max(np.abs(T - exact)))
    assert errs[0] < 1e-2
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.05)
    assert errs[1] / errs[2] == pytest.approx(4.0, rel=0.05)


def test_boundary_conditions_insulated_left_and_pinned_right():
    gradients, right_gaps = [], []
    for n_x in (25, 50, 100):
        s = Slab(n_x=n_x, dt=200.0)
        T = steady_state(s)
        h = s.h
        # insulated left end: the symmetric ghost node makes row 0 read
        # K (2 T_1 - 2 T_0)/h^2 = eta T_0, i.e. a one-sided slope of O(h) -> 0
        K0 = s.k0 * (1 + s.beta * (T[0] - s.t_ref) / s.t_scale)
        assert (T[1] - T[0]) / h == pytest.approx(s.eta * T[0] * h / (2 * K0), rel=1e-6)
        gradients.append((T[1] - T[0]) / h)
        # pinned right end: the last node is one step h from T_right, the gap closes as O(h)
        right_gaps.append(s.t_right - T[-1])
        interior_slope = (T[-1] - T[-2]) / h
        assert s.t_right - T[-1] == pytest.approx(interior_slope * h, rel=0.05)
    assert gradients[0] / gradients[1] == pytest.approx(2.0, rel=0.02)
    assert gradients[1] / gradients[2] == pytest.approx(2.0, rel=0.02)
    assert right_gaps[0] / right_gaps[1] == pytest.approx(2.0, rel=0.05)
    assert right_gaps[2] < 0.02 * (s.t_right - T[0])


def test_uniform_right_temperature_without_losses_is_an_equilibrium():
    s = Slab(n_x=30, eta=0.0, t_init=150.0)
    sim = s
    x = sim.initial_state(1)[0]
    np.testing.assert_allclose(sim.step(x, np.zeros(s.n_u)), x, rtol=1e-14)


def test_batch_equals_one_by_one():
    s = Slab(n_x=37)
    sim = s
    rng = np.random.default_rng(2)
    M = 9
    X = 100.0 + 50.0 * rng.random((M, s.n_x))
    U = rng.standard_normal((M, s.n_u))
    W = 0.3 * rng.standard_normal((M, s.n_u))
    batch = sim.step(X, U, W)
    single = np.stack([sim.step(X[m], U[m], W[m]) for m in range(M)])
    # bitwise: the runs' tridiagonal blocks are uncoupled (zero off-diagonals between them), so
    # the elimination does exactly the same arithmetic as for each run alone
    np.testing.assert_array_equal(batch, single)
    assert batch.shape == (M, s.n_x) and single.shape == (M, s.n_x)
    # one input row broadcast to the batch
    np.testing.assert_allclose(sim.step(X, U[0]), np.stack([sim.step(X[m], U[0]) for m in range(M)]),
                               rtol=1e-13, atol=0)
    # process noise enters through the input channels
    np.testing.assert_allclose(batch, sim.step(X, U + W), rtol=1e-14, atol=0)


def test_rollout_equals_repeated_step():
    s = Slab(n_x=25)
    sim = s
    rng = np.random.default_rng(3)
    M, T = 4, 12
    X0 = sim.initial_state(M) + rng.standard_normal((M, s.n_x))
    U = rng.standard_normal((M, T, s.n_u))
    W = rng.standard_normal((M, T, s.n_u)) * 0.3
    out = rollout(sim, X0, U, W)
    assert out.shape == (M, T + 1, s.n_x)
    x = X0.copy()
    np.testing.assert_array_equal(out[:, 0], X0)
    for k in range(T):
        x = sim.step(x, U[:, k], W[:, k])
        np.testing.assert_allclose(out[:, k + 1], x, rtol=1e-14, atol=0)
    # a shared input sequence (T, n_u) for every run
    shared = rollout(sim, X0, U[0])
    np.testing.assert_allclose(shared[2], rollout(sim, X0[2:3], U[0])[0], rtol=1e-13, atol=0)


def test_observe_reads_the_sensor_nodes():
    s = Slab()
    sim = s
    np.testing.assert_array_equal(s.sensor_nodes(), [10, 30, 50, 70, 90])
    X = np.arange(3 * s.n_x, dtype=float).reshape(3, s.n_x)
    np.testing.assert_array_equal(sim.observe(X), X[:, [10, 30, 50, 70, 90]])
    np.testing.assert_array_equal(sim.observe(X[1]), X[1, [10, 30, 50, 70, 90]])


def test_heater_profiles_integrate_to_one():
    s = Slab()
    b = s.heater_profiles()
    assert b.shape == (s.n_x, s.n_u)
    np.testing.assert_allclose(b.sum(axis=0) * s.h, 1.0, rtol=1e-6)
    np.testing.assert_allclose(b, heater_matrix(s), rtol=1e-12)
    # each peaks at its centre node
    np.testing.assert_array_equal(np.argmax(b, axis=0), [10, 30, 50, 70, 90])


def test_exact_energy_balance_for_constant_conductivity():
    """beta = gamma = 0: with the trapezoid weights h (1/2, 1, ..., 1) the discrete Laplacian
    telescopes to the boundary flux, so each step satisfies exactly
    E_{k+1} - E_k = dt [ K (T_right - T_{k+1,n-1}) / h - eta E_{k+1} + sum_j u_j (b_j-mass) ]."""
    s = Slab(n_x=40, beta=0.0, gamma=0.0)
    sim = s
    rng = np.random.default_rng(4)
    wts = np.full(s.n_x, s.h)
    wts[0] *= 0.5
    mass = wts @ s.heater_profiles()
    x = sim.initial_state(1)[0]
    for _ in range(5):
        u = rng.standard_normal(s.n_u)
        x1 = sim.step(x, u)
        lhs = wts @ (x1 - x)
        rhs = s.dt * (s.k0 * (s.t_right - x1[-1]) / s.h - s.eta * (wts @ x1) + mass @ u)
        assert lhs == pytest.approx(rhs, rel=1e-10, abs=1e-10)
        x = x1


def test_heating_raises_mean_temperature_by_dt_u():
    """The response to a heater input is dt u b_j smoothed by the implicit step: the slab's mean
    temperature (trapezoid weights, which the ghost-node row needs to be conservative) rises by
    dt u / (L (1 + dt eta)), up to the heat the implicit step already pushes through the pinned
    end (~exp(-distance / sqrt(dt K)) ~ 1e-4 for the heaters at 0.3 L and 0.5 L)."""
    s = Slab()
    sim = s
    x = sim.initial_state(1)[0]
    wts = np.full(s.n_x, s.h)
    wts[0] *= 0.5
    for j in (1, 2):
        u = np.zeros(s.n_u)
        u[j] = 2.0
        rise = wts @ (sim.step(x, u) - sim.step(x, np.zeros(s.n_u))) / s.length
        assert rise == pytest.approx(s.dt * u[j] / (s.length * (1 + s.dt * s.eta)), rel=1e-3)
    # the step is affine in u (K is frozen at T_k)
    rng = np.random.default_rng(5)
    u1, u2 = rng.standard_normal((2, s.n_u))
    y0, y1, y2 = sim.step(x, 0 * u1), sim.step(x, u1), sim.step(x, u2)
    np.testing.assert_allclose(sim.step(x, u1 + u2) - y0, (y1 - y0) + (y2 - y0), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("x_shape,u_shape", [
    ((3, 29), (3, 5)),      # wrong number of nodes
    ((3, 30), (3, 4)),      # wrong number of inputs
    ((3, 30), (2, 5)),      # batch sizes that do not broadcast
    ((30,), (6,)),          # single run, wrong input length
])
def test_step_rejects_wrong_shapes(x_shape, u_shape):
    sim = Slab(n_x=30)
    with pytest.raises(ValueError):
        sim.step(np.full(x_shape, 100.0), np.zeros(u_shape))


def test_step_rejects_wrong_noise_shape():
    sim = Slab(n_x=30)
    with pytest.raises(ValueError):
        sim.step(np.full((3, 30), 100.0), np.zeros((3, 5)), np.zeros((3, 4)))


def test_clip_inputs():
    u = np.array([[-3.0, 0.5, 7.0]])
    assert clip_inputs(u, -math.inf, math.inf) is u
    np.testing.assert_array_equal(clip_inputs(u, 0.0, 2.0), [[0.0, 0.5, 2.0]])
    # per-input limits
    np.testing.assert_array_equal(clip_inputs(u, np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.4, 9.0])),
                                  [[-1.0, 0.4, 7.0]])


def test_noise_sequences_common_random_numbers():
    s = flat(n_steps=20, k_band=10, lqr_k_switch=10)
    p, info = s.problem, s.info
    w, v = noise_sequences(p, info, seed=7, runs=6)
    assert w.shape == (6, 20, 5) and v.shape == (6, 21, 5)
    w3, v3 = noise_sequences(p, info, seed=7, runs=range(3, 5))
    np.testing.assert_array_equal(w3, w[3:5])
    np.testing.assert_array_equal(v3, v[3:5])
    # run i is the i-th child of SeedSequence(seed), whatever else is drawn (sep 0.1's streams)
    child = np.random.default_rng(np.random.SeedSequence(7).spawn(5)[4])
    np.testing.assert_array_equal(w[4], child.standard_normal((20, 5)) * 0.3)
    w_other, _ = noise_sequences(p, info, seed=8, runs=6)
    assert not np.allclose(w_other, w)
    big_w, big_v = noise_sequences(p.replace(n_steps=2000), info, seed=7, runs=1)
    assert np.std(big_w) == pytest.approx(0.3, rel=0.05)
    assert np.std(big_v) == pytest.approx(1.0, rel=0.05)


def test_noise_of_a_large_run_index_is_immediate():
    """A plant node with run = 10^6 draws its noise directly (no spawn of 10^6 children)."""
    import time

    s = flat(n_steps=20, k_band=10, lqr_k_switch=10)
    t0 = time.perf_counter()
    w, _ = noise_sequences(s.problem, s.info, seed=3, runs=[10**6])
    assert time.perf_counter() - t0 < 1.0         # the old spawn(10^6 + 1) took ~10 s
    ref = np.random.default_rng(np.random.SeedSequence(3, spawn_key=(10**6,))).standard_normal((20, 5)) * 0.3
    np.testing.assert_array_equal(w[0], ref)


def test_per_channel_noise_levels():
    s = flat(n_steps=4000, k_band=10, lqr_k_switch=10, w_std=[0.1, 0.2, 0.3, 0.4, 0.5])
    w, _ = noise_sequences(s.problem, s.info, seed=1, runs=1)
    np.testing.assert_allclose(w[0].std(axis=0), [0.1, 0.2, 0.3, 0.4, 0.5], rtol=0.05)
