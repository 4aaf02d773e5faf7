"""Time-varying Kalman filter on a linear time-varying model (the ROM, or the oracle's).

Model (`sep_estimator.ltv.LTVModel`, k = 0..N):
    a_{k+1} = A_k a_k + B_k du_k + B_w,k w_k,  w ~ N(0, W)
    dy_k    = C_k a_k + v_k,                   v ~ N(0, V)
    df_k    = G_k a_k                          (field output map)

The model may be the ROM augmented with disturbance states z = [a; d]
(`sep_estimator.disturbance`): the same recursions on z.

Forward Riccati (offline, `kalman_gains`): P_{0|-1} = P_0 (`LTVModel.P0`: zero when the initial
state is known exactly, blockdiag(0, diag(sigma_0^2)) with disturbance states),
    S_k = C_k P_{k|k-1} C_k' + V,  L_k = P_{k|k-1} C_k' S_k^{-1},
    P_{k|k} = (I - L_k C_k) P_{k|k-1} (I - L_k C_k)' + L_k V L_k'     (Joseph form)
    P_{k+1|k} = A_k P_{k|k} A_k' + B_w,k W B_w,k'.

`KalmanFilter` runs it online for a batch of M runs (M = 1 in a ROS node): it uses the
precomputed gains while every measurement arrives, and propagates its own covariance (the same
formulas) from the first skipped update on.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel, prior_covariances


def measurement_update(P: np.ndarray, C: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gain L = P C' S^{-1} and the Joseph-form posterior covariance."""
    S = C @ P @ C.T + V
    L = np.linalg.solve(S, C @ P).T          # P C' S^{-1}  (S, P symmetric)
    I_LC = np.eye(P.shape[0]) - L @ C
    P_post = I_LC @ P @ I_LC.T + L @ V @ L.T
    return L, 0.5 * (P_post + P_post.T)


def time_update(P: np.ndarray, A: np.ndarray, Bw: np.ndarray, W: np.ndarray) -> np.ndarray:
    P_next = A @ P @ A.T + Bw @ W @ Bw.T
    return 0.5 * (P_next + P_next.T)


def kalman_gains(model: LTVModel, W: np.ndarray, V: np.ndarray, P0: np.ndarray | None = None) -> KalmanSchedule:
    """The Kalman gains of `model`: the forward Riccati recursion (module docstring) for k = 0..N.

    Parameters
    ----------
    model : LTVModel
        The filter's model (A_k, B_w,k, C_k).
    W : ndarray, shape (n_w, n_w)
        Process noise covariance.
    V : ndarray, shape (n_y, n_y)
        Sensor noise covariance.
    P0 : ndarray, shape (n, n), optional
        P_{0|-1}; default the model's prior (`LTVModel.initial_covariance`).

    Returns
    -------
    KalmanSchedule
        L_k, P_{k|k} and P_{k|k-1} for k = 0..N.
    """
    A, Bw, C = model.A, model.noise_input, model.C
    N1, n_y, n = C.shape
    L = np.zeros((N1, n, n_y))
    P_post = np.zeros((N1, n, n))
    P_prior = np.zeros((N1, n, n))
    P = model.initial_covariance() if P0 is None else np.array(P0, dtype=float)
    for k in range(N1):
        P_prior[k] = P
        L[k], P_post[k] = measurement_update(P, C[k], V)
        if k < N1 - 1:
            P = time_update(P_post[k], A[k], Bw[k], W)
    return KalmanSchedule(L, P_post, P_prior)


def schedule_from_posteriors(model: LTVModel, L: np.ndarray, P_post: np.ndarray, W: np.ndarray) -> KalmanSchedule:
    """A schedule from stored gains and posteriors (the priors are recomputed)."""
    return KalmanSchedule(L, P_post, prior_covariances(model, P_post, W))


