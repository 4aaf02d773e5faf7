"""Open-loop nominal trajectory optimization from black-box experiments only.

Nominal cost (`sep_plant.problem`) written as a sum of squares J(U) = |r(U)|^2 with
    r = [ sqrt(q_k / n_f) (f_k - f*)  (k = 1..N),  sqrt(r_u) u_k  (k = 0..N-1) ],
f_k = field(x_k) the plant's field (n_f nodes) along the noise-free trajectory.

Sensitivities df_k/du_j come from impulse-sensitivity experiments on the plant:
perturb input channel c at step j by eps and run from the nominal state at j. All
N n_u experiments run as one batch in lockstep, so at step k only the n_u (k+1)
experiments that have started are simulated (the active part), and their field
deviations D_k (n_u (k+1), n_f) are folded straight into the Gauss-Newton normal
equations  J'J += (q_k/n_f) D_k D_k',  J'r += (q_k/n_f) D_k (f_k - f*)  without
storing the N n_f x N n_u Jacobian.

Methods:
* ``gn`` (default): Levenberg-Marquardt on (J'J + lambda diag(J'J)) dU = -J'r with
  accept/reject on the true cost; converges in a few iterations.
* ``gd``: the paper's gradient descent U <- U - alpha grad J (grad J = 2 J'r) with
  backtracking; slow, kept for comparison.

Belief space: the cost of a belief b_k = (mu_k, Sigma_k) is
    J_b = sum_k q_k mean_i [(mu_{k,i} - f*_i)^2 + Sigma_{k,ii}] + r_u sum |u_k|^2,
with the belief from an EnKF along the nominal observations ybar_k = h(xbar_k(U)) (fixed
random numbers and antithetic pairs, so J_b is a deterministic function of U whose mean
has no first-order sampling noise to overfit). Its GN step uses the
nominal-trajectory sensitivities (d mu / dU = d xbar / dU to first order, since the
filter follows observations that move with the nominal), and each step is accepted
on the true J_b.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from sep_estimator.enkf import EnKFResult, EnsembleKalmanFilter
from sep_plant.problem import Objective, Problem
from sep_plant.protocol import Plant, fields, nominal_states, noise_channels

from sep_control.compute.budget import runs_per_batch
from sep_control.evaluation.metrics import nominal_cost
from sep_control.compute.progress import progress
from sep_control.design.tvera import identify


# ------------------------------------------------------------------ helpers
def objective_of(plant: Plant, problem: Problem) -> Objective:
    """The problem's objective on this plant's field nodes."""
    return Objective.of(problem, np.asarray(plant.field_coordinates()))


def belief_cost(belief: EnKFResult, U: np.ndarray, obj: Objective) -> float:
    """J_b: nominal cost of the belief mean plus the weighted mean variance."""
    spread = float(obj.q[1:] @ np.mean(belief.std[1:] ** 2, axis=1))
    return float(nominal_cost(belief.mean, U, obj)) + spread


def run_belief(plant: Plant, U: np.ndarray, problem: Problem, members: int, seed: int,
               memory_budget: int | None = None) -> EnKFResult:
    """EnKF belief of the field along the nominal observations of U (same random numbers for every U).

    The members' forecast steps go in batches that fit `memory_budget` (`sep_control.compute.budget`):
    a plant's step needs several state-sized temporaries per run, so 200 members of a large grid
    in one call would need far more than the ensemble itself. Runs do not interact, so the
    batching changes no member."""
    ybar = plant.observe(nominal_states(plant, U))
    n_w = noise_channels(plant)
    batch = runs_per_batch(int(plant.n_x), int(plant.n_field), memory_budget)

    def step(X: np.ndarray, Uk: np.ndarray, Wk: np.ndarray | None = None) -> np.ndarray:
        if X.shape[0] <= batch:
            return plant.step(X, Uk) if Wk is None else plant.step(X, Uk, Wk)
        out = np.empty_like(X)
        for a in range(0, X.shape[0], batch):
            b = slice(a, a + batch)
            out[b] = plant.step(X[b], Uk[b]) if Wk is None else plant.step(X[b], Uk[b], Wk[b])
        return out

    enkf = EnsembleKalmanFilter(step, plant.observe, problem.channels("w_std", n_w),
                                problem.channels("v_std", int(plant.n_y)), np.random.default_rng(seed),
                                antithetic=True, field=plant.field,
                                noise_on_inputs=bool(getattr(plant, "noise_on_inputs", True)))
    return enkf.run(plant.initial_state(members), U, ybar)


@dataclass
class NormalEquations:
    JtJ: np.ndarray    # (N n_u, N n_u)
    Jtr: np.ndarray    # (N n_u,)
    experiments: int   # simulator runs used
    run_steps: int     # run-steps simulated


def sensitivity_normal_equations(plant: Plant, U: np.ndarray, Xbar: np.ndarray, obj: Objective,
                                 eps: float = 1e-4, residual_field: np.ndarray | None = None,
                                 gram: bool = True) -> NormalEquations:
    """Build J'J and J'r from N n_u batched impulse-sensitivity experiments around (Xbar, U).

    Xbar (N+1, n_x) are the nominal states; `residual_field` (N+1, n_f) replaces their field as
    the trajectory whose residual f_k - f* enters J'r (the belief mean, for the belief-space
    problem). Columns are ordered (j, c) -> j n_u + c. With gram=False only J'r is formed.
    """
    N, n_u = U.shape
    n = N * n_u
    q = obj.q
    Fbar = fields(plant, Xbar)
    n_f = Fbar.shape[1]
    res = (Fbar if residual_field is None else residual_field) - obj.target
    JtJ = np.zeros((n, n)) if gram else np.empty((0, 0))
    Jtr = np.zeros(n)
    X = np.empty((0, Xbar.shape[1]))
    eye = np.eye(n_u) * eps
    run_steps = 0
    # J'J is formed chunk by chunk: the weighted Jacobian rows of `chunk` steps are laid side by
    # side (row c holds experiment c's field deviations at those steps, zero before it started)
    # and multiplied as rows @ rows.T in one BLAS call (a symmetric rank-k update), which runs
    # several times faster than one small product per step and 1.4x faster than the transposed
    # layout's rows.T @ rows (plate 64^2: 1.37 vs 2.01 s per Gram matrix, one core)
    chunk = max(1, min(N, (1 << 22) // max(1, n_f * n)))
    rows = np.zeros((n, chunk * n_f)) if gram else None
    filled = 0
    for k in range(N):
        # start the n_u experiments of step k from the nominal state, then step every active run
        X = np.vstack([X, np.repeat(Xbar[k][None], n_u, axis=0)])
        Uk = np.repeat(U[k][None], X.shape[0], axis=0)
        Uk[-n_u:] += eye
        X = plant.step(X, Uk)
        run_steps += X.shape[0]
        D = (plant.field(X) - Fbar[k + 1]) / eps               # (n_u (k+1), n_f)
        m = D.shape[0]
        w = q[k + 1] / n_f
        Jtr[:m] += w * (D @ res[k + 1])
        if gram:
            np.multiply(D, np.sqrt(w), out=rows[:m, filled * n_f:(filled + 1) * n_f])
            filled += 1
            if filled == chunk or k == N - 1:
                used = rows[:m, :filled * n_f]
                JtJ[:m, :m] += used @ used.T
                used[:] = 0.0
                filled = 0
    # input penalty r_u |u|^2
    if gram:
        JtJ[np.diag_indices(n)] += obj.r_u
    Jtr += obj.r_u * U.ravel()
    return NormalEquations(JtJ, Jtr, n, run_steps)


def rom_normal_equations(plant: Plant, U: np.ndarray, obj: Objective, residual_field: np.ndarray,
                         p: int = 15, q: int = 15, n_r: int = 20, sv_tol: float = 1e-10,
                         impulse: float = 0.01) -> NormalEquations:
    """J'J and J'r of the ROM Jacobian, formed densely (for checks: the optimizer solves the
    same Gauss-Newton step through `RomLinearization` without forming them).

    The field sensitivities df_k/du_j are taken from the identified ROM, G_k A_{k-1} ... A_{j+1} B_j:
        M_k = [A_{k-1} M_{k-1}, B_{k-1}]   (n_r x k n_u: the state response to every past input)
        J'J += M_k' (w_k G_k' G_k) M_k,   J'r += M_k' w_k G_k' (f_k - f*),   w_k = q_k / n_f.
    """
    N, n_u = U.shape
    n = N * n_u
    ident = identify(plant, U, p, q, n_r, sv_tol, impulse)
    model = ident.model
    res = residual_field - obj.target
    w = obj.q / res.shape[1]
    JtJ = np.zeros((n, n))
    Jtr = np.zeros(n)
    M = np.zeros((model.n, n))
    for k in range(1, N + 1):
        m = n_u * k
        M[:, :m - n_u] = model.A[k - 1] @ M[:, :m - n_u]
        M[:, m - n_u:m] = model.B[k - 1]
        Mk = M[:, :m]
        JtJ[:m, :m] += Mk.T @ ((w[k] * model.G.gram(k)) @ Mk)
        Jtr[:m] += Mk.T @ (w[k] * model.G.project(k, res[k]))
    JtJ[np.diag_indices(n)] += obj.r_u
    Jtr += obj.r_u * U.ravel()
    return NormalEquations(JtJ, Jtr, ident.data.experiments, ident.data.experiments * (p + q))


# ------------------------------------------------------------ linearizations
#: an identification at U' serves at U when max|U - U'| <= SAME_INPUT_RTOL max|U'|: the Markov
#: parameters then differ by O(1e-6) relative, the accuracy the identification itself reaches
SAME_INPUT_RTOL = 1e-6


def same_input(U_a: np.ndarray, U_b: np.ndarray, rtol: float = SAME_INPUT_RTOL) -> bool:
    """Whether a linearization at U_a serves at U_b: max|U_a - U_b| <= rtol max|U_a|."""
    return U_a.shape == U_b.shape and float(np.max(np.abs(U_a - U_b))) <= \
        rtol * max(float(np.max(np.abs(U_a))), 1e-12)
class SensitivityLinearization:
    """Gauss-Newton/LM steps and gradients from dense normal equations (sensitivity Jacobian)."""

    def __init__(self, ne: NormalEquations, shape: tuple[int, int]):
        self.ne, self.shape, self.experiments = ne, shape, ne.experiments
        self.identification = None

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
        return 2.0 * self.ne.Jtr.reshape(self.shape)

    def predicted_change(self, dU: np.ndarray) -> float:
        """The Gauss-Newton model's change of the cost, 2 J'r dU + dU' J'J dU."""
        d = dU.ravel()
        return float(2.0 * self.ne.Jtr @ d + d @ (self.ne.JtJ @ d))


class RomLinearization:
    """The Gauss-Newton model of the cost on an identified ROM, solved as a linear-quadratic
    problem (no N n_u x N n_u matrix): with the field deviation df_k = G_k a_k,
    a_{k+1} = A_k a_k + B_k du_k, a_0 = 0, the LM step minimizes

        sum_{k=1..N} w_k |G_k a_k + e_k|^2 + sum_j [ r_u |u_j + du_j|^2 + lam du_j' D_j du_j ],

    e_k = f_k - f* (the nominal's field, or the belief mean), w_k = q_k / n_f, D_j the diagonal of
    the Gauss-Newton matrix J'J (Levenberg-Marquardt scaling, as the dense solve uses). One
    backward Riccati pass with affine terms and one forward pass: O(N n_r^3), whatever n_x is;
    G enters only through G_k' G_k and G_k' e_k (`FieldMap.gram`, `FieldMap.project`). The step
    equals the dense solve of the same Jacobian (tests/test_rom_jacobian.py)."""

    def __init__(self, identification, obj: Objective, residual_field: np.ndarray, U: np.ndarray):
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


#: an accepted step that moved U by at most NEAR_OPTIMUM (max |dU| / max |U|) or lowered the cost
#: by at most NEAR_DECREASE (relative) marks the optimum's neighbourhood: the Gauss-Newton steps
#: after it move U by 1e-3 and less, or lower the cost by 1e-5 and less (every shipped scenario;
#: Allen-Cahn's weakly weighted inputs, r_u = 1e-5, still move by percents there), so a model
#: identified there is the one the belief refinement and the design go on with
NEAR_OPTIMUM = 1e-2
NEAR_DECREASE = 1e-3

#: relative damping of an input held at an active bound in the ROM step (see RomLinearization.step)
FREEZE = 1e10


def active_bounds(U: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Inputs at a bound whose descent direction leaves the box (projected-gradient active set):
    u <= lo with dJ/du > 0, or u >= hi with dJ/du < 0. Those are held in the next step, so that
    the step of the free inputs is not spent against a bound and then clipped away."""
    span = np.maximum(np.abs(hi - lo), 1.0)
    span = np.where(np.isfinite(span), span, 1.0)
    eps = 1e-9 * span
    return ((U <= lo + eps) & (grad > 0)) | ((U >= hi - eps) & (grad < 0))


# --------------------------------------------------------------- optimizer
@dataclass
class OptimizationResult:
    U: np.ndarray                          # (N, n_u) optimized nominal input
    cost: float                            # final objective (nominal or belief cost)
    history: list[float] = field(default_factory=list)   # objective after each iteration
    iterations: int = 0
    experiments: int = 0                   # black-box runs used for sensitivities
    seconds: float = 0.0
    method: str = "gn"
    objective: str = "nominal"
    identification: object = None          # ROM path: the last TV-ERA model (at or near the final U)
    belief: EnKFResult | None = None       # belief objective: the belief at the final U
    linearizations: list[str] = field(default_factory=list)  # "sensitivity", "rom", "rom (proposal)", "rom (kept)"
    stop: str = ""                         # why it stopped


def optimize(plant: Plant, problem: Problem, U0: np.ndarray | None = None, method: str = "gn",
             objective: str = "nominal", max_iter: int | None = None, tol: float = 1e-7,
             eps: float = 1e-4, step_size: float = 1e-3, members: int = 200, seed: int = 0,
             show_progress: bool = True, jacobian: str = "sensitivity",
             rom: dict | None = None, reuse: "OptimizationResult | None" = None,
             chord: bool = False, max_trials: int = 12,
             bounds: tuple[np.ndarray, np.ndarray] | None = None,
             relinearize_rtol: float = SAME_INPUT_RTOL, rom_near_optimum: bool = False,
             rom_proposal: dict | None = None) -> OptimizationResult:
    """Minimize the nominal (``objective='nominal'``) or belief-space (``'belief'``) cost.

    method ``gn`` (Levenberg-Marquardt) or ``gd`` (gradient descent with step `step_size`
    and backtracking). `jacobian` ``sensitivity`` (N n_u impulse-sensitivity experiments) or
    ``rom`` (a TV-ERA model identified at the iterates, settings `rom` passed to `identify`;
    the step is then an LQ problem on the ROM, `RomLinearization`); with `rom_near_optimum` the
    sensitivity Jacobian serves until an accepted step reaches the optimum's neighbourhood (it
    moves U by at most `NEAR_OPTIMUM` or lowers the objective by at most `NEAR_DECREASE`), and the
    ROM one from there on (one identification near the optimum, which the belief refinement and
    the design reuse, instead of N n_u more sensitivity runs). `rom_proposal` (settings that
    override `rom`, e.g. forward impulses and a coarser field basis) serves the identifications
    made far from the optimum (the first, and those after a step outside that neighbourhood):
    they only propose steps, which the true objective accepts,
    while the ones near the optimum, which the belief refinement and the design reuse, keep
    `rom`. Stops after
    `max_iter` iterations, when an accepted trial lowers the objective by less than `tol` relative
    (such a step is not taken: it keeps the last linearization at the final input), or, for the
    belief objective (gn), when the Gauss-Newton model predicts a decrease below `tol` relative
    for the next step (that trial, an EnKF run, is not evaluated). `stop` says which. Every
    step is accepted on the true objective, whichever Jacobian proposed it. With the ROM
    Jacobian the result carries its last identification (`identification`: at the final input,
    or within `relinearize_rtol` of it), and `reuse` (an earlier result) starts from it; `chord` keeps the
    first identification for every iteration (a chord method: the belief-space refinement moves
    U by ~1e-4 relative, and its Jacobian is the nominal's to first order anyway), and
    `relinearize_rtol` keeps it while U stays that close to where it was made (`same_input`;
    the default identifies again after every step). Near the optimum the Gauss-Newton steps move
    U by 1e-3 and less, and a model identified a step earlier proposes them as well: the steps
    are accepted on the true objective whichever model proposed them, and when every trial
    from a kept model fails, the trials are repeated once on a model identified at U.
    Input limits: the problem's u_min/u_max, or `bounds` = (lo, hi), each broadcastable to
    (N, n_u) (per-step bounds: the limits tightened by a margin for the feedback). Projected
    Levenberg-Marquardt: inputs at an active bound (`active_bounds`) are held, the others step,
    and the trial point is projected onto the box before the true objective accepts it.
    """
    if method not in ("gn", "gd"):
        raise ValueError(f"method must be 'gn' or 'gd', got {method!r}")
    if objective not in ("nominal", "belief"):
        raise ValueError(f"objective must be 'nominal' or 'belief', got {objective!r}")
    if jacobian not in ("sensitivity", "rom"):
        raise ValueError(f"jacobian must be 'sensitivity' or 'rom', got {jacobian!r}")
    max_iter = max_iter if max_iter is not None else (10 if method == "gn" else 60)
    t0 = time.perf_counter()
    n_u = int(plant.n_u)
    U = problem.u_start(n_u) if U0 is None else np.array(U0, dtype=float)
    lo, hi = problem.limits(n_u) if bounds is None else bounds
    lo = np.broadcast_to(np.asarray(lo, dtype=float), U.shape)
    hi = np.broadcast_to(np.asarray(hi, dtype=float), U.shape)
    bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
    U = np.clip(U, lo, hi)
    obj = objective_of(plant, problem)

    last_belief: dict = {}

    def evaluate(Uc: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        Xc = nominal_states(plant, Uc)
        Fc = fields(plant, Xc)
        if objective == "nominal":
            return float(nominal_cost(Fc, Uc, obj)), Xc, Fc
        b = run_belief(plant, Uc, problem, members, seed, (rom or {}).get("memory_budget"))
        last_belief["try"] = b
        return belief_cost(b, Uc, obj), Xc, b.mean

    # the newest identification (one: each holds the nominal states and the field basis), or the
    # one handed over by an earlier stage
    identified = [reuse.identification] if reuse is not None and reuse.identification is not None else []

    mode = [jacobian]      # "sensitivity" switches to "rom" near the optimum (rom_near_optimum)
    settled = [False]      # the last accepted step was in the optimum's neighbourhood

    def linearize(Uc: np.ndarray, Xc: np.ndarray, residual: np.ndarray, rtol: float = relinearize_rtol):
        if mode[0] == "rom":
            near = [i for i in identified if chord or same_input(i.U, Uc, rtol)]
            if near:
                ident = near[0]                       # identified at (or within rtol of) this input
            else:
                far = rom_proposal is not None and not settled[0]
                ident = identify(plant, Uc, **{**(rom or {}), **(rom_proposal if far else {})})
                identified[:] = [ident]
                result.experiments += ident.data.experiments
            result.linearizations.append("rom (kept)" if near else "rom (proposal)" if far else "rom")
            return RomLinearization(ident, obj, residual, Uc)
        ne = sensitivity_normal_equations(plant, Uc, Xc, obj, eps, residual, gram=(method == "gn"))
        result.experiments += ne.experiments
        result.linearizations.append("sensitivity")
        return SensitivityLinearization(ne, Uc.shape)

    J, X, field_for_residual = evaluate(U)
    result = OptimizationResult(U, J, [J], method=method, objective=objective)
    last_belief["b"] = last_belief.get("try")        # the belief at U until a step is taken
    lam, alpha = 1e-3, step_size
    lin = linearize(U, X, field_for_residual)
    bar = progress(range(max_iter), desc=f"optimize[{method},{objective}]", enabled=show_progress)

    # belief objective: a trial the Gauss-Newton model predicts to lower J_b by less than tol is
    # not evaluated (an EnKF run). The nominal objective evaluates every trial (one rollout): an
    # inexact model (a ROM Jacobian, Burgers: Markov error 2.5e-4) can predict less than tol where
    # the true cost still falls by more (stopping there left Burgers' optimum 2e-5 higher)
    predict_stop = method == "gn" and objective == "belief"

    def attempt(lin, lam: float, alpha: float):
        """Up to max_trials damped steps from U: ("accepted", ...) with the first the true objective
        accepts, ("converged", ...) when `predict_stop` and the Gauss-Newton model predicts a
        decrease below tol relative (the trial is not evaluated), else ("rejected", ...)."""
        frozen = active_bounds(U, lin.gradient(), lo, hi) if bounded else None
        for _ in range(max_trials):
            if method == "gn":
                dU = lin.step(lam, frozen)
            else:
                dU = -alpha * lin.gradient()
                if frozen is not None:
                    dU[frozen] = 0.0
            U_try = np.clip(U + dU, lo, hi)
            if predict_stop and 0.0 <= -lin.predicted_change(U_try - U) < tol * J:
                return "converged", lam, alpha, None
            J_try, X_try, f_try = evaluate(U_try)
            if np.isfinite(J_try) and J_try < J:
                return "accepted", lam, alpha, (U_try, J_try, X_try, f_try)
            lam, alpha = lam * 4.0, alpha * 0.5
        return "rejected", lam, alpha, None

    for it in bar:
        outcome, lam_next, alpha_next, trial = attempt(lin, lam, alpha)
        if outcome == "rejected" and lin.identification is not None and not chord \
                and not same_input(lin.identification.U, U):
            # every trial failed on a model kept from an earlier input: once more on one made here
            settled[0] = True
            lin = linearize(U, X, field_for_residual, SAME_INPUT_RTOL)
            outcome, lam_next, alpha_next, trial = attempt(lin, lam, alpha)
        lam, alpha = lam_next, alpha_next
        if outcome != "accepted":
            result.stop = ("the model predicts a decrease below tol" if outcome == "converged"
                           else f"no trial of {max_trials} lowered the objective")
            break
        U_try, J_try, X_try, f_try = trial
        rel = (J - J_try) / max(J, 1e-300)
        if rel < tol:
            # a decrease below tol is no real improvement (for the belief an ensemble estimate's),
            # and staying at U keeps the linearization made here (an identification the belief
            # refinement and the design reuse) at the final input
            result.stop = "the step lowered the objective by less than tol (not taken)"
            break
        moved = float(np.max(np.abs(U_try - U))) / max(float(np.max(np.abs(U))), 1e-12)
        settled[0] = moved <= NEAR_OPTIMUM or rel <= NEAR_DECREASE
        U, J, X, field_for_residual = U_try, J_try, X_try, f_try
        last_belief["b"] = last_belief.get("try")
        lam, alpha = max(lam / 3.0, 1e-9), alpha * 1.2
        result.history.append(J)
        result.iterations = it + 1
        if hasattr(bar, "set_postfix"):
            bar.set_postfix(J=f"{J:.6g}")
        if it == max_iter - 1 and lin.identification is None:
            result.stop = f"max_iter = {max_iter}"
            break
        if rom_near_optimum and lin.identification is None and settled[0]:
            mode[0] = "rom"     # near the optimum: TV-ERA once, here, instead of N n_u sensitivity runs
        lin = linearize(U, X, field_for_residual)   # ROM path at the end too: the design reuses it
        if it == max_iter - 1:
            result.stop = f"max_iter = {max_iter}"
    # the ROM path ends with its last identification, at the final input or within
    # relinearize_rtol of it: a later stage's chord starts from it, and the design reuses it as
    # its TV-ERA model when it is at the final input (`same_input`) instead of identifying again
    result.identification = getattr(lin, "identification", None)
    result.belief = last_belief.get("b")
    result.U, result.cost, result.seconds = U, J, time.perf_counter() - t0
    return result
