"""TV-ERA recovers a known discrete LTV system; horizon start; slab impulse experiments."""
import numpy as np
import pytest

from core_helpers import coarse_scenario, ltv_system
from core_helpers import one_blas_thread  # noqa: F401  (fixture)
from sep_control.design.tvera import MarkovData, extend_nominal, impulse_experiments, tv_era
from sep_plant.protocol import nominal_states as nominal_rollout

N_ORDER, N_U, N_Y, N_F, N = 6, 2, 2, 8, 40
P = Q = 5

pytestmark = pytest.mark.usefixtures("one_blas_thread")


def exact_markov(A, B, C, F, N, lags, field_lags):
    """Y[j, l-1] = C_{j+l} A_{j+l-1} ... A_{j+1} B_j and Yf likewise with F (j < N)."""
    Y = np.zeros((N, lags, C.shape[1], B.shape[2]))
    Yf = np.zeros((N, field_lags, F.shape[1], B.shape[2]))
    steps = A.shape[0]
    for j in range(N):
        M = B[j]
        for lag in range(1, max(lags, field_lags) + 1):
            k = j + lag
            if k > steps:
                break                      # past the defined system (only j + lag <= N is used)
            if lag <= lags:
                Y[j, lag - 1] = C[k] @ M
            if lag <= field_lags:
                Yf[j, lag - 1] = F[k] @ M
            if k < steps:
                M = A[k] @ M
    return Y, Yf


@pytest.fixture(scope="module")
def known_system():
    rng = np.random.default_rng(42)
    steps = N + P + Q                      # the system is defined past N for the last Hankels
    A, B, C, F = ltv_system(rng, steps, N_ORDER, N_U, N_Y, N_F, radius=0.9)
    Y, Yf = exact_markov(A, B, C, F, N, P + Q, Q)
    real, sv = tv_era(MarkovData.from_dense(Y, Yf, delta=1.0, experiments=0, n_u=N_U), N, P, Q, n_r=8)
    return A, B, C, F, Y, real, sv


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_markov_parameters_recovered(known_system):
    A, B, C, F, Y, real, _ = known_system
    Yr = real.markov_all(P + Q)
    valid = (np.arange(N)[:, None] + np.arange(1, P + Q + 1)[None, :]) <= N
    assert rel(Yr[valid], Y[valid]) <= 1e-8
    # beyond the Hankel lags too: the whole horizon, j + lag <= N
    Y_all, _ = exact_markov(A, B, C, F, N, N, 1)
    Yr_all = real.markov_all(N)
    valid = (np.arange(N)[:, None] + np.arange(1, N + 1)[None, :]) <= N
    for j in range(N):
        for lag in range(1, N - j + 1):
            scale = np.linalg.norm(Y_all[j, 0])
            assert np.linalg.norm(Yr_all[j, lag - 1] - Y_all[j, lag - 1]) <= 1e-8 * scale
    assert np.all(Yr_all[~valid] == 0)
    # markov agrees with the vectorized version
    for j, k in [(0, 1), (0, 17), (3, 4), (12, 40), (39, 40)]:
        np.testing.assert_allclose(real.markov(k, j), Yr_all[j, k - j - 1], rtol=1e-12, atol=1e-14)


def test_field_map_reproduces_field_markov_parameters(known_system):
    A, B, C, F, Y, real, _ = known_system
    Yf_all, _ = exact_markov(A, B, F, F, N, N, 1)        # field Markov parameters, every lag
    for j in range(N):
        M = real.B[j]
        for k in range(j + 1, N + 1):
            got = real.G.matrix(k) @ M
            want = Yf_all[j, k - j - 1]
            assert np.linalg.norm(got - want) <= 1e-8 * np.linalg.norm(Yf_all[j, 0])
            if k < N:
                M = real.A[k] @ M


