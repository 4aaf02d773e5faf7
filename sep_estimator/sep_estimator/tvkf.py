"""Time-varying Kalman filter on the reduced-order model (ROM).

ROM (zero-padded to n_r, k = 0..N):
    a_{k+1} = A_k a_k + B_k (du_k + w_k),  w ~ N(0, W)
    dy_k    = C_k a_k + v_k,               v ~ N(0, V)
    dT_k    = G_k a_k                      (field output map)

Forward Riccati (offline, `kalman_gains`): P_{0|-1} = 0 (T(x,0) is known exactly),
    S_k = C_k P_{k|k-1} C_k' + V,  L_k = P_{k|k-1} C_k' S_k^{-1},
    P_{k|k} = (I - L_k C_k) P_{k|k-1} (I - L_k C_k)' + L_k V L_k'     (Joseph form)
    P_{k+1|k} = A_k P_{k|k} A_k' + B_k W B_k'.

`RomKalmanFilter` runs it online for a batch of M runs (M = 1 in a ROS node): it
uses the precomputed gains while every measurement arrives, and propagates its own
covariance (the same formulas) from the first skipped update on.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _update(P: np.ndarray, C: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measurement update: gain L and Joseph-form posterior covariance."""
    S = C @ P @ C.T + V
    L = np.linalg.solve(S, C @ P).T          # P C' S^{-1}  (S, P symmetric)
    I_LC = np.eye(P.shape[0]) - L @ C
    P_post = I_LC @ P @ I_LC.T + L @ V @ L.T
    return L, 0.5 * (P_post + P_post.T)


def _predict(P: np.ndarray, A: np.ndarray, B: np.ndarray, W: np.ndarray) -> np.ndarray:
    P_next = A @ P @ A.T + B @ W @ B.T
    return 0.5 * (P_next + P_next.T)


@dataclass
class KalmanSchedule:
    L: np.ndarray        # (N+1, n_r, n_y)
    P_post: np.ndarray   # (N+1, n_r, n_r)
    P_prior: np.ndarray  # (N+1, n_r, n_r)


def kalman_gains(A: np.ndarray, B: np.ndarray, C: np.ndarray, W: np.ndarray, V: np.ndarray,
                 P0: np.ndarray | None = None) -> KalmanSchedule:
    """Forward Riccati recursion for k = 0..N (A, B: N steps; C: N+1 steps)."""
    N1, n_y, n = C.shape
    L = np.zeros((N1, n, n_y))
    P_post = np.zeros((N1, n, n))
    P_prior = np.zeros((N1, n, n))
    P = np.zeros((n, n)) if P0 is None else np.array(P0, dtype=float)
    for k in range(N1):
        P_prior[k] = P
        L[k], P_post[k] = _update(P, C[k], V)
        if k < N1 - 1:
            P = _predict(P_post[k], A[k], B[k], W)
    return KalmanSchedule(L, P_post, P_prior)


def field_std(G: np.ndarray, P: np.ndarray) -> np.ndarray:
    """sqrt(diag(G P G')) per node, for one step (G (n_x, n)) or all steps (G (N+1, n_x, n))."""
    var = np.einsum("...ij,...jk,...ik->...i", G, P, G)
    return np.sqrt(np.maximum(var, 0.0))


