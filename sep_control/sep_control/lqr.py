"""Finite-horizon time-varying LQR and the tracking law around the nominal.

For a_{k+1} = A_k a_k + B_k du_k, minimize
    sum_{k<N} (a_k' Q_k a_k + du_k' R du_k) + a_N' Q_N a_N
by the backward Riccati recursion (S_N = Q_N):
    K_k = -(R + B_k' S_{k+1} B_k)^{-1} B_k' S_{k+1} A_k
    S_k = Q_k + A_k' S_{k+1} (A_k + B_k K_k),
so du_k = K_k a_k. On the ROM the state weight comes from the outputs, Q_k = C_k' Q_y,k C_k.

Online: u_k = clip(ubar_k + K_k ahat_{k|k}, u_min, u_max).
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np


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


def command(u_nom_k: np.ndarray, K_k: np.ndarray, a_hat: np.ndarray, u_min: float, u_max: float) -> np.ndarray:
    """u_k = clip(ubar_k + K_k ahat_k); a_hat (M, n) or (n,)."""
    u = u_nom_k + a_hat @ K_k.T
    if np.isfinite(u_min) or np.isfinite(u_max):
        u = np.clip(u, u_min, u_max)
    return u
