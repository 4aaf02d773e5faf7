"""Model-based oracle: the same LQG on full-order finite-difference Jacobians.

For comparison only. Around the nominal (xbar_k, ubar_k), central differences of the
plant give the full-order perturbation model
    A_k = df/dx (n_x x n_x),  B_k = df/du (n_x x n_u),  [B_w,k = df/dw],
    C_k = dh/dx (n_y x n_x),  G_k = dfield/dx (n_field x n_x; the identity when field_is_state),
all N steps' 2 (n_x + n_u) perturbed runs stepped as one batch. The LQR and Kalman filter are
the ROM's (same weights, same noise), on n_x states. Its cost grows as n_x^3 per step: the
point of the ROM is not to need it. Perturbing the state vector is the one thing here that
goes beyond the black box (states must be real vectors), acceptable for a comparison.

On a truth plant (`sep evaluate --truth/--perturb`, docs/robustness.md) the oracle is the
full-order ideal of the truth that tracks the DESIGN's nominal (`truth_oracle`): the truth's
Jacobians along the design's nominal states, with the truth's known offsets from them as affine
terms (an affine LQR with a feed-forward and an affine Kalman filter).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.design import Design
from sep_estimator.ltv import LQG, DenseFieldMap, IdentityFieldMap, LTVModel
from sep_plant.protocol import Plant, nominal_states, noise_channels

from sep_control.design.gains import GainsResult, design_lqg, lqr_gains
from sep_estimator.tvkf import kalman_gains


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
    scenario when none is given): the design's LQG, disturbance states included (the same input
    directions or sensor biases, prior and walk: they live in input and output space, not in
    the ROM's coordinates), on the full-order Jacobians instead of the ROM."""
    plant = plant if plant is not None else design.scenario.plant
    X = nominal_states(plant, design.nominal.u)
    full = full_order_model(plant, X, design.nominal.u)
    return design_lqg(full, design.problem, design.disturbance).lqg("oracle_lqg")


class OracleUnavailable(ValueError):
    """No full-order oracle on this truth plant (the message says why)."""


@dataclass(frozen=True)
class AffineTerms:
    """What the truth plant's full-order model around the design's nominal adds to the linear one:

        dx_{k+1} = A_k dx_k + B_k du_k + r_k + B_w,k w_k,   dy_k = C_k dx_k + e_k + v_k,
        df_k     = G_k dx_k + g_k,                           dx_0 = a0,

    with dx = x - xbar, du = u - ubar, dy = y - ybar, df = f - fbar around the design's nominal
    (xbar: the model's states under ubar) and the affine LQR's input u_k = ubar_k + kappa_k + K_k dxhat_k.
    """

    u_nom: np.ndarray      # (N, n_u)     ubar_k + kappa_k: the law's nominal input (feed-forward added)
    r: np.ndarray          # (N, n_x)     f_truth(xbar_k, ubar_k) - xbar_{k+1}
    y: np.ndarray          # (N+1, n_y)   h_truth(xbar_k) - ybar_k (a sensor bias, ...)
    field: np.ndarray      # (N+1, n_field) field_truth(xbar_k) - fbar_k
    a0: np.ndarray         # (n_x,)       x_truth,0 - xbar_0 (known exactly, as the initial state is)


@dataclass(frozen=True)
class Oracle:
    """The full-order oracle: its LQG and, on a truth plant, the affine terms (None: linear)."""

    lqg: LQG
    affine: AffineTerms | None = None


