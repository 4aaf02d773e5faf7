"""Shared helpers for the tests/test_core_*.py tests of the pure numerical core.

Everything here is written from the equations of docs/method.md and the documented index
conventions, *not* from the library's internals, so that the tests check the library
against an independent reference:

* `dense_step` / `dense_jacobians`: the backward-Euler slab step with K frozen at T_k as a
  dense linear solve, and its exact (analytic) Jacobians.
* `linear_system`: random stable LTI/LTV test systems; `kalman_filter`: the textbook KF.
* `flat`: a scenario from sep 0.1's flat slab keys (the slab and its problem in one mapping);
  `coarse_scenario`: the reference physics on a coarse grid / time step (see its docstring).
* `cached_design` / `cached_oracle`: run_design / oracle_lqg results cached per process (tests
  treat them as read-only), so several test files share one design per scenario.

The slab helpers take a `SlabPlant` (its keys are attributes: n_x, length, k0, beta, ...).
* `one_blas_thread`: a fixture limiting BLAS to one thread (import it into a test module).
* `rewrite_design_file`: a copy of a design file with its meta or members changed (format tests).
"""
from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

from sep_plant.plants.slab import SlabPlant
from sep_plant.scenario import Scenario

Slab = SlabPlant


# --------------------------------------------------------------- slab model
def d2_matrix(n_x: int, h: float) -> np.ndarray:
    """Second difference with the insulated-left ghost node (T_{-1} = T_1) and the Dirichlet
    node x = L eliminated (its contribution T_right / h^2 on the last row is *not* included)."""
    D = np.zeros((n_x, n_x))
    for i in range(n_x):
        D[i, i] = -2.0
        if i > 0:
            D[i, i - 1] = 1.0
        if i < n_x - 1:
            D[i, i + 1] = 1.0
    D[0, 1] = 2.0
    return D / h**2


def conductivity(s: SlabPlant, T: np.ndarray) -> np.ndarray:
    """K(x_i, T_i) = k0 (1 + beta (T - t_ref)/t_scale)(1 + gamma x/L)."""
    x = np.arange(s.n_x) * s.length / s.n_x
    return s.k0 * (1.0 + s.beta * (T - s.t_ref) / s.t_scale) * (1.0 + s.gamma * x / s.length)


def conductivity_dT(s: SlabPlant) -> np.ndarray:
    """dK/dT at every node (K is affine in T)."""
    x = np.arange(s.n_x) * s.length / s.n_x
    return s.k0 * s.beta / s.t_scale * (1.0 + s.gamma * x / s.length)


def heater_matrix(s: SlabPlant) -> np.ndarray:
    """b_j(x_i): unit-mass Gaussians, computed from the scenario numbers directly."""
    x = np.arange(s.n_x) * s.length / s.n_x
    out = np.empty((s.n_x, s.n_u))
    sig = s.heater_sigma * s.length
    for j, c in enumerate(s.heater_centers):
        out[:, j] = np.exp(-0.5 * ((x - c * s.length) / sig) ** 2) / (sig * math.sqrt(2 * math.pi))
    return out


def spatial_operator(s: SlabPlant, T_k: np.ndarray, T: np.ndarray) -> np.ndarray:
    """K(T_k) (D2 T + Dirichlet term) - eta T: the right-hand side of the PDE without inputs."""
    h = s.length / s.n_x
    lap = d2_matrix(s.n_x, h) @ T
    lap[-1] += s.t_right / h**2
    return conductivity(s, T_k) * lap - s.eta * T


def dense_step(s: SlabPlant, T: np.ndarray, u: np.ndarray) -> np.ndarray:
    """T_{k+1} from T_{k+1} - T_k = dt [K(T_k)(D2 T_{k+1} + bc) - eta T_{k+1} + B u] (dense solve)."""
    h = s.length / s.n_x
    K = conductivity(s, T)
    M = (1.0 + s.dt * s.eta) * np.eye(s.n_x) - s.dt * K[:, None] * d2_matrix(s.n_x, h)
    rhs = T + s.dt * heater_matrix(s) @ u
    rhs[-1] += s.dt * K[-1] * s.t_right / h**2
    return np.linalg.solve(M, rhs)


