"""Markdown + PNG report of analysed bags (the paper's figures rebuilt from recorded topics).

Figures (matplotlib, Agg backend, written next to report.md), for any plant:

* field.png: closed-loop field vs nominal at the band window's start and end. 1-D plants: lines
  over x with the band [f* - band, f* + band] shaded; grid plants (2-D, 3-D: middle slice):
  heat maps of the closed-loop (mean) field, the nominal and their difference;
* estimation.png: field-estimate error with its 2-sigma bounds at the two unsensed nodes where
  the reconstruction std is largest (`figures.spread_nodes`); grid plants also get the std map
  with those nodes marked;
* inputs.png: applied inputs vs nominal, labelled with the plant's input names;
* field_image.png (bags with the optional image topic): one frame of field_image as a viewer
  shows the sensor_msgs/Image (`render_image_frame`).

For many episodes every run is drawn thin, their mean thick, and the table has one row per
episode plus the pooled row.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sep_control.evaluation import metrics as M
from sep_control.bags.analysis import AggregateReport, EpisodeReport
from sep_control.bags.bag_io import BagError, Episode, read_episode
from sep_estimator.ltv import sensed_nodes
from sep_control.evaluation.figures import (band_limits, draw_field, is_map, line_coordinate, node_label, pyplot, save_figure,
                                 spread_nodes)
from sep_plant import topics as T

LATENCY_NOTE = ("latency = receive time of command k minus receive time of measurements k, "
                "both in the recorder's clock (bag log time)")


def _reports(rep) -> list[EpisodeReport]:
    return rep.reports if isinstance(rep, AggregateReport) else [rep]


def _unit(r: EpisodeReport) -> str:
    info = r.info
    return f" [{info.field_unit}]" if info is not None and info.field_unit else ""


def _field_label(r: EpisodeReport) -> str:
    e, info = r.episode, r.info
    name = info.field_name if info is not None else (e.field_name or "field")
    return name + _unit(r)


def _can_draw_field(r: EpisodeReport) -> bool:
    return r.objective is not None and r.xyz is not None and bool(np.isfinite(r.episode.F).any())


# ---------------------------------------------------------------------- field figure
def fig_field(rep, path: Path) -> Path | None:
    """Closed-loop field vs nominal at the band window's start and end (None: nothing to draw)."""
    reps = _reports(rep)
    r0 = reps[0]
    if not _can_draw_field(r0):
        return None
    F = np.stack([r.episode.F for r in reps])
    if is_map(r0.info):
        return _field_maps(r0, F, path)
    return _field_lines(r0, F, path)


def _field_lines(r0: EpisodeReport, F: np.ndarray, path: Path) -> Path:
    plt = pyplot()
    obj, xyz, dt = r0.objective, r0.xyz, r0.episode.dt
    many = F.shape[0] > 1
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    x, _ = line_coordinate(xyz)
    order = np.argsort(x, kind="stable")
    for ax, k in zip(axes, obj.window):
        ax.fill_between(x[order], (obj.target - obj.band)[order], (obj.target + obj.band)[order], color="0.9",
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
    axes[0].set_ylabel(_field_label(r0))
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
            fig.colorbar(im, ax=list(axes[row, :2]), label=_field_label(r0), shrink=0.8)
            diff = mean[k] - r0.F_nom[k]
            lim = float(np.nanmax(np.abs(diff))) or 1.0
            axes[row, 2].set_title(f"closed loop - nominal, {t}", fontsize=9)
            dim = draw_field(axes[row, 2], info, xyz, diff, vmin=-lim, vmax=lim, cmap="coolwarm")
            fig.colorbar(dim, ax=axes[row, 2], label="difference" + _unit(r0), shrink=0.8)
        else:
            fig.colorbar(im, ax=axes[row, 0], label=_field_label(r0), shrink=0.8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)            # constrained layout (colorbars spanning two panels)
    plt.close(fig)
    return path


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


def fig_estimation(rep, path: Path) -> Path | None:
    """Estimation error with 2-sigma bounds at the two nodes of `estimation_nodes` (grid
    plants: with the std map, the nodes marked)."""
    reps = _reports(rep)
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
    axes[0].set_ylabel("estimation error" + _unit(r0))
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
    fig.colorbar(im, ax=ax, label="std" + _unit(r0))
    for n, i in enumerate(nodes):         # map axes: horizontal = 2nd grid axis (y), vertical = 1st (x)
        ax.annotate(str(n + 1), (r0.xyz[i, 1], r0.xyz[i, 0]), color="w", ha="center", va="center", fontsize=9,
                    fontweight="bold", bbox={"boxstyle": "circle", "fc": "none", "ec": "w", "lw": 1.5},
                    annotation_clip=False)


# --------------------------------------------------------------------- input figure
def fig_inputs(rep, path: Path) -> Path | None:
    """Applied inputs (mean over runs for many) vs the design's nominal, labelled with the
    plant's input names."""
    reps = _reports(rep)
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


# ----------------------------------------------------------------- image topic frame
def _episode_of(source) -> Episode:
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


def render_image_frame(source, topic_key: str = T.FIELD_IMAGE, step: int | None = None,
                       path: str | Path = "field_image.png", *, scale: int | None = None) -> Path:
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


# ------------------------------------------------------------------------- markdown
def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.3e}"
    return str(v)


def _table_keys(rows: dict[str, dict[str, Any]]) -> list[str]:
    extra = ("field_nees", "latency_estimate_p50_s")
    return [k for k in (*M.JSON_KEYS, *extra) if any(r.get(k) is not None for r in rows.values())]


