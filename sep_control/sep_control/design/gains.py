"""Finite-horizon time-varying LQR and the tracking law around the nominal.

For a_{k+1} = A_k a_k + B_k du_k, minimize
    sum_{k<N} (a_k' Q_k a_k + du_k' R du_k) + a_N' Q_N a_N
by the backward Riccati recursion (S_N = Q_N):
    K_k = -(R + B_k' S_{k+1} B_k)^{-1} B_k' S_{k+1} A_k
    S_k = Q_k + A_k' S_{k+1} (A_k + B_k K_k),
so du_k = K_k a_k. On the ROM the state weight comes from the outputs, Q_k = C_k' Q_y,k C_k, or
(problem key lqr_weighting: field) from the field the design's map reconstructs, f = G_k a + fbar_k:
Q_k = G_k' Q_f,k G_k, Q_f,k = w_k I (`Problem.lqr_field_weights`: mean or sum over the nodes),
computed as w_k G_k' G_k (`FieldMap.gram`: g_k' g_k for a POD map, nothing in n_field), so the
weight between the sensors counts too (`state_weights`). Either way K_k is precomputed: the
online law costs the same.

With disturbance states (`sep_estimator.disturbance`: z = [a; d], d held constant in the
prediction) the same Riccati recursion on the augmented model, A_z = [[A, A_ad], [0, I]],
B_z = [B; 0], Q_z = blockdiag(Q, 0) (the true outputs C a, not the measured C a + F d; or the field G a, which d
does not move),
gives K_k = [K_a,k, K_d,k] (`augmented_lqr`): K_a is the ROM's gain exactly (the a-block of the
recursion does not see d), and
    input kind (A_ad = B E): K_d ~ -E, the bias cancelled as far as R lets it (R weighs du, so
        the Riccati does not cancel where cancelling costs more than it saves; exact
        cancellation du = K_a ahat - E dhat is the R -> 0 limit);
    output kind (A_ad = 0): K_d = 0, a sensor bias is removed from the estimate, never acted on.

Online: u_k = clip(ubar_k + K_k zhat_{k|k}, u_min, u_max).
`design_lqg` puts the LQR and the Kalman filter together on one model (ROM or oracle, with or
without disturbance states): the gains only (`GainsResult`); the design's field map is
compressed afterwards, against the spread these gains give the ROM state
(`sep_control.design.field_map`).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.disturbance import Disturbance, augment, cross_input, noise_covariance
from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel
from sep_estimator.tvkf import kalman_gains, schedule_from_posteriors
from sep_plant.problem import Problem
from sep_plant.protocol import clip_inputs


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


def augmented_lqr(A: np.ndarray, B: np.ndarray, A_ad: np.ndarray, K_a: np.ndarray, S_a: np.ndarray,
                  R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The TV-LQR of the model augmented with n_d constant states d (`sep_estimator.disturbance`),
    from the ROM's gains K_a (N, n_u, n) and cost-to-go S_a (N+1, n, n) (`tv_lqr` on A, B, Q).

    A_z = [[A, A_ad], [0, I]], B_z = [B; 0], Q_z = blockdiag(Q, 0): the recursion of `tv_lqr` on z
    in blocks, S_z = [[S_a, S_ad], [S_ad', S_dd]] (S_ad = 0, S_dd = 0 at N); with S_a, S_ad, S_dd
    at k+1, A, A_ad, B at k and X = A_ad + B K_d:
        K_d,k = -(R + B' S_a B)^{-1} B' (S_a A_ad + S_ad)
        S_ad,k = A' (S_a X + S_ad),   S_dd,k = (A_ad' S_a + S_ad') X + A_ad' S_ad + S_dd.
    The a-block is the ROM's recursion unchanged, so K_z = [K_a, K_d] holds K_a exactly.

    Parameters
    ----------
    A, B : ndarray, shape (N, n, n), (N, n, n_u)
        The ROM.
    A_ad : ndarray, shape (N, n, n_d)
        How d enters the state: B_k E (input kind), 0 (output kind).
    K_a, S_a : ndarray, shape (N, n_u, n), (N+1, n, n)
        The ROM's `tv_lqr` result.
    R : ndarray, shape (n_u, n_u)

    Returns
    -------
    K : ndarray, shape (N, n_u, n + n_d)
    S : ndarray, shape (N+1, n + n_d, n + n_d)
    """
    N, n, n_d = A_ad.shape
    K = np.zeros((N, B.shape[2], n + n_d))
    S = np.zeros((N + 1, n + n_d, n + n_d))
    K[:, :, :n], S[:, :n, :n] = K_a, S_a
    Sad, Sdd = np.zeros((n, n_d)), np.zeros((n_d, n_d))
    for k in range(N - 1, -1, -1):
        Sa, Bk, Ek = S_a[k + 1], B[k], A_ad[k]
        BtS = Bk.T @ Sa
        Kd = -np.linalg.solve(R + BtS @ Bk, BtS @ Ek + Bk.T @ Sad)
        X = Ek + Bk @ Kd
        Sdd = (Ek.T @ Sa + Sad.T) @ X + Ek.T @ Sad + Sdd
        Sdd = 0.5 * (Sdd + Sdd.T)
        Sad = A[k].T @ (Sa @ X + Sad)
        K[k, :, n:] = Kd
        S[k, :n, n:], S[k, n:, :n], S[k, n:, n:] = Sad, Sad.T, Sdd
    return K, S


