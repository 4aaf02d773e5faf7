"""Time-varying Eigensystem Realization Algorithm (Majji, Juang & Junkins 2010).

Markov parameters of the perturbation system around the nominal,
    Y_{k,j} = C_k A_{k-1} ... A_{j+1} B_j        (response at step k to an input impulse at j < k),
come from impulse-response experiments on the black box (`impulse_experiments`): input
channel c at step j perturbed by +-delta (central differences: no O(delta) bias), outputs
recorded for lags 1..p+q.

At each step k the generalized Hankel matrix of p future outputs and q_k = min(q, k) past
inputs factors as H_k = O_k R_k:
    H_k[i, m] = Y_{k+i, k-1-m},   H_k = U S V',  O_k = U_n S_n^{1/2},  R_k = S_n^{1/2} V_n'
with n_k the ROM order (<= n_r, singular values below rel_tol * sigma_1 dropped). Then
    C_k = first block row of O_k,   B_{k-1} = first block column of R_k,
    A_k = O_{k+1}^+ H'_k R_k^+,     H'_k[i, m] = Y_{k+1+i, k-1-m}  (shifted Hankel),
so A_k maps the coordinates of step k into those of step k+1 (consistent coordinates).
Near k = 0 only k past inputs exist and n_k grows (0, n_u, 2 n_u, ...), A_k rectangular.
The nominal is extended past N (last input held) so the last Hankel matrices are complete.

The field output map G_k (dT_k = G_k a_k) follows from the field Markov parameters of the
same experiments (full-field snapshots): G_k = Hf_k V_n S_n^{-1/2}, Hf_k[0, m] = Yf_{k, k-1-m}.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_plant.slab import SlabSimulator

from .progress import progress


@dataclass
class MarkovData:
    """Markov parameters from impulse experiments around a nominal of N steps.

    Y[j, l]  = Y_{j+l, j}  (n_y, n_u) for lags l = 1..L (index l-1), inputs j = 0..N-1;
    Yf[j, l] = Yf_{j+l, j} (n_x, n_u) field Markov parameters, lags 1..Lf.
    """
    Y: np.ndarray          # (N, L, n_y, n_u)
    Yf: np.ndarray         # (N, Lf, n_x, n_u)
    delta: float
    experiments: int


def extend_nominal(U: np.ndarray, extra: int) -> np.ndarray:
    """Hold the last input for `extra` steps past N."""
    return np.vstack([U, np.repeat(U[-1:], extra, axis=0)])


def impulse_experiments(sim: SlabSimulator, U: np.ndarray, lags: int, field_lags: int,
                        delta: float, Xbar_ext: np.ndarray | None = None,
                        show_progress: bool = False) -> MarkovData:
    """Central-difference impulse responses for every input step j < N and channel c.

    All 2 N n_u experiments run as one batch in lockstep over global steps; experiment
    (j, c, +-) is active for steps j..j+lags-1 only, so the batch holds at most
    2 n_u lags runs. `Xbar_ext` is the nominal over N + lags steps (computed if None).
    """
    N, n_u = U.shape
    U_ext = extend_nominal(U, lags)
    if Xbar_ext is None:
        Xbar_ext = sim.rollout(sim.initial_state()[None], U_ext[None])[0]
    n_y, n_x = sim.n_y, sim.n_x
    Y = np.zeros((N, lags, n_y, n_u))
    Yf = np.zeros((N, field_lags, n_x, n_u))
    # active experiments: state (2 n_u per start step) stacked as [start j][sign][channel]
    pert = np.vstack([np.eye(n_u), -np.eye(n_u)]) * delta        # (2 n_u, n_u)
    X = np.empty((0, n_x))
    starts: list[int] = []
    steps = progress(range(N + lags - 1), desc="TV-ERA experiments", enabled=show_progress)
    for k in steps:
        if starts and starts[0] + lags <= k:        # oldest experiments are complete
            starts.pop(0)
            X = X[2 * n_u:]
        if k < N:
            starts.append(k)
            X = np.vstack([X, np.repeat(Xbar_ext[k][None], 2 * n_u, axis=0)])
        if not starts:
            continue
        Uk = np.repeat(U_ext[k][None], X.shape[0], axis=0)
        if k < N:
            Uk[-2 * n_u:] += pert
        X = sim.step(X, Uk)
        # record lag k+1-j for every active experiment j
        Xs = X.reshape(len(starts), 2, n_u, n_x)
        diff = (Xs[:, 0] - Xs[:, 1]) / (2 * delta)                # (n_start, n_u, n_x)
        j = np.asarray(starts)
        lag = k + 1 - j                                           # 1..lags
        Y[j, lag - 1] = sim.observe(diff).transpose(0, 2, 1)
        keep = lag <= field_lags
        if np.any(keep):
            Yf[j[keep], lag[keep] - 1] = diff[keep].transpose(0, 2, 1)
    return MarkovData(Y, Yf, delta, 2 * N * n_u)


def identify(sim: SlabSimulator, U: np.ndarray, p: int, q: int, n_r: int, sv_tol: float = 1e-10,
             impulse: float = 0.01, show_progress: bool = False):
    """TV-ERA around the nominal input U: returns (T_nom (N+1, n_x), MarkovData, Realization, delta).

    The nominal is extended p+q steps past N (last input held) so every Hankel matrix up to
    k = N is complete; the impulse amplitude delta is `impulse` times the RMS nominal input.
    """
    N = U.shape[0]
    lags = p + q
    X_ext = sim.rollout(sim.initial_state()[None], extend_nominal(U, lags)[None])[0]
    delta = impulse * max(float(np.sqrt(np.mean(U**2))), 1e-3)
    data = impulse_experiments(sim, U, lags, q, delta, X_ext, show_progress=show_progress)
    real = tv_era(data, N, p, q, n_r, sv_tol, show_progress=show_progress)
    return X_ext[: N + 1], data, real, delta


@dataclass
class Realization:
    """Zero-padded time-varying ROM (see design_file for the index conventions)."""
    dims: np.ndarray        # (N+1,) n_k
    A: np.ndarray           # (N, n_r, n_r)
    B: np.ndarray           # (N, n_r, n_u)
    C: np.ndarray           # (N+1, n_y, n_r)
    G: np.ndarray           # (N+1, n_x, n_r)
    hankel_sv: np.ndarray   # (N+1, n_sv) singular values of H_k (zero padded)


def _hankel(Y: np.ndarray, k: int, p: int, q_k: int, shift: int) -> np.ndarray:
    """[Y_{k+shift+i, k-1-m}] for i < p, m < q_k as a (p n_y, q_k n_u) matrix."""
    _, L, n_y, n_u = Y.shape
    H = np.empty((p, n_y, q_k, n_u))
    for m in range(q_k):
        j = k - 1 - m
        lags = np.arange(p) + shift + m + 1          # (k + shift + i) - j
        H[:, :, m, :] = Y[j, lags - 1]
    return H.reshape(p * n_y, q_k * n_u)


def tv_era(data: MarkovData, N: int, p: int, q: int, n_r: int, rel_tol: float = 1e-10,
           show_progress: bool = False) -> Realization:
    """Realize (A_k, B_k, C_k, G_k) for k = 0..N from Markov parameters (needs lags >= p+q)."""
    Y, Yf = data.Y, data.Yf
    _, L, n_y, n_u = Y.shape
    n_x = Yf.shape[2]
    if L < p + q:
        raise ValueError(f"need Markov parameters up to lag p+q = {p + q}, have {L}")
    if Yf.shape[1] < q:
        raise ValueError(f"need field Markov parameters up to lag q = {q}, have {Yf.shape[1]}")
    n_sv = min(p * n_y, q * n_u)
    dims = np.zeros(N + 1, dtype=np.int64)
    A = np.zeros((N, n_r, n_r))
    B = np.zeros((N, n_r, n_u))
    C = np.zeros((N + 1, n_y, n_r))
    G = np.zeros((N + 1, n_x, n_r))
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
        B[k - 1, :n, :] = R[:, :n_u]
        O_pinv[k] = Us[:, :n].T / sq[:, None]
        R_pinv[k] = Vt[:n].T / sq[None, :]
        # field map: first block row of the field Hankel [Yf_{k,k-1-m}]_m = Yf[k-1-m, lag m+1]
        Hf = np.concatenate([Yf[k - 1 - m, m] for m in range(q_k)], axis=1)   # (n_x, q_k n_u)
        G[k, :, :n] = Hf @ R_pinv[k]
    for k in range(1, N):
        n, n_next = dims[k], dims[k + 1]
        if n == 0 or n_next == 0:
            continue
        Hs = _hankel(Y, k, p, min(q, k), 1)
        A[k, :n_next, :n] = O_pinv[k + 1] @ Hs @ R_pinv[k]
    return Realization(dims, A, B, C, G, sv)


def rom_markov(real: Realization, k: int, j: int) -> np.ndarray:
    """ROM Markov parameter C_k A_{k-1} ... A_{j+1} B_j (n_y, n_u), j < k."""
    M = real.B[j]
    for i in range(j + 1, k):
        M = real.A[i] @ M
    return real.C[k] @ M


def rom_markov_all(real: Realization, lags: int) -> np.ndarray:
    """ROM Markov parameters for all j < N and lags 1..lags with j+lag <= N: (N, lags, n_y, n_u),
    zero where j + lag > N. Vectorized over j (one batched product per lag)."""
    N = real.A.shape[0]
    out = np.zeros((N, lags) + (real.C.shape[1], real.B.shape[2]))
    M = real.B.copy()                                     # state response at step j+1: (N, n_r, n_u)
    for lag in range(1, lags + 1):
        j = np.arange(N - lag + 1)                        # j + lag <= N
        out[j, lag - 1] = real.C[j + lag] @ M[j]
        if lag < lags:
            nxt = j[j + lag < N]
            M[nxt] = real.A[nxt + lag] @ M[nxt]
    return out
