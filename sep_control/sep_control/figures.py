"""The paper's figures as PNG (matplotlib, Agg backend): plotting only, no computation.

fig_nominal         nominal belief trajectory and optimal control        (paper Fig. 2a-b)
fig_mean_vs_nominal closed-loop mean field vs nominal at 37.5 s, 62.5 s  (paper Fig. 1a)
fig_estimation      estimation error with 2-sigma bounds at 0.4L, 0.9L,
                    against the open-loop deviation                      (paper Fig. 1b-c)
fig_rom_sweep       Hankel singular values, Markov error and cost vs n_r
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from sep_plant.scenario import Scenario


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> Path:
    """Lay out, write as PNG (110 dpi) and close `fig`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path


def fig_nominal(path: Path, s: Scenario, belief_mean: np.ndarray, belief_std: np.ndarray,
                u_nom: np.ndarray) -> Path:
    plt = pyplot()
    x = s.grid() / s.length
    t = np.arange(s.n_steps + 1) * s.dt
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for time_s in (0.0, 12.5, 25.0, 37.5, 50.0, 62.5):
        k = min(int(round(time_s / s.dt)), s.n_steps)
        line, = a.plot(x, belief_mean[k], label=f"t = {t[k]:.1f} s")
        a.fill_between(x, belief_mean[k] - 2 * belief_std[k], belief_mean[k] + 2 * belief_std[k],
                       color=line.get_color(), alpha=0.2)
    a.axhspan(s.t_target - s.band, s.t_target + s.band, color="0.85", zorder=0, label="target band")
    a.set(xlabel="x / L", ylabel="T [F]", title="Nominal belief: mean +- 2 sigma (EnKF)")
    a.legend(fontsize=8)
    for j in range(s.n_u):
        b.step(t[:-1], u_nom[:, j], where="post", label=f"heater {j} @ {s.heater_centers[j]:.1f} L")
    b.set(xlabel="t [s]", ylabel="u", title="Optimal open-loop control")
    b.legend(fontsize=8)
    return save_figure(fig, path)


def fig_mean_vs_nominal(path: Path, s: Scenario, T_nom: np.ndarray,
                        means: Mapping[str, np.ndarray]) -> Path:
    """`means[name]` is the mean trajectory (N+1, n_x) of a controller over the runs."""
    plt = pyplot()
    x = s.grid() / s.length
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, time_s in zip(axes, (37.5, 62.5)):
        k = min(int(round(time_s / s.dt)), s.n_steps)
        ax.plot(x, T_nom[k], "k-", lw=2, label="nominal")
        for name, M in means.items():
            ax.plot(x, M[k], "--", label=f"{name} mean")
        ax.axhspan(s.t_target - s.band, s.t_target + s.band, color="0.9", zorder=0)
        ax.set(xlabel="x / L", title=f"t = {k * s.dt:.1f} s")
    axes[0].set_ylabel("T [F]")
    axes[0].legend(fontsize=8)
    return save_figure(fig, path)


def fig_estimation(path: Path, s: Scenario, T_nom: np.ndarray, T_cl: np.ndarray, T_hat: np.ndarray,
                   T_std: np.ndarray, T_ol: np.ndarray, positions: Sequence[float] = (0.4, 0.9)) -> Path:
    """One run: estimation error T_hat - T with +-2 sigma, and T - T_nom closed vs open loop."""
    plt = pyplot()
    t = np.arange(s.n_steps + 1) * s.dt
    xg = s.grid()
    fig, axes = plt.subplots(1, len(positions), figsize=(11, 4), sharey=True)
    for ax, pos in zip(np.atleast_1d(axes), positions):
        i = int(np.argmin(np.abs(xg - pos * s.length)))
        ax.fill_between(t, -2 * T_std[:, i], 2 * T_std[:, i], color="C0", alpha=0.25, label="+-2 sigma")
        ax.plot(t, T_hat[:, i] - T_cl[:, i], "C0", lw=1, label="estimation error")
        ax.plot(t, T_cl[:, i] - T_nom[:, i], "C2", lw=1, label="closed loop T - nominal")
        ax.plot(t, T_ol[:, i] - T_nom[:, i], "C3", lw=1, label="open loop T - nominal")
        ax.set(xlabel="t [s]", title=f"x = {xg[i] / s.length:.2f} L")
    np.atleast_1d(axes)[0].set_ylabel("[F]")
    np.atleast_1d(axes)[0].legend(fontsize=8)
    return save_figure(fig, path)


def fig_rom_sweep(path: Path, hankel_sv: np.ndarray, k: int, rows: Sequence[Mapping]) -> Path:
    """rows: dicts with n_r, n_r_used, markov_rel_error, cost_mean (ROM-LQG), cost_oracle."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    sv = hankel_sv[k][hankel_sv[k] > 0]
    a.semilogy(np.arange(1, sv.size + 1), sv / sv[0], "o-", ms=3)
    for r in rows:
        a.axvline(r["n_r_used"], color="0.7", lw=0.8)
    a.set(xlabel="index", ylabel="sigma_i / sigma_1", title=f"Hankel singular values at k = {k}")
    n = [r["n_r"] for r in rows]
    b.semilogy(n, [r["markov_rel_error"] for r in rows], "o-", label="Markov relative error")
    b.set(xlabel="n_r (cap)", ylabel="Markov relative error")
    b2 = b.twinx()
    b2.plot(n, [r["cost_mean"] / r["cost_oracle"] for r in rows], "s--C1", label="cost / oracle cost")
    b2.set_ylabel("ROM-LQG cost / oracle cost")
    b.set_title("ROM order sweep")
    h1, l1 = b.get_legend_handles_labels()
    h2, l2 = b2.get_legend_handles_labels()
    b.legend(h1 + h2, l1 + l2, fontsize=8)
    return save_figure(fig, path)
