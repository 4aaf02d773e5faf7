"""Model-based oracle: the same LQG on full-order finite-difference Jacobians.

For comparison only. Around the nominal (xbar_k, ubar_k), central differences of the
simulator give the full-order perturbation model
    A_k = df/dx (n_x x n_x),  B_k = df/du (n_x x n_u),  C = dh/dx (n_y x n_x),
all N steps' 2 (n_x + n_u) perturbed runs stepped as one batch. The LQR and Kalman
filter are the ROM's (same weights, same noise), on n_x states; the field estimate is
the state estimate itself (G_k = I). Its cost grows as n_x^3 per step: the point of
the ROM is not to need it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.design_file import Design
from sep_plant.slab import SlabSimulator

from .design import lqg_gains


@dataclass
class LinearLQG:
    """A linear time-varying LQG around the nominal (ROM or full order)."""
    name: str
    A: np.ndarray        # (N, n, n)
    B: np.ndarray        # (N, n, n_u)
    C: np.ndarray        # (N+1, n_y, n)
    G: np.ndarray        # (N+1, n_x, n) field map
    K: np.ndarray        # (N, n_u, n)
    L: np.ndarray        # (N+1, n, n_y)
    P_post: np.ndarray   # (N+1, n, n)
    field_std: np.ndarray  # (N+1, n_x)


def rom_lqg(design: Design) -> LinearLQG:
    return LinearLQG("rom_lqg", design.A, design.B, design.C, design.G, design.K, design.L,
                     design.P_post, design.field_std)


def full_order_jacobians(sim: SlabSimulator, X: np.ndarray, U: np.ndarray, dx: float = 1e-3,
                         du: float = 1e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A (N, n_x, n_x), B (N, n_x, n_u), C (n_y, n_x) by central differences around (X, U)."""
    N, n_u = U.shape
    n_x = X.shape[1]
    ex, eu = np.eye(n_x) * dx, np.eye(n_u) * du
    # per step: [x+dx e_i, x-dx e_i] (2 n_x runs) then [u+du e_c, u-du e_c] (2 n_u runs)
    Xp = np.concatenate([X[:N, None] + ex, X[:N, None] - ex,
                         np.repeat(X[:N, None], 2 * n_u, axis=1)], axis=1)
    Up = np.concatenate([np.repeat(U[:, None], 2 * n_x, axis=1), U[:, None] + eu, U[:, None] - eu], axis=1)
    R = sim.step(Xp.reshape(-1, n_x), Up.reshape(-1, n_u)).reshape(N, 2 * (n_x + n_u), n_x)
    A = ((R[:, :n_x] - R[:, n_x:2 * n_x]) / (2 * dx)).transpose(0, 2, 1)
    B = ((R[:, 2 * n_x:2 * n_x + n_u] - R[:, 2 * n_x + n_u:]) / (2 * du)).transpose(0, 2, 1)
    x0 = X[0]
    C = ((sim.observe(x0 + ex) - sim.observe(x0 - ex)) / (2 * dx)).T
    return A, B, C


def oracle_lqg(design: Design, sim: SlabSimulator | None = None) -> LinearLQG:
    """Full-order LQG around the design's nominal."""
    s = design.scenario
    sim = sim or SlabSimulator(s)
    A, B, C = full_order_jacobians(sim, design.T_nom, design.u_nom)
    Cs = np.broadcast_to(C, (s.n_steps + 1,) + C.shape)
    K, kf = lqg_gains(A, B, Cs, s)
    G = np.broadcast_to(np.eye(s.n_x), (s.n_steps + 1, s.n_x, s.n_x))
    return LinearLQG("oracle_lqg", A, B, Cs, G, K, kf.L, kf.P_post,
                     np.sqrt(np.maximum(np.einsum("kii->ki", kf.P_post), 0.0)))

