"""Time-varying linear MPC on the identified ROM around the nominal, with input limits.

At step k, from the estimate a_k = ahat_{k|k}, choose the input deviations
z = [du_k; ...; du_{k+H-1}] (H = min(horizon, N - k)) minimizing

    sum_{j=k}^{k+H-1} (a_j' Q_j a_j + du_j' R du_j) + a_{k+H}' S_{k+H} a_{k+H}
    a_{j+1} = A_j a_j + B_j du_j,      u_min - ubar_j <= du_j <= u_max - ubar_j,

with the LQR's weights (Q_j = C_j' Q_y,j C_j, R = lqr_r I) and its Riccati cost-to-go S as the
terminal weight, so that the unconstrained minimizer's first move is exactly the TV-LQR law
du_k = K_k a_k (dynamic programming).

With disturbance states (`sep_estimator.disturbance`) a is the filter's whole state z = [a; d]:
the prediction holds dhat constant, a_{j+1} = A_j a_j + B_j (du_j + E dhat) (input kind; a sensor
bias, the output kind, does not move a), the weight is Q_z = blockdiag(C' Q_y C, 0) and the
terminal weight the augmented Riccati cost-to-go (`sep_control.design.gains.lqr_gains`), so the
unconstrained first move is the augmented LQR law du_k = K_k z_k. du stays the real input
deviation, so its bounds are the limits minus the nominal as without disturbance states (in a
formulation on v = du + E dhat they would move by E dhat, per run).

Condensed, a_{k+i} = Phi_i a_k + Gamma_i z and

    cost = z' P_k z + 2 a_k' F_k' z + const,   P_k = Rbar + sum_i Gamma_i' Q Gamma_i,   F_k = Gamma' Qbar Phi.

P_k (its Cholesky factor) and F_k are computed once for every k (`RomMPC.__init__`; O(N H^3 n_u^2
n_r) flops, N (H n_u)^2 numbers). Per step: the unconstrained minimizer z0 = -P_k^{-1} F_k a_k
(a triangular solve); if it satisfies the bounds it is the QP's solution (exact, no solver).
Otherwise OSQP solves the box-constrained QP: set up once with P's dense upper-triangle pattern,
then P, q, l, u updated in place and warm-started from the previous solution shifted by one
step. A solve that does not converge, or runs past `time_budget_s`, falls back to the clipped
LQR command, counted (`MPCStats`); the returned input is always clipped to the limits (the
solver meets them only to its tolerance). Beyond the horizon's end (k + H > N) the padded
moves are fixed at zero.

Rate limits (problem key du_max): |u_j - u_{j-1}| <= du_max per channel adds the rows

    -du_max - (ubar_{k+i} - ubar_{k+i-1}) <= du_{k+i} - du_{k+i-1} <= du_max - (ubar_{k+i} - ubar_{k+i-1}),
    i = 1..H-1 (H = min(horizon, N - k)),

to the QP's constraint matrix [I; D], and the first move's box is intersected with
u_{k-1} -+ du_max - ubar_k, u_{k-1} the run's previous input (known: the law keeps it; none at
k = 0). The unconstrained minimizer is checked against all rows at once for every run (one
vectorized test); a run that violates one solves the QP. The returned input is clipped to the
box, then to u_{k-1} -+ du_max (`sep_plant.protocol.clip_rate`), so the plant never has to.

The Monte Carlo and the nodes run it as the control law `sep_control.control.controllers.MpcLaw`
(which keeps each run's warm start). Pure numpy/scipy + osqp: no ROS import.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from sep_estimator.ltv import LQG
from sep_plant.problem import Problem
from sep_plant.protocol import clip_inputs, clip_rate

from sep_control.design.gains import lqr_gains

#: OSQP's infinity (a constraint row with these bounds is free)
OSQP_INF = 1e30
#: OSQP settings: absolute/relative tolerance on the deviations (inputs are O(0.1-1)), and the
#: iteration cap; solution polishing makes the active set exact
OSQP_SETTINGS = dict(eps_abs=1e-8, eps_rel=1e-8, max_iter=4000, polishing=True, verbose=False,
                     warm_starting=True, adaptive_rho=True)
DEFAULT_HORIZON = 20
DEFAULT_BUDGET_S = 0.02


@dataclass
class MPCStats:
    """What the controller did: steps solved without the QP (unconstrained optimum feasible), by
    OSQP, and fallbacks to the clipped LQR (solver failure or over budget), with solve times."""

    horizon: int | None = None
    unconstrained: int = 0
    qp: int = 0
    fallbacks: int = 0
    fallback_reasons: dict = field(default_factory=dict)
    qp_seconds: list = field(default_factory=list)

    @classmethod
    def merged(cls, parts: Iterable["MPCStats"]) -> "MPCStats":
        """The counts of several controllers (the Monte Carlo's chunks) added up, in order."""
        out = cls()
        for p in parts:
            out.horizon = p.horizon if out.horizon is None else out.horizon
            out.unconstrained += p.unconstrained
            out.qp += p.qp
            out.fallbacks += p.fallbacks
            for why, n in p.fallback_reasons.items():
                out.fallback_reasons[why] = out.fallback_reasons.get(why, 0) + n
            out.qp_seconds.extend(p.qp_seconds)
        return out

    def as_dict(self) -> dict:
        """The summary and /diagnostics values (the same keys offline and online)."""
        t = np.asarray(self.qp_seconds)
        return {"mpc_horizon": self.horizon, "mpc_unconstrained_steps": self.unconstrained,
                "mpc_qp_steps": self.qp, "mpc_fallbacks": self.fallbacks,
                "mpc_fallback_reasons": dict(self.fallback_reasons),
                "mpc_qp_p50_s": float(np.percentile(t, 50)) if t.size else None,
                "mpc_qp_p99_s": float(np.percentile(t, 99)) if t.size else None}


class RomMPC:
    """Box-constrained TV-MPC on an LQG's model (the design's ROM) around the nominal input."""

    def __init__(self, lqg: LQG, problem: Problem, u_nom: np.ndarray, horizon: int = DEFAULT_HORIZON,
                 time_budget_s: float | None = None, solver_settings: dict | None = None):
        """`time_budget_s`: a QP slower than this falls back to the clipped LQR (online: the node
        sets DEFAULT_BUDGET_S); None (offline) never, so that results do not depend on load."""
        import osqp

        if horizon < 1:
            raise ValueError(f"MPC horizon must be >= 1, got {horizon}")
        m = lqg.model                   # the filter's model: z = [a; d] with disturbance states
        self.K = lqg.K
        self.u_nom = np.asarray(u_nom, dtype=float)
        self.N, self.n_u = self.u_nom.shape
        self.n, self.H = m.n, int(min(horizon, self.N))
        self.lo, self.hi = problem.limits(self.n_u)
        self.du_max = problem.channels("du_max", self.n_u)
        self.rated = bool(np.any(np.isfinite(self.du_max)))
        self.budget = None if time_budget_s is None else float(time_budget_s)
        _, S, Q, R = lqr_gains(lqg.rom, problem, lqg.disturbance)
        self.P, self.chol, self.F = self._condense(m.A, m.B, Q, R, S)
        nz = self.H * self.n_u
        # the dense upper triangle in CSC order (column by column, rows 0..j): a fixed pattern, so
        # every step's P_k is an in-place update of the values
        cols = np.repeat(np.arange(nz), np.arange(1, nz + 1))
        rows = np.concatenate([np.arange(j + 1) for j in range(nz)])
        self._iu = (rows, cols)
        indptr = np.concatenate([[0], np.cumsum(np.arange(1, nz + 1))])
        P0 = sp.csc_matrix((self.P[0][self._iu], rows, indptr), shape=(nz, nz))
        self.solver = osqp.OSQP()
        settings = {**OSQP_SETTINGS, **({"time_limit": self.budget} if self.budget else {}), **(solver_settings or {})}
        A = sp.identity(nz, format="csc")
        if self.rated:               # rows z_i - z_{i-1}, i = 1..H-1
            A = sp.vstack([A, self._difference()], format="csc")
        self.solver.setup(P=P0, q=np.zeros(nz), A=A, l=-np.ones(A.shape[0]), u=np.ones(A.shape[0]), **settings)
        self._rho0 = float(settings.get("rho", 0.1))
        self._solved = osqp.SolverStatus.OSQP_SOLVED
        self._time_limit = osqp.SolverStatus.OSQP_TIME_LIMIT_REACHED
        self._P_step = 0
        self.stats = MPCStats(horizon=self.H)

    # ------------------------------------------------------------ offline
    def _condense(self, A, B, Q, R, S):
        """P_k, chol(P_k) and F_k for k = 0..N-1 (moves past N padded with identity weight)."""
        N, n, n_u, H = self.N, self.n, self.n_u, self.H
        nz = H * n_u
        P = np.zeros((N, nz, nz))
        F = np.zeros((N, nz, n))
        for k in range(N):
            Hk = min(H, N - k)
            Pk = np.zeros((nz, nz))
            Fk = np.zeros((nz, n))
            Phi = np.eye(n)
            Gam = np.zeros((n, nz))                # a_{k+i} = Phi a_k + Gam z
            for i in range(Hk):
                j = k + i
                if i > 0:                          # stage cost on a_{k+i} (a_k itself: constant)
                    Pk += Gam.T @ Q[j] @ Gam
                    Fk += Gam.T @ Q[j] @ Phi
                Pk[i * n_u:(i + 1) * n_u, i * n_u:(i + 1) * n_u] += R
                Gam = A[j] @ Gam
                Gam[:, i * n_u:(i + 1) * n_u] += B[j]
                Phi = A[j] @ Phi
            Pk += Gam.T @ S[k + Hk] @ Gam          # terminal weight: the Riccati cost-to-go
            Fk += Gam.T @ S[k + Hk] @ Phi
            for i in range(Hk, H):                 # padding past N: du = 0, decoupled
                Pk[i * n_u:(i + 1) * n_u, i * n_u:(i + 1) * n_u] = np.eye(n_u)
            P[k] = 0.5 * (Pk + Pk.T)
            F[k] = Fk
        chol = np.stack([sla.cho_factor(P[k], lower=True)[0] for k in range(N)])
        return P, chol, F

    def bounds(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Bounds on z at step k: limits minus the nominal, zero for moves past N."""
        Hk = min(self.H, self.N - k)
        lo = np.zeros((self.H, self.n_u))
        hi = np.zeros((self.H, self.n_u))
        lo[:Hk] = self.lo - self.u_nom[k:k + Hk]
        hi[:Hk] = self.hi - self.u_nom[k:k + Hk]
        return lo.ravel(), hi.ravel()

    def _difference(self) -> sp.csc_matrix:
        """D ((H-1) n_u, H n_u): (D z)_i = du_{k+i} - du_{k+i-1}, i = 1..H-1."""
        H, n_u = self.H, self.n_u
        D = sp.diags([np.ones(H * n_u), -np.ones(H * n_u)], [0, -n_u], shape=(H * n_u, H * n_u), format="csr")
        return D[n_u:]

    def rate_bounds(self, k: int, prev: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of every constraint row (box rows, then the difference rows) at step k for runs
        whose previous inputs are `prev` (M, n_u) (None: none, step 0): (M, H n_u + (H-1) n_u) each."""
        H, n_u, N = self.H, self.n_u, self.N
        Hk = min(H, N - k)
        lo_box, hi_box = self.bounds(k)
        M = 1 if prev is None else prev.shape[0]
        lo = np.tile(lo_box, (M, 1))
        hi = np.tile(hi_box, (M, 1))
        if prev is not None and k > 0:           # the first move within du_max of u_{k-1}
            lo[:, :n_u] = np.maximum(lo[:, :n_u], prev - self.du_max - self.u_nom[k])
            hi[:, :n_u] = np.minimum(hi[:, :n_u], prev + self.du_max - self.u_nom[k])
        d_lo = np.full((H - 1, n_u), -OSQP_INF)
        d_hi = np.full((H - 1, n_u), OSQP_INF)
        if Hk > 1:
            dnom = np.diff(self.u_nom[k:k + Hk], axis=0)          # (Hk-1, n_u)
            d_lo[:Hk - 1] = np.maximum(-self.du_max - dnom, -OSQP_INF)
            d_hi[:Hk - 1] = np.minimum(self.du_max - dnom, OSQP_INF)
        return (np.concatenate([lo, np.tile(d_lo.ravel(), (M, 1))], axis=1),
                np.concatenate([hi, np.tile(d_hi.ravel(), (M, 1))], axis=1))

    def _rows(self, Z: np.ndarray) -> np.ndarray:
        """[z, D z] of solutions Z (M, H n_u): every constraint row's value."""
        Zr = Z.reshape(Z.shape[0], self.H, self.n_u)
        return np.concatenate([Z, (Zr[:, 1:] - Zr[:, :-1]).reshape(Z.shape[0], -1)], axis=1)

    # ------------------------------------------------------------- online
    def unconstrained(self, k: int, a: np.ndarray) -> np.ndarray:
        """The unconstrained minimizers for estimates a (M, n): (M, H n_u)."""
        return self._unconstrained(k, np.atleast_2d(a) @ self.F[k].T)

    def _unconstrained(self, k: int, q: np.ndarray) -> np.ndarray:
        return -sla.cho_solve((self.chol[k], True), q.T).T

    def command(self, k: int, a: np.ndarray, warm: np.ndarray | None = None,
                fail: bool = False, prev: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """u_k for one estimate a (n,): (input (n_u,), the solution to warm-start the next step
        from, None after a fallback). The online path is `command_batch` of one run, so it equals
        the offline Monte Carlo's. `fail` forces the fallback path (for tests and benchmarks);
        `prev` (n_u,): u_{k-1}, for the rate limits."""
        fallbacks = self.stats.fallbacks
        U, Z = self.command_batch(k, np.atleast_2d(a), None if warm is None else np.atleast_2d(warm), fail,
                                  None if prev is None else np.atleast_2d(prev))
        return U[0], (None if self.stats.fallbacks > fallbacks else Z[0])

    def command_batch(self, k: int, A_hat: np.ndarray, warm: np.ndarray | None = None,
                      fail: bool = False, prev: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """u_k for M estimates (M, n) at once: the feasible unconstrained ones in one solve, the
        others one QP each (`fail`: every one falls back). `prev` (M, n_u): the runs' inputs of
        step k-1 (rate limits; None: none). Returns (inputs (M, n_u), solutions (M, H n_u) for
        warm starts; zero after a fallback)."""
        Q = A_hat @ self.F[k].T                       # the QPs' linear terms, (M, H n_u)
        Z = self._unconstrained(k, Q)
        if self.rated:                                 # every run's rows at once (vectorized)
            if prev is not None and prev.shape[0] != Z.shape[0]:
                prev = None
            L, Uu = self.rate_bounds(k, prev)
            R = self._rows(Z)
            tol = 1e-12 * (1.0 + np.abs(R))
            ok = np.all((R >= L - tol) & (R <= Uu + tol), axis=1) & (not fail)
            bound_of = (lambda r: (L[r if L.shape[0] > 1 else 0], Uu[r if Uu.shape[0] > 1 else 0]))
        else:
            lo, hi = self.bounds(k)
            tol = 1e-12 * (1.0 + np.abs(Z))
            ok = np.all((Z >= lo - tol) & (Z <= hi + tol), axis=1) & (not fail)
            bound_of = (lambda r: (lo, hi))
        self.stats.unconstrained += int(ok.sum())
        U = self.u_nom[k] + Z[:, :self.n_u]
        for r in np.flatnonzero(~ok):
            z, why = (None, "forced") if fail else self._solve(k, A_hat[r], *bound_of(r),
                                                               None if warm is None else warm[r], Q[r])
            if z is None:
                self.stats.fallbacks += 1
                self.stats.fallback_reasons[why] = self.stats.fallback_reasons.get(why, 0) + 1
                U[r] = self.u_nom[k] + self.K[k] @ A_hat[r]
                Z[r] = 0.0
            else:
                self.stats.qp += 1
                U[r] = self.u_nom[k] + z[:self.n_u]
                Z[r] = z
        U = self._clip(U)
        if self.rated and prev is not None and k > 0:
            U = clip_rate(U, prev, self.du_max)
        return U, Z

    def shift(self, z: np.ndarray | None) -> np.ndarray | None:
        """A solution of step k as the warm start of step k+1 (moves shifted, last one held)."""
        if z is None:
            return None
        Z = np.asarray(z).reshape(*np.shape(z)[:-1], self.H, self.n_u)
        out = np.concatenate([Z[..., 1:, :], Z[..., -1:, :]], axis=-2)
        return out.reshape(np.shape(z))

    def _solve(self, k: int, a: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               warm: np.ndarray | None, q: np.ndarray | None = None) -> tuple[np.ndarray | None, str]:
        """The box QP of step k for the estimate a (its linear term q = F_k a when given)."""
        t0 = time.perf_counter()
        if self._P_step != k:
            self.solver.update(Px=self.P[k][self._iu])
            self._P_step = k
        self.solver.update(q=self.F[k] @ a if q is None else q, l=lo, u=hi)
        # every solve starts from the same solver state (rho, duals) and its own warm start, so a
        # run's inputs do not depend on which runs were solved before it (batch = one by one)
        self.solver.update_settings(rho=self._rho0)
        x0 = np.zeros_like(lo) if warm is None else warm
        nz = self.H * self.n_u
        self.solver.warm_start(x=np.clip(x0, lo[:nz], hi[:nz]), y=np.zeros_like(lo))
        res = self.solver.solve(raise_error=False)
        dt = time.perf_counter() - t0
        self.stats.qp_seconds.append(dt)
        if res.info.status_val == self._time_limit or (self.budget is not None and dt > self.budget):
            return None, "over time budget"
        if res.info.status_val != self._solved or res.x is None or not np.all(np.isfinite(res.x)):
            return None, f"osqp: {res.info.status}"
        return np.clip(res.x, lo[:nz], hi[:nz]), "ok"

    def _clip(self, u: np.ndarray) -> np.ndarray:
        return clip_inputs(u, self.lo, self.hi)