def output_weights(C: np.ndarray, q_y: np.ndarray) -> np.ndarray:
    """Q_k = C_k' (q_y,k I) C_k for all k (C (N+1, n_y, n), q_y (N+1,))."""
    return q_y[:, None, None] * np.einsum("kyi,kyj->kij", C, C)


def field_weights(G, q_f: np.ndarray) -> np.ndarray:
    """Q_k = G_k' (q_f,k I) G_k = q_f,k G_k' G_k for all k (G a field map of N+1 steps, q_f (N+1,))."""
    return np.stack([q_f[k] * G.gram(k) for k in range(q_f.shape[0])])


def state_weights(model: LTVModel, problem: Problem) -> np.ndarray:
    """Q_k (N+1, n, n) of the LQR on `model` (its own state a, no disturbance states): on the
    outputs, C_k' Q_y,k C_k, or on the reconstructed field, G_k' Q_f,k G_k (problem.lqr_weighting)."""
    if problem.lqr_weighting == "field":
        return field_weights(model.G, problem.lqr_field_weights(model.G.n_field))
    return output_weights(model.C, problem.lqr_output_weights(model.n_y))


def command(u_nom_k: np.ndarray, K_k: np.ndarray, a_hat: np.ndarray, u_min, u_max) -> np.ndarray:
    """u_k = clip(ubar_k + K_k zhat_k); a_hat (M, n) or (n,) the filter's state (with the
    disturbance estimates, if any); limits scalars or (n_u,)."""
    return clip_inputs(u_nom_k + a_hat @ K_k.T, u_min, u_max)


@dataclass(frozen=True)
class GainsResult:
    """The LQG gains designed on one model (`design_lqg`)."""

    model: LTVModel        # the filter's model: the ROM, or the ROM with disturbance states (z = [a; d])
    K: np.ndarray          # (N, n_u, n_z) LQR gains, du_k = K_k zhat_{k|k}
    kf: KalmanSchedule     # the forward Riccati recursion's gains L_k and covariances P_k|k, P_k|k-1
    W: np.ndarray          # (n_w, n_w) process noise covariance (with the disturbance walk's channels)
    V: np.ndarray          # (n_y, n_y) sensor noise covariance
    rom: LTVModel | None = None                # the ROM on a (None: `model`)
    disturbance: Disturbance | None = None     # the disturbance states (None: none)
    problem: Problem | None = None             # the weights they were designed with (`regained`)

    def lqg(self, name: str = "rom_lqg", rom: LTVModel | None = None) -> LQG:
        """The LQG of these gains on `rom` (default: the ROM they were designed on; else the same
        A_k, B_k, C_k with another field map), augmented with the disturbance states. The priors
        are recomputed from the posteriors, exactly as a loaded design file rebuilds them, and the
        field std (`LQG.field_std`) is that of the model's field map."""
        base = self.model if self.rom is None else self.rom
        r = base if rom is None else rom
        m = self.model if rom is None else augment(r, self.disturbance)
        return LQG(name, m, self.K, schedule_from_posteriors(m, self.kf.L, self.kf.P_post, self.W), self.W, self.V,
                   disturbance=self.disturbance, rom=r)


