"""Time-varying Eigensystem Realization Algorithm (Majji, Juang & Junkins 2010).

The Markov parameters Y_{k,j} = C_k A_{k-1} ... A_{j+1} B_j of the perturbation system around
the nominal come from impulse experiments on the black box (`sep_control.design.impulse`).
At each step k the generalized Hankel matrix of p future outputs and q_k = min(q, k) past
inputs factors as H_k = O_k R_k:
    H_k[i, m] = Y_{k+i, k-1-m},   H_k = U S V',  O_k = U_n S_n^{1/2},  R_k = S_n^{1/2} V_n'
with n_k the ROM order (<= n_r, singular values below rel_tol * sigma_1 dropped). Then
    C_k = first block row of O_k,   B_{k-1} = first block column of R_k,
    A_k = O_{k+1}^+ H'_k R_k^+,     H'_k[i, m] = Y_{k+1+i, k-1-m}  (shifted Hankel),
so A_k maps the coordinates of step k into those of step k+1 (consistent coordinates).
Near k = 0 only k past inputs exist and n_k grows (0, n_u, 2 n_u, ...), A_k rectangular.
The nominal is extended past N (last input held) so the last Hankel matrices are complete.
Noise channels, when identified, are realized with the inputs and split off as B_w,k; above
`noise_sketch.SKETCH_FROM` channels they are r_w random combinations per start step, lifted back
to the plant's channels (`sep_control.design.noise_sketch`).

The field output map G_k (df_k = G_k a_k) follows from the field Markov parameters of the
same experiments (field snapshots): G_k = Hf_k V_n S_n^{-1/2}, Hf_k[0, m] = Yf_{k, k-1-m}, kept
on the experiments' orthonormal basis Phi, so G_k = Phi g_k (`sep_estimator.ltv.PODFieldMap`):
memory n_field r + N r n_r, never N n_field n_r.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.ltv import LTVModel, PODFieldMap
from sep_plant.protocol import Plant, noise_channels, nominal_states

from sep_control.compute.progress import progress
from sep_control.design.basis import truncate
from sep_control.design.noise_sketch import sketch_for
from sep_control.design.svd import svd
# the experiments' names, also for the callers that take them from here
from sep_control.design.impulse import (FIELD_TOL, SCHEMES, MarkovData, experiment_chunks,  # noqa: F401
                                        extend_nominal, impulse_experiments)


@dataclass
class Identification:
    """A TV-ERA model and what it was identified from."""

    model: LTVModel
    hankel_sv: np.ndarray   # (N+1, n_sv) singular values of H_k (zero padded)
    data: MarkovData
    delta: float            # impulse amplitude
    X_ext: np.ndarray       # (N+1+lags, n_x) nominal states, extended past N
    U: np.ndarray           # (N, n_u) the nominal input it was identified around
    scheme: str = "central"  # the impulse scheme it was identified with
    field_tol: float = FIELD_TOL  # the field basis' relative tolerance
    p: int = 0              # Hankel block rows and columns it was identified with
    q: int = 0
    stride: int = 1         # impulses at every stride-th start step (`impulse_experiments`)
    inputs_only: bool = False   # the plant's noise channels were not impulsed (no B_w)
    coarse: bool = False    # a coarse proposal model (`RomSettings.coarse`)

    def made_with(self, scheme: str, field_tol: float | None = None, p: int | None = None,
                  q: int | None = None, noise: bool = True) -> bool:
        """Whether it was identified with these settings (a coarse proposal model never is, even
        where its settings equal the design's), its noise channels included when the plant has
        them (`noise` False: whether or not)."""
        return (not self.coarse and not (noise and self.inputs_only) and self.scheme == scheme
                and self.field_tol == (FIELD_TOL if field_tol is None else field_tol)
                and (p is None or self.p == p) and (q is None or self.q == q))


@dataclass(frozen=True)
class RomSettings:
    """The settings of one TV-ERA identification (`identify`; defaults: docs/reference/cli.md)."""

    p: int = 15                     # Hankel block rows (future outputs)
    q: int = 15                     # Hankel block columns (past inputs)
    n_r: int = 20                   # ROM order cap
    sv_tol: float = 1e-10           # relative singular-value cutoff
    impulse: float = 0.01           # impulse amplitude relative to the RMS nominal input
    scheme: str = "central"         # impulse scheme (`SCHEMES`)
    field_tol: float | None = None  # the field basis' relative tolerance (None: FIELD_TOL)
    memory_budget: int | None = None  # bytes for a batch of experiments (None: the default budget)
    chunks: int = 1                 # experiments in this many chunks of start steps
    engine: object = None           # `sep_control.compute.engine` running the chunks (None: in-process)
    noise_std: object = None        # the problem's w_std (sketch weights W^{1/2}; None: 1 per channel)
    noise_probes: int | None = None  # combinations of a sketch (`noise_sketch`; None: SKETCH_PROBES, 0: none)
    stride: int = 1                 # impulses at every stride-th start step, the rest interpolated
    inputs_only: bool = False       # impulse the inputs only, not the plant's noise channels (no B_w)
    field_basis: str = "gram"       # how the field basis finds new directions ("svd": 0.8.0's)
    coarse: bool = False            # the optimizer's coarse proposal settings (its models are never full ones)

    def identify(self, plant: Plant, U: np.ndarray, show_progress: bool = False) -> Identification:
        """`identify` around the nominal input U with these settings."""
        ident = identify(plant, U, self.p, self.q, self.n_r, self.sv_tol, self.impulse, show_progress,
                         field_tol=self.field_tol, memory_budget=self.memory_budget, scheme=self.scheme,
                         chunks=self.chunks, engine=self.engine, noise_std=self.noise_std,
                         noise_probes=self.noise_probes, stride=self.stride, inputs_only=self.inputs_only,
                         field_basis=self.field_basis)
        ident.coarse = self.coarse
        return ident


def identify(plant: Plant, U: np.ndarray, p: int, q: int, n_r: int, sv_tol: float = 1e-10,
             impulse: float = 0.01, show_progress: bool = False, field_tol: float | None = None,
             memory_budget: int | None = None, scheme: str = "central", chunks: int = 1,
             engine=None, noise_std=None, noise_probes: int | None = None, stride: int = 1,
             inputs_only: bool = False, field_basis: str = "gram") -> Identification:
    """TV-ERA around the nominal input U: impulse experiments, then the realization (`tv_era`).

    The nominal is extended p+q steps past N (last input held) so every Hankel matrix up to
    k = N is complete; the impulse amplitude delta is `impulse` times the RMS nominal input.

    Parameters
    ----------
    plant : Plant
        The black-box plant (only step, observe, field and state snapshots are used).
    U : ndarray, shape (N, n_u)
        The nominal input.
    p, q : int
        Hankel block rows (future outputs) and columns (past inputs); experiments of p + q steps.
    n_r : int
        ROM order cap.
    sv_tol : float
        Relative Hankel singular-value cutoff.
    impulse : float
        Impulse amplitude relative to the RMS nominal input.
    show_progress : bool
        Draw progress bars.
    field_tol : float, optional
        The field basis' relative tolerance (None: `FIELD_TOL`).
    memory_budget : int, optional
        Bytes for a batch of experiments (None: the default budget).
    scheme : {"central", "forward"}
        Impulse scheme (`sep_control.design.impulse.impulse_experiments`).
    chunks : int
        Experiments in this many chunks of start steps (`experiment_chunks`).
    engine : optional
        The `sep_control.compute.engine` that runs the chunks (None: in-process).
    noise_std : float or array, optional
        The process-noise stds w_std of the noise channels (None: 1), the weights of a sketch.
    noise_probes : int, optional
        Combinations per start step when the noise channels are sketched (`noise_sketch.sketch_for`:
        only above SKETCH_FROM channels; None: SKETCH_PROBES; 0: never).
    stride : int
        Impulses at every stride-th start step and the last; the Markov parameters between them
        interpolated linearly (`sep_control.design.impulse.interpolate_starts`).
    inputs_only : bool
        Impulse the n_u inputs only (a model for the optimizer's steps: no B_w).
    field_basis : {"gram", "svd"}
        How the field basis finds new directions (`sep_control.design.basis`; "svd": 0.8.0's).

    Returns
    -------
    Identification
        The model, the Hankel singular values, the Markov data and the nominal it was made around.
    """
    N = U.shape[0]
    lags = p + q
    X_ext = nominal_states(plant, extend_nominal(U, lags))
    delta = impulse * max(float(np.sqrt(np.mean(U**2))), 1e-3)
    ftol = FIELD_TOL if field_tol is None else field_tol
    skipped = inputs_only and not getattr(plant, "noise_on_inputs", True) and noise_channels(plant) > 0
    noise = None if skipped or getattr(plant, "noise_on_inputs", True) else \
        sketch_for(noise_channels(plant), noise_std, noise_probes, hold=stride)
    extra = {} if stride == 1 and not skipped else dict(stride=stride, inputs_only=skipped)
    data = impulse_experiments(plant, U, lags, q, delta, X_ext, show_progress=show_progress, field_tol=ftol,
                               memory_budget=memory_budget, scheme=scheme, chunks=chunks, engine=engine,
                               noise=noise, field_basis=field_basis, **extra)
    model, sv = tv_era(data, N, p, q, n_r, sv_tol, show_progress=show_progress, field_tol=ftol)
    return Identification(model, sv, data, delta, X_ext, np.array(U, dtype=float), scheme, ftol, p, q, stride,
                          skipped)


def _hankel(Y: np.ndarray, k: int, p: int, q_k: int, shift: int) -> np.ndarray:
    """[Y_{k+shift+i, k-1-m}] for i < p, m < q_k as a (p n_y, q_k n_ch) matrix."""
    _, L, n_y, n_ch = Y.shape
    H = np.empty((p, n_y, q_k, n_ch))
    for m in range(q_k):
        j = k - 1 - m
        lags = np.arange(p) + shift + m + 1          # (k + shift + i) - j
        H[:, :, m, :] = Y[j, lags - 1]
    return H.reshape(p * n_y, q_k * n_ch)


# ~63 lines: 26 of them the public function's numpydoc docstring
def tv_era(data: MarkovData, N: int, p: int, q: int, n_r: int, rel_tol: float = 1e-10,
           show_progress: bool = False, field_tol: float = FIELD_TOL) -> tuple[LTVModel, np.ndarray]:
    """Realize (A_k, B_k, C_k, G_k) for k = 0..N from Markov parameters (the module docstring).

    Parameters
    ----------
    data : MarkovData
        Markov parameters up to lag p + q (outputs) and q (field), from `impulse_experiments`.
    N : int
        Horizon: A_k, B_k for k < N and C_k, G_k for k <= N.
    p, q : int
        Hankel block rows (future outputs) and columns (past inputs).
    n_r : int
        ROM order cap.
    rel_tol : float
        Hankel singular values below rel_tol sigma_1 are dropped.
    show_progress : bool
        Draw a progress bar.
    field_tol : float
        The field map's basis is truncated to the span its g_k use, at this relative tolerance.

    Returns
    -------
    model : LTVModel
        The ROM, states zero-padded to n_r (B_w split off when there are noise channels).
    hankel_sv : ndarray, shape (N+1, n_sv)
        Singular values of every H_k (zero padded).
    """
    Y, Yc = data.Y, data.Yc
    _, L, n_y, n_ch = Y.shape
    if L < p + q:
        raise ValueError(f"need Markov parameters up to lag p+q = {p + q}, have {L}")
    if Yc.shape[1] < q:
        raise ValueError(f"need field Markov parameters up to lag q = {q}, have {Yc.shape[1]}")
    dims = np.zeros(N + 1, dtype=np.int64)
    B = np.zeros((N, n_r, n_ch))
    C = np.zeros((N + 1, n_y, n_r))
    g = np.zeros((N + 1, Yc.shape[2], n_r))             # G_k = basis g_k
    sv = np.zeros((N + 1, min(p * n_y, q * n_ch)))
    # O_k^+ = S^{-1/2} U',  R_k^+ = V S^{-1/2} for every k (needed one step ahead)
    O_pinv: list[np.ndarray | None] = [None] * (N + 1)
    R_pinv: list[np.ndarray | None] = [None] * (N + 1)
    for k in progress(range(N + 1), desc="TV-ERA realization", enabled=show_progress):
        q_k = min(q, k)
        if q_k == 0:
            continue
        Us, S, Vt = svd(_hankel(Y, k, p, q_k, 0))
        sv[k, :S.size] = S
        n = int(min(n_r, np.sum(S > rel_tol * S[0]))) if S[0] > 0 else 0
        dims[k] = n
        if n == 0:
            continue
        sq = np.sqrt(S[:n])
        C[k, :, :n] = (Us[:, :n] * sq)[:n_y]                  # first block row of O_k
        B[k - 1, :n, :] = (sq[:, None] * Vt[:n])[:, :n_ch]    # first block column of R_k
        O_pinv[k] = Us[:, :n].T / sq[:, None]
        R_pinv[k] = Vt[:n].T / sq[None, :]
        # field map: first block row of the field Hankel [Yf_{k,k-1-m}]_m = Yf[k-1-m, lag m+1],
        # on the field basis (coefficients only: nothing of size n_field here)
        Hc = np.concatenate([Yc[k - 1 - m, m] for m in range(q_k)], axis=1)   # (r_f, q_k n_ch)
        g[k, :, :n] = Hc @ R_pinv[k]
    A = _transitions(Y, p, q, n_r, dims, O_pinv, R_pinv)
    return _assemble(data, A, B, C, g, dims, field_tol), sv


def _transitions(Y: np.ndarray, p: int, q: int, n_r: int, dims: np.ndarray, O_pinv: list,
                 R_pinv: list) -> np.ndarray:
    """A_k = O_{k+1}^+ H'_k R_k^+ for k = 1..N-1 (A_0 = 0: the state at k = 0 is empty), (N, n_r, n_r)."""
    N = dims.shape[0] - 1
    A = np.zeros((N, n_r, n_r))
    for k in range(1, N):
        n, n_next = dims[k], dims[k + 1]
        if n == 0 or n_next == 0:
            continue
        Hs = _hankel(Y, k, p, min(q, k), 1)
        A[k, :n_next, :n] = O_pinv[k + 1] @ Hs @ R_pinv[k]
    return A


def _assemble(data: MarkovData, A: np.ndarray, B: np.ndarray, C: np.ndarray, g: np.ndarray, dims: np.ndarray,
              field_tol: float) -> LTVModel:
    """The LTVModel: B split into the inputs' B and the noise channels' B_w, and the field map on
    the basis truncated to the span its g_k use (the field reconstruction needs no more)."""
    n_u, n_ch = data.n_u, B.shape[2]
    N1, r_f, n_r = g.shape
    Bw = B[:, :, n_u:].copy() if n_ch > n_u else None
    if Bw is not None and data.noise is not None:
        Bw = data.noise.lift(Bw)               # B^_j = B~_j L_j on the plant's n_w channels
    Phi, coef = truncate(data.basis, g.transpose(1, 0, 2).reshape(r_f, -1), field_tol)
    g = coef.reshape(Phi.shape[1], N1, n_r).transpose(1, 0, 2)
    return LTVModel(A=A, B=B[:, :, :n_u].copy() if Bw is not None else B, C=C,
                    G=PODFieldMap(np.ascontiguousarray(Phi), np.ascontiguousarray(g)), dims=dims, Bw=Bw)


def markov_relative_error(model: LTVModel, Y: np.ndarray, noise=None) -> float:
    """|Y_rom - Y_exp|_F / |Y_exp|_F over every recorded Markov parameter with j + lag <= N
    (all channels: inputs, then noise channels when identified, or the combinations of the
    sketch `noise` they were identified on)."""
    N, L = Y.shape[:2]
    m = model if model.Bw is None else LTVModel(model.A, np.concatenate([model.B, identified_noise_input(model, noise)],
                                                                        axis=2), model.C, model.G, model.dims)
    Yr = m.markov_all(L)
    valid = (np.arange(N)[:, None] + np.arange(1, L + 1)[None, :]) <= N
    return float(np.linalg.norm((Yr - Y)[valid]) / np.linalg.norm(Y[valid]))


def identified_noise_input(model: LTVModel, noise=None, start: int = 0) -> np.ndarray:
    """The model's B_w on the channels its noise experiments used: B_w itself, or on a sketch's
    combinations (`NoiseSketch.sketched`) when `noise` is one."""
    return model.Bw if noise is None else noise.sketched(model.Bw, start)
