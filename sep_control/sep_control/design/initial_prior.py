"""The design's account of an uncertain initial state: initial-condition states on the ROM.

A plant with an initial-state distribution (`sep_plant.initial`: the optional method
``initial_states(seeds)``) starts each run somewhere around its nominal initial state
``initial_state`` (the design's nominal starts there). A TV-ERA ROM cannot represent that
deviation: its state is spanned by the responses to past inputs (n_0 = 0 at step 0), and the
deviation of the initial state moves the outputs and the field from step 0 on, along directions
no input need excite. So the design appends initial-condition (IC) states c to the ROM.

S sampled initial states x_0^(i) are stepped under the nominal input over the whole horizon
(S N plant run-steps, `SAMPLES` draws); their deviations from the nominal trajectory,

    dz^(i) = [dy_0^(i)/s_y; df_0^(i)/s_f; ...; dy_N^(i)/s_y; df_N^(i)/s_f]
    (dy_k = y_k^(i) - ybar_k, df_k = f_k^(i) - fbar_k; s_y, s_f the rms of all dy, all df, so
    that the outputs and the field count alike),

are compressed by a POD (SVD of [dz^(1) ... dz^(S)] = U S V'): the n_c <= `MAX_IC_STATES` leading
trajectory modes with S_j > `IC_TOL` S_1. Mode j's rows at step k give the columns j of
C^c_k (n_y, n_c) and G^c_k (n_field, n_c), and the sample's coordinates c^(i) = U_c' dz^(i) its IC
state. The IC states are constant, and the ROM on z = [a; c] is

    a_{k+1} = A_k a_k + B_k du_k + B_w,k w_k,   c_{k+1} = c_k,
    dy_k = C_k a_k + C^c_k c + v_k,             df_k = G_k a_k + G^c_k c,
    [a_0; c] ~ N(0, P_0),  P_0 = blockdiag(0, cov(c)),  cov(c) = (1/S) sum_i c^(i) c^(i)'
    = diag(S_j^2) / S

(the second moment about 0, the filter's prior mean: the nominal starts from the mean initial
state, and a mean deviation of the free responses, the plant's nonlinearity, counts in it). The
Kalman filter estimates c from the first measurement on; the LQR (whose state weight reads C_z
or G_z with their cross terms) acts on the estimated deviation through K_c. The IC states are
what `fit` says of the sampled deviations: the fraction of their energy the kept modes hold.

A plant without the distribution, or whose draws all equal its initial state (a built-in with
``initial_spread`` 0), leaves the design untouched, bit for bit (`fit_initial_prior` returns
None). A design file keeps the ROM with its IC states and P_0 (member ``rom_P0``).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.ltv import DenseFieldMap, LTVModel, PODFieldMap
from sep_plant.initial import sample_initial_states
from sep_plant.protocol import Plant, fields, outputs, rollout

from sep_control.design.svd import svd

#: sampled initial states whose free responses the IC modes are fitted to
SAMPLES = 64
#: at most this many IC states
MAX_IC_STATES = 8
#: IC modes with a singular value above IC_TOL times the largest are kept
IC_TOL = 1e-3
#: the field basis's new directions (the IC modes' fields outside the ROM's basis) are kept to
#: this relative singular value
BASIS_TOL = 1e-10


@dataclass(frozen=True)
class InitialPrior:
    """The IC modes fitted to sampled free responses (module docstring)."""

    C: np.ndarray            # (N+1, n_y, n_c) C^c_k: the modes' outputs
    G: np.ndarray            # (N+1, n_field, n_c) G^c_k: the modes' fields
    cov: np.ndarray          # (n_c, n_c) cov(c) = diag(S_j^2) / S
    fit: float               # the kept modes' share of the sampled deviations' energy (scaled dz)
    run_steps: int           # plant run-steps the free responses took

    @property
    def n_c(self) -> int:
        return int(self.cov.shape[0])


def fit_initial_prior(plant: Plant, U: np.ndarray, y_nom: np.ndarray, f_nom: np.ndarray,
                      samples: int = SAMPLES, seed: int = 0, max_states: int = MAX_IC_STATES,
                      tol: float = IC_TOL) -> InitialPrior | None:
    """The IC modes of the free responses of `samples` sampled initial states (module docstring).

    Parameters
    ----------
    plant : Plant
        The plant (its optional ``initial_states``).
    U : ndarray, shape (N, n_u)
        The nominal input.
    y_nom, f_nom : ndarray, shape (N+1, n_y), (N+1, n_field)
        The nominal outputs and field (from the nominal initial state).
    samples : int
        S sampled initial states (runs 0..S-1 of `sep_plant.initial.initial_states` under `seed`).
    max_states, tol : int, float
        At most `max_states` modes, those with S_j > tol S_1.

    Returns
    -------
    InitialPrior or None
        None when the plant's initial state is not uncertain (or no draw moves the outputs or field).
    """
    X0 = sample_initial_states(plant, samples, seed)
    if X0 is None:
        return None
    S, N1 = X0.shape[0], y_nom.shape[0]
    X = rollout(plant, X0, U)                                          # (S, N+1, n_x)
    dY = outputs(plant, X) - y_nom[None]                               # (S, N+1, n_y)
    dF = fields(plant, X) - f_nom[None]                                # (S, N+1, n_field)
    del X
    s_y = _rms(dY)
    s_f = _rms(dF)
    if s_y == 0.0 and s_f == 0.0:
        return None
    n_y = dY.shape[2]
    Z = np.concatenate([dY / max(s_y, 1e-300), dF / max(s_f, 1e-300)], axis=2).reshape(S, -1)  # (S, D)
    w, V = np.linalg.eigh(Z @ Z.T)                                     # Z Z' = V S^2 V': modes U = Z' V / S
    order = np.argsort(w)[::-1]
    w, V = np.maximum(w[order], 0.0), V[:, order]
    sv = np.sqrt(w)
    n_c = int(min(max_states, np.count_nonzero(sv > tol * sv[0])))
    modes = (Z.T @ V[:, :n_c]) / sv[:n_c]                              # (D, n_c), orthonormal columns
    modes = modes.reshape(N1, -1, n_c)
    Cc = modes[:, :n_y] * s_y
    Gc = modes[:, n_y:] * s_f
    fit = float(np.sum(w[:n_c]) / np.sum(w))
    return InitialPrior(np.ascontiguousarray(Cc), np.ascontiguousarray(Gc), np.diag(w[:n_c] / S), fit,
                        int(S * (N1 - 1)))


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a ** 2))) if a.size else 0.0


def with_initial_states(rom: LTVModel, prior: InitialPrior | None) -> LTVModel:
    """The ROM on z = [a; c] (module docstring): A_z = blockdiag(A_k, I), B_z = [B_k; 0],
    B_w,z = [B_w,k; 0], C_z = [C_k, C^c_k], G_z = [G_k, G^c_k] (a POD map keeps its basis and
    gains the directions of G^c outside it), dims n_k + n_c, P_0 = blockdiag(P_0 or 0, cov(c));
    `rom` itself when `prior` is None.

    Raises
    ------
    ValueError
        The prior's steps or outputs do not match the ROM's.
    """
    if prior is None:
        return rom
    N, n, n_c = rom.n_steps, rom.n, prior.n_c
    if prior.C.shape[:2] != (N + 1, rom.n_y):
        raise ValueError(f"the initial prior's output modes have shape {prior.C.shape}, the ROM "
                         f"{(N + 1, rom.n_y)} steps x outputs")
    nz = n + n_c
    A = np.zeros((N, nz, nz))
    A[:, :n, :n] = rom.A
    A[:, n:, n:] = np.eye(n_c)
    B = np.concatenate([rom.B, np.zeros((N, n_c, rom.n_u))], axis=1)
    Bw = None if rom.Bw is None else np.concatenate([rom.Bw, np.zeros((N, n_c, rom.Bw.shape[2]))], axis=1)
    C = np.concatenate([rom.C, prior.C], axis=2)
    P0 = np.zeros((nz, nz))
    if rom.P0 is not None:
        P0[:n, :n] = rom.P0
    P0[n:, n:] = prior.cov
    return LTVModel(A=A, B=B, C=C, G=extended_field_map(rom.G, prior.G), dims=np.asarray(rom.dims) + n_c,
                    Bw=Bw, P0=P0)


def extended_field_map(G, Gc: np.ndarray):
    """[G_k, G^c_k] for Gc (N+1, n_field, n_c): a POD map Phi g_k becomes [Phi, Phi_c] [[g_k, Phi' G^c_k],
    [0, Phi_c' G^c_k]], Phi_c an orthonormal basis of the G^c_k columns outside Phi (to `BASIS_TOL`); a
    dense map is stacked as it is."""
    if isinstance(G, PODFieldMap):
        Phi, g = G.Phi, G.g
        N1, n_f, n_c = Gc.shape
        cols = np.moveaxis(Gc, 0, 1).reshape(n_f, -1)                   # (n_field, (N+1) n_c)
        resid = cols - Phi @ (Phi.T @ cols)
        Ur, S, _ = svd(resid)
        scale = float(np.linalg.norm(cols, 2)) if cols.size else 0.0
        r = int(np.count_nonzero(S > BASIS_TOL * scale)) if scale > 0 else 0
        Phi_c = Ur[:, :r]
        Phi_e = np.concatenate([Phi, Phi_c], axis=1)
        g_e = np.zeros((N1, Phi_e.shape[1], G.n + n_c))
        g_e[:, :Phi.shape[1], :G.n] = g
        g_e[:, :, G.n:] = np.einsum("fr,kfc->krc", Phi_e, Gc)
        return PODFieldMap(np.ascontiguousarray(Phi_e), g_e)
    return DenseFieldMap(np.concatenate([np.stack([G.matrix(k) for k in range(Gc.shape[0])]), Gc], axis=2))