class RomKalmanFilter:
    """Online filter for a batch of M runs (M = 1 in the estimator node).

    Per step k: `update(k, dy)` (or `skip(k)` when the measurement is missing or
    rejected), then `predict(k, du_applied)`. `a` holds the current estimate (M, n_r).
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, C: np.ndarray, G: np.ndarray,
                 L: np.ndarray, P_post: np.ndarray, P_prior: np.ndarray, W: np.ndarray,
                 V: np.ndarray, batch: int = 1):
        self.A, self.B, self.C, self.G = A, B, C, G
        self.L_sched, self.P_post_sched, self.P_prior_sched = L, P_post, P_prior
        self.W, self.V = W, V
        self.n = A.shape[1]
        self.a = np.zeros((batch, self.n))
        self.P = P_prior[0].copy()
        self.k = 0                     # step the current estimate refers to
        self.posterior = False         # whether `a` already includes the measurement of step k
        self.on_schedule = True        # every update so far happened: precomputed gains apply

    # ---------------------------------------------------------------- steps
    def update(self, k: int, dy: np.ndarray) -> np.ndarray:
        """Measurement update at step k with dy = y_k - ybar_k, shape (M, n_y) or (n_y,)."""
        self._expect(k, posterior=False)
        if self.on_schedule:
            L = self.L_sched[k]
            self.P = self.P_post_sched[k]
        else:
            L, self.P = _update(self.P, self.C[k], self.V)
        innov = np.atleast_2d(dy) - self.a @ self.C[k].T
        self.a = self.a + innov @ L.T
        self.posterior = True
        return self.a

    def skip(self, k: int) -> np.ndarray:
        """No usable measurement at step k: keep the prior (covariance not reduced)."""
        self._expect(k, posterior=False)
        if self.on_schedule:
            self.P = self.P_prior_sched[k].copy()
            self.on_schedule = False
        self.posterior = True
        return self.a

    def predict(self, k: int, du: np.ndarray) -> np.ndarray:
        """Time update from k to k+1 with the applied input deviation du_k, (M, n_u) or (n_u,)."""
        self._expect(k, posterior=True)
        self.a = self.a @ self.A[k].T + np.atleast_2d(du) @ self.B[k].T
        if self.on_schedule:
            self.P = self.P_prior_sched[k + 1]
        else:
            self.P = _predict(self.P, self.A[k], self.B[k], self.W)
        self.k, self.posterior = k + 1, False
        return self.a

    # ------------------------------------------------------------- outputs
    def field_deviation(self) -> np.ndarray:
        """G_k a: reconstructed field deviation (M, n_x)."""
        return self.a @ self.G[self.k].T

    def field_std(self, precomputed: np.ndarray | None = None) -> np.ndarray:
        """Per-node std of the field estimate; `precomputed[k]` is used while on schedule."""
        if self.on_schedule and precomputed is not None and self.posterior:
            return precomputed[self.k]
        return field_std(self.G[self.k], self.P)

    def restart_at(self, k: int) -> None:
        """Start (or restart) at step k with no information: a = 0 (the nominal), P = open-loop
        covariance of a_k. Used by a node that joins or rejoins an episode mid-way."""
        self.a = np.zeros_like(self.a)
        self.P = open_loop_covariance(self.A, self.B, self.W, k)
        self.k, self.posterior, self.on_schedule = k, False, k == 0

    def _expect(self, k: int, posterior: bool) -> None:
        if k != self.k or self.posterior != posterior:
            state = "after" if self.posterior else "before"
            raise RuntimeError(f"filter is at step {self.k} ({state} its update); got a call for step {k}")


def open_loop_covariance(A: np.ndarray, B: np.ndarray, W: np.ndarray, k: int) -> np.ndarray:
    """Covariance of a_k with no measurement since a_0 (used to restart a filter mid-episode)."""
    P = np.zeros((A.shape[1], A.shape[1]))
    for j in range(k):
        P = _predict(P, A[j], B[j], W)
    return P


def filter_from_schedule(A: np.ndarray, B: np.ndarray, C: np.ndarray, G: np.ndarray, L: np.ndarray,
                         P_post: np.ndarray, w_std: float, v_std: float, batch: int = 1) -> RomKalmanFilter:
    """A `RomKalmanFilter` from stored gains and posteriors (W = w_std^2 I, V = v_std^2 I).

    P_{k|k-1} is rebuilt from the posteriors: P_{0|-1} = 0, P_{k+1|k} = A P_{k|k} A' + B W B'.
    """
    W = np.eye(B.shape[2]) * w_std**2
    V = np.eye(C.shape[1]) * v_std**2
    P_prior = np.zeros_like(P_post)
    P_prior[1:] = A @ P_post[:-1] @ A.transpose(0, 2, 1) + B @ W @ B.transpose(0, 2, 1)
    return RomKalmanFilter(A, B, C, G, L, P_post, P_prior, W, V, batch=batch)


def filter_from_design(design, batch: int = 1) -> RomKalmanFilter:
    """A `RomKalmanFilter` for a loaded `design_file.Design`."""
    s = design.scenario
    return filter_from_schedule(design.A, design.B, design.C, design.G, design.L, design.P_post,
                                s.w_std, s.v_std, batch)
