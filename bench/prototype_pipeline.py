"""An independent, compact numpy prototype of the paper's pipeline, the yardstick of sep's design time.

Written from the method's description (docs/method.md), not from sep's code; it uses only the
scenario's plant (`step`, `observe`, `field`, `initial_state`) and the problem's numbers:

1. open-loop nominal U by projected gradient descent on the nominal cost
       J(U) = sum_{k=1..N} q_k mean_i (f_{k,i} - f*_i)^2 + r_u sum_k |u_k|^2,
   the gradient dJ/du_{j,c} from one forward-difference sensitivity run per (j, c), started from
   the nominal state at j and stepped to N (one batch growing by n_u runs a step), Armijo
   backtracking; stopped when an iteration lowers J by less than `settle` (relative) or after
   `max_iter` iterations;
2. the EnKF belief along the nominal (members stepped with process noise on the inputs, updated
   with perturbed observations of the noise-free nominal);
3. TV-ERA from central impulse experiments at every step (2 N n_u runs of p + q steps, one
   batch), a Hankel SVD per step, A_k from the shifted Hankel, C_k, B_k, the field map G_k;
4. the TV-LQR (output weights, lqr_r) and TV Kalman filter (W through B_k, V) recursions on the ROM.

    python bench/prototype_pipeline.py        # times it on the reference scenario
Pure numpy: no ROS import.
"""
from __future__ import annotations

import time

import numpy as np


