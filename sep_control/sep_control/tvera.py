"""Time-varying Eigensystem Realization Algorithm (Majji, Juang & Junkins 2010).

Markov parameters of the perturbation system around the nominal,
    Y_{k,j} = C_k A_{k-1} ... A_{j+1} B_j        (response at step k to an input impulse at j < k),
come from impulse-response experiments on the black box (`impulse_experiments`): channel c at
step j perturbed by +-delta (central differences: no O(delta) bias), outputs h(x) and field
f(x) recorded for lags 1..p+q. The channels are the n_u inputs and, for a plant whose process
noise does not enter through the inputs, its n_w noise channels too (then B_w,k is identified
the same way as B_k).

At each step k the generalized Hankel matrix of p future outputs and q_k = min(q, k) past
inputs factors as H_k = O_k R_k:
    H_k[i, m] = Y_{k+i, k-1-m},   H_k = U S V',  O_k = U_n S_n^{1/2},  R_k = S_n^{1/2} V_n'
with n_k the ROM order (<= n_r, singular values below rel_tol * sigma_1 dropped). Then
    C_k = first block row of O_k,   B_{k-1} = first block column of R_k,
    A_k = O_{k+1}^+ H'_k R_k^+,     H'_k[i, m] = Y_{k+1+i, k-1-m}  (shifted Hankel),
so A_k maps the coordinates of step k into those of step k+1 (consistent coordinates).
Near k = 0 only k past inputs exist and n_k grows (0, n_u, 2 n_u, ...), A_k rectangular.
The nominal is extended past N (last input held) so the last Hankel matrices are complete.

The field output map G_k (df_k = G_k a_k) follows from the field Markov parameters of the
same experiments (field snapshots): G_k = Hf_k V_n S_n^{-1/2}, Hf_k[0, m] = Yf_{k, k-1-m}.
Only `plant.step`, `plant.observe`, `plant.field` and state snapshots are used.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.ltv import DenseFieldMap, LTVModel
from sep_plant.protocol import Plant, noise_channels, rollout

from .progress import progress


@dataclass
class MarkovData:
    """Markov parameters from impulse experiments around a nominal of N steps.

    Y[j, l]  = Y_{j+l, j}  (n_y, n_ch) for lags l = 1..L (index l-1), inputs j = 0..N-1;
    Yf[j, l] = Yf_{j+l, j} (n_field, n_ch) field Markov parameters, lags 1..Lf.
    Channels: the n_u inputs, then the noise channels (only when noise is not on the inputs).
    """
    Y: np.ndarray          # (N, L, n_y, n_ch)
    Yf: np.ndarray         # (N, Lf, n_field, n_ch)
    delta: float
    experiments: int
    n_u: int               # the first n_u channels are the inputs

    @property
    def Y_inputs(self) -> np.ndarray:
        return self.Y[..., :self.n_u]


@dataclass
class Identification:
    """A TV-ERA model and what it was identified from."""

    model: LTVModel
    hankel_sv: np.ndarray   # (N+1, n_sv) singular values of H_k (zero padded)
    data: MarkovData
    delta: float            # impulse amplitude
    X_ext: np.ndarray       # (N+1+lags, n_x) nominal states, extended past N
    U: np.ndarray           # (N, n_u) the nominal input it was identified around


def extend_nominal(U: np.ndarray, extra: int) -> np.ndarray:
    """Hold the last input for `extra` steps past N."""
    return np.vstack([U, np.repeat(U[-1:], extra, axis=0)])


def impulse_experiments(plant: Plant, U: np.ndarray, lags: int, field_lags: int, delta: float,
                        Xbar_ext: np.ndarray | None = None, show_progress: bool = False) -> MarkovData:
    """Central-difference impulse responses for every input step j < N and channel c.

    All 2 N n_ch experiments run as one batch in lockstep over global steps; experiment
    (j, c, +-) is active for steps j..j+lags-1 only, so the batch holds at most 2 n_ch lags
    runs. `Xbar_ext` is the nominal over N + lags steps (computed if None).
    """
    N, n_u = U.shape
    U_ext = extend_nominal(U, lags)
    if Xbar_ext is None:
        Xbar_ext = rollout(plant, plant.initial_state(1), U_ext)[0]
    n_w = 0 if getattr(plant, "noise_on_inputs", True) else noise_channels(plant)
    n_ch = n_u + n_w
    n_y, n_f, n_x = int(plant.n_y), int(plant.n_field), int(plant.n_x)
    Y = np.zeros((N, lags, n_y, n_ch))
    Yf = np.zeros((N, field_lags, n_f, n_ch))
    # per start step: [+delta e_c for every channel, -delta e_c for every channel]
    pert = np.vstack([np.eye(n_ch), -np.eye(n_ch)]) * delta        # (2 n_ch, n_ch)
    X = np.empty((0, n_x))
    starts: list[int] = []
    steps = progress(range(N + lags - 1), desc="TV-ERA experiments", enabled=show_progress)
    for k in steps:
        if starts and starts[0] + lags <= k:        # oldest experiments are complete
            starts.pop(0)
            X = X[2 * n_ch:]
        if k < N:
            starts.append(k)
            X = np.vstack([X, np.repeat(Xbar_ext[k][None], 2 * n_ch, axis=0)])
        if not starts:
            continue
        Uk = np.repeat(U_ext[k][None], X.shape[0], axis=0)
        Wk = np.zeros((X.shape[0], n_w)) if n_w else None
        if k < N:
            Uk[-2 * n_ch:] += pert[:, :n_u]
            if n_w:
                Wk[-2 * n_ch:] += pert[:, n_u:]
        X = plant.step(X, Uk, Wk)
        # record lag k+1-j for every active experiment j
        j = np.asarray(starts)
        lag = k + 1 - j                                           # 1..lags
        Yo = plant.observe(X).reshape(len(starts), 2, n_ch, n_y)
        Y[j, lag - 1] = ((Yo[:, 0] - Yo[:, 1]) / (2 * delta)).transpose(0, 2, 1)
        keep = lag <= field_lags
        if np.any(keep):
            rows = np.flatnonzero(np.repeat(keep, 2 * n_ch))
            Ff = plant.field(X[rows]).reshape(int(keep.sum()), 2, n_ch, n_f)
            Yf[j[keep], lag[keep] - 1] = ((Ff[:, 0] - Ff[:, 1]) / (2 * delta)).transpose(0, 2, 1)
    return MarkovData(Y, Yf, delta, 2 * N * n_ch, n_u)


def identify(plant: Plant, U: np.ndarray, p: int, q: int, n_r: int, sv_tol: float = 1e-10,
             impulse: float = 0.01, show_progress: bool = False) -> Identification:
    """TV-ERA around the nominal input U.

    The nominal is extended p+q steps past N (last input held) so every Hankel matrix up to
    k = N is complete; the impulse amplitude delta is `impulse` times the RMS nominal input.
    """
    N = U.shape[0]
    lags = p + q
    X_ext = rollout(plant, plant.initial_state(1), extend_nominal(U, lags))[0]
    delta = impulse * max(float(np.sqrt(np.mean(U**2))), 1e-3)
    data = impulse_experiments(plant, U, lags, q, delta, X_ext, show_progress=show_progress)
    model, sv = tv_era(data, N, p, q, n_r, sv_tol, show_progress=show_progress)
    return Identification(model, sv, data, delta, X_ext, np.array(U, dtype=float))


def _hankel(Y: np.ndarray, k: int, p: int, q_k: int, shift: int) -> np.ndarray:
    """[Y_{k+shift+i, k-1-m}] for i < p, m < q_k as a (p n_y, q_k n_ch) matrix."""
    _, L, n_y, n_ch = Y.shape
    H = np.empty((p, n_y, q_k, n_ch))
    for m in range(q_k):
        j = k - 1 - m
        lags = np.arange(p) + shift + m + 1          # (k + shift + i) - j
        H[:, :, m, :] = Y[j, lags - 1]
    return H.reshape(p * n_y, q_k * n_ch)


def tv_era(data: MarkovData, N: int, p: int, q: int, n_r: int, rel_tol: float = 1e-10,
           show_progress: bool = False) -> tuple[LTVModel, np.ndarray]:
    """Realize (A_k, B_k, C_k, G_k) for k = 0..N from Markov parameters (needs lags >= p+q).

    Returns the model (B_w split off when there are noise channels) and the Hankel singular
    values (N+1, n_sv)."""
    Y, Yf = data.Y, data.Yf
    _, L, n_y, n_ch = Y.shape
    n_f = Yf.shape[2]
    if L < p + q:
        raise ValueError(f"need Markov parameters up to lag p+q = {p + q}, have {L}")
    if Yf.shape[1] < q:
        raise ValueError(f"need field Markov parameters up to lag q = {q}, have {Yf.shape[1]}")
    n_sv = min(p * n_y, q * n_ch)
    dims = np.zeros(N + 1, dtype=np.int64)
    A = np.zeros((N, n_r, n_r))
    B = np.zeros((N, n_r, n_ch))
    C = np.zeros((N + 1, n_y, n_r))
    G = np.zeros((N + 1, n_f, n_r))
    sv = np.zeros((N + 1, n_sv))
    # O_k^+ = S^{-1/2} U',  R_k^+ = V S^{-1/2} for every k (needed one step ahead)
    O_pinv: list[np.ndarray | None] = [None] * (N + 1)
    R_pinv: list[np.ndarray | None] = [None] * (N + 1)
    for k in progress(range(N + 1), desc="TV-ERA realization", enabled=show_progress):
        q_k = min(q, k)
        if q_k == 0:
            continue
        H = _hankel(Y, k, p, q_k, 0)
        Us, S, Vt = np.linalg.svd(H, full_matrices=False)
        sv[k, :S.size] = S
        n = int(min(n_r, np.sum(S > rel_tol * S[0]))) if S[0] > 0 else 0
        dims[k] = n
        if n == 0:
            continue
        sq = np.sqrt(S[:n])
        O = Us[:, :n] * sq
        R = sq[:, None] * Vt[:n]
        C[k, :, :n] = O[:n_y]
        B[k - 1, :n, :] = R[:, :n_ch]
        O_pinv[k] = Us[:, :n].T / sq[:, None]
        R_pinv[k] = Vt[:n].T / sq[None, :]
        # field map: first block row of the field Hankel [Yf_{k,k-1-m}]_m = Yf[k-1-m, lag m+1]
        Hf = np.concatenate([Yf[k - 1 - m, m] for m in range(q_k)], axis=1)   # (n_f, q_k n_ch)
        G[k, :, :n] = Hf @ R_pinv[k]
    for k in range(1, N):
        n, n_next = dims[k], dims[k + 1]
        if n == 0 or n_next == 0:
            continue
        Hs = _hankel(Y, k, p, min(q, k), 1)
        A[k, :n_next, :n] = O_pinv[k + 1] @ Hs @ R_pinv[k]
    n_u = data.n_u
    Bw = B[:, :, n_u:].copy() if n_ch > n_u else None
    model = LTVModel(A=A, B=B[:, :, :n_u].copy() if Bw is not None else B, C=C, G=DenseFieldMap(G),
                     dims=dims, Bw=Bw)
    return model, sv


def markov_relative_error(model: LTVModel, Y: np.ndarray) -> float:
    """|Y_rom - Y_exp|_F / |Y_exp|_F over every recorded Markov parameter with j + lag <= N
    (all channels: inputs, then noise channels when identified)."""
    N, L = Y.shape[:2]
    m = model if model.Bw is None else LTVModel(model.A, np.concatenate([model.B, model.Bw], axis=2),
                                                 model.C, model.G, model.dims)
    Yr = m.markov_all(L)
    valid = (np.arange(N)[:, None] + np.arange(1, L + 1)[None, :]) <= N
    return float(np.linalg.norm((Yr - Y)[valid]) / np.linalg.norm(Y[valid]))
