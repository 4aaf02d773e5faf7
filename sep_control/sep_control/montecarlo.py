"""Closed-loop Monte Carlo on the nonlinear simulator, vectorized across runs.

All M runs advance together: one banded solve per step for the plant, one batched
product per step for the filter and the gains. Run i with base seed s uses the noise
of `sep_plant.noise.noise_sequences(scenario, s, [i])`, the same numbers a plant node
started with seed=s, run=i draws, so a ROS episode reproduces run i exactly and every
controller sees the same random numbers (common random numbers).

Per step k = 0..N (as the ROS graph does it):
    y_k = h(T_k) + v_k;  ahat_{k|k} = KF update with y_k - ybar_k;
    u_k = clip(ubar_k + K_k ahat_{k|k})   (open loop: u_k = ubar_k, the filter still runs);
    T_{k+1} = f(T_k, u_k + w_k);          ahat_{k+1|k} = KF predict with u_k - ubar_k.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_estimator.design_file import Design
from sep_estimator.tvkf import filter_from_schedule
from sep_plant.noise import noise_sequences
from sep_plant.slab import SlabSimulator, clip_inputs

from .lqr import command
from .metrics import MetricsAccumulator
from .oracle import LinearLQG, oracle_lqg, rom_lqg


@dataclass
class MonteCarloResult:
    controller: str
    T: np.ndarray          # (M_keep, N+1, n_x) true field of the first M_keep runs (all by default)
    U: np.ndarray          # (M, N, n_u) applied inputs (after limits, before process noise)
    Y: np.ndarray          # (M, N+1, n_y) measurements
    T_hat: np.ndarray      # (M_est, N+1, n_x) reconstructed field of the first M_est runs
    T_std: np.ndarray      # (N+1, n_x) its per-node std (same for every run)
    T_mean: np.ndarray     # (N+1, n_x) mean true field over all runs
    coverage_2sigma: float  # over all runs, nodes and steps k >= 1
    summary: dict          # DESIGN.md §3 metrics over all runs (streamed, see MetricsAccumulator)

    def metrics(self, design: Design | None = None) -> dict:
        return dict(self.summary)


def simulate(design: Design, controller: str, seed: int, runs: int | range | list[int],
             oracle: LinearLQG | None = None, keep_estimates: int | None = None,
             sim: SlabSimulator | None = None, keep_trajectories: int | None = None) -> MonteCarloResult:
    """Run `controller` ('open_loop', 'rom_lqg' or 'oracle_lqg') for the given runs.

    Metrics are accumulated step by step over all runs; the full field trajectories (and
    estimates) are kept for the first `keep_trajectories` (`keep_estimates`) runs, all by
    default. Keep few on large grids: M N n_x numbers add up.
    """
    if controller not in ("open_loop", "rom_lqg", "oracle_lqg"):
        raise ValueError(f"unknown controller {controller!r}: use open_loop, rom_lqg or oracle_lqg")
    s = design.scenario
    sim = sim or SlabSimulator(s)
    idx = range(runs) if isinstance(runs, int) else runs
    w, v = noise_sequences(s, seed, idx)
    M, N = w.shape[0], s.n_steps
    if controller == "oracle_lqg":
        lqg = oracle if oracle is not None else oracle_lqg(design, sim)
    else:
        lqg = rom_lqg(design)
    feedback = controller != "open_loop"
    kf = filter_from_schedule(lqg.A, lqg.B, lqg.C, lqg.G, lqg.L, lqg.P_post, s.w_std, s.v_std, batch=M)
    n_keep = M if keep_estimates is None else min(M, keep_estimates)
    n_traj = M if keep_trajectories is None else min(M, keep_trajectories)
    acc = MetricsAccumulator(s, design.T_nom, M)

    T = np.empty((n_traj, N + 1, s.n_x))
    U = np.empty((M, N, s.n_u))
    Y = np.empty((M, N + 1, s.n_y))
    T_hat = np.empty((n_keep, N + 1, s.n_x))
    covered = 0
    x = sim.initial_state(M)
    for k in range(N + 1):
        T[:, k] = x[:n_traj]
        acc.add_state(k, x)
        Y[:, k] = sim.observe(x) + v[:, k]
        a = kf.update(k, Y[:, k] - design.y_nom[k])
        est = design.T_nom[k] + a @ lqg.G[k].T
        T_hat[:, k] = est[:n_keep]
        if k > 0:
            covered += int(np.count_nonzero(np.abs(est - x) <= 2.0 * lqg.field_std[k]))
        if k == N:
            break
        if feedback:
            u = command(design.u_nom[k], lqg.K[k], a, s.u_min, s.u_max)
        else:
            u = clip_inputs(np.broadcast_to(design.u_nom[k], (M, s.n_u)), s)
        U[:, k] = u
        acc.add_input(k, u)
        x = sim.step(x, u, w[:, k])
        kf.predict(k, u - design.u_nom[k])
    coverage = covered / (M * N * s.n_x)
    summary = acc.result({"coverage_2sigma": coverage})
    return MonteCarloResult(controller, T, U, Y, T_hat, lqg.field_std.copy(), acc.mean_traj, coverage,
                            summary)
