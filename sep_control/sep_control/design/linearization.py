"""Gauss-Newton models of the cost around an input: from sensitivities or from an identified ROM.

The cost is a sum of squares J(U) = |r(U)|^2 with
    r = [ sqrt(q_k / n_f) (f_k - f*)  (k = 1..N),  sqrt(r_u) u_k  (k = 0..N-1) ],
f_k = field(x_k) the plant's field (n_f nodes) along the noise-free trajectory (for the
belief-space cost, the belief mean: `sep_control.design.belief`).

* `SensitivityLinearization`: the dense normal equations J'J, J'r from N n_u batched
  impulse-sensitivity experiments (`sensitivity_normal_equations`).
* `RomLinearization`: the same Gauss-Newton model on an identified TV-ERA model, solved as a
  linear-quadratic problem by one Riccati pass (no N n_u x N n_u matrix).

Both offer `step(lam, frozen)` (the Levenberg-Marquardt step), `gradient()` and
`predicted_change(dU)`; which of them the optimizer uses at an iterate is decided by a
strategy (`sep_control.design.jacobians`).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from sep_estimator.enkf import EnKFResult
from sep_plant.device import array_module_of, step_resident, to_device, to_host_of
from sep_plant.problem import Objective
from sep_plant.protocol import Plant, fields

from sep_control.design.tvera import Identification

#: an identification at U' serves at U when max|U - U'| <= SAME_INPUT_RTOL max|U'|: the Markov
#: parameters then differ by O(1e-6) relative, the accuracy the identification itself reaches
SAME_INPUT_RTOL = 1e-6

#: relative damping of an input held at an active bound in the ROM step (see RomLinearization.step)
FREEZE = 1e10


def same_input(U_a: np.ndarray, U_b: np.ndarray, rtol: float = SAME_INPUT_RTOL) -> bool:
    """Whether a linearization at U_a serves at U_b: max|U_a - U_b| <= rtol max|U_a|."""
    return U_a.shape == U_b.shape and float(np.max(np.abs(U_a - U_b))) <= \
        rtol * max(float(np.max(np.abs(U_a))), 1e-12)


@dataclass(frozen=True)
class Point:
    """An evaluated input of the optimization."""

    U: np.ndarray                    # (N, n_u) input
    J: float                         # its objective (nominal or belief cost)
    X: np.ndarray                    # (N+1, n_x) noise-free states
    residual_field: np.ndarray       # (N+1, n_f) the field whose f_k - f* enters J'r
    belief: EnKFResult | None = None  # belief objective: the EnKF belief at U


class Linearization(Protocol):
    """A Gauss-Newton model of the cost at one input."""

    identification: Identification | None   # the ROM it rests on (None: sensitivities)

    def step(self, lam: float, frozen: np.ndarray | None = None) -> np.ndarray: ...

    def gradient(self) -> np.ndarray: ...

    def predicted_change(self, dU: np.ndarray) -> float: ...


# ------------------------------------------------------------ sensitivities
@dataclass
class NormalEquations:
    JtJ: np.ndarray    # (N n_u, N n_u)
    Jtr: np.ndarray    # (N n_u,)
    experiments: int   # simulator runs used
    run_steps: int     # run-steps simulated


class _ChunkedGram:
    """J'J accumulated chunk by chunk: the weighted Jacobian rows of `chunk` steps are laid side
    by side (row c holds experiment c's field deviations at those steps, zero before it started)
    and multiplied as rows @ rows.T in one BLAS call (a symmetric rank-k update), which runs
    several times faster than one small product per step and 1.4x faster than the transposed
    layout's rows.T @ rows (plate 64^2: 1.37 vs 2.01 s per Gram matrix, one core). `xp`: the
    array module the rows and J'J live in (a device's: cuBLAS there, J'J downloaded once)."""

    def __init__(self, n: int, n_f: int, N: int, xp=np):
        self.n_f, self.filled, self.xp = n_f, 0, xp
        self.chunk = max(1, min(N, (1 << 22) // max(1, n_f * n)))
        self.rows = xp.zeros((n, self.chunk * n_f))
        self.JtJ = xp.zeros((n, n))

    def add(self, D: np.ndarray, sqrt_w: float, last: bool) -> None:
        """Add one step's deviations D (m, n_f) with weight sqrt(w); `last`: flush."""
        m, n_f = D.shape[0], self.n_f
        self.xp.multiply(D, sqrt_w, out=self.rows[:m, self.filled * n_f:(self.filled + 1) * n_f])
        self.filled += 1
        if self.filled == self.chunk or last:
            used = self.rows[:m, :self.filled * n_f]
            self.JtJ[:m, :m] += used @ used.T
            if self.chunk > 1:         # one step a chunk: the next step overwrites every used row
                used[:] = 0.0
            self.filled = 0


def sensitivity_normal_equations(plant: Plant, U: np.ndarray, Xbar: np.ndarray, obj: Objective,
                                 eps: float = 1e-4, residual_field: np.ndarray | None = None,
                                 gram: bool = True) -> NormalEquations:
    """Build J'J and J'r from N n_u batched impulse-sensitivity experiments around (Xbar, U).

    Perturb input channel c at step j by eps and run from the nominal state at j. All N n_u
    experiments run as one batch in lockstep, so at step k only the n_u (k+1) experiments that
    have started are simulated, and their field deviations D_k (n_u (k+1), n_f) are folded
    straight into the normal equations  J'J += (q_k/n_f) D_k D_k',  J'r += (q_k/n_f) D_k (f_k - f*)
    without storing the N n_f x N n_u Jacobian.
    Xbar (N+1, n_x) are the nominal states; `residual_field` (N+1, n_f) replaces their field as
    the trajectory whose residual f_k - f* enters J'r (the belief mean, for the belief-space
    problem). Columns are ordered (j, c) -> j n_u + c. With gram=False only J'r is formed.
    The batch grows in place in one (N n_u, n_x) buffer. On a device (`sep_plant.device`) the
    batch, D_k and the sums stay there for the whole pass: the inputs go up (N n_u numbers a
    step) and J'J, J'r come down once.
    """
    N, n_u = U.shape
    n = N * n_u
    q = obj.q
    Fbar = fields(plant, Xbar)
    n_f = Fbar.shape[1]
    res = (Fbar if residual_field is None else residual_field) - obj.target
    xp, step = array_module_of(plant), step_resident(plant)
    Fbar_d, res_d = to_device(plant, Fbar), to_device(plant, res)
    Xbar_d = to_device(plant, Xbar)
    Jtr = xp.zeros(n)
    X = xp.empty((n, Xbar.shape[1]))
    eye = np.eye(n_u) * eps
    run_steps = 0
    acc = _ChunkedGram(n, n_f, N, xp) if gram else None
    for k in range(N):
        # start the n_u experiments of step k from the nominal state, then step every active run
        m = n_u * (k + 1)
        X[m - n_u:m] = Xbar_d[k]
        Uk = np.repeat(U[k][None], m, axis=0)
        Uk[-n_u:] += eye
        X[:m] = step(X[:m], to_device(plant, Uk))
        run_steps += m
        D = plant.field(X[:m]) - Fbar_d[k + 1]                   # (n_u (k+1), n_f)
        D /= eps
        w = q[k + 1] / n_f
        Jtr[:m] += w * (D @ res_d[k + 1])
        if acc is not None:
            acc.add(D, np.sqrt(w), last=k == N - 1)
    # input penalty r_u |u|^2
    JtJ = np.empty((0, 0))
    Jtr = to_host_of(plant, Jtr)
    if acc is not None:
        JtJ = to_host_of(plant, acc.JtJ)
        if not (np.isfinite(JtJ).all() and np.isfinite(Jtr).all()):
            raise FloatingPointError("sensitivity experiments gave non-finite field deviations")
        JtJ[np.diag_indices(n)] += obj.r_u
    Jtr += obj.r_u * U.ravel()
    return NormalEquations(JtJ, Jtr, n, run_steps)


class SensitivityLinearization:
    """Gauss-Newton/LM steps and gradients from dense normal equations (sensitivity Jacobian)."""

    identification: Identification | None = None

    def __init__(self, ne: NormalEquations, shape: tuple[int, int]):
        self.ne, self.shape, self.experiments = ne, shape, ne.experiments

    def step(self, lam: float, frozen: np.ndarray | None = None) -> np.ndarray:
        """(J'J + lam diag(J'J)) dU = -J'r on the free variables (`frozen` ones: dU = 0)."""
        H = self.ne.JtJ + lam * np.diag(np.diag(self.ne.JtJ))
        if frozen is None or not frozen.any():
            return -np.linalg.solve(H, self.ne.Jtr).reshape(self.shape)
        free = ~frozen.ravel()
        dU = np.zeros(H.shape[0])
        dU[free] = -np.linalg.solve(H[np.ix_(free, free)], self.ne.Jtr[free])
        return dU.reshape(self.shape)

    def gradient(self) -> np.ndarray:
        """dJ/dU = 2 J'r, (N, n_u)."""
        return 2.0 * self.ne.Jtr.reshape(self.shape)

    def predicted_change(self, dU: np.ndarray) -> float:
        """The Gauss-Newton model's change of the cost, 2 J'r dU + dU' J'J dU."""
        d = dU.ravel()
        return float(2.0 * self.ne.Jtr @ d + d @ (self.ne.JtJ @ d))


# --------------------------------------------------------------------- ROM
class RomLinearization:
    """The Gauss-Newton model of the cost on an identified ROM, solved as a linear-quadratic
    problem (no N n_u x N n_u matrix): with the field deviation df_k = G_k a_k,
    a_{k+1} = A_k a_k + B_k du_k, a_0 = 0, the LM step minimizes

        sum_{k=1..N} w_k |G_k a_k + e_k|^2 + sum_j [ r_u |u_j + du_j|^2 + lam du_j' D_j du_j ],

    e_k = f_k - f* (the nominal's field, or the belief mean), w_k = q_k / n_f, D_j the diagonal of
    the Gauss-Newton matrix J'J (Levenberg-Marquardt scaling, as the dense solve uses). One
    backward Riccati pass with affine terms and one forward pass: O(N n_r^3), whatever n_x is;
    G enters only through G_k' G_k and G_k' e_k (`FieldMap.gram`, `FieldMap.project_all`). The step
    equals the dense solve of the same Jacobian (tests/test_rom_jacobian.py)."""

    def __init__(self, identification: Identification, obj: Objective, residual_field: np.ndarray,
                 U: np.ndarray, one_pass: bool = True):
        m = identification.model
        self.identification, self.model, self.U = identification, m, U
        self.experiments = identification.data.experiments
        N = U.shape[0]
        w = obj.q / residual_field.shape[1]
        e = residual_field - obj.target
        n = m.n
        self.H = np.zeros((N + 1, n, n))
        self.h = np.zeros((N + 1, n))
        for k in range(1, N + 1):
            self.H[k] = w[k] * m.G.gram(k)
        if one_pass:        # G_k' e_k for every k in one pass over Phi (`FieldMap.project_all`)
            self.h[1:] = w[1:, None] * m.G.project_all(e)[1:]
        else:               # step by step: 0.8.0's arithmetic (experiment plan 0.8)
            for k in range(1, N + 1):
                self.h[k] = w[k] * m.G.project(k, e[k])
        self.r_u = obj.r_u
        # diagonal of J'J: r_u + diag(B_j' P_{j+1} B_j), P_k = H_k + A_k' P_{k+1} A_k
        self.D = np.empty(U.shape)
        P = self.H[N].copy()
        for j in range(N - 1, -1, -1):
            self.D[j] = self.r_u + np.einsum("ic,ij,jc->c", m.B[j], P, m.B[j])
            if j > 0:
                P = self.H[j] + m.A[j].T @ P @ m.A[j]

    def step(self, lam: float, frozen: np.ndarray | None = None) -> np.ndarray:
        """The LM step; `frozen` (N, n_u) inputs held (an active bound): their damping is made
        FREEZE times their curvature, so their step is ~1/FREEZE of a free one (then clipped)."""
        m, N = self.model, self.U.shape[0]
        n_u = self.U.shape[1]
        hold = np.zeros(self.U.shape) if frozen is None else FREEZE * frozen * (self.r_u + self.D)
        K = np.empty((N, n_u, m.n))
        kff = np.empty((N, n_u))
        S, s = self.H[N].copy(), self.h[N].copy()
        for k in range(N - 1, -1, -1):
            A, B = m.A[k], m.B[k]
            SB = S @ B
            Quu = B.T @ SB
            Quu[np.diag_indices(n_u)] += self.r_u + lam * self.D[k] + hold[k]
            Qux = SB.T @ A
            qu = self.r_u * self.U[k] + B.T @ s
            sol = np.linalg.solve(Quu, np.column_stack([Qux, qu]))
            K[k], kff[k] = -sol[:, :-1], -sol[:, -1]
            if k > 0:
                S = self.H[k] + A.T @ S @ A + Qux.T @ K[k]
                S = 0.5 * (S + S.T)
                s = self.h[k] + A.T @ s + Qux.T @ kff[k]
        dU = np.empty_like(self.U)
        a = np.zeros(m.n)
        for k in range(N):
            dU[k] = K[k] @ a + kff[k]
            a = m.A[k] @ a + m.B[k] @ dU[k]
        return dU

    def predicted_change(self, dU: np.ndarray) -> float:
        """The Gauss-Newton model's change of the cost along dU: with a_0 = 0,
        a_{k+1} = A_k a_k + B_k du_k, sum_k (a_k' H_k a_k + 2 h_k' a_k) + r_u sum_j (2 u_j + du_j)' du_j."""
        m = self.model
        a = np.zeros(m.n)
        total = 0.0
        for k in range(self.U.shape[0]):
            a = m.A[k] @ a + m.B[k] @ dU[k]
            total += float(a @ (self.H[k + 1] @ a) + 2.0 * self.h[k + 1] @ a)
        return total + self.r_u * float(np.sum((2.0 * self.U + dU) * dU))

    def gradient(self) -> np.ndarray:
        """dJ/dU = 2 J'r by the adjoint recursion p_k = h_k + A_k' p_{k+1}: 2 (B_j' p_{j+1} + r_u u_j)."""
        m, N = self.model, self.U.shape[0]
        g = np.empty_like(self.U)
        p = self.h[N].copy()
        for j in range(N - 1, -1, -1):
            g[j] = m.B[j].T @ p + self.r_u * self.U[j]
            if j > 0:
                p = self.h[j] + m.A[j].T @ p
        return 2.0 * g