def lqr_gains(rom: LTVModel, problem: Problem, disturbance: Disturbance | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The TV-LQR on the ROM, augmented with `disturbance` (`augmented_lqr`).

    Returns
    -------
    K : ndarray, shape (N, n_u, n_z)
        du_k = K_k z_k.
    S : ndarray, shape (N+1, n_z, n_z)
        The Riccati cost-to-go (the MPC's terminal weight).
    Q : ndarray, shape (N+1, n_z, n_z)
        Q_z,k = blockdiag(Q_k, 0), Q_k = C_k' Q_y,k C_k (the true outputs) or G_k' Q_f,k G_k
        (the field, `state_weights`).
    R : ndarray, shape (n_u, n_u)
        lqr_r I.
    """
    Q = state_weights(rom, problem)
    R = np.eye(rom.n_u) * problem.lqr_r
    K, S = tv_lqr(rom.A, rom.B, Q, R)
    if disturbance is not None:
        K, S = augmented_lqr(rom.A, rom.B, cross_input(rom, disturbance), K, S, R)
        Q = np.pad(Q, ((0, 0), (0, disturbance.n_d), (0, disturbance.n_d)))
    return K, S, Q, R


def design_lqg(model: LTVModel, problem: Problem, disturbance: Disturbance | None = None) -> GainsResult:
    """TV-LQR (weights on the outputs or the field, `state_weights`) and TV Kalman filter for
    `model` under `problem`'s weights and noise: Q_k = C_k' Q_y,k C_k or G_k' Q_f,k G_k, R = lqr_r I, W = diag(w_std^2), V = diag(v_std^2);
    with `disturbance` both on the augmented model z = [a; d] (`sep_estimator.disturbance.augment`,
    `augmented_lqr`; the filter from P_0 = blockdiag(0, diag(sigma_0^2)), W_z with the walk).

    Parameters
    ----------
    model : LTVModel
        The model (a ROM, or the oracle's full-order one).
    problem : Problem
        LQR weights (lqr_q_early, lqr_q_late, lqr_k_switch, lqr_r) and noise stds (w_std, v_std).
    disturbance : Disturbance, optional
        Disturbance states of the filter (`sep_estimator.disturbance.choose`); None: none.

    Returns
    -------
    GainsResult
        K, the Kalman schedule, W and V on the (augmented) model; `GainsResult.lqg(name)` makes the LQG.
    """
    K, _, _, _ = lqr_gains(model, problem, disturbance)
    W, V = problem.noise_covariances(model.noise_input.shape[2], model.n_y)
    z = augment(model, disturbance)
    Wz = noise_covariance(W, disturbance)
    return GainsResult(z, K, kalman_gains(z, Wz, V), Wz, V, model, disturbance, problem)


def regained(gains: GainsResult, rom: LTVModel) -> GainsResult:
    """`gains` with the LQR redesigned on `rom` (the same A_k, B_k, C_k, another field map: the
    compressed one) when its problem weighs the field, so that K and the MPC's weights (`lqr_gains`
    on the design's map) agree; the filter does not change (it does not read the field map).
    Unchanged for the output weighting."""
    p = gains.problem
    if p is None or p.lqr_weighting != "field":
        return gains
    K = lqr_gains(rom, p, gains.disturbance)[0]
    return GainsResult(gains.model, K, gains.kf, gains.W, gains.V, rom, gains.disturbance, p)


def estimate_covariances(model: LTVModel, K: np.ndarray, kf, V: np.ndarray, closed_loop: bool = True) -> np.ndarray:
    """Sigma_k = cov(ahat_{k|k}) for k = 0..N (N+1, n, n), limits ignored. The estimate starts at
    0 and grows by the innovations, which are white and orthogonal to it; it moves with the closed
    loop A_k + B_k K_k (du_k = K_k ahat_{k|k}) or, `closed_loop` False, with A_k:
        Sigma_k^+ = Sigma_k^- + L_k (C_k P_k^- C_k' + V) L_k',
        Sigma_{k+1}^- = A_cl,k Sigma_k^+ A_cl,k',   Sigma_0^- = 0.
    The state's covariance is Sigma_k + P_k|k (the estimation error is orthogonal to the estimate).
    Sigma_0^- = 0 whatever the prior P_0 (`LTVModel.P0`, disturbance states): the estimate starts
    at the prior mean; P_0 enters through P_0^- = P_0 (kf.P_prior[0]), so Sigma_0 + P_0|0 = P_0."""
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
    """sigma_u (N, n_u): the closed-loop std of the feedback du_k = K_k zhat_{k|k} (limits ignored):
    sigma_u,k^2 = diag(K_k Sigma_k K_k'), Sigma_k = cov(zhat_{k|k}) (`estimate_covariances`; with
    disturbance states it includes the spread of K_d dhat under the prior)."""
    S = estimate_covariances(lqg.model, lqg.K, lqg.kf, lqg.V)[:-1]
    return np.sqrt(np.maximum(np.einsum("kui,kij,kuj->ku", lqg.K, S, lqg.K), 0.0))
