"""The Monte Carlo evaluation's figures as PNG (`sep evaluate`): plotting only, no computation.

Fields are drawn as lines over x for 1-D plants and as heat maps for grid plants (2-D; the
middle slice along the last axis for 3-D), so every figure works for every plant (drawing
primitives: `sep_control.evaluation.drawing`; the recorded-bag report's figures: `sep_control.bags.figures`):

nominal_belief_figure       nominal belief (mean +- 2 sigma, or maps; the nominal field where the design
                            has no belief) and optimal control (paper Fig. 2a-b)
mc_mean_vs_nominal_figure   closed-loop mean field vs nominal at the band window's start and end (Fig. 1a)
mc_estimation_figure        one run's estimation error with 2-sigma bounds at the two unsensed nodes
                            where the reconstruction std is largest, against the open-loop deviation
                            (Fig. 1b-c)
mc_std_map_figure           mean reconstruction std over the band window
rom_sweep_figure            Hankel singular values, Markov error and cost vs n_r
inputs_vs_limits_figure     each input over time against its limits, for several controllers (one run)
robustness_figure           in band and mean cost against a swept truth-plant key, one line per controller
recipe_figure               a time-varying target (a recipe) over time: f* with each hold's band, the
                            nominal and each controller's field range over the nodes, and the largest
                            |f - f*| over the nodes against the holds' bands
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from sep_control.evaluation.drawing import (band_limits, draw_field, is_map, line_coordinate, node_label, pyplot,
                                  save_keeping_layout, save_figure, spread_nodes, unit_suffix)
from sep_plant.protocol import PlantInfo


def nominal_belief_figure(path: Path, info: PlantInfo, xyz: np.ndarray, target: np.ndarray, band: float,
                          belief_mean: np.ndarray, belief_std: np.ndarray | None, u_nom: np.ndarray,
                          window: tuple[int, int]) -> Path:
    """Nominal belief (mean +- 2 sigma over x at six times; maps at the window's start and end)
    and the optimal open-loop inputs. With `belief_std` None (a design without belief
    statistics: opaque-state plants) `belief_mean` is the nominal field, drawn without a band."""
    plt = pyplot()
    N = u_nom.shape[0]
    t = np.arange(N + 1) * info.dt
    unit = unit_suffix(info.field_unit)
    what = "nominal field" if belief_std is None else "belief mean"
    if is_map(info):
        fig, axes = plt.subplots(1, 3, figsize=(14, 4))
        lo, hi = band_limits(target, band)
        for ax, k in zip(axes[:2], window):
            ax.set_title(f"{what}, t = {t[k]:.4g} s")
            im = draw_field(ax, info, xyz, belief_mean[k], vmin=lo, vmax=hi)
            fig.colorbar(im, ax=ax, label=info.field_name + unit)
        b = axes[2]
    else:
        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
        for k in np.unique(np.linspace(0, N, 6).round().astype(int)):
            x, _ = line_coordinate(xyz)
            order = np.argsort(x)
            line = a.plot(x[order], belief_mean[k][order], label=f"t = {t[k]:.4g} s")[0]
            if belief_std is not None:
                a.fill_between(x[order], (belief_mean[k] - 2 * belief_std[k])[order],
                               (belief_mean[k] + 2 * belief_std[k])[order], color=line.get_color(), alpha=0.2)
        x, xl = line_coordinate(xyz)
        order = np.argsort(x)
        a.fill_between(x[order], (target - band)[order], (target + band)[order], color="0.85", zorder=0,
                       label="target band")
        a.set(xlabel=xl, ylabel=info.field_name + unit,
              title="Nominal belief: mean +- 2 sigma (EnKF)" if belief_std is not None else
              "Nominal field (no belief: opaque plant states)")
        a.legend(fontsize=8)
    for j in range(u_nom.shape[1]):
        b.step(t[:-1], u_nom[:, j], where="post", label=info.input_names[j])
    b.set(xlabel="t [s]", ylabel="u", title="Optimal open-loop control")
    b.legend(fontsize=7, ncol=max(1, u_nom.shape[1] // 6))
    return save_figure(fig, path)


def mc_mean_vs_nominal_figure(path: Path, info: PlantInfo, xyz: np.ndarray, target: np.ndarray, band: float,
                              F_nom: np.ndarray, means: Mapping[str, np.ndarray], window: tuple[int, int]) -> Path:
    """`means[name]` is the mean field trajectory (N+1, n_field) of a controller over the runs."""
    plt = pyplot()
    unit = unit_suffix(info.field_unit)
    if is_map(info):
        names = list(means)
        fig, axes = plt.subplots(2, 1 + len(names), figsize=(4.2 * (1 + len(names)), 7.4), squeeze=False)
        lo, hi = band_limits(target, band)
        for row, k in enumerate(window):
            panels = [("nominal", F_nom[k])] + [(f"{n} mean", means[n][k]) for n in names]
            for ax, (title, vals) in zip(axes[row], panels):
                ax.set_title(f"{title}, t = {k * info.dt:.4g} s", fontsize=9)
                im = draw_field(ax, info, xyz, vals, vmin=lo, vmax=hi)
            fig.colorbar(im, ax=list(axes[row]), label=info.field_name + unit, shrink=0.8)
        return save_keeping_layout(fig, path)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    x, xl = line_coordinate(xyz)
    order = np.argsort(x)
    for ax, k in zip(axes, window):
        ax.plot(x[order], F_nom[k][order], "k-", lw=2, label="nominal")
        for name, M in means.items():
            ax.plot(x[order], M[k][order], "--", label=f"{name} mean")
        ax.fill_between(x[order], (target - band)[order], (target + band)[order], color="0.9", zorder=0)
        ax.set(xlabel=xl, title=f"t = {k * info.dt:.4g} s")
    axes[0].set_ylabel(info.field_name + unit)
    axes[0].legend(fontsize=8)
    return save_figure(fig, path)


def mc_estimation_figure(path: Path, info: PlantInfo, xyz: np.ndarray, F_nom: np.ndarray, F_cl: np.ndarray,
                         F_hat: np.ndarray, F_std: np.ndarray, F_ol: np.ndarray | None, window: tuple[int, int],
                         sensed: Sequence[int] = ()) -> Path:
    """One run: estimation error f_hat - f with +-2 sigma, and f - f_nom closed vs open loop, at
    the two unsensed nodes (not in `sensed`) where the mean reconstruction std over the band
    window is largest."""
    plt = pyplot()
    k0, k1 = window
    nodes = spread_nodes(F_std[k0:k1 + 1].mean(axis=0), xyz, exclude=sensed)
    t = np.arange(F_nom.shape[0]) * info.dt
    fig, axes = plt.subplots(1, len(nodes), figsize=(5.5 * len(nodes), 4), sharey=True, squeeze=False)
    for ax, i in zip(axes[0], nodes):
        ax.fill_between(t, -2 * F_std[:, i], 2 * F_std[:, i], color="C0", alpha=0.25, label="+-2 sigma")
        ax.plot(t, F_hat[:, i] - F_cl[:, i], "C0", lw=1, label="estimation error")
        ax.plot(t, F_cl[:, i] - F_nom[:, i], "C2", lw=1, label="closed loop - nominal")
        if F_ol is not None:
            ax.plot(t, F_ol[:, i] - F_nom[:, i], "C3", lw=1, label="open loop - nominal")
        ax.set(xlabel="t [s]", title=node_label(xyz, i, info))
    unit = unit_suffix(info.field_unit)
    axes[0, 0].set_ylabel(info.field_name + unit)
    axes[0, 0].legend(fontsize=8)
    return save_figure(fig, path)


def mc_std_map_figure(path: Path, info: PlantInfo, xyz: np.ndarray, F_std: np.ndarray,
                      window: tuple[int, int]) -> Path:
    """Mean reconstruction std over the band window (a map for grid plants, a line for 1-D)."""
    plt = pyplot()
    k0, k1 = window
    std = F_std[k0:k1 + 1].mean(axis=0)
    fig, ax = plt.subplots(figsize=(5.5 if is_map(info) else 8, 4.2))
    ax.set_title(f"estimation std, mean over t = {k0 * info.dt:.4g}..{k1 * info.dt:.4g} s")
    im = draw_field(ax, info, xyz, std, cmap="viridis")
    unit = unit_suffix(info.field_unit)
    if im is not None:
        fig.colorbar(im, ax=ax, label="std" + unit)
    else:
        ax.set_ylabel("std" + unit)
    return save_figure(fig, path)


def rom_sweep_figure(path: Path, hankel_sv: np.ndarray, k: int, rows: Sequence[Mapping]) -> Path:
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
    if all(r.get("cost_oracle") for r in rows):
        b2 = b.twinx()
        b2.plot(n, [r["cost_mean"] / r["cost_oracle"] for r in rows], "s--C1", label="cost / oracle cost")
        b2.set_ylabel("ROM-LQG cost / oracle cost")
        h2, l2 = b2.get_legend_handles_labels()
    else:
        h2, l2 = [], []
    b.set_title("ROM order sweep")
    h1, l1 = b.get_legend_handles_labels()
    b.legend(h1 + h2, l1 + l2, fontsize=8)
    return save_figure(fig, path)


def inputs_vs_limits_figure(path: Path, info: PlantInfo, u_nom: np.ndarray, inputs: Mapping[str, np.ndarray],
                            u_min: np.ndarray, u_max: np.ndarray, window: tuple[int, int]) -> Path:
    """One panel per input: the nominal and each controller's applied input u_k (one run) over
    time, the limits shaded outside, the band window marked."""
    plt = pyplot()
    N, n_u = u_nom.shape
    t = np.arange(N) * info.dt
    fig, axes = plt.subplots(n_u, 1, figsize=(8.0, 1.6 * n_u + 0.6), sharex=True, squeeze=False)
    names = list(getattr(info, "input_names", [])) or [f"u{j}" for j in range(n_u)]
    for j, ax in enumerate(axes[:, 0]):
        ax.plot(t, u_nom[:, j], color="black", lw=1.0, ls="--", label="nominal")
        for (label, U), color in zip(inputs.items(), ("tab:red", "tab:blue", "tab:green", "tab:purple")):
            ax.step(t, U[:, j], where="post", color=color, lw=0.9, label=label)
        lo, hi = float(u_min[j]), float(u_max[j])
        top = max(float(np.max([U[:, j].max() for U in inputs.values()] + [u_nom[:, j].max()])),
                  hi if np.isfinite(hi) else 0)
        bot = min(float(np.min([U[:, j].min() for U in inputs.values()] + [u_nom[:, j].min()])),
                  lo if np.isfinite(lo) else 0)
        pad = 0.08 * max(top - bot, 1e-6)
        if np.isfinite(hi):
            ax.axhspan(hi, top + pad, color="0.85", zorder=0)
        if np.isfinite(lo):
            ax.axhspan(bot - pad, lo, color="0.85", zorder=0)
        ax.axvspan(window[0] * info.dt, min(window[1], N) * info.dt, color="tab:orange", alpha=0.08, zorder=0)
        ax.set_ylim(bot - pad, top + pad)
        ax.set_ylabel(names[j] if j < len(names) else f"u{j}")
    axes[0, 0].legend(loc="upper right", fontsize=7, ncol=len(inputs) + 1)
    axes[-1, 0].set_xlabel("t [s]  (grey: outside the limits; orange: band window)")
    return save_figure(fig, path)


def robustness_figure(path: Path, key: str, values: Sequence[float],
                      rows: Mapping[str, Sequence[Mapping | None]], model_value: float | None = None) -> Path:
    """`sep evaluate --robustness`: in band (left) and mean cost (right, log scale) against the swept
    key, one line per controller; rows[controller][i] are the metrics at values[i] (None: not run
    there); `model_value`, when the design's own value is in range, is marked."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    x = np.asarray(values, dtype=float)
    for name, points in rows.items():
        band = [np.nan if p is None else p["in_band"] for p in points]
        cost = [np.nan if p is None else p["cost_mean"] for p in points]
        a.plot(x, band, "o-", ms=4, label=name)
        b.plot(x, cost, "o-", ms=4, label=name)
    for ax in (a, b):
        if model_value is not None and x.min() <= model_value <= x.max():
            ax.axvline(model_value, color="0.6", lw=0.8, ls="--", label="the design's plant")
        ax.set_xlabel(key + " (truth plant)")
    a.set(ylabel="share of runs in band", ylim=(-0.02, 1.02), title="In band against the truth plant")
    b.set(ylabel="mean cost", title="Cost against the truth plant")
    if np.all(np.isfinite([p["cost_mean"] for pts in rows.values() for p in pts if p is not None])):
        b.set_yscale("log")
    a.legend(fontsize=8)
    return save_figure(fig, path)


def recipe_figure(path: Path, info: PlantInfo, obj, F_nom: np.ndarray | None,
                  fields: Mapping[str, np.ndarray]) -> Path:
    """The target drawn over time (a recipe, or a target expression in t).

    Top: f*_k (its range over the nodes), each hold's band [min f* - band_s, max f* + band_s]
    shaded over its steps, the nominal field's range over the nodes and, for each entry of
    `fields` ((M, N+1, n_field) runs, or (N+1, n_field)), the range over its runs and nodes.
    Bottom: max_i |f_{k,i} - f*_{k,i}| over time (the runs' largest for many runs) against each
    hold's band.

    Parameters
    ----------
    obj : sep_plant.problem.Objective
        The objective (its target per step, `segments`).
    """
    plt = pyplot()
    N = obj.n_steps
    t = np.arange(N + 1) * info.dt
    target = np.broadcast_to(obj.target, (N + 1, info.n_field)) if np.ndim(obj.target) == 1 else obj.target
    unit = unit_suffix(info.field_unit)
    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, height_ratios=(2, 1))
    for j, (k0, k1, band) in enumerate(obj.segments):
        a.fill_between(t[k0:k1 + 1], target[k0:k1 + 1].min(axis=1) - band, target[k0:k1 + 1].max(axis=1) + band,
                       color="0.85", zorder=0, label="hold bands" if j == 0 else None)
        b.hlines(band, t[k0], t[k1], color="k", lw=1.5, label="hold band" if j == 0 else None)
    a.plot(t, target.mean(axis=1), "k-", lw=1.2, label="target f*")
    if np.ptp(target, axis=1).max() > 0:
        a.fill_between(t, target.min(axis=1), target.max(axis=1), color="k", alpha=0.15)
    if F_nom is not None:
        a.plot(t, F_nom.min(axis=1), "k--", lw=0.8, label="nominal (min, max over nodes)")
        a.plot(t, F_nom.max(axis=1), "k--", lw=0.8)
        b.plot(t, np.max(np.abs(F_nom - target), axis=1), "k--", lw=1, label="nominal")
    for i, (name, F) in enumerate(fields.items()):
        F = F[None] if F.ndim == 2 else F
        color = f"C{i}"
        a.fill_between(t, np.min(F, axis=(0, 2)), np.max(F, axis=(0, 2)), color=color, alpha=0.3,
                       label=f"{name} ({F.shape[0]} run{'s' if F.shape[0] > 1 else ''}: range)")
        b.plot(t, np.max(np.abs(F - target), axis=(0, 2)), color=color, lw=1.2, label=name)
    a.set(ylabel=info.field_name + unit, title="Recipe: target and field over time")
    a.legend(fontsize=7, loc="lower right")
    a.grid(alpha=0.3)
    b.set(xlabel="t [s]", ylabel="max |f - f*|" + unit)
    b.set_ylim(bottom=0)
    b.legend(fontsize=7, loc="upper right")
    b.grid(alpha=0.3)
    return save_figure(fig, path)