def dense_jacobians(s: SlabPlant, T: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact dT_{k+1}/dT_k and dT_{k+1}/du_k of `dense_step`.

    M(T_k) T_{k+1} = T_k + dt B u + bc(T_k), row i of M and bc depend on T_k only through
    K_i(T_{k,i}), so d/dT_{k,i}: M dT_{k+1} = e_i [1 + dt K_i' (D2 T_{k+1} + bc/K)_i].
    """
    h = s.length / s.n_x
    K = conductivity(s, T)
    M = (1.0 + s.dt * s.eta) * np.eye(s.n_x) - s.dt * K[:, None] * d2_matrix(s.n_x, h)
    T1 = dense_step(s, T, u)
    lap = d2_matrix(s.n_x, h) @ T1
    lap[-1] += s.t_right / h**2
    A = np.linalg.solve(M, np.diag(1.0 + s.dt * conductivity_dT(s) * lap))
    B = np.linalg.solve(M, s.dt * heater_matrix(s))
    return A, B


# ------------------------------------------------------------ linear systems
def stable_matrix(rng: np.random.Generator, n: int, radius: float) -> np.ndarray:
    """Random n x n matrix with spectral norm `radius` (so every product of them is stable)."""
    M = rng.standard_normal((n, n))
    return radius * M / np.linalg.norm(M, 2)


def ltv_system(rng: np.random.Generator, steps: int, n: int, n_u: int, n_y: int, n_f: int,
               radius: float = 0.9):
    """A_k, B_k (k < steps), C_k, F_k (k <= steps) of a random stable LTV system."""
    A = np.stack([stable_matrix(rng, n, radius) for _ in range(steps)])
    B = rng.standard_normal((steps, n, n_u))
    C = rng.standard_normal((steps + 1, n_y, n))
    F = rng.standard_normal((steps + 1, n_f, n))
    return A, B, C, F


def kalman_filter(A, B, C, W, V, m0, P0, U, Y):
    """Textbook KF for x+ = A x + B (u + w), y = C x + v (LTI), filtering Y[1..N].

    Returns posterior means (N+1, n) and covariances (N+1, n, n) (k = 0: the prior)."""
    N = U.shape[0]
    m, P = np.array(m0, float), np.array(P0, float)
    means, covs = [m.copy()], [P.copy()]
    for k in range(N):
        m = A @ m + B @ U[k]
        P = A @ P @ A.T + B @ W @ B.T
        S = C @ P @ C.T + V
        G = P @ C.T @ np.linalg.inv(S)
        m = m + G @ (Y[k + 1] - C @ m)
        P = P - G @ S @ G.T
        means.append(m.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs)


# --------------------------------------------------------------- scenarios
def flat(**keys) -> Scenario:
    """A canonical scenario from sep 0.1's flat keys (slab keys and problem keys in one mapping)."""
    return Scenario.from_dict(keys)


def coarse_scenario(n_x: int = 30, n_steps: int = 80, **changes) -> Scenario:
    """The reference physics and 62.5 s horizon on a coarse grid and a coarse time step.

    dt = 62.5 s / n_steps, k_band and lqr_k_switch at the same *times* as the reference
    (37.5 s and 30 s). The noise is rescaled so that it means the same in continuous time:
    process noise w (held for one step) contributes variance ~ dt w_std^2 per second, and
    sensor information ~ 1 / (dt v_std^2) per second, so both stds scale with sqrt(0.25 / dt).
    Without this rescaling a 3x larger step means ~3x the process-noise power and a third of
    the measurements, and no controller can keep the field in the band (checked: ROM-LQG and
    the oracle both fall to ~27 % in band at n_x = 30, N = 80, w_std = 0.3, v_std = 1), which
    would test the scenario rather than the method.
    """
    dt = 62.5 / n_steps
    f = math.sqrt(0.25 / dt)
    base = dict(n_x=n_x, n_steps=n_steps, dt=dt, k_band=round(37.5 / dt), lqr_k_switch=round(30.0 / dt),
                w_std=0.3 * f, v_std=1.0 * f)
    base.update(changes)
    return flat(**base)


@functools.lru_cache(maxsize=None)
def cached_design(scenario: Scenario, **settings):
    """run_design(scenario, DesignSettings(**settings)), computed once per test process."""
    from threadpoolctl import threadpool_limits

    from sep_control.design.pipeline import DesignSettings, run_design

    # one BLAS thread, as the CLI does by default: many small matrices, 2 cores
    with threadpool_limits(limits=1):
        return run_design(scenario.plant, scenario.problem, DesignSettings(**settings), show_progress=False,
                          log=lambda msg: None)


@functools.lru_cache(maxsize=None)
def cached_oracle(scenario: Scenario, **settings):
    from threadpoolctl import threadpool_limits

    from sep_control.evaluation.oracle import oracle_lqg

    design = cached_design(scenario, **settings)
    with threadpool_limits(limits=1):
        return oracle_lqg(design, scenario.plant)


@pytest.fixture
def one_blas_thread():
    """Fixture (import it into a test module as a fixture): one BLAS thread for the test.
    The work is many small matrices; on 2 shared cores extra BLAS threads only oversubscribe."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        yield


#: a tiny but meaningful scenario (sep 0.1's flat slab keys): 20 nodes, 40 steps over the reference's
#: 62.5 s, the band from 37.5 s; the CLI, packaging and install tests design it in about a second
TINY_YAML = """\
# tiny test scenario (keys that differ from the reference)
n_x: 20
n_steps: 40
dt: 1.5625
k_band: 24
lqr_k_switch: 19
w_std: 0.12
v_std: 0.4
"""


# --------------------------------------------------------------- design files
def rewrite_design_file(src, dst, edit_meta=None, **arrays):
    """Copy a design file with meta changed by `edit_meta(dict)` and members replaced/removed (None)."""
    with np.load(src, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    m = json.loads(members["meta"].tobytes().decode())
    if edit_meta is not None:
        m = edit_meta(m)
    members["meta"] = np.frombuffer(json.dumps(m).encode(), dtype=np.uint8)
    for k, v in arrays.items():
        if v is None:
            members.pop(k)
        else:
            members[k] = v
    np.savez(dst, **members)
    return dst
