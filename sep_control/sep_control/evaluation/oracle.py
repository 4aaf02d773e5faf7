"""Model-based oracle: the same LQG on full-order finite-difference Jacobians.

For comparison only. Around the nominal (xbar_k, ubar_k), central differences of the
plant give the full-order perturbation model
    A_k = df/dx (n_x x n_x),  B_k = df/du (n_x x n_u),  [B_w,k = df/dw],
    C_k = dh/dx (n_y x n_x),  G_k = dfield/dx (n_field x n_x; the identity when field_is_state),
all N steps' 2 (n_x + n_u) perturbed runs stepped as one batch. The LQR and Kalman filter are
the ROM's (same weights, same noise), on n_x states. Its cost grows as n_x^3 per step: the
point of the ROM is not to need it. Perturbing the state vector is the one thing here that
goes beyond the black box (states must be real vectors), acceptable for a comparison.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_estimator.design_file import Design
from sep_estimator.ltv import LQG, DenseFieldMap, IdentityFieldMap, LTVModel
from sep_plant.protocol import Plant, nominal_states, noise_channels

from sep_control.design.gains import design_lqg


def rom_lqg(design: Design) -> LQG:
    return design.lqg


def _central(fn, X: np.ndarray, e: np.ndarray, h: float) -> np.ndarray:
    """(fn(x + h e_i) - fn(x - h e_i)) / 2h for every row x of X (N', n_x) and every e_i:
    (N', n_out, n_e)."""
    n_e, n_x = e.shape[0], X.shape[1]
    chunk = max(1, (1 << 24) // (2 * n_e * n_x))        # ~128 MB of perturbed states at a time
    out = []
    for s in range(0, X.shape[0], chunk):
        Xc = X[s:s + chunk]
        P = np.concatenate([Xc[:, None] + e, Xc[:, None] - e], axis=1).reshape(-1, n_x)
        R = fn(P).reshape(Xc.shape[0], 2, n_e, -1)
        out.append(((R[:, 0] - R[:, 1]) / (2 * h)).transpose(0, 2, 1))
    return np.concatenate(out)


def full_order_model(plant: Plant, X: np.ndarray, U: np.ndarray, dx: float = 1e-3,
                     du: float = 1e-4) -> LTVModel:
    """The full-order LTV model by central differences around the states X (N+1, n_x) and U."""
    if getattr(plant, "state_is_opaque", False):
        raise ValueError("no full-order oracle for a plant whose states are opaque (state_is_opaque, e.g. a "
                         "Co-Simulation FMU's serialized state): it differentiates the step with respect to the state")
    N, n_u = U.shape
    n_x = X.shape[1]
    ex, eu = np.eye(n_x) * dx, np.eye(n_u) * du
    noise_in = bool(getattr(plant, "noise_on_inputs", True))
    n_w = 0 if noise_in else noise_channels(plant)
    # per step: [x+dx e_i, x-dx e_i] (2 n_x runs), [u+du e_c, u-du e_c] (2 n_u), [w+-du e_c] (2 n_w)
    Xp = np.concatenate([X[:N, None] + ex, X[:N, None] - ex,
                         np.repeat(X[:N, None], 2 * (n_u + n_w), axis=1)], axis=1)
    Up = np.concatenate([np.repeat(U[:, None], 2 * n_x, axis=1), U[:, None] + eu, U[:, None] - eu,
                         np.repeat(U[:, None], 2 * n_w, axis=1)], axis=1)
    runs = 2 * (n_x + n_u + n_w)
    Wp = None
    if n_w:
        ew = np.eye(n_w) * du
        Wp = np.concatenate([np.zeros((N, 2 * (n_x + n_u), n_w)), np.repeat(ew[None], N, axis=0),
                             np.repeat(-ew[None], N, axis=0)], axis=1).reshape(-1, n_w)
    R = plant.step(Xp.reshape(-1, n_x), Up.reshape(-1, n_u), Wp).reshape(N, runs, n_x)
    A = ((R[:, :n_x] - R[:, n_x:2 * n_x]) / (2 * dx)).transpose(0, 2, 1)
    o = 2 * n_x
    B = ((R[:, o:o + n_u] - R[:, o + n_u:o + 2 * n_u]) / (2 * du)).transpose(0, 2, 1)
    Bw = None
    if n_w:
        o += 2 * n_u
        Bw = ((R[:, o:o + n_w] - R[:, o + n_w:o + 2 * n_w]) / (2 * du)).transpose(0, 2, 1)
    C = _central(plant.observe, X, ex, dx)                      # (N+1, n_y, n_x)
    if getattr(plant, "field_is_state", False):
        G = IdentityFieldMap(n_x)
    else:
        G = DenseFieldMap(_central(plant.field, X, ex, dx))
    return LTVModel(A=A, B=B, C=C, G=G, dims=np.full(N + 1, n_x, dtype=np.int64), Bw=Bw)


def oracle_lqg(design: Design, plant: Plant | None = None) -> LQG:
    """Full-order LQG around the design's nominal (rebuilds the plant from the design's
    scenario when none is given)."""
    plant = plant if plant is not None else design.scenario.plant
    X = nominal_states(plant, design.nominal.u)
    return design_lqg(full_order_model(plant, X, design.nominal.u), design.problem).lqg("oracle_lqg")
