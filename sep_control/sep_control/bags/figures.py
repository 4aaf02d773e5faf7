"""The recorded-bag report's figures as PNG (`sep analyze`), for any plant: plotting only.

Each takes an `EpisodeReport` or `AggregateReport` (`sep_control.bags.analysis`) and a path,
and returns the path, or None when the bags lack the topics the figure needs:

episode_field_figure       closed-loop field vs nominal at the band window's start and end. 1-D
                           plants: lines over x with the band [f* - band, f* + band] shaded;
                           grid plants (2-D, 3-D: middle slice): heat maps of the closed-loop
                           (mean) field, the nominal and their difference
episode_estimation_figure  field-estimate error with its 2-sigma bounds at the two unsensed nodes
                           where the reconstruction std is largest (`estimation_nodes`); grid
                           plants also get the std map with those nodes marked
episode_inputs_figure      applied inputs vs nominal, labelled with the plant's input names
episode_disturbance_figure the disturbance estimates d_hat_k (designs with disturbance states),
                           labelled with their directions (the design's map, when given)
render_image_frame         one frame of an image topic (field_image) as a viewer shows the
                           sensor_msgs/Image

For many episodes every run is drawn thin and their mean thick. Drawing primitives:
`sep_control.evaluation.drawing`; the Monte Carlo evaluation's figures: `sep_control.evaluation.figures`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sep_control.bags.analysis import AggregateReport, EpisodeReport, reports_of
from sep_control.bags.reader import Episode, read_episode
from sep_control.bags.storage import BagError
from sep_control.evaluation.drawing import (band_limits, draw_field, is_map, line_coordinate, node_label, pyplot,
                                  save_figure, save_keeping_layout, spread_nodes, unit_suffix)
from sep_estimator.ltv import sensed_nodes
from sep_plant import topics as T

Reports = EpisodeReport | AggregateReport


def disturbance_axis_label(kind: str | None) -> str:
    """The disturbance figure's y label: 'input bias', 'forcing (noise channels)', 'sensor bias',
    a combination's parts joined ('forcing (noise channels) / sensor bias'), 'd_hat' unknown."""
    names = {"input": "input bias", "noise": "forcing (noise channels)", "output": "sensor bias"}
    if kind is None or any(p not in names for p in kind.split("+")):
        return "d_hat"
    return " / ".join(names[p] for p in kind.split("+"))


def unit_label(r: EpisodeReport) -> str:
    """' [unit]' of the plant's field ('' when the plant is not described or has no unit)."""
    info = r.info
    return unit_suffix(info.field_unit) if info is not None else ""


def field_label(r: EpisodeReport) -> str:
    """The field's name and unit for an axis or colorbar."""
    e, info = r.episode, r.info
    name = info.field_name if info is not None else (e.field_name or "field")
    return name + unit_label(r)


def _can_draw_field(r: EpisodeReport) -> bool:
    return r.objective is not None and r.xyz is not None and bool(np.isfinite(r.episode.F).any())


# ---------------------------------------------------------------------- field figure
def episode_field_figure(rep: Reports, path: Path) -> Path | None:
    """Closed-loop field vs nominal at the band window's start and end (None: nothing to draw)."""
    reps = reports_of(rep)
    r0 = reps[0]
    if not _can_draw_field(r0):
        return None
    F = np.stack([r.episode.F for r in reps])
    if is_map(r0.info):
        return _field_maps(r0, F, path)
    return _field_lines(r0, F, path)


def episode_recipe_figure(rep: Reports, path: Path) -> Path | None:
    """A time-varying target (a recipe) over time with each hold's band, the recorded field's
    range over the nodes (and runs) and the nominal's (`evaluation.figures.recipe_figure`);
    None for a target constant in time or nothing to draw."""
    from sep_control.evaluation.figures import recipe_figure

    reps = reports_of(rep)
    r0 = reps[0]
    if not _can_draw_field(r0) or np.ndim(r0.objective.target) < 2:
        return None
    F = np.stack([r.episode.F for r in reps])
    name = "closed loop" if F.shape[0] == 1 else "closed loop"
    return recipe_figure(path, r0.info, r0.objective, r0.F_nom, {name: F})