def metrics_rows(rep) -> dict[str, dict[str, Any]]:
    if isinstance(rep, AggregateReport):
        return {**rep.rows, "all episodes": rep.metrics}
    return {rep.name: rep.metrics}


def markdown_table(rows: dict[str, dict[str, Any]]) -> str:
    keys = _table_keys(rows)
    head = "| episode | " + " | ".join(keys) + " |"
    sep = "|---|" + "---|" * len(keys)
    body = ["| " + name + " | " + " | ".join(_fmt(r.get(k)) for k in keys) + " |" for name, r in rows.items()]
    return "\n".join([head, sep, *body])


def scenario_line(r: EpisodeReport) -> str | None:
    """One line describing the plant and the objective of the metrics."""
    e, info, obj = r.episode, r.info, r.objective
    if r.scenario is None:
        return None
    parts = [f"plant `{r.scenario.plant_type}`"]
    if info is not None:
        grid = f", grid {' x '.join(map(str, info.grid_shape))}" if info.grid_shape else ""
        parts.append(f"{info.n_field} field nodes{grid}, {info.n_u} inputs, {info.n_y} outputs")
    parts.append(f"dt = {e.dt:g} s, N = {e.n_steps}")
    if obj is not None:
        tgt = f"{obj.target[0]:g}" if np.ptp(obj.target) == 0 else \
            f"target field {obj.target.min():.4g}..{obj.target.max():.4g}"
        parts.append(f"band {tgt} ± {obj.band:g}{_unit(r)} for k = {obj.window[0]}..{obj.window[1]}")
    return "Scenario: " + ", ".join(parts) + f" (source: {e.scenario_source})"


def _problems(rep, reps: list[EpisodeReport]) -> list[str]:
    """Notes of the report: missing topics, truncation, mismatches, reader notes."""
    out = []
    for r in reps:
        e = r.episode
        if e.missing:
            out.append(f"`{r.name}`: missing topics {', '.join(e.missing)}")
        if not e.complete:
            out.append(f"`{r.name}`: truncated bag, analysed what was recovered")
        if r.mismatch:
            out.append(f"`{r.name}`: SCENARIO MISMATCH with the design file: {'; '.join(r.mismatch)}")
        out += [f"`{r.name}`: {n}" for n in r.notes if not n.startswith("missing topics")]
        if e.ignored_topics:
            out.append(f"`{r.name}`: ignored topics outside the contract: {', '.join(e.ignored_topics)}")
    if isinstance(rep, AggregateReport):
        out += rep.notes
    return out


def _figure_lines(rep, out: Path) -> list[str]:
    lines = ["## Figures", ""]
    for fn, title, fname in ((fig_field, "Closed-loop field vs nominal", "field.png"),
                             (fig_estimation, "Estimation error with 2-sigma bounds", "estimation.png"),
                             (fig_inputs, "Inputs vs nominal", "inputs.png")):
        p = fn(rep, out / fname)
        if p is None:
            lines.append(f"- {title}: not drawn (the bag lacks the topics it needs)")
        else:
            lines += [f"### {title}", "", f"![{title}]({fname})", ""]
    ep = _reports(rep)[0].episode
    k = image_step(ep)
    if k is not None:
        render_image_frame(ep, T.FIELD_IMAGE, k, out / "field_image.png")
        title = f"field_image at k = {k} as a viewer shows it"
        lines += [f"### {title}", "", f"![{title}](field_image.png)", "",
                  "(sensor_msgs/Image 32FC1, grey from the frame's minimum to its maximum)", ""]
    return lines


def controller_line(reps) -> str:
    """The feedback law(s) of the episodes, from the LQR node's /diagnostics."""
    names = sorted({r.metrics.get("controller") or "not reported (sep < 0.3: the LQR)" for r in reps})
    line = ", ".join(names)
    if "rom_mpc" in names:
        qp = sum(r.metrics.get("mpc_qp_steps") or 0 for r in reps)
        fb = sum(r.metrics.get("mpc_fallbacks") or 0 for r in reps)
        line += f" ({qp} steps solved a QP, {fb} fell back to the clipped LQR)"
    return line


def write_report(rep, out_dir: str | Path, figures: bool = True) -> Path:
    """Write report.md (+ PNGs) for an `EpisodeReport` or `AggregateReport`; returns report.md."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reps = _reports(rep)
    agg = isinstance(rep, AggregateReport)
    lines = [f"# sep bag analysis: {'%d episodes' % len(reps) if agg else reps[0].name}", ""]
    lines.append("Bags: " + ", ".join(f"`{r.episode.path}`" for r in reps[:10]) +
                 (f" and {len(reps) - 10} more" if len(reps) > 10 else ""))
    scen = scenario_line(reps[0])
    if scen is not None:
        lines.append(scen)
    lines.append("Design file: " + ("given (nominal comparisons included)" if reps[0].design is not None else
                                    "none (no nominal comparisons; pass --design)"))
    lines.append("Controller: " + controller_line(reps))
    lines += ["", "## Metrics", "", markdown_table(metrics_rows(rep)), "", f"- {LATENCY_NOTE}.",
              "- coverage_2sigma: share of node-steps k >= 1 with |f_hat - f| <= 2 std; field_nees: mean "
              "((f_hat - f)/std)^2 (about 1 when consistent).",
              "- mean_dev_start / mean_dev_end: max over nodes of |mean field - nominal| at the band window's "
              "first / last step.",
              "- deadline_misses / rejected_messages: last /diagnostics values (summed over episodes).", ""]
    problems = _problems(rep, reps)
    if problems:
        lines += ["## Notes", ""] + [f"- {p}" for p in problems[:50]] + [""]
    if figures:
        lines += _figure_lines(rep, out)
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
