"""Finite-horizon time-varying LQR and the tracking law around the nominal.

For a_{k+1} = A_k a_k + B_k du_k, minimize
    sum_{k<N} (a_k' Q_k a_k + du_k' R du_k) + a_N' Q_N a_N
by the backward Riccati recursion (S_N = Q_N):
    K_k = -(R + B_k' S_{k+1} B_k)^{-1} B_k' S_{k+1} A_k
    S_k = Q_k + A_k' S_{k+1} (A_k + B_k K_k),
so du_k = K_k a_k. On the ROM the state weight comes from the outputs, Q_k = C_k' Q_y,k C_k.

Online: u_k = clip(ubar_k + K_k ahat_{k|k}, u_min, u_max).
`design_lqg` puts the LQR and the Kalman filter together on one model (ROM or oracle), and
compresses a POD field map to the directions the ROM state reaches (`compress_field_map`).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sep_estimator.ltv import LQG, LTVModel, PODFieldMap, psd_factor
from sep_estimator.tvkf import kalman_gains, schedule_from_posteriors
from sep_plant.problem import Problem

#: relative tolerance of the design's field map against the ROM state's spread
#: (`compress_field_map`, `state_spread`). Measured on the four shipped scenarios (200 closed-loop
#: runs each, the same runs with the full and the compressed map): the reconstructed field moved by
#: at most 9.3e-4 of the largest per-node std (8.3e-5 rms), the 2-sigma coverage not at all (4
#: digits), and Phi shrank 59 -> 24 (reference), 220 -> 70 (plate 64^2), 246 -> 86 (block 24^3),
#: 517 -> 158 (Allen-Cahn) columns
FIELD_MAP_TOL = 1e-5


def tv_lqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gains K (N, n_u, n) and cost-to-go S (N+1, n, n) for A (N, n, n), B (N, n, n_u), Q (N+1, n, n)."""
    N, n, n_u = B.shape
    K = np.zeros((N, n_u, n))
    S = np.zeros((N + 1, n, n))
    S[N] = Q[N]
    for k in range(N - 1, -1, -1):
        Sn, Ak, Bk = S[k + 1], A[k], B[k]
        BtS = Bk.T @ Sn
        K[k] = -np.linalg.solve(R + BtS @ Bk, BtS @ Ak)
        Sk = Q[k] + Ak.T @ Sn @ (Ak + Bk @ K[k])
        S[k] = 0.5 * (Sk + Sk.T)
    return K, S


def output_weights(C: np.ndarray, q_y: np.ndarray) -> np.ndarray:
    """Q_k = C_k' (q_y,k I) C_k for all k (C (N+1, n_y, n), q_y (N+1,))."""
    return q_y[:, None, None] * np.einsum("kyi,kyj->kij", C, C)


def command(u_nom_k: np.ndarray, K_k: np.ndarray, a_hat: np.ndarray, u_min, u_max) -> np.ndarray:
    """u_k = clip(ubar_k + K_k ahat_k); a_hat (M, n) or (n,); limits scalars or (n_u,)."""
    u = u_nom_k + a_hat @ K_k.T
    if np.any(np.isfinite(u_min)) or np.any(np.isfinite(u_max)):
        u = np.clip(u, u_min, u_max)
    return u


def state_spread(model: LTVModel, K: np.ndarray, kf, V: np.ndarray) -> np.ndarray:
    """X_k = P_k|k + cov(ahat_k) in closed loop + cov(ahat_k) in open loop (N+1, n, n): covers the
    ROM state's covariance with the LQG running (P_k|k + the closed-loop estimate's, which moves
    along B_k through the feedback) and without it (P_k|k + the open-loop estimate's)."""
    return (kf.P_post + estimate_covariances(model, K, kf, V, closed_loop=True)
            + estimate_covariances(model, K, kf, V, closed_loop=False))


