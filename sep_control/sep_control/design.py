"""The offline design pipeline: black-box simulator in, design file out.

1. open-loop nominal: mean-only Gauss-Newton/LM (or gradient descent), then the
   belief-space problem warm-started from it (EnKF belief along nominal observations);
2. TV-ERA reduced-order model from central-difference impulse experiments around the
   nominal, with the field output map;
3. time-varying LQR (weights on the outputs) and Kalman filter on the ROM.

Only `SlabSimulator.initial_state/step/observe` and state snapshots are used.
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

import platform
import time
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from sep_estimator.design_file import Design
from sep_estimator.tvkf import field_std, kalman_gains
from sep_plant.scenario import Scenario
from sep_plant.slab import SlabSimulator

from . import __version__
from .lqr import output_weights, tv_lqr
from .metrics import nominal_cost
from .optimize import optimize, run_belief
from .tvera import identify, rom_markov_all


@dataclass
class DesignSettings:
    """Knobs of the offline design (defaults: DESIGN.md)."""
    method: str = "gn"              # "gn" (Levenberg-Marquardt) or "gd" (paper's gradient descent)
    jacobian: str = "sensitivity"   # "sensitivity" (N n_u experiments) or "rom" (TV-ERA model, large grids)
    belief: bool = True             # refine the mean-only optimum in belief space
    max_iter: int | None = None     # optimizer iterations (None: 10 for gn, 60 for gd)
    belief_iter: int = 2            # belief-space GN iterations after the mean-only optimum
    fd_eps: float = 1e-4            # sensitivity experiment amplitude
    step_size: float = 1e-3         # gradient-descent step alpha
    ensemble: int = 200             # EnKF members (even: antithetic pairs)
    n_r: int = 20                   # ROM order cap
    p: int = 15                     # Hankel block rows (future outputs)
    q: int = 15                     # Hankel block columns (past inputs)
    sv_tol: float = 1e-10           # relative singular-value cutoff
    impulse: float = 0.01           # impulse amplitude relative to the RMS nominal input
    seed: int = 0                   # EnKF random numbers

    def check(self) -> None:
        if self.method not in ("gn", "gd"):
            raise ValueError(f"method must be 'gn' or 'gd', got {self.method!r}")
        if self.jacobian not in ("sensitivity", "rom"):
            raise ValueError(f"jacobian must be 'sensitivity' or 'rom', got {self.jacobian!r}")
        for name in ("n_r", "p", "q", "ensemble"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.ensemble % 2 or self.ensemble < 4:
            raise ValueError(f"ensemble must be even and >= 4 (antithetic pairs), got {self.ensemble}")
        for name in ("fd_eps", "impulse", "sv_tol", "step_size"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")


def lqg_gains(A: np.ndarray, B: np.ndarray, C: np.ndarray, s: Scenario):
    """TV-LQR gains K (weights on the outputs) and TV-KF schedule for a (padded) LTV model."""
    Q = output_weights(C, s.lqr_output_weights())
    R = np.eye(s.n_u) * s.lqr_r
    K, _ = tv_lqr(A, B, Q, R)
    kf = kalman_gains(A, B, C, np.eye(s.n_u) * s.w_std**2, np.eye(s.n_y) * s.v_std**2)
    return K, kf


def run_design(s: Scenario, settings: DesignSettings | None = None, show_progress: bool = True,
               log=print) -> Design:
    """Run the whole offline design for scenario `s` and return the `Design`."""
    st = settings or DesignSettings()
    st.check()
    sim = SlabSimulator(s)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    # 1. nominal trajectory --------------------------------------------------
    t0 = time.perf_counter()
    rom = {"p": st.p, "q": st.q, "n_r": st.n_r, "sv_tol": st.sv_tol, "impulse": st.impulse}
    opt = optimize(sim, s, method=st.method, objective="nominal", max_iter=st.max_iter,
                   eps=st.fd_eps, step_size=st.step_size, show_progress=show_progress,
                   jacobian=st.jacobian, rom=rom)
    log(f"mean-only {st.method} ({st.jacobian} Jacobian): J = {opt.cost:.6g} after {opt.iterations} iterations "
        f"({opt.experiments} experiments, {opt.seconds:.2f} s)")
    U, mean_only_cost = opt.U, opt.cost
    belief_hist: list[float] = []
    if st.belief:
        bopt = optimize(sim, s, U0=U, method="gn", objective="belief", max_iter=st.belief_iter,
                        eps=st.fd_eps, members=st.ensemble, seed=st.seed, show_progress=show_progress,
                        jacobian=st.jacobian, rom=rom)
        log(f"belief-space gn: J_b = {bopt.history[0]:.8g} -> {bopt.cost:.8g} "
            f"({bopt.iterations} iterations, {bopt.seconds:.2f} s)")
        U, belief_hist = bopt.U, bopt.history
    timings["optimize_s"] = time.perf_counter() - t0
    belief = run_belief(sim, U, s, st.ensemble, st.seed)

    # 2. TV-ERA ------------------------------------------------------------
    t0 = time.perf_counter()
    T_nom, data, real, delta = identify_rom(sim, U, st, show_progress)
    timings["identify_s"] = time.perf_counter() - t0
    markov_err = markov_relative_error(real, data.Y)
    log(f"TV-ERA: n_r = {int(real.dims.max())} (cap {st.n_r}), {data.experiments} impulse experiments, "
        f"Markov relative error {markov_err:.2e}")

    # 3. LQG on the ROM ----------------------------------------------------
    t0 = time.perf_counter()
    K, kf = lqg_gains(real.A, real.B, real.C, s)
    fstd = field_std(real.G, kf.P_post)
    timings["gains_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_all

    meta: dict[str, Any] = {
        "settings": asdict(st),
        "provenance": {"tool": "sep design", "version": __version__, "python": platform.python_version(),
                       "numpy": np.__version__, "created_unix": time.time(), "seed": st.seed},
        "timings": timings,
        "optimizer": {"method": st.method, "mean_only_cost": mean_only_cost,
                      "mean_only_history": opt.history, "belief_history": belief_hist,
                      "experiments": opt.experiments, "nominal_cost": float(nominal_cost(T_nom, U, s))},
        "validation": {"markov_rel_error": markov_err, "impulse_amplitude": delta,
                       "max_dev_in_band_window": float(np.max(np.abs(T_nom[s.k_band:] - s.t_target)))},
    }
    return Design(scenario=s, u_nom=U, y_nom=sim.observe(T_nom), T_nom=T_nom, belief_mean=belief.mean,
                  belief_std=belief.std, rom_dims=real.dims, A=real.A, B=real.B, C=real.C, G=real.G,
                  K=K, L=kf.L, P_post=kf.P_post, field_std=fstd, hankel_sv=real.hankel_sv, meta=meta)


def identify_rom(sim: SlabSimulator, U: np.ndarray, st: DesignSettings, show_progress: bool = False):
    """`tvera.identify` with the design's settings: (T_nom, MarkovData, Realization, delta)."""
    return identify(sim, U, st.p, st.q, st.n_r, st.sv_tol, st.impulse, show_progress)


def with_rom(design: Design, real) -> Design:
    """`design` with its ROM replaced by `real` and the LQG gains redesigned (same nominal)."""
    s = design.scenario
    K, kf = lqg_gains(real.A, real.B, real.C, s)
    return replace(design, rom_dims=real.dims, A=real.A, B=real.B, C=real.C, G=real.G, K=K, L=kf.L,
                   P_post=kf.P_post, field_std=field_std(real.G, kf.P_post), hankel_sv=real.hankel_sv)


def markov_relative_error(real, Y: np.ndarray) -> float:
    """|Y_rom - Y_exp|_F / |Y_exp|_F over every recorded Markov parameter with j + lag <= N."""
    N, L = Y.shape[:2]
    Yr = rom_markov_all(real, L)
    valid = (np.arange(N)[:, None] + np.arange(1, L + 1)[None, :]) <= N
    return float(np.linalg.norm((Yr - Y)[valid]) / np.linalg.norm(Y[valid]))