class KalmanFilter:
    """Online filter for a batch of M runs (M = 1 in the estimator node).

    Per step k: `update(k, dy)` (or `skip(k)` when the measurement is missing or rejected),
    then `predict(k, du_applied)`. `a` holds the current estimate (M, n) of the model's whole
    state (z = [a; d] with disturbance states).

    Parameters
    ----------
    lqg : LQG
        Its model, Kalman schedule, noise covariances and field std schedule.
    batch : int, default 1
        Number of runs M.

    Attributes
    ----------
    a : ndarray, shape (M, n)
        The current estimate of step `k`: zhat_{k|k-1}, or zhat_{k|k} after the update.
    P : ndarray, shape (n, n)
        Its covariance.
    k : int
        The step the estimate refers to.
    posterior : bool
        Whether `a` already includes the measurement of step k.
    on_schedule : bool
        Every update so far happened: the precomputed gains apply (else the filter propagates
        its own covariance).
    """

    def __init__(self, lqg: LQG, batch: int = 1):
        m = lqg.model
        self.model = m
        self.A, self.B, self.Bw, self.C, self.G = m.A, m.B, m.noise_input, m.C, m.G
        self.sched = lqg.kf
        self.W, self.V = lqg.W, lqg.V
        self.P0 = m.initial_covariance()
        self.field_std_sched = lqg.field_std
        self.n = m.n
        self.a = np.zeros((batch, self.n))
        self.P = self.sched.P_prior[0].copy()
        self.k = 0                     # step the current estimate refers to
        self.posterior = False         # whether `a` already includes the measurement of step k
        self.on_schedule = True        # every update so far happened: precomputed gains apply

    # ---------------------------------------------------------------- steps
    def update(self, k: int, dy: np.ndarray) -> np.ndarray:
        """Measurement update at step k with dy = y_k - ybar_k, shape (M, n_y) or (n_y,)."""
        self._expect(k, posterior=False)
        if self.on_schedule:
            L = self.sched.L[k]
            self.P = self.sched.P_post[k]
        else:
            L, self.P = measurement_update(self.P, self.C[k], self.V)
        innov = np.atleast_2d(dy) - self.a @ self.C[k].T
        self.a = self.a + innov @ L.T
        self.posterior = True
        return self.a

    def skip(self, k: int) -> np.ndarray:
        """No usable measurement at step k: keep the prior (covariance not reduced)."""
        self._expect(k, posterior=False)
        if self.on_schedule:
            self.P = self.sched.P_prior[k].copy()
            self.on_schedule = False
        self.posterior = True
        return self.a

    def predict(self, k: int, du: np.ndarray) -> np.ndarray:
        """Time update from k to k+1 with the applied input deviation du_k, (M, n_u) or (n_u,)."""
        self._expect(k, posterior=True)
        self.a = self.a @ self.A[k].T + np.atleast_2d(du) @ self.B[k].T
        if self.on_schedule:
            self.P = self.sched.P_prior[k + 1]
        else:
            self.P = time_update(self.P, self.A[k], self.Bw[k], self.W)
        self.k, self.posterior = k + 1, False
        return self.a

    # ------------------------------------------------------------- outputs
    def innovation_covariance(self, k: int, P_prior: np.ndarray) -> np.ndarray:
        """S_k = C_k P_{k|k-1} C_k' + V."""
        C = self.C[k]
        return C @ P_prior @ C.T + self.V

    def gain_after_update(self) -> np.ndarray:
        """L_k = P_{k|k} C_k' V^{-1} (equal to the Kalman gain of step k): maps a change of the
        prior through the update of step k (used to correct a late input exactly)."""
        C = self.C[self.k]
        return np.linalg.solve(self.V, C @ self.P).T

    def field_deviation(self) -> np.ndarray:
        """G_k a: reconstructed field deviation (M, n_field)."""
        return self.G.apply(self.k, self.a)

    def field_std(self) -> np.ndarray:
        """Per-node std of the field estimate (precomputed while on schedule)."""
        if self.on_schedule and self.posterior:
            return self.field_std_sched[self.k]
        return self.G.std(self.k, self.P)

    def restart_at(self, k: int) -> None:
        """Start (or restart) at step k with no information: a = 0 (the nominal), P = open-loop
        covariance of a_k from the prior P_0. Used by a node that joins or rejoins an episode mid-way."""
        self.a = np.zeros_like(self.a)
        self.P = open_loop_covariance(self.A, self.Bw, self.W, k, self.P0)
        self.k, self.posterior, self.on_schedule = k, False, k == 0

    def _expect(self, k: int, posterior: bool) -> None:
        if k != self.k or self.posterior != posterior:
            state = "after" if self.posterior else "before"
            raise RuntimeError(f"filter is at step {self.k} ({state} its update); got a call for step {k}")


def open_loop_covariance(A: np.ndarray, Bw: np.ndarray, W: np.ndarray, k: int,
                         P0: np.ndarray | None = None) -> np.ndarray:
    """Covariance of a_k with no measurement since a_0 ~ N(0, P0) (P0 None: zero), used to
    restart a filter mid-episode."""
    P = np.zeros((A.shape[1], A.shape[1])) if P0 is None else np.array(P0, dtype=float)
    for j in range(k):
        P = time_update(P, A[j], Bw[j], W)
    return P
