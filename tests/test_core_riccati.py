"""Finite-horizon Riccati recursions vs scipy's DARE; the online ROM Kalman filter."""
import numpy as np
import pytest
from scipy.linalg import solve_discrete_are

from core_helpers import ltv_system, stable_matrix
from sep_control.design.gains import command, output_weights, tv_lqr
from sep_estimator.ltv import LQG, DenseFieldMap, LTVModel, field_std
from sep_estimator.tvkf import (KalmanFilter, kalman_gains, schedule_from_posteriors,
                                open_loop_covariance)


def lti(seed, n=5, n_u=2, n_y=3, radius=1.1):
    rng = np.random.default_rng(seed)
    A = stable_matrix(rng, n, radius)          # spectral norm 1.1: possibly unstable
    B = rng.standard_normal((n, n_u))
    C = rng.standard_normal((n_y, n))
    return A, B, C


@pytest.mark.parametrize("seed", [0, 1])
def test_tv_lqr_converges_to_the_dare(seed):
    A, B, C = lti(seed)
    n, n_u = B.shape
    N = 400
    Qm = C.T @ C + 0.1 * np.eye(n)
    R = np.diag([0.5, 2.0])
    K, S = tv_lqr(np.broadcast_to(A, (N, n, n)), np.broadcast_to(B, (N, n, n_u)),
                  np.broadcast_to(Qm, (N + 1, n, n)), R)
    assert K.shape == (N, n_u, n) and S.shape == (N + 1, n, n)
    P = solve_discrete_are(A, B, Qm, R)
    K_inf = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    np.testing.assert_allclose(S[0], P, rtol=1e-9, atol=1e-9 * np.abs(P).max())
    np.testing.assert_allclose(K[0], K_inf, rtol=1e-9, atol=1e-9 * np.abs(K_inf).max())
    # the terminal condition and symmetry
    np.testing.assert_array_equal(S[N], Qm)
    np.testing.assert_allclose(S, S.transpose(0, 2, 1), atol=1e-12 * np.abs(P).max())
    # u = K x is stabilizing
    assert np.max(np.abs(np.linalg.eigvals(A + B @ K[0]))) < 1.0


def test_tv_lqr_is_optimal_on_a_short_horizon():
    """x0' S_0 x0 is the minimum of the finite-horizon cost: brute force by least squares."""
    rng = np.random.default_rng(3)
    N, n, n_u = 6, 3, 2
    A = rng.standard_normal((N, n, n))
    B = rng.standard_normal((N, n, n_u))
    Qs = np.stack([np.eye(n) * (1 + k) for k in range(N + 1)])
    R = np.eye(n_u) * 0.3
    K, S = tv_lqr(A, B, Qs, R)
    x0 = rng.standard_normal(n)

    def cost(Uflat):
        x, J = x0, 0.0
        for k in range(N):
            u = Uflat[k * n_u:(k + 1) * n_u]
            J += x @ Qs[k] @ x + u @ R @ u
            x = A[k] @ x + B[k] @ u
        return J + x @ Qs[N] @ x

    # the cost is quadratic in U: minimize exactly through its Hessian and gradient
    m = N * n_u
    E = np.eye(m)
    J0 = cost(np.zeros(m))
    H = np.array([[cost(E[i] + E[j]) - cost(E[i]) - cost(E[j]) + J0 for j in range(m)] for i in range(m)])
    g = np.array([cost(E[i]) - cost(-E[i]) for i in range(m)]) / 2
    U_opt = -np.linalg.solve(H, g)
    assert cost(U_opt) == pytest.approx(x0 @ S[0] @ x0, rel=1e-9)
    # and the closed-loop feedback attains it
    x, U_fb = x0, []
    for k in range(N):
        U_fb.append(K[k] @ x)
        x = A[k] @ x + B[k] @ U_fb[-1]
    np.testing.assert_allclose(np.concatenate(U_fb), U_opt, rtol=1e-7, atol=1e-9)


