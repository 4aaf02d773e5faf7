"""The nominal corrected for the limits' clipping of the feedback, on the ROM (no plant steps).

Under input limits the separation of nominal and feedback breaks: the LQG law
u_k = clip(ubar_k + K_k zhat_k) loses the part of its feedback that the limits cut off, and how
much depends on where the nominal sits. On a flat optimum the open-loop optimizer may stop
anywhere; where it holds inputs at a limit, every run's feedback is clipped on one side there
(the FMU rod: without limits both of two nominals of equal J give a closed-loop cost of 7.38, with
them 9.33 and 9.74).

The designed ROM predicts that cost. A Monte Carlo of the closed loop on the ROM, M runs in
lockstep, with the same filter (the LQG's model, gains L_k, K_k) and the law's clipping,
estimates the expected objective of the closed loop around the nominal moved by Delta:

    x_{k+1} = A_k x_k + B_k (u_k - ubar_k) + B_w,k w_k          x: the ROM state's deviation
    a^D_{k+1} = A_k a^D_k + B_k Delta_k                         the moved nominal, to first order
    zhat_k = zhat_k^- + L_k (C_k (x_k - a^D_k) + v_k - C_z,k zhat_k^-)
    u_k = clip(ubar_k + Delta_k + K_k zhat_k)  (then the rate clip of |u_k - u_{k-1}| <= du_max)
    zhat_{k+1}^- = A_z,k zhat_k + B_z,k (u_k - ubar_k - Delta_k)
    J = sum_{k>=1} (q_k / n_f) |e_k + G_k x_k|^2 + r_u sum_k |u_k|^2,   e_k = fbar_k - f*_k

(|e + G x|^2 through G_k' G_k and G_k' e_k: nothing of size n_f per run). With the random
numbers held (common random numbers) J is piecewise quadratic in Delta; its gradient comes from
one reverse (adjoint) pass, and L-BFGS-B minimizes it inside the limits. Only the ROM's
validity bounds the move: the design rolls the moved nominal out on the plant, identifies and
designs again, and keeps whichever design the ROM Monte Carlo of fresh random numbers predicts
cheaper (`sep_control.design.pipeline`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from sep_estimator.ltv import LQG, psd_factor
from sep_plant.problem import Objective, Problem
from sep_plant.protocol import rate_clip_sequence

#: runs of the ROM Monte Carlo (ROM-sized arrays only: 500 runs x 250 steps x 22 states is 1 MB a step's history)
SAMPLES = 500
#: L-BFGS-B iterations of the correction
MAX_ITER = 200


@dataclass(frozen=True)
class ClosedLoopRom:
    """What the ROM Monte Carlo needs of a design: the LQG, the nominal and the objective."""

    lqg: LQG
    u_nom: np.ndarray        # (N, n_u) ubar
    f_nom: np.ndarray        # (N+1, n_f) fbar
    objective: Objective
    lo: np.ndarray           # (n_u,)
    hi: np.ndarray           # (n_u,)
    du_max: np.ndarray | None
    W: np.ndarray            # (n_w, n_w) the ROM's process noise covariance
    V: np.ndarray            # (n_y, n_y)

    @property
    def rom(self):
        """The ROM the LQG was designed on (its filter's model without disturbance states)."""
        return self.lqg.rom if self.lqg.rom is not None else self.lqg.model

    @classmethod
    def of(cls, lqg: LQG, u_nom: np.ndarray, f_nom: np.ndarray, objective: Objective,
           problem: Problem) -> "ClosedLoopRom":
        rom = lqg.rom if lqg.rom is not None else lqg.model
        n_u = u_nom.shape[1]
        lo, hi = problem.limits(n_u)
        du = problem.channels("du_max", n_u)
        W, V = problem.noise_covariances(rom.noise_input.shape[2], rom.C.shape[1])
        return cls(lqg, np.asarray(u_nom, float), np.asarray(f_nom, float), objective,
                   np.broadcast_to(lo, (n_u,)).astype(float), np.broadcast_to(hi, (n_u,)).astype(float),
                   None if np.all(np.isinf(du)) else np.asarray(du, float), W, V)


class _Noise:
    """The Monte Carlo's random numbers, drawn once (common random numbers for every Delta)."""

    def __init__(self, rom, W: np.ndarray, V: np.ndarray, M: int, seed: int):
        rng = np.random.default_rng(seed)
        N, n = rom.A.shape[0], rom.A.shape[1]
        self.x0 = (rng.standard_normal((M, n)) @ psd_factor(rom.initial_covariance()).T)
        self.w = rng.standard_normal((N, M, W.shape[0])) @ psd_factor(W).T
        self.v = rng.standard_normal((N + 1, M, V.shape[0])) @ psd_factor(V).T


class RomClosedLoop:
    """J(Delta) and dJ/dDelta of the ROM Monte Carlo (module docstring) for one design.

    What does not depend on Delta is formed once per design (the correction's L-BFGS-B calls
    the Monte Carlo a few hundred times): w_k B_w,k' - ubar_k B_k' (common random numbers) and
    the transposed matrices. The filter's update goes through the n_y outputs (C x, then L):
    cheaper than through C' L' (n_r x n_z) when n_y is small."""

    def __init__(self, cl: ClosedLoopRom, samples: int = SAMPLES, seed: int = 0):
        self.cl = cl
        lqg = cl.lqg
        self.rom = rom = cl.rom
        self.zm = zm = lqg.model
        N, n_r = rom.A.shape[0], rom.A.shape[1]
        obj = cl.objective
        n_f = cl.f_nom.shape[1]
        self.w = np.asarray(obj.q, float) / n_f
        tgt = np.broadcast_to(obj.targets(0, N), cl.f_nom.shape)
        e = cl.f_nom - tgt
        self.ee = np.einsum("kf,kf->k", e, e)
        self.ge = np.stack([rom.G.project(k, e[k]) for k in range(N + 1)])      # G_k' e_k (N+1, n_r)
        self.gram = np.stack([rom.G.gram(k) for k in range(N + 1)])             # (N+1, n_r, n_r)
        self.N, self.n_r, self.M = N, n_r, samples
        self.K = lqg.K
        self.L = lqg.kf.L
        self.AT, self.BT = rom.A.transpose(0, 2, 1).copy(), rom.B.transpose(0, 2, 1).copy()
        self.CT, self.CzT = rom.C.transpose(0, 2, 1).copy(), zm.C.transpose(0, 2, 1).copy()
        self.AzT, self.BzT = zm.A.transpose(0, 2, 1).copy(), zm.B.transpose(0, 2, 1).copy()
        self.LT, self.KT = self.L.transpose(0, 2, 1).copy(), self.K.transpose(0, 2, 1).copy()
        noise = _Noise(rom, cl.W, cl.V, samples, seed)
        self.x0, self.v = noise.x0, noise.v
        self.cw = (np.einsum("kmw,kiw->kmi", noise.w, rom.noise_input)         # w_k B_w,k' - ubar_k B_k'
                   - np.einsum("ku,kiu->ki", cl.u_nom, rom.B)[:, None, :])

    def cost(self, delta: np.ndarray, limits: bool = True) -> float:
        """The expected closed-loop objective of the nominal moved by delta (N, n_u)."""
        return self._run(delta, limits, grad=False)[0]

    def cost_and_gradient(self, delta: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost with the limits and its gradient dJ/dDelta (N, n_u)."""
        return self._run(delta, True, grad=True)

    def _run(self, delta: np.ndarray, limits: bool, grad: bool):
        rom, zm, cl = self.rom, self.zm, self.cl
        N, M, r_u = self.N, self.M, float(cl.objective.r_u)
        ub, w = cl.u_nom, self.w
        lo, hi = (cl.lo, cl.hi) if limits else (np.full_like(cl.lo, -np.inf), np.full_like(cl.hi, np.inf))
        rate = cl.du_max if limits else None
        m = ub + delta                                            # the law's feed-forward
        aD = np.zeros((N + 1, self.n_r))                          # the moved nominal's ROM state
        for k in range(N):
            aD[k + 1] = rom.A[k] @ aD[k] + rom.B[k] @ delta[k]
        yD = np.einsum("kyi,ki->ky", rom.C[:N], aD[:N])           # C_k a^D_k
        mBz = np.einsum("ku,kzu->kz", m, zm.B)                    # (ubar_k + Delta_k) B_z,k'
        x = self.x0
        zmin = np.zeros((M, zm.A.shape[1]))
        J = np.zeros(M)
        X, U, MB, MR = [], [], [], []      # what the reverse pass needs (grad only)
        p = None
        for k in range(N + 1):
            if k >= 1:     # (q_k / n_f) |e_k + G_k x_k|^2 = w_k (e_k'e_k + x_k'(G_k'G_k x_k + 2 G_k'e_k))
                J += w[k] * (self.ee[k] + np.einsum("mi,mi->m", x, x @ self.gram[k] + 2.0 * self.ge[k]))
            if k == N:
                break
            innov = x @ self.CT[k]
            innov -= zmin @ self.CzT[k]
            innov += self.v[k] - yD[k]
            zhat = innov @ self.LT[k]
            zhat += zmin
            v = zhat @ self.KT[k]
            v += m[k]
            u = b = np.clip(v, lo, hi)
            mr = None
            if rate is not None and p is not None:
                u = np.clip(b, p - rate, p + rate)
                mr = (b > p - rate) & (b < p + rate)
            if grad:
                X.append(x); U.append(u); MB.append((v > lo) & (v < hi)); MR.append(mr)
            p = u
            J += r_u * np.einsum("mu,mu->m", u, u)
            x = x @ self.AT[k]
            x += u @ self.BT[k]
            x += self.cw[k]
            zmin = zhat @ self.AzT[k]
            zmin += u @ self.BzT[k]
            zmin -= mBz[k]
        Jm = float(J.mean())
        if not grad:
            return Jm, None
        # the reverse pass: adjoints of x_k, zhat_k^-, a^D_k and of u_{k-1} (the rate clip's p)
        g = np.zeros_like(delta)
        gx = 2.0 * w[N] * (self.ge[N] + x @ self.gram[N])
        gz = np.zeros_like(zmin)
        gD = np.zeros(self.n_r)
        gp = None
        for k in range(N - 1, -1, -1):
            gdu = gz @ zm.B[k]
            gu = gx @ rom.B[k]
            gu += gdu
            gu += (2.0 * r_u) * U[k]
            if gp is not None:
                gu += gp
            gdelta = gD @ rom.B[k] - gdu.sum(axis=0)
            if MR[k] is not None:
                gb, gp = np.where(MR[k], gu, 0.0), np.where(MR[k], 0.0, gu)
            else:
                gb, gp = gu, None
            gv = np.where(MB[k], gb, 0.0)
            gdelta += gv.sum(axis=0)
            gzhat = gz @ zm.A[k]
            gzhat += gv @ self.K[k]
            gy = gzhat @ self.L[k]
            gx = gx @ rom.A[k]
            gx += gy @ rom.C[k]
            gz = gzhat
            gz -= gy @ zm.C[k]
            gD = gD @ rom.A[k] - rom.C[k].T @ gy.sum(axis=0)
            if k >= 1:
                gx += 2.0 * w[k] * (self.ge[k] + X[k] @ self.gram[k])
            g[k] = gdelta
        return Jm, g / M


@dataclass(frozen=True)
class Correction:
    """The result of `correct_nominal`."""

    U: np.ndarray            # (N, n_u) the moved nominal ubar + Delta
    predicted: float         # the ROM Monte Carlo's closed-loop cost there (its random numbers)
    iterations: int          # L-BFGS-B's


def rate_violation(U: np.ndarray, du_max: np.ndarray) -> tuple[float, np.ndarray]:
    """V = sum_k |max(|u_k - u_{k-1}| - du_max, 0)|^2 over k >= 1 and its gradient dV/dU (N, n_u)."""
    D = np.diff(U, axis=0)
    v = np.maximum(np.abs(D) - du_max, 0.0)
    gD = 2.0 * v * np.sign(D)
    g = np.zeros_like(U)
    g[1:] += gD
    g[:-1] -= gD
    return float(np.sum(v * v)), g


#: the rate penalty's weights (continuation): rho_0 = C / (N n_u du_max^2), C the predicted cost
#: (a violation of du_max at every step then costs about C), then RATE_RHO_GROWTH times that
RATE_RHO_GROWTH = 100.0


def correct_nominal(mc: RomClosedLoop, before: float, max_iter: int = MAX_ITER) -> Correction:
    """Minimize the ROM Monte Carlo's expected closed-loop cost over Delta, lo <= ubar + Delta <= hi,
    from Delta = 0, where it is `before` (`mc.cost` of zeros).

    With rate limits the nominal must respect them too (the optimizer's nominal does): a
    quadratic penalty rho V(ubar + Delta) on their violation (`rate_violation`) joins the cost,
    minimized at rho_0 then at RATE_RHO_GROWTH rho_0 (max_iter / 2 iterations each), and what is
    left of the violation is clipped forward in time (`rate_clip_sequence`, as the optimizer's
    trials are); the predicted cost returned is that of the feasible nominal."""
    cl = mc.cl
    ub = cl.u_nom
    lo = np.broadcast_to(cl.lo, ub.shape) - ub
    hi = np.broadcast_to(cl.hi, ub.shape) - ub
    bounds = [(None if not np.isfinite(a) else float(a), None if not np.isfinite(b) else float(b))
              for a, b in zip(lo.ravel(), hi.ravel())]
    rate = cl.du_max
    rho0 = 0.0 if rate is None else before / (ub.size * float(np.max(rate)) ** 2)
    rhos = [0.0] if rate is None else [rho0, RATE_RHO_GROWTH * rho0]
    x, nit = np.zeros(ub.size), 0
    for rho in rhos:
        def fun(d: np.ndarray, rho: float = rho) -> tuple[float, np.ndarray]:
            J, g = mc.cost_and_gradient(d.reshape(ub.shape))
            if rho:
                V, gV = rate_violation(ub + d.reshape(ub.shape), rate)
                J, g = J + rho * V, g + rho * gV
            return J, g.ravel()

        res = minimize(fun, x, jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": max_iter // len(rhos)})
        x, nit = res.x, nit + int(res.nit)
    U = np.clip(ub + x.reshape(ub.shape), cl.lo, cl.hi)
    if rate is None:
        return Correction(U, float(res.fun), nit)
    U = rate_clip_sequence(U, rate)
    return Correction(U, mc.cost(U - ub), nit)
