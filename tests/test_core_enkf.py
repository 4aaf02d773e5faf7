"""Ensemble Kalman Filter against the exact Kalman filter on a linear-Gaussian system."""
import numpy as np
import pytest

from core_helpers import kalman_filter, stable_matrix
from sep_estimator.enkf import EnsembleKalmanFilter

N_X, N_U, N_Y, STEPS = 4, 2, 2, 30
W_STD, V_STD = 0.5, 0.4


def linear_problem(seed=0):
    rng = np.random.default_rng(seed)
    A = stable_matrix(rng, N_X, 0.95)
    B = rng.standard_normal((N_X, N_U))
    C = rng.standard_normal((N_Y, N_X))
    U = rng.standard_normal((STEPS, N_U))
    # a true trajectory and its noisy observations
    x = np.zeros(N_X)
    Y = np.zeros((STEPS + 1, N_Y))
    for k in range(STEPS):
        x = A @ x + B @ (U[k] + W_STD * rng.standard_normal(N_U))
        Y[k + 1] = C @ x + V_STD * rng.standard_normal(N_Y)
    step = lambda X, Uk: X @ A.T + Uk @ B.T
    observe = lambda X: X @ C.T
    return A, B, C, U, Y, step, observe


def exact(A, B, C, U, Y):
    W, V = np.eye(N_U) * W_STD**2, np.eye(N_Y) * V_STD**2
    m, P = kalman_filter(A, B, C, W, V, np.zeros(N_X), np.zeros((N_X, N_X)), U, Y)
    return m, np.sqrt(np.einsum("kii->ki", P)), P


def enkf_errors(M, seeds, antithetic=False):
    """RMS errors of the EnKF mean / std relative to the KF's (averaged over seeds)."""
    A, B, C, U, Y, step, observe = linear_problem()
    m_kf, s_kf, _ = exact(A, B, C, U, Y)
    em, es = [], []
    for seed in seeds:
        f = EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(seed), antithetic)
        r = f.run(np.zeros((M, N_X)), U, Y)
        assert r.mean.shape == (STEPS + 1, N_X) and r.std.shape == (STEPS + 1, N_X)
        em.append(np.sqrt(np.mean((r.mean[1:] - m_kf[1:]) ** 2)))
        es.append(np.sqrt(np.mean((r.std[1:] - s_kf[1:]) ** 2)))
    scale = np.sqrt(np.mean(s_kf[1:] ** 2))          # typical posterior std
    return np.mean(em) / scale, np.mean(es) / scale


def test_enkf_converges_to_the_kalman_filter_as_the_ensemble_grows():
    small_m, small_s = enkf_errors(100, range(4))
    big_m, big_s = enkf_errors(4000, range(4))
    # sampling error ~ 1/sqrt(M): a factor sqrt(40) ~ 6 between the two
    assert big_m < 0.35 * small_m
    assert big_s < 0.35 * small_s
    # small in absolute terms: a few percent of the posterior std
    assert big_m < 0.05 and big_s < 0.05
    assert small_m > 0.03       # (the small ensemble is visibly noisy: the test can tell)


def test_enkf_full_covariance_approaches_the_kalman_covariance():
    """The ensemble's full covariance (not only the diagonal) after the last analysis."""
    A, B, C, U, Y, step, observe = linear_problem(1)
    _, _, P_kf = exact(A, B, C, U, Y)
    f = EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(3))
    X = np.zeros((8000, N_X))
    for k in range(STEPS):
        X = f.analysis(f.forecast(X, U[k]), Y[k + 1])
    P = np.cov(X.T)
    assert np.linalg.norm(P - P_kf[-1]) < 0.06 * np.linalg.norm(P_kf[-1])


def test_antithetic_forecast_mean_is_the_noise_free_propagation():
    A, B, C, U, Y, step, observe = linear_problem(2)
    rng = np.random.default_rng(5)
    X = rng.standard_normal((64, N_X)) * 3.0
    f = EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(6), antithetic=True)
    for k in range(5):
        Xf = f.forecast(X, U[k])
        np.testing.assert_allclose(Xf.mean(axis=0), A @ X.mean(axis=0) + B @ U[k], rtol=0, atol=1e-10)
        assert np.std(Xf - X @ A.T - U[k] @ B.T) > 0.1          # but noise was applied
        X = Xf


def test_antithetic_ensemble_stays_symmetric_and_unbiased():
    """Linear model, symmetric start: members i and i + M/2 stay mirror images about the mean
    through forecast and analysis, so the mean update is exactly mean + K (y - H mean)."""
    A, B, C, U, Y, step, observe = linear_problem(3)
    f = EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(7), antithetic=True)
    M = 40
    X = np.zeros((M, N_X))
    for k in range(STEPS):
        Xf = f.forecast(X, U[k])
        mean_f = Xf.mean(axis=0)
        Xa = f.analysis(Xf, Y[k + 1])
        dev = Xa - Xa.mean(axis=0)
        np.testing.assert_allclose(dev[: M // 2], -dev[M // 2:], atol=1e-10)
        # the mean follows the (ensemble-gain) Kalman update without sampling noise
        Af = Xf - mean_f
        HA = Af @ C.T
        P_xy, P_yy = Af.T @ HA / (M - 1), HA.T @ HA / (M - 1) + np.eye(N_Y) * V_STD**2
        gain = P_xy @ np.linalg.inv(P_yy)
        np.testing.assert_allclose(Xa.mean(axis=0), mean_f + gain @ (Y[k + 1] - C @ mean_f), atol=1e-10)
        X = Xa


def test_antithetic_needs_an_even_ensemble():
    A, B, C, U, Y, step, observe = linear_problem()
    f = EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(0), antithetic=True)
    with pytest.raises(ValueError, match="even"):
        f.forecast(np.zeros((5, N_X)), U[0])


def test_enkf_is_reproducible_with_the_same_generator():
    A, B, C, U, Y, step, observe = linear_problem()
    runs = [EnsembleKalmanFilter(step, observe, W_STD, V_STD, np.random.default_rng(11)).run(
        np.zeros((50, N_X)), U, Y) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].mean, runs[1].mean)
    np.testing.assert_array_equal(runs[0].std, runs[1].std)
