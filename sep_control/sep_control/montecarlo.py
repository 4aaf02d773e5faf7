"""Closed-loop Monte Carlo on the nonlinear plant, vectorized across runs.

All M runs advance together: one batched plant step per step, one batched product per step
for the filter and the gains. Run i with base seed s uses the noise of
`sep_plant.noise.noise_sequences(problem, info, s, [i])`, the same numbers a plant node started
with seed=s, run=i draws, so a ROS episode reproduces run i exactly and every controller sees
the same random numbers (common random numbers).

Per step k = 0..N (as the ROS graph does it):
    y_k = h(x_k) + v_k;  ahat_{k|k} = KF update with y_k - ybar_k;
    u_k = clip(ubar_k + K_k ahat_{k|k})   (open loop: u_k = clip(ubar_k), the filter still runs);
    x_{k+1} = f(x_k, u_k, w_k);           ahat_{k+1|k} = KF predict with u_k - ubar_k.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from sep_estimator.design_file import Design
from sep_estimator.ltv import LQG
from sep_estimator.tvkf import KalmanFilter
from sep_plant.noise import noise_sequences
from sep_plant.protocol import Plant, clip_inputs

from .lqr import command
from .metrics import MetricsAccumulator
from .oracle import oracle_lqg


@dataclass
class MonteCarloResult:
    controller: str
    F: np.ndarray          # (M_keep, N+1, n_field) true field of the first M_keep runs (all by default)
    U: np.ndarray          # (M, N, n_u) applied inputs (after limits, before process noise)
    Y: np.ndarray          # (M, N+1, n_y) measurements
    F_hat: np.ndarray      # (M_est, N+1, n_field) reconstructed field of the first M_est runs
    F_std: np.ndarray      # (N+1, n_field) its per-node std (same for every run)
    F_mean: np.ndarray     # (N+1, n_field) mean true field over all runs
    coverage_2sigma: float  # over all runs, nodes and steps k >= 1
    summary: dict          # DESIGN.md §3 metrics over all runs (streamed, see MetricsAccumulator)

    def metrics(self) -> dict:
        return dict(self.summary)


CONTROLLER_NAMES = ("open_loop", "rom_lqg", "oracle_lqg")


def simulate(plant: Plant, design: Design, controller: str, seed: int, runs: int | Iterable[int],
             oracle: LQG | None = None, keep_estimates: int | None = None,
             keep_trajectories: int | None = None) -> MonteCarloResult:
    """Run `controller` ('open_loop', 'rom_lqg' or 'oracle_lqg') on `plant` for the given runs.

    Metrics are accumulated step by step over all runs; the full field trajectories (and
    estimates) are kept for the first `keep_trajectories` (`keep_estimates`) runs, all by
    default. Keep few on large grids: M N n_field numbers add up.
    """
    if controller not in CONTROLLER_NAMES:
        raise ValueError(f"unknown controller {controller!r}: use {', '.join(CONTROLLER_NAMES)}")
    problem, info, nom = design.problem, design.info, design.nominal
    idx = range(runs) if isinstance(runs, int) else list(runs)
    w, v = noise_sequences(problem, info, seed, idx)
    M, N = w.shape[0], problem.n_steps
    lqg = (oracle if oracle is not None else oracle_lqg(design, plant)) if controller == "oracle_lqg" \
        else design.lqg
    feedback = controller != "open_loop"
    lo, hi = problem.limits(info.n_u)
    kf = KalmanFilter(lqg, batch=M)
    G = lqg.model.G
    n_keep = M if keep_estimates is None else min(M, keep_estimates)
    n_traj = M if keep_trajectories is None else min(M, keep_trajectories)
    acc = MetricsAccumulator(design.objective, nom.field, M)

    F = np.empty((n_traj, N + 1, info.n_field))
    U = np.empty((M, N, info.n_u))
    Y = np.empty((M, N + 1, info.n_y))
    F_hat = np.empty((n_keep, N + 1, info.n_field))
    covered = 0
    x = plant.initial_state(M)
    for k in range(N + 1):
        f = plant.field(x)
        F[:, k] = f[:n_traj]
        acc.add_field(k, f)
        Y[:, k] = plant.observe(x) + v[:, k]
        a = kf.update(k, Y[:, k] - nom.y[k])
        est = nom.field[k] + G.apply(k, a)
        F_hat[:, k] = est[:n_keep]
        if k > 0:
            covered += int(np.count_nonzero(np.abs(est - f) <= 2.0 * lqg.field_std[k]))
        if k == N:
            break
        if feedback:
            u = command(nom.u[k], lqg.K[k], a, lo, hi)
        else:
            u = clip_inputs(np.broadcast_to(nom.u[k], (M, info.n_u)), lo, hi)
        U[:, k] = u
        acc.add_input(k, u)
        x = plant.step(x, u, w[:, k])
        kf.predict(k, u - nom.u[k])
    coverage = covered / (M * N * info.n_field)
    summary = acc.result({"coverage_2sigma": coverage})
    return MonteCarloResult(controller, F, U, Y, F_hat, lqg.field_std.copy(), acc.mean_traj, coverage, summary)