def _field_lines(r0: EpisodeReport, F: np.ndarray, path: Path) -> Path:
    plt = pyplot()
    obj, xyz, dt = r0.objective, r0.xyz, r0.episode.dt
    many = F.shape[0] > 1
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    x, _ = line_coordinate(xyz)
    order = np.argsort(x, kind="stable")
    for ax, k in zip(axes, obj.window):
        tgt = obj.target_at(k)
        ax.fill_between(x[order], (tgt - obj.band)[order], (tgt + obj.band)[order], color="0.9",
                        label=f"target ± {obj.band:g}")
        for row in F[:, k]:
            draw_field(ax, r0.info, xyz, row, color="C0", lw=0.6 if many else 1.5, alpha=0.35 if many else 1)
        if many:
            draw_field(ax, r0.info, xyz, np.nanmean(F[:, k], axis=0), color="C0", lw=2,
                       label=f"mean of {F.shape[0]} runs")
        else:
            ax.lines[-1].set_label("closed loop (bag)")
        if r0.F_nom is not None:
            draw_field(ax, r0.info, xyz, r0.F_nom[k], color="k", ls="--", lw=1.2, label="nominal")
        ax.set_title(f"t = {k * dt:.4g} s (k = {k})")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(field_label(r0))
    axes[0].legend(loc="lower right", fontsize=8)
    return save_figure(fig, path)


def _field_maps(r0: EpisodeReport, F: np.ndarray, path: Path) -> Path:
    plt = pyplot()
    obj, xyz, info, dt = r0.objective, r0.xyz, r0.info, r0.episode.dt
    lo, hi = band_limits(obj.target, obj.band)
    mean = np.nanmean(F, axis=0)
    closed = "closed loop" if F.shape[0] == 1 else f"closed-loop mean of {F.shape[0]} runs"
    cols = 3 if r0.F_nom is not None else 1
    fig, axes = plt.subplots(2, cols, figsize=(4.6 * cols, 7.4), squeeze=False, layout="constrained")
    for row, k in enumerate(obj.window):
        t = f"t = {k * dt:.4g} s"
        axes[row, 0].set_title(f"{closed}, {t}", fontsize=9)
        im = draw_field(axes[row, 0], info, xyz, mean[k], vmin=lo, vmax=hi)
        if r0.F_nom is not None:
            axes[row, 1].set_title(f"nominal, {t}", fontsize=9)
            draw_field(axes[row, 1], info, xyz, r0.F_nom[k], vmin=lo, vmax=hi)
            fig.colorbar(im, ax=list(axes[row, :2]), label=field_label(r0), shrink=0.8)
            diff = mean[k] - r0.F_nom[k]
            lim = float(np.nanmax(np.abs(diff))) or 1.0
            axes[row, 2].set_title(f"closed loop - nominal, {t}", fontsize=9)
            dim = draw_field(axes[row, 2], info, xyz, diff, vmin=-lim, vmax=lim, cmap="coolwarm")
            fig.colorbar(dim, ax=axes[row, 2], label="difference" + unit_label(r0), shrink=0.8)
        else:
            fig.colorbar(im, ax=axes[row, 0], label=field_label(r0), shrink=0.8)
    return save_keeping_layout(fig, path)        # constrained layout (colorbars spanning two panels)


# ----------------------------------------------------------------- estimation figure
def estimation_nodes(reps: list[EpisodeReport]) -> list[int]:
    """The two unsensed nodes (with a design: those no sensor reads, `ltv.sensed_nodes`) where the
    reconstruction std (mean over the band window and the runs) is largest, spread apart."""
    r0 = reps[0]
    k0, k1 = r0.objective.window if r0.objective is not None else (1, r0.episode.n_steps)
    std = np.stack([r.episode.F_std[k0:k1 + 1] for r in reps])
    score = np.nan_to_num(np.nanmean(std, axis=(0, 1)), nan=-np.inf)
    sensed = sensed_nodes(r0.design.rom, P=r0.design.lqg.kf.P_prior[-1]) if r0.design is not None else []
    return spread_nodes(score, r0.xyz, exclude=sensed)