def test_order_and_horizon_start(known_system):
    A, B, C, F, Y, real, hankel_sv = known_system
    # ROM order grows by n_u per step until it saturates at the true order (n_r = 8 is a cap only)
    np.testing.assert_array_equal(real.dims[:5], [0, 2, 4, 6, 6])
    assert np.all(real.dims[3:] == N_ORDER)
    # A_0 maps from the 0-dimensional state at k = 0; A_1 is 4 x 2, A_2 is 6 x 4 (rectangular)
    assert np.all(real.A[0] == 0)
    assert np.all(real.A[1][4:] == 0) and np.all(real.A[1][:, 2:] == 0)
    assert np.linalg.matrix_rank(real.A[1][:4, :2]) == 2
    assert np.all(real.A[2][6:] == 0) and np.all(real.A[2][:, 4:] == 0)
    # B_j lives in the dims of step j+1; C_0 = 0 (nothing to observe at k = 0); padding is zero
    assert np.all(real.B[0][2:] == 0) and np.all(real.B[1][4:] == 0)
    assert np.all(real.C[0] == 0) and np.all(real.C[1][:, 2:] == 0)
    assert np.all(real.A[10][6:] == 0) and np.all(real.A[10][:, 6:] == 0)
    # Markov parameters that start at the first steps are still exact
    for j in range(3):
        for lag in range(1, P + Q + 1):
            np.testing.assert_allclose(real.markov(j + lag, j), Y[j, lag - 1],
                                       rtol=0, atol=1e-8 * np.linalg.norm(Y[j, 0]))
    # Hankel singular values: 6 significant ones, the rest at rounding level
    sv = hankel_sv[20]
    assert sv[5] > 1e-6 * sv[0] and sv[6] < 1e-12 * sv[0]


def test_order_cap_truncates():
    rng = np.random.default_rng(7)
    A, B, C, F = ltv_system(rng, N + P + Q, N_ORDER, N_U, N_Y, N_F)
    Y, Yf = exact_markov(A, B, C, F, N, P + Q, Q)
    real, _ = tv_era(MarkovData.from_dense(Y, Yf, 1.0, 0, N_U), N, P, Q, n_r=3)
    assert real.dims.max() == 3 and real.A.shape == (N, 3, 3)
    # a truncated ROM is an approximation, not garbage: first Markov parameters roughly right
    err = rel(real.markov_all(1)[:, 0], Y[:, 0])
    assert 1e-6 < err < 1.0


def test_needs_enough_lags():
    rng = np.random.default_rng(8)
    A, B, C, F = ltv_system(rng, N + P + Q, N_ORDER, N_U, N_Y, N_F)
    Y, Yf = exact_markov(A, B, C, F, N, P + Q - 1, Q)
    with pytest.raises(ValueError, match="lag"):
        tv_era(MarkovData.from_dense(Y, Yf, 1.0, 0, N_U), N, P, Q, n_r=8)


def test_slab_rom_matches_long_impulse_experiments():
    """Identify from (p+q)-lag experiments on a small slab, validate against experiments that
    run to the end of the horizon (lags up to N): relative error < 1e-6."""
    sc = coarse_scenario(n_x=20, n_steps=40)
    s = sim = sc.plant
    n_steps = sc.problem.n_steps
    rng = np.random.default_rng(3)
    U = 0.1 + 0.05 * rng.standard_normal((n_steps, s.n_u))
    p = q = 8
    delta = 1e-3
    Xext = nominal_rollout(sim, extend_nominal(U, p + q))
    data = impulse_experiments(sim, U, p + q, q, delta, Xext)
    assert data.Y.shape == (n_steps, p + q, s.n_y, s.n_u) and data.Yf.shape == (n_steps, q, s.n_x, s.n_u)
    assert data.experiments == 2 * n_steps * s.n_u
    real, _ = tv_era(data, n_steps, p, q, n_r=20)
    long = impulse_experiments(sim, U, n_steps, 1, delta)
    np.testing.assert_allclose(long.Y[:, : p + q], data.Y, rtol=1e-12, atol=1e-14)   # same experiments
    Yr = real.markov_all(n_steps)
    valid = (np.arange(n_steps)[:, None] + np.arange(1, n_steps + 1)[None, :]) <= n_steps
    assert rel(Yr[valid], long.Y[valid]) < 1e-6
    # the field map reproduces the recorded field responses at lag 1 (the whole field, not 5 sensors)
    G = np.stack([real.G.matrix(k) for k in range(1, n_steps + 1)])
    np.testing.assert_allclose(np.einsum("jxr,jru->jxu", G, real.B), data.Yf[:, 0],
                               rtol=0, atol=1e-6 * np.abs(data.Yf[:, 0]).max())