def test_kalman_gains_converge_to_the_steady_state_filter():
    A, B, C = lti(4, radius=0.97)
    n, n_u = B.shape
    n_y = C.shape[0]
    N = 600
    W = np.diag([0.09, 0.2])
    V = np.eye(n_y) * 0.5
    kf = kalman_gains(model(np.broadcast_to(A, (N, n, n)), np.broadcast_to(B, (N, n, n_u)),
                            np.broadcast_to(C, (N + 1, n_y, n))), W, V)
    # dual DARE: prior covariance P = A P A' - A P C'(C P C' + V)^-1 C P A' + B W B'
    P = solve_discrete_are(A.T, C.T, B @ W @ B.T, V)
    L = P @ C.T @ np.linalg.inv(C @ P @ C.T + V)
    P_post = P - L @ C @ P
    tol = dict(rtol=1e-8, atol=1e-10 * np.abs(P).max())
    np.testing.assert_allclose(kf.P_prior[-1], P, **tol)
    np.testing.assert_allclose(kf.L[-1], L, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(kf.P_post[-1], P_post, **tol)
    # P_{0|-1} = 0 (known initial state): no gain at k = 0
    assert np.all(kf.P_prior[0] == 0) and np.all(kf.L[0] == 0)


def model(A, B, C, G=None):
    G = np.zeros((C.shape[0], 1, A.shape[1])) if G is None else G
    return LTVModel(A, B, C, DenseFieldMap(G), dims=np.full(C.shape[0], A.shape[1]))


def RomKalmanFilter(A, B, C, G, L, P_post, P_prior, W, V, batch=1, field_std=None):
    """A KalmanFilter on (A, B, C, G) with the given schedule (optionally a precomputed field std)."""
    from sep_estimator.ltv import KalmanSchedule

    lqg = LQG("test", model(A, B, C, G), np.zeros((A.shape[0], B.shape[2], A.shape[1])),
              KalmanSchedule(L, P_post, P_prior), W, V, field_std)
    return KalmanFilter(lqg, batch)


def ltv_schedule(seed=5, N=25, n=4, n_u=2, n_y=3, n_x=7):
    rng = np.random.default_rng(seed)
    A, B, C, G = ltv_system(rng, N, n, n_u, n_y, n_x, radius=0.95)
    W = np.eye(n_u) * 0.3**2
    V = np.eye(n_y) * 1.0
    return A, B, C, G, W, V, kalman_gains(model(A, B, C, G), W, V)


def reference_filter(A, B, C, W, V, P, a, k_from, k_to, dys, dus, skips=()):
    """Straightforward KF (standard-form update) from step k_from with prior (a, P)."""
    out = []
    for k in range(k_from, k_to):
        if k not in skips:
            S = C[k] @ P @ C[k].T + V
            Lk = P @ C[k].T @ np.linalg.inv(S)
            a = a + (dys[k] - a @ C[k].T) @ Lk.T
            P = P - Lk @ S @ Lk.T
        out.append((a.copy(), P.copy()))
        if k == A.shape[0]:
            break
        a = a @ A[k].T + dus[k] @ B[k].T
        P = A[k] @ P @ A[k].T + B[k] @ W @ B[k].T
    return out


def test_schedule_matches_reference_filter():
    A, B, C, G, W, V, kf = ltv_schedule()
    N = A.shape[0]
    rng = np.random.default_rng(0)
    dys, dus = rng.standard_normal((N + 1, 3)), rng.standard_normal((N, 2))
    ref = reference_filter(A, B, C, W, V, np.zeros((4, 4)), np.zeros((1, 4)), 0, N, dys, dus)
    f = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V)
    for k in range(N):
        a = f.update(k, dys[k])
        np.testing.assert_allclose(a, ref[k][0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(kf.P_post[k], ref[k][1], rtol=1e-9, atol=1e-12)
        f.predict(k, dus[k])


def test_batched_filter_equals_per_run_filters():
    A, B, C, G, W, V, kf = ltv_schedule()
    N, M = A.shape[0], 6
    rng = np.random.default_rng(1)
    dys = rng.standard_normal((N + 1, M, 3))
    dus = rng.standard_normal((N, M, 2))
    batch = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V, batch=M)
    singles = [RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V) for _ in range(M)]
    skip_at = 9                                  # a missed measurement in every filter, same step
    for k in range(N + 1):
        if k == skip_at:
            batch.skip(k)
            for f in singles:
                f.skip(k)
        else:
            batch.update(k, dys[k])
            for m, f in enumerate(singles):
                f.update(k, dys[k, m])
        np.testing.assert_allclose(batch.a, np.vstack([f.a for f in singles]), rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(batch.field_deviation(), np.vstack([f.field_deviation() for f in singles]),
                                   rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(batch.field_std(), singles[0].field_std(), rtol=1e-12)
        if k < N:
            batch.predict(k, dus[k])
            for m, f in enumerate(singles):
                f.predict(k, dus[k, m])


def test_skip_then_online_covariance_is_the_filter_without_that_update():
    A, B, C, G, W, V, kf = ltv_schedule()
    N = A.shape[0]
    rng = np.random.default_rng(2)
    dys, dus = rng.standard_normal((N + 1, 3)), rng.standard_normal((N, 2))
    skips = {7, 8, 15}
    ref = reference_filter(A, B, C, W, V, np.zeros((4, 4)), np.zeros((1, 4)), 0, N + 1, dys, dus, skips)
    f = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V, field_std=np.zeros((N + 1, 7)))
    for k in range(N + 1):
        if k in skips:
            a_before = f.a.copy()
            f.skip(k)
            np.testing.assert_array_equal(f.a, a_before)
        else:
            f.update(k, dys[k])
        assert f.on_schedule == (k < 7)
        np.testing.assert_allclose(f.a, ref[k][0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(f.P, ref[k][1], rtol=1e-9, atol=1e-12)
        # the reported field std follows the online covariance, not the stored schedule (zeros here)
        want = np.sqrt(np.diag(G[k] @ ref[k][1] @ G[k].T))
        np.testing.assert_allclose(f.field_std(), want if k >= 7 else 0.0, rtol=1e-9)
        if k < N:
            f.predict(k, dus[k])
    # after the skips the covariance is larger than the schedule's (less information)
    assert np.trace(ref[N][1]) > np.trace(kf.P_post[N])


def test_restart_at_gives_zero_estimate_and_open_loop_covariance():
    A, B, C, G, W, V, kf = ltv_schedule()
    N = A.shape[0]
    f = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V, batch=3)
    rng = np.random.default_rng(3)
    for k in range(5):
        f.update(k, rng.standard_normal((3, 3)))
        f.predict(k, rng.standard_normal((3, 2)))
    k0 = 11
    f.restart_at(k0)
    assert np.all(f.a == 0) and f.a.shape == (3, 4) and f.k == k0
    # by hand: P_k = sum_{j<k} Phi(k, j+1) B_j W B_j' Phi(k, j+1)'
    P = np.zeros((4, 4))
    for j in range(k0):
        Phi = np.eye(4)
        for i in range(j + 1, k0):
            Phi = A[i] @ Phi
        P += Phi @ B[j] @ W @ B[j].T @ Phi.T
    np.testing.assert_allclose(f.P, P, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(open_loop_covariance(A, B, W, k0), P, rtol=1e-10, atol=1e-12)
    # and it filters on from there like the reference filter started from that prior
    dys, dus = rng.standard_normal((N + 1, 3, 3)), rng.standard_normal((N, 3, 2))
    ref = reference_filter(A, B, C, W, V, P, np.zeros((3, 4)), k0, N, dys, dus)
    for k in range(k0, N):
        f.update(k, dys[k])
        np.testing.assert_allclose(f.a, ref[k - k0][0], rtol=1e-9, atol=1e-12)
        f.predict(k, dus[k])
    # restart at 0 is the scheduled filter again
    f.restart_at(0)
    assert f.on_schedule and np.all(f.P == 0)


def test_out_of_order_calls_raise():
    A, B, C, G, W, V, kf = ltv_schedule()
    f = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V)
    dy, du = np.zeros(3), np.zeros(2)
    with pytest.raises(RuntimeError):
        f.predict(0, du)                 # predict before the update of step 0
    with pytest.raises(RuntimeError):
        f.update(1, dy)                  # wrong step
    f.update(0, dy)
    with pytest.raises(RuntimeError):
        f.update(0, dy)                  # twice
    with pytest.raises(RuntimeError):
        f.skip(0)                        # skip after the update
    with pytest.raises(RuntimeError):
        f.predict(1, du)                 # wrong step
    f.predict(0, du)
    with pytest.raises(RuntimeError):
        f.predict(1, du)                 # predict without update/skip
    f.skip(1)
    f.predict(1, du)
    assert f.k == 2


def test_schedule_from_posteriors_rebuilds_the_priors():
    A, B, C, G, W, V, kf = ltv_schedule()
    sched = schedule_from_posteriors(model(A, B, C, G), kf.L, kf.P_post, W)
    np.testing.assert_allclose(sched.P_prior, kf.P_prior, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(sched.L, kf.L)


def test_noise_input_map_other_than_the_inputs():
    """B_w != B: the covariance propagates with B_w W B_w', the estimate with B du."""
    A, B, C, G, W, V, _ = ltv_schedule()
    rng = np.random.default_rng(9)
    Bw = rng.standard_normal((A.shape[0], 4, 3))
    Ww = np.diag([0.1, 0.2, 0.3])
    m = LTVModel(A, B, C, DenseFieldMap(G), np.full(C.shape[0], 4), Bw=Bw)
    kf = kalman_gains(m, Ww, V)
    P = kf.P_post[0]
    for k in range(3):
        np.testing.assert_allclose(kf.P_prior[k + 1], A[k] @ kf.P_post[k] @ A[k].T + Bw[k] @ Ww @ Bw[k].T,
                                   rtol=1e-12, atol=1e-14)
    assert P.shape == (4, 4)


def test_field_std_formula():
    rng = np.random.default_rng(4)
    G = rng.standard_normal((3, 7, 4))
    L = rng.standard_normal((3, 4, 4))
    P = L @ L.transpose(0, 2, 1)
    want = np.sqrt(np.einsum("kii->ki", G @ P @ G.transpose(0, 2, 1)))
    np.testing.assert_allclose(field_std(G, P), want, rtol=1e-12)
    np.testing.assert_allclose(field_std(G[1], P[1]), want[1], rtol=1e-12)


def test_output_weights_and_command():
    rng = np.random.default_rng(5)
    C = rng.standard_normal((4, 3, 5))
    q = np.array([0.1, 0.2, 1.0, 1.0])
    Q = output_weights(C, q)
    for k in range(4):
        np.testing.assert_allclose(Q[k], q[k] * C[k].T @ C[k], rtol=1e-12)
    K = rng.standard_normal((2, 5))
    a = rng.standard_normal((6, 5))
    u0 = np.array([0.5, -0.5])
    np.testing.assert_allclose(command(u0, K, a, -np.inf, np.inf), u0 + a @ K.T, rtol=1e-14)
    np.testing.assert_array_equal(command(u0, K, a * 100, -1.0, 2.0), np.clip(u0 + 100 * a @ K.T, -1.0, 2.0))


def test_field_std_between_predict_and_update_is_the_prior_std():
    """After predict(k-1) the estimate is a_{k|k-1}: its field std is sqrt(diag(G_k P_{k|k-1} G_k')),
    on schedule as well as off it (the covariance must follow the estimate it describes)."""
    A, B, C, G, W, V, kf = ltv_schedule()
    f = RomKalmanFilter(A, B, C, G, kf.L, kf.P_post, kf.P_prior, W, V, field_std=np.zeros((A.shape[0] + 1, 7)))
    for k in range(6):
        f.update(k, np.zeros(3))
        assert np.all(f.field_std() == 0)          # after the update, on schedule: the precomputed one
        f.predict(k, np.zeros(2))
        want = np.sqrt(np.diag(G[k + 1] @ kf.P_prior[k + 1] @ G[k + 1].T))
        np.testing.assert_allclose(f.field_std(), want, rtol=1e-9)