def _rollout(plant, x0: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    X = [x0]
    for u in U:
        X.append(plant.step(X[-1][None], u[None])[0])
    X = np.array(X)
    return X, plant.field(X)


def _cost(F, U, target, q, r_u) -> float:
    return float(q[1:] @ np.mean((F[1:] - target) ** 2, axis=1) + r_u * np.sum(U**2))


def _gradient(plant, X, F, U, target, q, r_u, eps=1e-4) -> np.ndarray:
    """dJ/dU by forward differences: run (j, c) perturbed at step j, stepped from x_j to N."""
    N, n_u = U.shape
    runs = np.empty((N * n_u, X.shape[1]))
    g = 2 * r_u * U.copy()
    wF = 2.0 * q[:, None] * (F - target) / F.shape[1]           # dJ/df_k
    for k in range(N):
        runs[k * n_u:(k + 1) * n_u] = X[k]
        m = (k + 1) * n_u
        Uk = np.repeat(U[k][None], m, axis=0)
        Uk[k * n_u:m] += eps * np.eye(n_u)
        runs[:m] = plant.step(runs[:m], Uk)
        dF = (plant.field(runs[:m]) - F[k + 1]) / eps            # (m, n_f) runs' field responses at k+1
        g.reshape(-1)[:m] += dF @ wF[k + 1]
    return g


def nominal(plant, problem, max_iter=10, settle=1e-2):
    obj_target = problem.target_field(np.asarray(plant.field_coordinates()))
    q, r_u = problem.q_weights(), float(problem.r_u)
    lo, hi = problem.limits(plant.n_u)
    x0 = plant.initial_state(1)[0]
    U = np.clip(problem.u_start(plant.n_u), lo, hi)
    X, F = _rollout(plant, x0, U)
    J = _cost(F, U, obj_target, q, r_u)
    alpha, history = None, [J]
    for _ in range(max_iter):
        g = _gradient(plant, X, F, U, obj_target, q, r_u)
        if alpha is None:
            alpha = 0.1 * max(np.abs(U).max(), 1e-3) / max(np.abs(g).max(), 1e-300)
        for _trial in range(20):                                   # Armijo backtracking
            Ut = np.clip(U - alpha * g, lo, hi)
            Xt, Ft = _rollout(plant, x0, Ut)
            Jt = _cost(Ft, Ut, obj_target, q, r_u)
            if Jt <= J - 1e-4 * np.sum(g * (U - Ut)):
                break
            alpha *= 0.5
        else:
            break
        rel = (J - Jt) / J
        U, X, F, J = Ut, Xt, Ft, Jt
        history.append(J)
        alpha *= 2.0
        if rel < settle:
            break
    return U, X, history


def enkf(plant, problem, U, X, members=200, seed=0):
    rng = np.random.default_rng(seed)
    N = U.shape[0]
    w = problem.channels("w_std", plant.n_u)
    v = problem.channels("v_std", plant.n_y)
    E = plant.initial_state(members)
    mean, var = [E.mean(0)], [E.var(0)]
    for k in range(N):
        E = plant.step(E, U[k] + w * rng.standard_normal((members, plant.n_u)))
        y = plant.observe(X[k + 1][None])[0] + v * rng.standard_normal(plant.n_y)
        Y = plant.observe(E)
        A, Yd = E - E.mean(0), Y - Y.mean(0)
        S = Yd.T @ Yd / (members - 1) + np.diag(v**2)
        K = np.linalg.solve(S, (A.T @ Yd / (members - 1)).T).T
        E = E + (y + v * rng.standard_normal((members, plant.n_y)) - Y) @ K.T
        mean.append(E.mean(0))
        var.append(E.var(0))
    return np.array(mean), np.array(var)


def tv_era(plant, U, X, p=15, q=15, n_r=20, impulse=0.01, tol=1e-10):
    N, n_u = U.shape
    L = p + q
    Ue = np.vstack([U, np.repeat(U[-1:], L, axis=0)])
    Xe, _ = _rollout(plant, X[0], Ue)
    d = impulse * max(np.sqrt(np.mean(U**2)), 1e-3)
    j = np.repeat(np.arange(N), 2 * n_u)                          # run r: start j, channel c, sign
    pert = np.tile(np.vstack([np.eye(n_u), -np.eye(n_u)]) * d, (N, 1))
    R = Xe[j].copy()
    Y = np.empty((N, L, plant.n_y, n_u))
    Yf = np.empty((N, q, plant.n_field, n_u))
    for t in range(L):
        R = plant.step(R, Ue[j + t] + (pert if t == 0 else 0.0))
        o = plant.observe(R).reshape(N, 2, n_u, -1)
        Y[:, t] = ((o[:, 0] - o[:, 1]) / (2 * d)).transpose(0, 2, 1)
        if t < q:
            f = plant.field(R).reshape(N, 2, n_u, -1)
            Yf[:, t] = ((f[:, 0] - f[:, 1]) / (2 * d)).transpose(0, 2, 1)

    def hankel(k, shift, qk):
        return np.hstack([np.vstack([Y[k - 1 - m, shift + m + i] for i in range(p)]) for m in range(qk)])

    A, B = np.zeros((N, n_r, n_r)), np.zeros((N, n_r, n_u))
    C, G = np.zeros((N + 1, plant.n_y, n_r)), np.zeros((N + 1, plant.n_field, n_r))
    Op, Rp, dims = [None] * (N + 1), [None] * (N + 1), np.zeros(N + 1, int)
    for k in range(1, N + 1):
        qk = min(q, k)
        Us, S, Vt = np.linalg.svd(hankel(k, 0, qk), full_matrices=False)
        n = int(min(n_r, np.sum(S > tol * S[0])))
        s = np.sqrt(S[:n])
        dims[k] = n
        C[k, :, :n] = (Us[:, :n] * s)[:plant.n_y]
        B[k - 1, :n] = (s[:, None] * Vt[:n])[:, :n_u]
        Op[k], Rp[k] = Us[:, :n].T / s[:, None], Vt[:n].T / s
        G[k, :, :n] = np.hstack([Yf[k - 1 - m, m] for m in range(qk)]) @ Rp[k]
    for k in range(1, N):
        A[k, :dims[k + 1], :dims[k]] = Op[k + 1] @ hankel(k, 1, min(q, k)) @ Rp[k]
    return A, B, C, G


def lqg(problem, A, B, C, n_y):
    N, n_r, n_u = B.shape
    wq = problem.lqr_output_weights(n_y)
    Rl = problem.lqr_r * np.eye(n_u)
    P = wq[N] * C[N].T @ C[N]
    K = np.zeros((N, n_u, n_r))
    for k in range(N - 1, -1, -1):
        BP = B[k].T @ P
        K[k] = np.linalg.solve(Rl + BP @ B[k], BP @ A[k])
        P = wq[k] * C[k].T @ C[k] + A[k].T @ P @ (A[k] - B[k] @ K[k])
        P = 0.5 * (P + P.T)
    W = np.diag(problem.channels("w_std", n_u) ** 2)
    V = np.diag(problem.channels("v_std", n_y) ** 2)
    Sig, Lg = np.zeros((n_r, n_r)), np.zeros((N + 1, n_r, n_y))
    for k in range(N):
        Sig = A[k] @ Sig @ A[k].T + B[k] @ W @ B[k].T
        Ck = C[k + 1]
        Lg[k + 1] = np.linalg.solve(Ck @ Sig @ Ck.T + V, Ck @ Sig).T
        Sig = (np.eye(n_r) - Lg[k + 1] @ Ck) @ Sig
    return K, Lg


def prototype_design(plant, problem) -> dict:
    """The four steps, timed; returns their seconds and the nominal cost's history."""
    t = [time.perf_counter()]
    U, X, history = nominal(plant, problem)
    t.append(time.perf_counter())
    enkf(plant, problem, U, X)
    t.append(time.perf_counter())
    A, B, C, G = tv_era(plant, U, X)
    t.append(time.perf_counter())
    lqg(problem, A, B, C, plant.n_y)
    t.append(time.perf_counter())
    s = np.diff(t)
    return {"total_s": t[-1] - t[0], "nominal_s": s[0], "enkf_s": s[1], "tvera_s": s[2], "lqg_s": s[3],
            "J": history[-1], "iterations": len(history) - 1}


if __name__ == "__main__":
    from sep_plant.scenario import reference
    scen = reference()
    print(prototype_design(scen.plant, scen.problem))
