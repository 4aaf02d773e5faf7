"""The paper's figures as PNG (matplotlib, Agg backend): plotting only, no computation.

Fields are drawn as lines over x for 1-D plants and as heat maps for grid plants (2-D; the
middle slice along the last axis for 3-D), so every figure works for every plant:

fig_nominal         nominal belief (mean +- 2 sigma, or maps) and optimal control (paper Fig. 2a-b)
fig_mean_vs_nominal closed-loop mean field vs nominal at the band window's start and end (Fig. 1a)
fig_estimation      estimation error with 2-sigma bounds at the two unsensed nodes where the
                    reconstruction std is largest, against the open-loop deviation (Fig. 1b-c)
fig_rom_sweep       Hankel singular values, Markov error and cost vs n_r
fig_inputs_limits   each input over time against its limits, for several controllers (one run)
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from sep_plant.protocol import PlantInfo
from sep_plant.topics import image_of_field


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


# ------------------------------------------------------------------ building blocks
def is_map(info: PlantInfo | None) -> bool:
    """Whether fields of this plant are drawn as heat maps (grid plants of 2 or 3 axes)."""
    return info is not None and info.grid_shape is not None and len(info.grid_shape) >= 2


def line_coordinate(xyz: np.ndarray) -> tuple[np.ndarray, str]:
    """The coordinate to plot a 1-D field against: the axis along which the nodes spread."""
    axis = int(np.argmax(np.ptp(xyz, axis=0))) if xyz.shape[0] > 1 else 0
    return xyz[:, axis], "xyz"[axis] + " [m]"


def map_extent(xyz: np.ndarray, grid_shape: Sequence[int]) -> list[float]:
    """imshow extent [x0, x1, y0, y1] of a grid field's first two axes (rows = first axis)."""
    g = xyz.reshape(tuple(grid_shape) + (3,))
    first = g[(slice(None),) + (0,) * (len(grid_shape) - 1)]
    second = g[(0, slice(None)) + (0,) * (len(grid_shape) - 2)]
    return [float(second[0, 1]), float(second[-1, 1]), float(first[-1, 0]), float(first[0, 0])]


def draw_field(ax, info: PlantInfo | None, xyz: np.ndarray, values: np.ndarray, *, label: str | None = None,
               vmin: float | None = None, vmax: float | None = None, cmap: str = "inferno", **line_kw):
    """A field on `ax`: a line over x (1-D), or a heat map (grid plants; 3-D: middle slice).
    Returns the image for a map (for a colorbar), else None."""
    if is_map(info):
        img = image_of_field(values, info.grid_shape)
        im = ax.imshow(img, origin="upper", extent=map_extent(xyz, info.grid_shape), vmin=vmin, vmax=vmax,
                       cmap=cmap, aspect="equal")
        ax.set(xlabel="y [m]", ylabel="x [m]")
        if len(info.grid_shape) == 3:
            ax.set_title((ax.get_title() + " " if ax.get_title() else "") + "(middle z slice)", fontsize=9)
        return im
    x, xl = line_coordinate(xyz)
    order = np.argsort(x, kind="stable")
    ax.plot(x[order], np.asarray(values)[order], label=label, **line_kw)
    ax.set_xlabel(xl)
    return None


def band_limits(target: np.ndarray, band: float) -> tuple[float, float]:
    return float(np.min(target) - band), float(np.max(target) + band)


def spread_nodes(score: np.ndarray, xyz: np.ndarray, count: int = 2, min_frac: float = 0.25,
                 exclude: Sequence[int] = ()) -> list[int]:
    """`count` nodes with the largest `score`, each at least `min_frac` of the domain's extent away
    from those already chosen (else the next best), none in `exclude`: e.g. the unsensed nodes
    where the reconstruction std is largest."""
    extent = float(np.max(np.ptp(xyz, axis=0))) or 1.0
    score = np.array(score, dtype=float)
    score[list(exclude)] = -np.inf
    chosen: list[int] = []
    for i in np.argsort(-score, kind="stable"):
        if all(np.linalg.norm(xyz[i] - xyz[j]) >= min_frac * extent for j in chosen):
            chosen.append(int(i))
        if len(chosen) == count:
            break
    for i in np.argsort(-score, kind="stable"):          # too few far apart: fill by score
        if len(chosen) == count:
            break
        if int(i) not in chosen:
            chosen.append(int(i))
    return chosen


def node_label(xyz: np.ndarray, i: int, info: PlantInfo | None) -> str:
    dims = info.spatial_dims if info is not None else 1
    return "node " + str(i) + " at (" + ", ".join(f"{c:.3g}" for c in xyz[i][:max(dims, 1)]) + ") m"


