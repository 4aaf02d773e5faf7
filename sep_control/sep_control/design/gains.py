"""Finite-horizon time-varying LQR and the tracking law around the nominal.

For a_{k+1} = A_k a_k + B_k du_k, minimize
    sum_{k<N} (a_k' Q_k a_k + du_k' R du_k) + a_N' Q_N a_N
by the backward Riccati recursion (S_N = Q_N):
    K_k = -(R + B_k' S_{k+1} B_k)^{-1} B_k' S_{k+1} A_k
    S_k = Q_k + A_k' S_{k+1} (A_k + B_k K_k),
so du_k = K_k a_k. On the ROM the state weight comes from the outputs, Q_k = C_k' Q_y,k C_k.

Online: u_k = clip(ubar_k + K_k ahat_{k|k}, u_min, u_max).
`design_lqg` puts the LQR and the Kalman filter together on one model (ROM or oracle): the
gains only (`GainsResult`); the design's field map is compressed afterwards, against the
spread these gains give the ROM state (`sep_control.design.field_map`).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel
from sep_estimator.tvkf import kalman_gains, schedule_from_posteriors
from sep_plant.problem import Problem


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


@dataclass(frozen=True)
class GainsResult:
    """The LQG gains designed on one model (`design_lqg`)."""

    model: LTVModel        # the model they were designed on
    K: np.ndarray          # (N, n_u, n) LQR gains, du_k = K_k ahat_{k|k}
    kf: KalmanSchedule     # the forward Riccati recursion's gains L_k and covariances P_k|k, P_k|k-1
    W: np.ndarray          # (n_w, n_w) process noise covariance
    V: np.ndarray          # (n_y, n_y) sensor noise covariance

    def lqg(self, name: str = "rom_lqg", model: LTVModel | None = None) -> LQG:
        """The LQG of these gains on `model` (default: the one they were designed on; else the
        same A_k, B_k, C_k with another field map). The priors are recomputed from the
        posteriors, exactly as a loaded design file rebuilds them, and the field std
        (`LQG.field_std`) is that of the model's field map."""
        m = self.model if model is None else model
        return LQG(name, m, self.K, schedule_from_posteriors(m, self.kf.L, self.kf.P_post, self.W), self.W, self.V)


def design_lqg(model: LTVModel, problem: Problem) -> GainsResult:
    """TV-LQR (weights on the outputs) and TV Kalman filter for `model` under `problem`'s
    weights and noise: Q_k = C_k' Q_y,k C_k, R = lqr_r I, W = diag(w_std^2), V = diag(v_std^2).

    Parameters
    ----------
    model : LTVModel
        The model (a ROM, or the oracle's full-order one).
    problem : Problem
        LQR weights (lqr_q_early, lqr_q_late, lqr_k_switch, lqr_r) and noise stds (w_std, v_std).

    Returns
    -------
    GainsResult
        K, the Kalman schedule, W and V on `model`; `GainsResult.lqg(name)` makes the LQG.
    """
    Q = output_weights(model.C, problem.lqr_output_weights(model.n_y))
    R = np.eye(model.n_u) * problem.lqr_r
    K, _ = tv_lqr(model.A, model.B, Q, R)
    W, V = problem.noise_covariances(model.noise_input.shape[2], model.n_y)
    return GainsResult(model, K, kalman_gains(model, W, V), W, V)


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