def episode_estimation_figure(rep: Reports, path: Path) -> Path | None:
    """Estimation error f_hat - f with 2-sigma bounds at the two nodes of `estimation_nodes`
    (grid plants: with the std map, the nodes marked); None without field estimates."""
    reps = reports_of(rep)
    r0 = reps[0]
    if r0.xyz is None or not np.isfinite(r0.err).any() or not np.isfinite(r0.episode.F_std).any():
        return None
    plt = pyplot()
    nodes = estimation_nodes(reps)
    grid = is_map(r0.info)
    panels = len(nodes) + (1 if grid else 0)
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 3.8), squeeze=False)
    axes = list(axes[0])
    if grid:
        _std_map(axes.pop(0), fig, reps, nodes)
    t = np.arange(r0.err.shape[0]) * r0.episode.dt
    many = len(reps) > 1
    for n, (ax, i) in enumerate(zip(axes, nodes)):
        for j, r in enumerate(reps):
            ax.plot(t, r.err[:, i], color="C1", lw=0.6 if many else 1.2, alpha=0.35 if many else 1.0,
                    label="estimation error" if j == 0 else None)
        std = np.nanmean(np.stack([r.episode.F_std[:, i] for r in reps]), axis=0)
        ax.fill_between(t, -2 * std, 2 * std, color="C0", alpha=0.2, label="± 2 sigma")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title((f"{n + 1}: " if grid else "") + node_label(r0.xyz, i, r0.info), fontsize=9)
        ax.set_xlabel("t [s]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("estimation error" + unit_label(r0))
    axes[0].legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def _std_map(ax, fig, reps: list[EpisodeReport], nodes: list[int]) -> None:
    """Mean reconstruction std over the band window as a map, the chosen nodes marked (3-D: the
    middle slice, the nodes projected onto it)."""
    r0 = reps[0]
    k0, k1 = r0.objective.window if r0.objective is not None else (1, r0.episode.n_steps)
    std = np.nanmean(np.stack([r.episode.F_std[k0:k1 + 1] for r in reps]), axis=(0, 1))
    dt = r0.episode.dt
    ax.set_title(f"estimation std, mean over t = {k0 * dt:.4g}..{k1 * dt:.4g} s", fontsize=9)
    im = draw_field(ax, r0.info, r0.xyz, std, cmap="viridis")
    fig.colorbar(im, ax=ax, label="std" + unit_label(r0))
    for n, i in enumerate(nodes):         # map axes: horizontal = 2nd grid axis (y), vertical = 1st (x)
        ax.annotate(str(n + 1), (r0.xyz[i, 1], r0.xyz[i, 0]), color="w", ha="center", va="center", fontsize=9,
                    fontweight="bold", bbox={"boxstyle": "circle", "fc": "none", "ec": "w", "lw": 1.5},
                    annotation_clip=False)


# --------------------------------------------------------------------- input figure
def episode_inputs_figure(rep: Reports, path: Path) -> Path | None:
    """Applied inputs (mean over runs for many) vs the design's nominal, labelled with the
    plant's input names; None without inputs."""
    reps = reports_of(rep)
    r0 = reps[0]
    U = np.stack([r.inputs for r in reps])
    if not np.isfinite(U).any():
        return None
    plt = pyplot()
    design, info = r0.design, r0.info
    names = list(info.input_names) if info is not None and len(info.input_names) == U.shape[2] else \
        [f"input {j}" for j in range(U.shape[2])]
    u_nom = design.nominal.u if design is not None and design.nominal.u.shape == U.shape[1:] else None
    t = np.arange(U.shape[1]) * r0.episode.dt
    fig, ax = plt.subplots(figsize=(10, 4))
    for j in range(U.shape[2]):
        c = f"C{j % 10}"
        if len(reps) > 1:
            for row in U[:, :, j]:
                ax.plot(t, row, color=c, lw=0.4, alpha=0.25)
        ax.step(t, np.nanmean(U[:, :, j], axis=0), where="post", color=c, lw=1.5, label=names[j])
        if u_nom is not None:
            ax.step(t, u_nom[:, j], where="post", color=c, ls="--", lw=1)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("input")
    ax.set_title("applied inputs (solid" + (", mean over runs" if len(reps) > 1 else "") + ")"
                 + (" vs nominal (dashed)" if u_nom is not None else ""))
    ax.grid(alpha=0.3)
    ax.legend(ncol=min(U.shape[2], 5), fontsize=8)
    return save_figure(fig, path)


def disturbance_names(r0: EpisodeReport, n_d: int) -> list[str]:
    """Labels of the disturbance states: their directions when the design (with n_d of them)
    and the plant's names are at hand (`sep_estimator.disturbance.direction_labels`), else d_i."""
    from sep_estimator.disturbance import direction_labels

    d, info = r0.design, r0.info
    dist = d.disturbance if d is not None else None
    if dist is None or dist.n_d != n_d or info is None:
        return [f"d_{i}" for i in range(n_d)]
    return direction_labels(dist, info.input_names, info.output_names)


def episode_disturbance_figure(rep: Reports, path: Path) -> Path | None:
    """The disturbance estimates d_hat_k over the episode (every run thin and their mean thick for
    many), one line per state labelled with its direction; None without disturbance states."""
    reps = reports_of(rep)
    r0 = reps[0]
    D = [r.episode.d_hat for r in reps]
    if not D[0].shape[1] or any(x.shape != D[0].shape for x in D) or not np.isfinite(D[0]).any():
        return None
    D = np.stack(D)
    plt = pyplot()
    n_d = D.shape[2]
    names = disturbance_names(r0, n_d)
    t = np.arange(D.shape[1]) * r0.episode.dt
    fig, ax = plt.subplots(figsize=(10, 4))
    for i in range(n_d):
        c = f"C{i % 10}"
        if len(reps) > 1:
            for row in D[:, :, i]:
                ax.plot(t, row, color=c, lw=0.4, alpha=0.25)
        ax.plot(t, np.nanmean(D[:, :, i], axis=0), color=c, lw=1.5, label=names[i])
    kind = r0.design.disturbance.kind if r0.design is not None and r0.design.disturbance is not None else None
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("t [s]")
    ax.set_ylabel(disturbance_axis_label(kind))
    ax.set_title("disturbance estimates d_hat_k" + (" (mean over runs)" if len(reps) > 1 else ""))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return save_figure(fig, path)


# ----------------------------------------------------------------- image topic frame
def _episode_of(source: Episode | EpisodeReport | str | Path) -> Episode:
    if isinstance(source, Episode):
        return source
    if isinstance(source, EpisodeReport):
        return source.episode
    return read_episode(source)


def image_step(ep: Episode, topic_key: str = T.FIELD_IMAGE) -> int | None:
    """The frame a report shows: the band window's end when it has an image, else the last
    step with one (None: no image on `topic_key`)."""
    frames = ep.images.get(topic_key, {})
    if not frames:
        return None
    if ep.scenario is not None and ep.scenario.problem.window[1] in frames:
        return ep.scenario.problem.window[1]
    return max(frames)


def render_image_frame(source: Episode | EpisodeReport | str | Path, topic_key: str = T.FIELD_IMAGE,
                       step: int | None = None, path: str | Path = "field_image.png", *,
                       scale: int | None = None) -> Path:
    """Write one recorded 32FC1 image frame as a PNG the way an image viewer (rqt_image_view,
    RViz, Foxglove) shows the sensor_msgs/Image: row 0 at the top, one grey level per pixel,
    scaled from the frame's minimum (black) to its maximum (white), no axes; each pixel is
    enlarged to a `scale` x `scale` block (default: about 320 pixels on the long side).

    `source`: an `Episode`, an `EpisodeReport` or a bag path; `step`: None for `image_step`.
    Raises `BagError` when the bag has no such frame."""
    ep = _episode_of(source)
    frames = ep.images.get(topic_key, {})
    k = image_step(ep, topic_key) if step is None else int(step)
    if k is None or k not in frames:
        have = f"steps {min(frames)}..{max(frames)}" if frames else "no frames"
        raise BagError(f"{ep.path}: no {topic_key} image at step {k} ({have})")
    img = np.asarray(frames[k], dtype=np.float64)
    finite = img[np.isfinite(img)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    grey = np.clip((img - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(img)
    grey = np.where(np.isfinite(grey), grey, 0.0)
    s = scale or max(1, 320 // max(img.shape))
    grey = np.kron(grey, np.ones((s, s)))
    rgb = np.repeat(np.round(grey * 255).astype(np.uint8)[:, :, None], 3, axis=2)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    pyplot().imsave(out, rgb)
    return out