# ------------------------------------------------------------------ paper figures
def fig_nominal(path: Path, info: PlantInfo, xyz: np.ndarray, target: np.ndarray, band: float,
                belief_mean: np.ndarray, belief_std: np.ndarray, u_nom: np.ndarray, window: tuple[int, int]) -> Path:
    """Nominal belief (mean +- 2 sigma over x at six times; maps at the window's start and end)
    and the optimal open-loop inputs."""
    plt = pyplot()
    N = u_nom.shape[0]
    t = np.arange(N + 1) * info.dt
    unit = f" [{info.field_unit}]" if info.field_unit else ""
    if is_map(info):
        fig, axes = plt.subplots(1, 3, figsize=(14, 4))
        lo, hi = band_limits(target, band)
        for ax, k in zip(axes[:2], window):
            ax.set_title(f"belief mean, t = {t[k]:.4g} s")
            im = draw_field(ax, info, xyz, belief_mean[k], vmin=lo, vmax=hi)
            fig.colorbar(im, ax=ax, label=info.field_name + unit)
        b = axes[2]
    else:
        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
        for k in np.unique(np.linspace(0, N, 6).round().astype(int)):
            x, _ = line_coordinate(xyz)
            order = np.argsort(x)
            line = a.plot(x[order], belief_mean[k][order], label=f"t = {t[k]:.4g} s")[0]
            a.fill_between(x[order], (belief_mean[k] - 2 * belief_std[k])[order],
                           (belief_mean[k] + 2 * belief_std[k])[order], color=line.get_color(), alpha=0.2)
        x, xl = line_coordinate(xyz)
        order = np.argsort(x)
        a.fill_between(x[order], (target - band)[order], (target + band)[order], color="0.85", zorder=0,
                       label="target band")
        a.set(xlabel=xl, ylabel=info.field_name + unit, title="Nominal belief: mean +- 2 sigma (EnKF)")
        a.legend(fontsize=8)
    for j in range(u_nom.shape[1]):
        b.step(t[:-1], u_nom[:, j], where="post", label=info.input_names[j])
    b.set(xlabel="t [s]", ylabel="u", title="Optimal open-loop control")
    b.legend(fontsize=7, ncol=max(1, u_nom.shape[1] // 6))
    return save_figure(fig, path)


def fig_mean_vs_nominal(path: Path, info: PlantInfo, xyz: np.ndarray, target: np.ndarray, band: float,
                        F_nom: np.ndarray, means: Mapping[str, np.ndarray], window: tuple[int, int]) -> Path:
    """`means[name]` is the mean field trajectory (N+1, n_field) of a controller over the runs."""
    plt = pyplot()
    unit = f" [{info.field_unit}]" if info.field_unit else ""
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
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path
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


def fig_estimation(path: Path, info: PlantInfo, xyz: np.ndarray, F_nom: np.ndarray, F_cl: np.ndarray,
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
    unit = f" [{info.field_unit}]" if info.field_unit else ""
    axes[0, 0].set_ylabel(info.field_name + unit)
    axes[0, 0].legend(fontsize=8)
    return save_figure(fig, path)


def fig_std_map(path: Path, info: PlantInfo, xyz: np.ndarray, F_std: np.ndarray, window: tuple[int, int]) -> Path:
    """Mean reconstruction std over the band window (a map for grid plants, a line for 1-D)."""
    plt = pyplot()
    k0, k1 = window
    std = F_std[k0:k1 + 1].mean(axis=0)
    fig, ax = plt.subplots(figsize=(5.5 if is_map(info) else 8, 4.2))
    ax.set_title(f"estimation std, mean over t = {k0 * info.dt:.4g}..{k1 * info.dt:.4g} s")
    im = draw_field(ax, info, xyz, std, cmap="viridis")
    unit = f" [{info.field_unit}]" if info.field_unit else ""
    if im is not None:
        fig.colorbar(im, ax=ax, label="std" + unit)
    else:
        ax.set_ylabel("std" + unit)
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


def fig_inputs_limits(path: Path, info: PlantInfo, u_nom: np.ndarray, inputs: Mapping[str, np.ndarray],
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
        top = max(float(np.max([U[:, j].max() for U in inputs.values()] + [u_nom[:, j].max()])), hi if np.isfinite(hi) else 0)
        bot = min(float(np.min([U[:, j].min() for U in inputs.values()] + [u_nom[:, j].min()])), lo if np.isfinite(lo) else 0)
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