def test_impulse_experiments_are_central_differences_of_the_black_box():
    """One Markov parameter recomputed by hand from two perturbed rollouts."""
    sc = coarse_scenario(n_x=20, n_steps=40)
    s = sim = sc.plant
    n_steps = sc.problem.n_steps
    U = np.full((n_steps, s.n_u), 0.2)
    delta = 1e-3
    data = impulse_experiments(sim, U, 6, 3, delta)
    j, c = 7, 3
    Up, Um = extend_nominal(U, 6), extend_nominal(U, 6)
    Up[j, c] += delta
    Um[j, c] -= delta
    Xp, Xm = nominal_rollout(sim, Up), nominal_rollout(sim, Um)
    for lag in range(1, 7):
        want = (sim.observe(Xp[j + lag]) - sim.observe(Xm[j + lag])) / (2 * delta)
        np.testing.assert_allclose(data.Y[j, lag - 1, :, c], want, rtol=1e-9, atol=1e-12)
    for lag in range(1, 4):
        want = (Xp[j + lag] - Xm[j + lag]) / (2 * delta)
        np.testing.assert_allclose(data.Yf[j, lag - 1, :, c], want, rtol=1e-9, atol=1e-12)
    # last input step: the held extension past N supplies the later lags
    j = n_steps - 1
    Up, Um = extend_nominal(U, 6), extend_nominal(U, 6)
    Up[j, 0] += delta
    Um[j, 0] -= delta
    want = (sim.observe(nominal_rollout(sim, Up)[j + 6]) - sim.observe(nominal_rollout(sim, Um)[j + 6])) / (2 * delta)
    np.testing.assert_allclose(data.Y[j, 5, :, 0], want, rtol=1e-9, atol=1e-12)


def test_forward_impulses_are_one_sided_differences_against_the_nominal():
    """scheme='forward': one perturbed run per impulse, differenced against the nominal run;
    half the experiments of 'central', and within O(delta) of its Markov parameters."""
    sc = coarse_scenario(n_x=20, n_steps=40)
    sim = sc.plant
    n_steps = sc.problem.n_steps
    U = np.full((n_steps, sim.n_u), 0.2)
    delta = 1e-3
    fwd = impulse_experiments(sim, U, 6, 3, delta, scheme="forward")
    cen = impulse_experiments(sim, U, 6, 3, delta)
    assert fwd.experiments == n_steps * sim.n_u == cen.experiments // 2
    j, c = 7, 3
    Up = extend_nominal(U, 6)
    Up[j, c] += delta
    Xp, X0 = nominal_rollout(sim, Up), nominal_rollout(sim, extend_nominal(U, 6))
    for lag in range(1, 7):
        want = (sim.observe(Xp[j + lag]) - sim.observe(X0[j + lag])) / delta
        np.testing.assert_allclose(fwd.Y[j, lag - 1, :, c], want, rtol=1e-8, atol=1e-11)
    for lag in range(1, 4):
        np.testing.assert_allclose(fwd.Yf[j, lag - 1, :, c], (Xp[j + lag] - X0[j + lag]) / delta,
                                   rtol=1e-8, atol=1e-11)
    # the one-sided bias is first order in delta: small here, and it halves with delta
    err = rel(fwd.Y, cen.Y)
    assert 0 < err < 1e-4
    half = rel(impulse_experiments(sim, U, 6, 3, delta / 2, scheme="forward").Y, cen.Y)
    assert 0.4 < half / err < 0.6


class LTVPlant:
    """The known LTV system as a black box: the state carries the step counter (x = [k, z])."""

    def __init__(self, A, B, C, F):
        self.A, self.B, self.C, self.F = A, B, C, F
        self.n_x, self.n_u, self.n_y, self.n_field = 1 + A.shape[1], B.shape[2], C.shape[1], F.shape[1]

    def initial_state(self, batch):
        return np.zeros((batch, self.n_x))

    def step(self, x, u, w=None):
        k = int(round(x[0, 0]))
        u = np.broadcast_to(u, (x.shape[0], self.n_u)) + (0 if w is None else w)
        z = x[:, 1:] @ self.A[k].T + u @ self.B[k].T
        return np.column_stack([x[:, 0] + 1, z])

    def observe(self, x):
        return x[:, 1:] @ self.C[int(round(x[0, 0]))].T

    def field(self, x):
        return x[:, 1:] @ self.F[int(round(x[0, 0]))].T


def test_forward_and_central_agree_on_a_linear_system(known_system):
    """No bias at all when the black box is linear: both schemes give the exact Markov parameters."""
    A, B, C, F, Y, _, _ = known_system
    plant = LTVPlant(A, B, C, F)
    U = np.zeros((N, N_U))
    fwd = impulse_experiments(plant, U, P + Q, Q, 0.5, scheme="forward")
    cen = impulse_experiments(plant, U, P + Q, Q, 0.5)
    valid = (np.arange(N)[:, None] + np.arange(1, P + Q + 1)[None, :]) <= N
    np.testing.assert_allclose(cen.Y[valid], Y[valid], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fwd.Y[valid], Y[valid], rtol=1e-9, atol=1e-10)


def test_unknown_impulse_scheme_is_refused():
    sc = coarse_scenario(n_x=20, n_steps=10)
    with pytest.raises(ValueError, match="impulse scheme"):
        impulse_experiments(sc.plant, np.zeros((10, sc.plant.n_u)), 4, 2, 1e-3, scheme="sideways")