# ~45 lines of statements; the rest is the docstring that says why this oracle
# ~65 lines: 46 of them the public function's docstring (the affine LQG it builds) and numpydoc
def truth_oracle(design: Design, truth: Plant, model: Plant | None = None) -> Oracle:
    """The full-order oracle of a truth plant: the ideal controller THERE for the design's goal.

    The design's nominal (xbar_k, ubar_k, ybar_k, fbar_k) is what every controller in the
    evaluation is asked to track, and the metrics measure the field against it. On the truth,
    ubar no longer produces xbar: the truth's own open-loop trajectory under ubar drifts away
    (a boundary held 3 degrees colder, weaker actuators). Linearizing the truth along that
    trajectory would give an LQG that tracks IT, so the "oracle" would be judged against a nominal
    it does not aim at. Instead the truth is linearized along the design's nominal states,

        A_k = df_truth/dx, B_k = df_truth/du, C_k = dh_truth/dx, G_k = dfield_truth/dx  at (xbar_k, ubar_k),

    and its one-step residual r_k = f_truth(xbar_k, ubar_k) - xbar_{k+1}, output and field offsets
    e_k = h_truth(xbar_k) - ybar_k, g_k = field_truth(xbar_k) - fbar_k, and initial offset
    a0 = x_truth,0 - xbar_0 are known affine terms (`AffineTerms`), which an ideal designer with
    the truth's model would know exactly. The LQR for dx_{k+1} = A dx + B du + r with the design's
    weights (Q_k = C_k' Q_y,k C_k, the true outputs' deviation from ybar: a sensor bias is not
    steered away) is affine: with the Riccati recursion's S_k, K_k and s_N = 0,

        kappa_k = -(R + B_k' S_{k+1} B_k)^{-1} B_k' (S_{k+1} r_k + s_{k+1}),
        s_k     = (A_k + B_k K_k)' (S_{k+1} r_k + s_{k+1}),

    u_k = clip(ubar_k + kappa_k + K_k dxhat_k); the Kalman filter (same gains: they do not depend on
    the offsets) starts at a0, predicts with + r_k and updates with dy_k - e_k. The truth's own
    initial state is known exactly, as the model's is to the design. When the truth is the
    model all offsets vanish (r = 0 exactly) and this is `oracle_lqg`; the caller then uses that one.

    Parameters
    ----------
    design : Design
        The design (nominal ubar, ybar, fbar; problem: weights and noise).
    truth : Plant
        The truth plant (`sep_plant.truth.truth_plant(...).plant`).
    model : Plant, optional
        The design's plant (xbar = its states under ubar); rebuilt from the design's scenario
        when None.

    Returns
    -------
    Oracle
        The full-order LQG of the truth along xbar and its affine terms.

    Raises
    ------
    OracleUnavailable
        The truth has another state dimension than the model (xbar is then not a state of it).
    """
    model = model if model is not None else design.scenario.plant
    if int(truth.n_x) != int(model.n_x):
        raise OracleUnavailable(f"the truth plant has n_x = {truth.n_x}, the design's plant n_x = {model.n_x}: "
                                "the design's nominal states are not states of the truth")
    nom, problem = design.nominal, design.problem
    X = nominal_states(model, nom.u)
    lin = full_order_model(truth, X, nom.u)
    K, S, _, R = lqr_gains(lin, problem)
    W, V = problem.noise_covariances(lin.noise_input.shape[2], lin.n_y)
    lqg = GainsResult(lin, K, kalman_gains(lin, W, V), W, V).lqg("oracle_lqg")
    r = np.asarray(truth.step(X[:-1], nom.u)) - X[1:]
    kappa = affine_feedforward(lin, K, S, R, r)
    affine = AffineTerms(u_nom=nom.u + kappa, r=r, y=np.asarray(truth.observe(X)) - nom.y,
                         field=np.asarray(truth.field(X)) - nom.field,
                         a0=np.asarray(truth.initial_state(1))[0] - X[0])
    return Oracle(lqg, affine)


def affine_feedforward(model: LTVModel, K: np.ndarray, S: np.ndarray, R: np.ndarray, r: np.ndarray) -> np.ndarray:
    """kappa (N, n_u): the affine LQR's feed-forward for the known terms r (N, n) of
    x_{k+1} = A_k x_k + B_k u_k + r_k (the `truth_oracle` recursion; K, S from `tv_lqr`)."""
    N = model.n_steps
    kappa = np.zeros((N, model.n_u))
    s = np.zeros(model.n)
    for k in range(N - 1, -1, -1):      # a backward recursion: one step depends on the next
        A, B = model.A[k], model.B[k]
        v = S[k + 1] @ r[k] + s
        kappa[k] = -np.linalg.solve(R + B.T @ S[k + 1] @ B, B.T @ v)
        s = (A + B @ K[k]).T @ v
    return kappa
