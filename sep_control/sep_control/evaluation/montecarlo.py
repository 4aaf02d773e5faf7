"""Closed-loop Monte Carlo on the nonlinear plant, vectorized across runs.

All M runs advance together: one batched plant step per step, one batched product per step
for the filter and the gains. Run i with base seed s uses the noise of
`sep_plant.noise.noise_sequences(problem, info, s, [i])`, the same numbers a plant node started
with seed=s, run=i draws, so a ROS episode reproduces run i exactly and every controller sees
the same random numbers (common random numbers).

Per step k = 0..N (as the ROS graph does it):
    y_k = h(x_k) + v_k;  ahat_{k|k} = KF update with y_k - ybar_k;
    u_k = controller.command(k, ahat_{k|k})   (`sep_control.control.controllers`: clip(ubar_k + K_k ahat),
                                              clip(ubar_k) in open loop, where the filter still runs,
                                              or the ROM-MPC's first move);
    x_{k+1} = f(x_k, u_k, w_k);           ahat_{k+1|k} = KF predict with u_k - ubar_k.

Rate limits (du_max): the plant enforces |u_k - u_{k-1}| <= du_max on the command as the plant
node does (`sep_plant.protocol.clip_rate`), and the summary adds rate_clips (channel-steps the
law's own rate clip changed: the LQR's), rate_violations (channel-steps the plant had to clip)
and rate_at_limit (share of channel-steps k >= 1 with |u_k - u_{k-1}| at du_max).

On a device (`sep_plant.device`) the runs' states stay there for the whole rollout
(`_Resident`): the plant steps them there, the metrics reduce the field there (per-run sums and
the summed field cross, `MetricsAccumulator.add_field`), the reconstruction f_nom + Phi (g_k a)
and the 2-sigma coverage count are formed there (Phi uploaded once), and only the outputs
(M n_y), the per-run sums and the kept trajectories come to the host. The filter and the
controller (n_r-sized) run on the host.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from sep_estimator.design import Design
from sep_estimator.ltv import LQG
from sep_estimator.tvkf import KalmanFilter
from sep_plant.device import array_module_of, base_plant, check_finite, step_resident, to_device, to_host_of
from sep_plant.initial import initial_states
from sep_plant.noise import noise_sequences
from sep_plant.protocol import Plant, clip_rate

from sep_control.compute.budget import runs_per_batch, worker_budget
from sep_control.control.controllers import CONTROLLER_NAMES, Controller, MpcOptions, make_controller
from sep_control.control.mpc import MPCStats
from sep_control.evaluation.metrics import MetricsAccumulator
from sep_control.evaluation.oracle import AffineTerms, Oracle, oracle_lqg


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
    summary: dict          # metrics (docs/method.md) over all runs (streamed, see MetricsAccumulator)

    def metrics(self) -> dict:
        return dict(self.summary)


__all__ = ["CONTROLLER_NAMES", "MonteCarloResult", "portable", "simulate"]


# ~72 lines: 42 of them the public function's numpydoc docstring
def simulate(plant: Plant, design: Design, controller: str, seed: int, runs: int | Iterable[int],
             oracle: LQG | Oracle | None = None, keep_estimates: int | None = None,
             keep_trajectories: int | None = None, memory_budget: int | None = None,
             engine=None, show_progress: bool = False,
             mpc: MpcOptions | dict | None = None) -> MonteCarloResult:
    """Closed-loop Monte Carlo of `controller` on `plant`, every run stepped together.

    Metrics are accumulated step by step over all runs. The runs go in chunks that fit
    `memory_budget`, one task each on `engine`; each run's noise is its own (seed, run) stream
    and every per-run quantity is computed row by row, so the chunking changes no result (the
    chunks' partial sums, the mean field, are added in chunk order).

    Parameters
    ----------
    plant : Plant
        The simulator (any plant of the plant protocol, docs/plants.md).
    design : Design
        The design file's contents: nominal, ROM, LQG, problem.
    controller : str
        'open_loop', 'rom_lqg', 'oracle_lqg' or 'rom_mpc' (`sep_control.control.controllers`).
    seed : int
        Base seed: run i draws `sep_plant.noise.noise_sequences(problem, info, seed, [i])`, the
        numbers of a plant node started with seed, run = i.
    runs : int or iterable of int
        A count (runs 0..M-1) or the run indices.
    oracle : LQG or Oracle, optional
        The oracle for 'oracle_lqg' (from the plant's Jacobians when None); an `Oracle` with
        affine terms is the full-order ideal of a truth plant (`oracle.truth_oracle`): its filter
        starts at a0, predicts with + r_k, updates with dy_k - e_k, and its law's nominal input
        is ubar_k + kappa_k.
    keep_estimates, keep_trajectories : int, optional
        How many runs' reconstructed (true) field trajectories to keep; all by default (keep
        few on large grids: M N n_field numbers add up).
    memory_budget : int, optional
        Bytes per chunk (`sep_control.compute.budget`; default a quarter of the free memory).
    engine : optional
        A `sep_control.compute.engine` engine; this process by default (on a cluster: at least
        two chunks per worker). `show_progress`: a progress bar over the chunks.
    mpc : MpcOptions or dict, optional
        Options of 'rom_mpc'; its counts join the summary (`MPCStats.as_dict`, the mpc_* keys).

    Returns
    -------
    MonteCarloResult
        Inputs and measurements of every run, the kept trajectories, the metrics
        (docs/method.md) in `summary`.
    """
    from sep_control.compute.engine import InProcess

    if controller not in CONTROLLER_NAMES:
        raise ValueError(f"unknown controller {controller!r}: use {', '.join(CONTROLLER_NAMES)}")
    engine = engine or InProcess()
    idx = list(range(runs) if isinstance(runs, int) else runs)
    M = len(idx)
    affine = None
    if controller == "oracle_lqg":
        orc = oracle if oracle is not None else oracle_lqg(design, plant)
        lqg, affine = (orc.lqg, orc.affine) if isinstance(orc, Oracle) else (orc, None)
    else:
        lqg = design.lqg
    n_keep = M if keep_estimates is None else min(M, keep_estimates)
    n_traj = M if keep_trajectories is None else min(M, keep_trajectories)
    batch = _batch_size(design, engine, M, memory_budget)
    chunks = [(a, idx[a:a + batch], max(0, min(batch, n_traj - a)), max(0, min(batch, n_keep - a)))
              for a in range(0, M, batch)]
    shared = dict(plant=engine.ship(plant), design=design if engine.local else portable(design), lqg=lqg,
                  controller=controller, seed=seed, mpc=MpcOptions.of(mpc), affine=affine)
    labels = [f"plant {type(base_plant(plant)).__name__}: Monte Carlo {controller}, runs {c[1][0]}..{c[1][-1]} (seed {seed})"
              for c in chunks]
    parts = engine.map(_mc_chunk, chunks, shared, labels, f"Monte Carlo {controller}",
                       show_progress=show_progress and len(chunks) > 1)
    return _assemble(design, controller, lqg, chunks, parts, n_traj, n_keep)


def _batch_size(design: Design, engine, M: int, memory_budget: int | None) -> int:
    """Runs per chunk: what fits the memory budget (a worker's on a cluster, with at least two
    chunks per worker)."""
    info = design.info
    in_process = engine.local
    budget = memory_budget if (memory_budget is not None or in_process) else worker_budget(engine)
    batch = runs_per_batch(info.n_x, info.n_field, budget)
    if not in_process:
        batch = min(batch, max(1, -(-M // (2 * engine.workers))))
    return batch


def _assemble(design: Design, controller: str, lqg: LQG, chunks: list, parts: list, n_traj: int,
              n_keep: int) -> MonteCarloResult:
    """The chunks' outputs in one result, in chunk order."""
    info, N = design.info, design.problem.n_steps
    M = sum(len(c[1]) for c in chunks)
    acc = MetricsAccumulator(design.objective, design.nominal.field, M)
    F = np.empty((n_traj, N + 1, info.n_field))
    F_hat = np.empty((n_keep, N + 1, info.n_field))
    U = np.empty((M, N, info.n_u))
    Y = np.empty((M, N + 1, info.n_y))
    covered = 0
    rate = {"rate_clips": 0, "rate_violations": 0, "at_limit": 0}
    for (a, ids, nf, ne), part in zip(chunks, parts):
        for key in rate:
            rate[key] += part["rate"][key]
        rows = slice(a, a + len(ids))
        acc.merge(part["acc"], rows)
        U[rows], Y[rows] = part["U"], part["Y"]
        F[a:a + nf], F_hat[a:a + ne] = part["F"], part["F_hat"]
        covered += part["covered"]
    coverage = covered / (M * N * info.n_field)
    extra = {"coverage_2sigma": coverage}
    if design.problem.rate_limited:
        extra.update(rate_clips=rate["rate_clips"], rate_violations=rate["rate_violations"],
                     rate_at_limit=rate["at_limit"] / max(1, M * (N - 1) * info.n_u))
    stats = [part["stats"] for part in parts if part["stats"] is not None]
    if stats:
        extra.update(MPCStats.merged(stats).as_dict())
    summary = acc.result(extra)
    return MonteCarloResult(controller, F, U, Y, F_hat, lqg.field_std.copy(), acc.mean_traj, coverage, summary)


def portable(design: Design) -> Design:
    """The design without its scenario's cached plant object (workers rebuild the plant)."""
    from dataclasses import replace

    sc = design.scenario
    return replace(design, scenario=type(sc)(sc.plant_type, sc.plant_config, sc.problem, sc.design))


def _mc_chunk(chunk: tuple, plant, design: Design, lqg: LQG, controller: str, seed: int,
              mpc: MpcOptions, affine: AffineTerms | None = None) -> dict:
    """Simulate one chunk (first row a, run ids, trajectories and estimates to keep) with a
    controller of its own (an MPC's warm starts are per run)."""
    from sep_control.compute.engine import local_plant

    a, run_ids, keep_f, keep_e = chunk
    plant = local_plant(plant)
    problem, info, nom = design.problem, design.info, design.nominal
    M, N = len(run_ids), problem.n_steps
    acc = MetricsAccumulator(design.objective, nom.field, M)
    out = _Outputs(F=np.empty((keep_f, N + 1, info.n_field)), U=np.empty((M, N, info.n_u)),
                   Y=np.empty((M, N + 1, info.n_y)), F_hat=np.empty((keep_e, N + 1, info.n_field)))
    law = make_controller(controller, lqg, problem, nom.u if affine is None else affine.u_nom, mpc)
    rate = {"rate_clips": 0, "rate_violations": 0, "at_limit": 0}
    covered = _run_batch(plant, design, lqg, law, seed, list(run_ids), slice(0, M), acc, out, affine, rate)
    rate["rate_clips"] = int(getattr(law, "rate_clips", 0))
    return {"acc": acc.state(), "U": out.U, "Y": out.Y, "F": out.F, "F_hat": out.F_hat, "covered": covered,
            "stats": law.stats, "rate": rate}


@dataclass
class _Outputs:
    F: np.ndarray
    U: np.ndarray
    Y: np.ndarray
    F_hat: np.ndarray


def _run_batch(plant: Plant, design: Design, lqg: LQG, law: Controller, seed: int, run_ids: list[int],
               rows: slice, acc: MetricsAccumulator, out: _Outputs, affine: AffineTerms | None = None,
               rate: dict | None = None) -> int:
    """Simulate the runs `run_ids` (rows `rows` of the outputs) under `law`; returns the covered
    node-steps. `affine`: the known offsets of a truth oracle's model (`oracle.AffineTerms`);
    `rate`: the plant's rate-limit counts are added to it (violations, at_limit)."""
    problem, info, nom = design.problem, design.info, design.nominal
    du_max = problem.channels("du_max", info.n_u) if problem.rate_limited else None
    w, v = noise_sequences(problem, info, seed, run_ids)
    M, N = len(run_ids), problem.n_steps
    kf = KalmanFilter(lqg, batch=M)
    y_nom, f_nom = nom.y, nom.field
    if affine is not None:
        kf.a = np.repeat(affine.a0[None], M, axis=0)
        y_nom, f_nom = nom.y + affine.y, nom.field + affine.field
    G = lqg.model.G
    a0 = rows.start
    keep_f = max(0, min(M, out.F.shape[0] - a0))           # kept trajectories in this batch
    keep_e = max(0, min(M, out.F_hat.shape[0] - a0))
    covered = 0
    dev = _Resident(plant, G, f_nom, lqg.field_std)
    step = step_resident(plant)
    x = dev.up(initial_states(plant, seed, run_ids))   # each run's own draw (`sep_plant.initial`)
    for k in range(N + 1):
        f = plant.field(x)
        if keep_f:
            out.F[a0:a0 + keep_f, k] = dev.down(f[:keep_f])
        acc.add_field(k, f, rows)
        y = dev.down(plant.observe(x)) + v[:, k]
        out.Y[rows, k] = y
        a = kf.update(k, y - y_nom[k])
        est = dev.estimate(k, a)
        if keep_e:
            out.F_hat[a0:a0 + keep_e, k] = dev.down(est[:keep_e])
        if k > 0:
            covered += dev.covered(k, est, f)
        if k == N:
            break
        u = law.command(k, a)
        if du_max is not None and k > 0:          # the plant's rate limit, as the plant node applies it
            prev = out.U[rows, k - 1]
            applied = clip_rate(u, prev, du_max)
            if rate is not None:
                rate["rate_violations"] += int(np.count_nonzero(applied != u))
                rate["at_limit"] += int(np.count_nonzero(np.abs(applied - prev) >= du_max * (1 - 1e-9)))
            u = applied
        out.U[rows, k] = u
        acc.add_input(k, u, rows)
        x = step(x, u, w[:, k])
        kf.predict(k, u - nom.u[k])
        if affine is not None:
            kf.a = kf.a + affine.r[k]
    return covered


class _Resident:
    """Where a Monte Carlo batch's n_field-sized work happens: the host for a numpy plant (the
    0.8.0 operations), the device of a `DevicePlant` otherwise (f_nom, the field std and the
    field map's Phi' uploaded once, in the precision the map reconstructs with)."""

    def __init__(self, plant: Plant, G, f_nom: np.ndarray, field_std: np.ndarray):
        self.plant, self.G, self.f_nom, self.field_std = plant, G, f_nom, field_std
        self.xp = xp = array_module_of(plant)
        if xp is not np:
            self.f_nom_d, self.two_std_d = to_device(plant, f_nom), to_device(plant, 2.0 * field_std)
            basis = G.reconstruction_basis() if hasattr(G, "reconstruction_basis") else None
            # None: a map without a basis (the oracle's identity) reconstructs through its own apply
            self.PhiT = None if basis is None else to_device(plant, basis, dtype=basis.dtype)

    def up(self, A: np.ndarray):
        return A if self.xp is np else to_device(self.plant, A)

    def down(self, A) -> np.ndarray:
        if self.xp is np:
            return A
        check_finite(A)
        return to_host_of(self.plant, A)

    def estimate(self, k: int, a: np.ndarray):
        """f_nom_k + G_k a: the reconstructed field of every run."""
        if self.xp is np:
            return self.f_nom[k] + self.G.apply(k, a)
        if self.PhiT is None:                        # a map without Phi (the oracle's): its own apply
            return self.f_nom_d[k] + to_device(self.plant, self.G.apply(k, a))
        c = to_device(self.plant, self.G.coefficients(k, a), dtype=self.PhiT.dtype)
        return self.f_nom_d[k] + (c @ self.PhiT).astype(np.float64)

    def covered(self, k: int, est, f) -> int:
        """Node-steps whose true field is within 2 sigma of the estimate."""
        if self.xp is np:
            return int(np.count_nonzero(np.abs(est - f) <= 2.0 * self.field_std[k]))
        return int(self.xp.count_nonzero(self.xp.abs(est - f) <= self.two_std_d[k]))
