"""The objectives the optimizer minimizes: the nominal cost and the belief-space cost.

Nominal cost (`sep_plant.problem.Objective.cost`, docs/method.md), of the noise-free trajectory:
    J(U) = sum_{k=1..N} q_k mean_i (f_{k,i} - f*_i)^2 + r_u sum_{k=0..N-1} |u_k|^2.

Belief space: the cost of a belief b_k = (mu_k, Sigma_k) is
    J_b = sum_k q_k mean_i [(mu_{k,i} - f*_i)^2 + Sigma_{k,ii}] + r_u sum |u_k|^2,
with the belief from an EnKF along the nominal observations ybar_k = h(xbar_k(U)) (fixed
random numbers and antithetic pairs, so J_b is a deterministic function of U whose mean
has no first-order sampling noise to overfit).
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_estimator.enkf import EnKFResult, EnsembleKalmanFilter
from sep_plant.device import array_module_of, device_runs_per_batch, step_resident, to_device, to_host_of
from sep_plant.problem import Objective, Problem
from sep_plant.protocol import Plant, nominal_states, noise_channels

from sep_control.compute.budget import runs_per_batch


def objective_of(plant: Plant, problem: Problem) -> Objective:
    """The problem's objective on this plant's field nodes."""
    return Objective.of(problem, np.asarray(plant.field_coordinates()), float(plant.dt))


def belief_cost(belief: EnKFResult, U: np.ndarray, obj: Objective) -> float:
    """J_b: nominal cost of the belief mean plus the weighted mean variance."""
    spread = float(obj.q[1:] @ np.mean(belief.std[1:] ** 2, axis=1))
    return float(obj.cost(belief.mean, U)) + spread


def run_belief(plant: Plant, U: np.ndarray, problem: Problem, members: int, seed: int,
               memory_budget: int | None = None, X: np.ndarray | None = None) -> EnKFResult:
    """EnKF belief of the field along the nominal observations of U (same random numbers for every U).

    The members' forecast steps go in batches that fit `memory_budget` (`sep_control.compute.budget`):
    a plant's step needs several state-sized temporaries per run, so 200 members of a large grid
    in one call would need far more than the ensemble itself. Runs do not interact, so the
    batching changes no member.

    Parameters
    ----------
    plant, U, problem
        The plant, the nominal input (N, n_u) and the problem (noise stds).
    members : int
        EnKF members (even: antithetic pairs).
    seed : int
        Seed of the EnKF's random numbers (the design's `enkf_seed`).
    memory_budget : int, optional
        Bytes for one batch of member steps (None: the default budget).
    X : ndarray, shape (N+1, n_x), optional
        The nominal states of U when the caller has them (None: rolled out here).

    Returns
    -------
    EnKFResult
        Belief mean and std of the field, (N+1, n_field) each.
    """
    ybar = plant.observe(nominal_states(plant, U) if X is None else X)
    n_w = noise_channels(plant)
    xp, stepper = array_module_of(plant), step_resident(plant)      # on a device the ensemble stays there
    batch = (runs_per_batch(int(plant.n_x), int(plant.n_field), memory_budget) if xp is np
             else device_runs_per_batch(plant))

    def step(X: np.ndarray, Uk: np.ndarray, Wk: np.ndarray | None = None) -> np.ndarray:
        if X.shape[0] <= batch:
            return stepper(X, Uk) if Wk is None else stepper(X, Uk, Wk)
        out = xp.empty_like(X)
        for a in range(0, X.shape[0], batch):
            b = slice(a, a + batch)
            out[b] = stepper(X[b], Uk[b]) if Wk is None else stepper(X[b], Uk[b], Wk[b])
        return out

    enkf = EnsembleKalmanFilter(step, plant.observe, problem.channels("w_std", n_w),
                                problem.channels("v_std", int(plant.n_y)), np.random.default_rng(seed),
                                antithetic=True, field=plant.field,
                                noise_on_inputs=bool(getattr(plant, "noise_on_inputs", True)),
                                upload=lambda a: to_device(plant, a), download=lambda a: to_host_of(plant, a))
    return enkf.run(plant.initial_state(members), U, ybar)
