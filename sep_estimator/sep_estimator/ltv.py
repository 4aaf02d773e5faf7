"""The linear time-varying model around a nominal, and the LQG designed on it.

One container (`LTVModel`) serves the identified reduced-order model (ROM), the full-order
oracle, the Monte Carlo, validation and the design file (k = 0..N, zero-padded to n states):

    a_{k+1} = A_k a_k + B_k du_k + B_w,k w_k        (k < N; B_w = B when noise enters the inputs)
    dy_k    = C_k a_k + v_k
    df_k    = G_k a_k                               (field deviation; G is an operator)
    a_0 ~ N(0, P_0)                                 (P_0 = 0: the initial state is known exactly)

The same container holds the ROM augmented with disturbance states, z = [a; d]
(`sep_estimator.disturbance.augment`), whose prior P_0 = blockdiag(0, diag(sigma_0^2)) is not zero.

Near k = 0 the ROM order n_k grows (only k past inputs exist); arrays are zero-padded to n with
the true orders in `dims`. Zero padding is exact: padded states start at zero and A, B never
excite them.

`FieldMap` is what the filter and the reports need from G: apply it to states, its rows'
variances under a covariance. `DenseFieldMap` stores G_k (N+1, n_field, n); `IdentityFieldMap`
is the oracle's G = I when the field is the state (no n_x^2 storage).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from sep_estimator.disturbance import Disturbance


class FieldMap(Protocol):
    """G_k as an operator: the field deviation df_k = G_k a_k of a state a_k."""

    n_field: int
    n: int

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        """G_k a for a batch a (M, n) -> (M, n_field)."""

    def matrix(self, k: int) -> np.ndarray:
        """G_k as a dense (n_field, n) array."""

    def std(self, k: int, P: np.ndarray) -> np.ndarray:
        """sqrt(diag(G_k P G_k')) (n_field,)."""

    def gram(self, k: int) -> np.ndarray:
        """G_k' G_k (n, n): what a quadratic cost on the field needs, whatever n_field is."""

    def project(self, k: int, v: np.ndarray) -> np.ndarray:
        """G_k' v for field vectors v (..., n_field) -> (..., n)."""

    def project_all(self, v: np.ndarray) -> np.ndarray:
        """G_k' v_k for every step at once: v (N+1, n_field) -> (N+1, n)."""


class DenseFieldMap:
    """G_k stored as (N+1, n_field, n)."""

    def __init__(self, G: np.ndarray):
        self.G = G
        self.n_field, self.n = int(G.shape[1]), int(G.shape[2])

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        return a @ self.G[k].T

    def matrix(self, k: int) -> np.ndarray:
        return self.G[k]

    def std(self, k: int, P: np.ndarray) -> np.ndarray:
        return field_std(self.G[k], P)

    def std_all(self, P: np.ndarray) -> np.ndarray:
        """(N+1, n_field) for covariances P (N+1, n, n)."""
        return field_std(self.G, P)

    def gram(self, k: int) -> np.ndarray:
        """G_k' G_k (n, n)."""
        return self.G[k].T @ self.G[k]

    def project(self, k: int, v: np.ndarray) -> np.ndarray:
        """G_k' v for field vectors v (..., n_field) -> (..., n)."""
        return v @ self.G[k]

    def project_all(self, v: np.ndarray) -> np.ndarray:
        """G_k' v_k, v (N+1, n_field) -> (N+1, n)."""
        return np.einsum("kfn,kf->kn", self.G, v)


def psd_factor(P: np.ndarray) -> np.ndarray:
    """L with L L' = P for a symmetric PSD P (n, n) or a stack (..., n, n): the eigen-factor
    V sqrt(max(w, 0)) of its symmetric part, defined where a Cholesky factor is not (singular P)."""
    w, V = np.linalg.eigh(0.5 * (P + np.swapaxes(P, -1, -2)))
    return V * np.sqrt(np.maximum(w, 0.0))[..., None, :]


class PODFieldMap:
    """G_k = Phi g_k: one orthonormal basis Phi (n_field, r) shared by every step and per-step
    coefficients g (N+1, r, n). Memory n_field r + N r n instead of N n_field n; G_k' G_k =
    g_k' g_k, so a quadratic field cost costs nothing in n_field."""

    def __init__(self, Phi: np.ndarray, g: np.ndarray):
        self.Phi, self.g = Phi, g
        self.n_field, self.n = int(Phi.shape[0]), int(g.shape[2])
        self.rank = int(Phi.shape[1])

    def coefficients(self, k: int, a: np.ndarray) -> np.ndarray:
        """c = a g_k': the field's coordinates in the basis, (..., n) -> (..., r)."""
        return a @ self.g[k].T

    def reconstruction_basis(self) -> np.ndarray:
        """Phi' (r, n_field) in the precision `apply` reconstructs with: apply = c Phi'."""
        return self.Phi.T

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        return self.coefficients(k, a) @ self.Phi.T

    def matrix(self, k: int) -> np.ndarray:
        return self.Phi @ self.g[k]

    def std(self, k: int, P: np.ndarray) -> np.ndarray:
        # diag(Phi g P g' Phi') = rowsum((Phi g L)^2) with P = L L'
        L = psd_factor(P)
        return np.sqrt(np.einsum("ij,ij->i", *(2 * [self.Phi @ (self.g[k] @ L)])))

    def std_all(self, P: np.ndarray) -> np.ndarray:
        return np.stack([self.std(k, P[k]) for k in range(P.shape[0])])

    def gram(self, k: int) -> np.ndarray:
        return self.g[k].T @ self.g[k]

    def project(self, k: int, v: np.ndarray) -> np.ndarray:
        return (v @ self.Phi) @ self.g[k]

    def project_all(self, v: np.ndarray) -> np.ndarray:
        # one pass over Phi for every step (a product per step reads all n_field r numbers of Phi
        # each time: 81 of them took 1.0 s at 65,536 x 330 on one core, one batched 0.1 s)
        return np.einsum("kr,krn->kn", v @ self.Phi, self.g)


class Float32Reconstruction(PODFieldMap):
    """A POD field map whose `apply`, the per-step reconstruction (a g_k') Phi', reads a float32
    copy of Phi. At large n_field the product is memory-bound (it streams n_field r numbers), so
    half the bytes is about half the time or less (65 536 x 69: 1.6 -> 0.46 ms, README,
    bench/bench_field.py); the deviation carries float32 round-off, ~1e-7 relative (the design's
    map itself is compressed at 1e-5), and is returned as float64. Everything else (std, gram, project) stays float64."""

    def __init__(self, base: PODFieldMap):
        super().__init__(base.Phi, base.g)
        self._PhiT32 = np.ascontiguousarray(base.Phi.T, dtype=np.float32)    # (r, n_field)

    def reconstruction_basis(self) -> np.ndarray:
        return self._PhiT32

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        return (self.coefficients(k, a).astype(np.float32) @ self._PhiT32).astype(np.float64)


#: reconstruction precisions the online estimator offers (parameter field_precision)
FIELD_PRECISIONS = ("auto", "float64", "float32")
#: 'auto' reconstructs in float32 from this size of Phi [bytes] on: below it Phi stays in the
#: caches and float64 costs little more (reference slab 19 kB, plate 64^2 2.3 MB); above it the
#: product is memory-bound (plate 256^2: 36 MB, float32 3.5x faster, README)
AUTO_FLOAT32_BYTES = 8 << 20


def resolve_precision(G: "FieldMap", precision: str) -> str:
    """The precision the reconstruction of G runs in for `precision`: 'float32' only for a POD map
    asked 'float32', or 'auto' with a Phi of at least AUTO_FLOAT32_BYTES; other maps are small
    and stay 'float64' (ValueError naming the choices for an unknown `precision`)."""
    if precision not in FIELD_PRECISIONS:
        raise ValueError(f"field precision must be one of {', '.join(FIELD_PRECISIONS)}, got {precision!r}")
    if not isinstance(G, PODFieldMap):
        return "float64"
    if precision == "auto":
        return "float32" if G.Phi.size * 8 >= AUTO_FLOAT32_BYTES else "float64"
    return precision


def in_precision(G: "FieldMap", precision: str) -> "FieldMap":
    """G for the online reconstruction in `resolve_precision(G, precision)`: G itself for
    float64, a `Float32Reconstruction` of a POD map for float32."""
    if resolve_precision(G, precision) == "float32" and not isinstance(G, Float32Reconstruction):
        return Float32Reconstruction(G)
    return G


class IdentityFieldMap:
    """G_k = I (the state is the field): the oracle's field map."""

    def __init__(self, n: int):
        self.n_field = self.n = int(n)

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        return a

    def matrix(self, k: int) -> np.ndarray:
        return np.eye(self.n)

    def std(self, k: int, P: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(P), 0.0))

    def std_all(self, P: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(np.einsum("kii->ki", P), 0.0))

    def gram(self, k: int) -> np.ndarray:
        return np.eye(self.n)

    def project(self, k: int, v: np.ndarray) -> np.ndarray:
        return v

    def project_all(self, v: np.ndarray) -> np.ndarray:
        return v


def field_std(G: np.ndarray, P: np.ndarray) -> np.ndarray:
    """sqrt(diag(G P G')) per node, for one step (G (n_f, n)) or all steps (G (N+1, n_f, n))."""
    var = np.einsum("...ij,...jk,...ik->...i", G, P, G)
    return np.sqrt(np.maximum(var, 0.0))


@dataclass
class LTVModel:
    """(A_k, B_k, C_k, G_k) for k = 0..N, zero-padded to n states (see the module docstring).

    Attributes
    ----------
    A : ndarray, shape (N, n, n)
        State transitions A_k, k < N.
    B : ndarray, shape (N, n, n_u)
        Input maps B_k, k < N.
    C : ndarray, shape (N+1, n_y, n)
        Output maps C_k, k <= N.
    G : FieldMap
        The field output map G_k (an operator: dense, POD, identity, padded).
    dims : ndarray, shape (N+1,), int
        The true order n_k at step k (the states beyond it are zero padding).
    Bw : ndarray, shape (N, n, n_w), or None
        The noise input map B_w,k; None: the noise enters through the inputs (B).
    P0 : ndarray, shape (n, n), or None
        The covariance of the initial state a_0; None: zero (known exactly).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    G: FieldMap
    dims: np.ndarray
    Bw: np.ndarray | None = None
    P0: np.ndarray | None = None

    def initial_covariance(self) -> np.ndarray:
        """P_0 (n, n): the prior covariance of a_0 (zeros when `P0` is None)."""
        return np.zeros((self.n, self.n)) if self.P0 is None else np.array(self.P0, dtype=float)

    @property
    def n_steps(self) -> int:
        return int(self.A.shape[0])

    @property
    def n(self) -> int:
        return int(self.A.shape[1])

    @property
    def n_u(self) -> int:
        return int(self.B.shape[2])

    @property
    def n_y(self) -> int:
        return int(self.C.shape[1])

    @property
    def noise_input(self) -> np.ndarray:
        """B_w,k (N, n, n_w): B when the noise enters through the inputs."""
        return self.B if self.Bw is None else self.Bw

    def markov(self, k: int, j: int) -> np.ndarray:
        """Markov parameter C_k A_{k-1} ... A_{j+1} B_j (n_y, n_u), j < k."""
        M = self.B[j]
        for i in range(j + 1, k):
            M = self.A[i] @ M
        return self.C[k] @ M

    def markov_all(self, lags: int) -> np.ndarray:
        """Markov parameters for all j < N and lags 1..lags with j + lag <= N: (N, lags, n_y, n_u),
        zero where j + lag > N. Vectorized over j (one batched product per lag)."""
        N = self.n_steps
        out = np.zeros((N, lags, self.n_y, self.n_u))
        M = self.B.copy()                                   # state response at step j+1: (N, n, n_u)
        for lag in range(1, lags + 1):
            j = np.arange(N - lag + 1)                      # j + lag <= N
            out[j, lag - 1] = self.C[j + lag] @ M[j]
            if lag < lags:
                nxt = j[j + lag < N]
                M[nxt] = self.A[nxt + lag] @ M[nxt]
        return out


def sensed_nodes(model: LTVModel, k: int | None = None, rtol: float = 1e-3,
                 P: np.ndarray | None = None) -> list[int]:
    """Field nodes that a sensor reads directly: output i reads node j when the row C_k[i] equals
    the field map's row G_k[j] (to `rtol`), found from the identified model alone (k: the last
    step by default). Sensors that average or mix the field read no single node. With `P`
    (n, n), a covariance of the state at step k, the rows are compared in the directions the
    state takes, (C_k[i] - G_k[j]) P^(1/2): a field map compressed to those directions
    (`sep_control.design.field_map.compress_field_map`) differs from C elsewhere; the covariance
    of an augmented state z = [a; d] counts with its a-block."""
    k = model.C.shape[0] - 1 if k is None else k
    G, C = model.G.matrix(k), model.C[k]
    if P is not None:
        L = psd_factor(P[:model.n, :model.n])
        G, C = G @ L, C @ L
    out = []
    for c in C:
        scale = float(np.linalg.norm(c))
        if scale == 0.0:
            continue
        d = np.linalg.norm(G - c, axis=1)
        j = int(np.argmin(d))
        if d[j] <= rtol * scale:       # identified rows agree to ~1e-12 for a point sensor
            out.append(j)
    return out


@dataclass
class KalmanSchedule:
    """Time-varying Kalman gains and covariances along the horizon (k = 0..N).

    Attributes
    ----------
    L : ndarray, shape (N+1, n, n_y)
        Kalman gains L_k.
    P_post : ndarray, shape (N+1, n, n)
        P_{k|k}, the covariance after the measurement update at k.
    P_prior : ndarray, shape (N+1, n, n)
        P_{k|k-1}, the covariance before it.
    """

    L: np.ndarray
    P_post: np.ndarray
    P_prior: np.ndarray


@dataclass
class LQG:
    """A time-varying LQG around a nominal: model, LQR gains, Kalman schedule, noise.

    du_k = K_k zhat_{k|k};  zhat_{k|k} = zhat_{k|k-1} + L_k (dy_k - C_k zhat_{k|k-1}).

    `model` is the filter's: the ROM itself (z = a), or the ROM augmented with disturbance
    states, z = [a; d] (`sep_estimator.disturbance.augment`; `disturbance` says how), on which
    K, the schedule and W are; `rom` is the ROM alone (n_r states: validation, the ROM sweep).

    Attributes
    ----------
    name : str
        'rom_lqg' or 'oracle_lqg'.
    model : LTVModel
        The filter's model (n_z = n_r + n_d states).
    K : ndarray, shape (N, n_u, n_z)
        LQR gains K_k.
    kf : KalmanSchedule
        Kalman gains and covariances on `model`.
    W : ndarray, shape (n_w, n_w)
        Process noise covariance (with the disturbance walk's channels).
    V : ndarray, shape (n_y, n_y)
        Sensor noise covariance.
    field_std : ndarray, shape (N+1, n_field)
        Reconstruction std sqrt(diag(G_k P_{k|k} G_k')) after the update; computed from the
        schedule when not given.
    disturbance : Disturbance or None
        The disturbance states (None: z = a).
    rom : LTVModel
        The ROM on a; `model` itself when not given (an LQG with disturbance states needs it).

    Raises
    ------
    ValueError
        Disturbance states without `rom`.
    """

    name: str
    model: LTVModel
    K: np.ndarray
    kf: KalmanSchedule
    W: np.ndarray
    V: np.ndarray
    field_std: np.ndarray | None = None
    disturbance: "Disturbance | None" = None
    rom: LTVModel | None = None

    def __post_init__(self) -> None:
        if self.rom is None:
            if self.disturbance is not None:
                raise ValueError("an LQG with disturbance states needs its ROM (rom=...)")
            self.rom = self.model
        if self.field_std is None:
            self.field_std = field_std_schedule(self.model.G, self.kf.P_post)

    @property
    def n_r(self) -> int:
        """The ROM's state dimension (the leading n_r entries of z)."""
        return self.rom.n

    @property
    def n_d(self) -> int:
        """The number of disturbance states (0: none)."""
        return 0 if self.disturbance is None else self.disturbance.n_d


def field_std_schedule(G: FieldMap, P: np.ndarray) -> np.ndarray:
    """sqrt(diag(G_k P_k G_k')) for every k: (N+1, n_field)."""
    if hasattr(G, "std_all"):
        return G.std_all(P)
    return np.stack([G.std(k, P[k]) for k in range(P.shape[0])])


def prior_covariances(model: LTVModel, P_post: np.ndarray, W: np.ndarray) -> np.ndarray:
    """P_{k|k-1} from the posteriors: P_{0|-1} = P_0 (`LTVModel.P0`, zero unless the model has
    disturbance states), P_{k+1|k} = A_k P_{k|k} A_k' + B_w W B_w'."""
    A, Bw = model.A, model.noise_input
    P_prior = np.zeros_like(P_post)
    P_prior[0] = model.initial_covariance()
    P_prior[1:] = A @ P_post[:-1] @ A.transpose(0, 2, 1) + Bw @ W @ Bw.transpose(0, 2, 1)
    return P_prior