def compress_field_map(G: PODFieldMap, X: np.ndarray, tol: float) -> PODFieldMap:
    """G_k = Phi g_k on fewer directions: the SVD U S V' of [g_0 L_0 ... g_N L_N], X_k = L_k L_k'
    (X (N+1, n, n): the state spread, `state_spread`), keeps U_r, the directions with
    S > tol S_1: Phi' = Phi U_r (still orthonormal), g_k' = U_r' g_k.

    What is dropped moves the field by less than tol times its largest spread, both the
    reconstructed mean and the std. Neither the LQR (weights on the outputs) nor the filter (it
    reads the outputs) uses G, so the gains do not change."""
    gL = G.g @ psd_factor(X)                                   # (N+1, r_f, n)
    U, S, _ = np.linalg.svd(np.concatenate(list(gL), axis=1), full_matrices=False)
    r = int(np.count_nonzero(S > tol * S[0])) if S.size and S[0] > 0 else 0
    Ur = U[:, :max(r, 1)] if G.rank else U[:, :0]
    return PODFieldMap(np.ascontiguousarray(G.Phi @ Ur), np.ascontiguousarray(np.matmul(Ur.T, G.g)))


def design_lqg(model: LTVModel, problem: Problem, name: str = "rom_lqg", map_tol: float | None = None) -> LQG:
    """TV-LQR (weights on the outputs) and TV Kalman filter for `model` under `problem`'s weights
    and noise: Q_k = C_k' Q_y,k C_k, R = lqr_r I, W = diag(w_std^2), V = diag(v_std^2). With
    `map_tol`, a POD field map is compressed against the ROM state's spread with and without
    the feedback (`state_spread`, `compress_field_map`); the gains do not depend on it."""
    Q = output_weights(model.C, problem.lqr_output_weights(model.n_y))
    R = np.eye(model.n_u) * problem.lqr_r
    K, _ = tv_lqr(model.A, model.B, Q, R)
    W, V = problem.noise_covariances(model.noise_input.shape[2], model.n_y)
    kf = kalman_gains(model, W, V)
    if map_tol is not None and isinstance(model.G, PODFieldMap):
        model = replace(model, G=compress_field_map(model.G, state_spread(model, K, kf, V), map_tol))
    # priors from the posteriors, exactly as a loaded design file rebuilds them
    return LQG(name, model, K, schedule_from_posteriors(model, kf.L, kf.P_post, W), W, V)


def estimate_covariances(model: LTVModel, K: np.ndarray, kf, V: np.ndarray, closed_loop: bool = True) -> np.ndarray:
    """Sigma_k = cov(ahat_{k|k}) for k = 0..N (N+1, n, n), limits ignored. The estimate starts at
    0 and grows by the innovations, which are white and orthogonal to it; it moves with the closed
    loop A_k + B_k K_k (du_k = K_k ahat_{k|k}) or, `closed_loop` False, with A_k:
        Sigma_k^+ = Sigma_k^- + L_k (C_k P_k^- C_k' + V) L_k',
        Sigma_{k+1}^- = A_cl,k Sigma_k^+ A_cl,k',   Sigma_0^- = 0.
    The state's covariance is Sigma_k + P_k|k (the estimation error is orthogonal to the estimate)."""
    m = model
    N, n = m.A.shape[0], m.A.shape[1]
    out = np.zeros((N + 1, n, n))
    Sm = np.zeros((n, n))
    for k in range(N + 1):
        C, L = m.C[k], kf.L[k]
        out[k] = Sm + L @ (C @ kf.P_prior[k] @ C.T + V) @ L.T
        if k < N:
            Acl = m.A[k] + m.B[k] @ K[k] if closed_loop else m.A[k]
            Sm = Acl @ out[k] @ Acl.T
    return out


def input_spread(lqg: LQG) -> np.ndarray:
    """sigma_u (N, n_u): the closed-loop std of the feedback du_k = K_k ahat_{k|k} (limits ignored):
    sigma_u,k^2 = diag(K_k Sigma_k K_k'), Sigma_k = cov(ahat_{k|k}) (`estimate_covariances`)."""
    S = estimate_covariances(lqg.model, lqg.K, lqg.kf, lqg.V)[:-1]
    return np.sqrt(np.maximum(np.einsum("kui,kij,kuj->ku", lqg.K, S, lqg.K), 0.0))
