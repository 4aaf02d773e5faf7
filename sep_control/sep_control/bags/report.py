"""The Markdown report of analysed bags (`sep analyze`): report.md with the metrics table, the
scenario and controller, the notes (missing topics, truncation, mismatches) and the figures of
`sep_control.bags.figures` (PNG, written next to report.md): field.png, estimation.png,
inputs.png, disturbance.png for designs with disturbance states, and field_image.png for bags
with the optional image topic.

For many episodes the table has one row per episode plus the pooled row ("all episodes").
Metric definitions: docs/method.md.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sep_control.bags.analysis import AggregateReport, EpisodeReport, reports_of
from sep_control.bags.figures import (disturbance_names, episode_disturbance_figure, episode_estimation_figure,
                                      episode_field_figure, episode_inputs_figure, episode_recipe_figure,
                                      image_step, render_image_frame, unit_label)
from sep_control.evaluation import metrics as M
from sep_plant import topics as T

LATENCY_NOTE = ("latency = receive time of command k minus receive time of measurements k, "
                "both in the recorder's clock (bag log time)")


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.3e}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(f"{x:.3g}" if isinstance(x, float) else str(x) for x in v) + "]"
    return str(v)


def _table_keys(rows: dict[str, dict[str, Any]]) -> list[str]:
    extra = ("field_nees", "latency_estimate_p50_s", "d_hat_end")
    return [k for k in (*M.JSON_KEYS, *extra) if any(r.get(k) is not None for r in rows.values())]


def metrics_rows(rep: EpisodeReport | AggregateReport) -> dict[str, dict[str, Any]]:
    """Table rows: episode name -> metrics (an aggregate adds the pooled row 'all episodes')."""
    if isinstance(rep, AggregateReport):
        return {**rep.rows, "all episodes": rep.metrics}
    return {rep.name: rep.metrics}


def markdown_table(rows: dict[str, dict[str, Any]]) -> str:
    """A Markdown table of the metrics that some row has (4 significant digits)."""
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
    if obj is not None and obj.holds is not None:
        parts.append("recipe, hold segments " + ", ".join(
            f"k = {k0}..{k1}: {_target_text(obj.targets(k0, k1))} ± {b:g}{unit_label(r)}" for k0, k1, b in obj.holds))
    elif obj is not None:
        tgt = _target_text(obj.targets(*obj.window))
        parts.append(f"band {tgt} ± {obj.band:g}{unit_label(r)} for k = {obj.window[0]}..{obj.window[1]}")
    return "Scenario: " + ", ".join(parts) + f" (source: {e.scenario_source})"


def _problems(rep: EpisodeReport | AggregateReport, reps: list[EpisodeReport]) -> list[str]:
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


def _target_text(target: np.ndarray) -> str:
    """A target (over nodes, or steps and nodes) in words: its value, or its range."""
    if np.ptp(target) == 0:
        return f"{np.ravel(target)[0]:g}"
    return f"target field {target.min():.4g}..{target.max():.4g}"


def segment_lines(rep: EpisodeReport | AggregateReport) -> list[str]:
    """A recipe's results per hold segment (the metrics' `segments`), as Markdown lines."""
    seg = rep.metrics.get("segments")
    if not seg:
        return []
    lines = ["## Hold segments", "", "| hold | steps | band | in band | max abs(f - f*) | 99 % quantile |",
             "|---|---|---|---|---|---|"]
    for j, s in enumerate(seg):
        lines.append(f"| {j + 1} | {s['k_start']}..{s['k_end']} | ± {s['band']:g} | {s['in_band']:.3f} | "
                     f"{s['max_dev']:.4g} | {s['max_dev_p99']:.4g} |")
    return lines + ["", "In band overall: the whole field inside every hold's band over that hold.", ""]


def _figure_lines(rep: EpisodeReport | AggregateReport, out: Path) -> list[str]:
    """Draw the figures into `out`; their Markdown section (a line for each one not drawn)."""
    lines = ["## Figures", ""]
    for fn, title, fname in ((episode_recipe_figure, "Recipe: target over time", "recipe.png"),
                             (episode_field_figure, "Closed-loop field vs nominal", "field.png"),
                             (episode_estimation_figure, "Estimation error with 2-sigma bounds", "estimation.png"),
                             (episode_inputs_figure, "Inputs vs nominal", "inputs.png"),
                             (episode_disturbance_figure, "Disturbance estimates", "disturbance.png")):
        p = fn(rep, out / fname)
        if p is None and fname in ("disturbance.png", "recipe.png"):
            continue                         # a design without disturbance states: nothing to say
        if p is None:
            lines.append(f"- {title}: not drawn (the bag lacks the topics it needs)")
        else:
            lines += [f"### {title}", "", f"![{title}]({fname})", ""]
    ep = reports_of(rep)[0].episode
    k = image_step(ep)
    if k is not None:
        render_image_frame(ep, T.FIELD_IMAGE, k, out / "field_image.png")
        title = f"field_image at k = {k} as a viewer shows it"
        lines += [f"### {title}", "", f"![{title}](field_image.png)", "",
                  "(sensor_msgs/Image 32FC1, grey from the frame's minimum to its maximum)", ""]
    return lines


def disturbance_line(r: EpisodeReport) -> str | None:
    """The disturbance states (kind and directions) of the episode's estimate, or None when it has none."""
    n_d = r.episode.d_hat.shape[1]
    if not n_d:
        return None
    d = r.design
    kind = d.disturbance.kind if d is not None and d.disturbance is not None else "of the estimator's design"
    return (f"Disturbance states: {kind}, n_d = {n_d} (d_hat_end: the estimates at the last step): "
            + "; ".join(disturbance_names(r, n_d)))


def controller_line(reps: list[EpisodeReport]) -> str:
    """The feedback law(s) of the episodes, from the LQR node's /diagnostics."""
    names = sorted({r.metrics.get("controller") or "not reported (sep < 0.3: the LQR)" for r in reps})
    line = ", ".join(names)
    if "rom_mpc" in names:
        qp = sum(r.metrics.get("mpc_qp_steps") or 0 for r in reps)
        fb = sum(r.metrics.get("mpc_fallbacks") or 0 for r in reps)
        line += f" ({qp} steps solved a QP, {fb} fell back to the clipped LQR)"
    return line


def write_report(rep: EpisodeReport | AggregateReport, out_dir: str | Path, figures: bool = True) -> Path:
    """Write report.md (and its PNG figures) of analysed bags.

    Parameters
    ----------
    rep : EpisodeReport or AggregateReport
        From `sep_control.bags.analysis.analyze` (one episode) or `aggregate` (many: one table
        row per episode plus the pooled row).
    out_dir : str or Path
        Report directory (created if needed; existing files of the same names are replaced).
    figures : bool, default True
        Draw field.png, estimation.png, inputs.png (and disturbance.png when the estimates have
        disturbance states, field_image.png when the bags have the image topic); False: the
        Markdown alone.

    Returns
    -------
    Path
        The written report.md.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reps = reports_of(rep)
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
    mm = rep.metrics["model_mismatch"]         # an aggregate's: the union over its episodes
    if mm:
        lines.append("Model mismatch (the design ran on another plant than its model): " + "; ".join(mm))
    dline = disturbance_line(reps[0])
    if dline is not None:
        lines.append(dline)
    lines += ["", "## Metrics", "", markdown_table(metrics_rows(rep)), "", f"- {LATENCY_NOTE}.",
              "- coverage_2sigma: share of node-steps k >= 1 with |f_hat - f| <= 2 std; field_nees: mean "
              "((f_hat - f)/std)^2 (about 1 when consistent).",
              "- mean_dev_start / mean_dev_end: max over nodes of |mean field - nominal| at the band window's "
              "first / last step.",
              "- deadline_misses / rejected_messages: last /diagnostics values (summed over episodes).", ""]
    lines += segment_lines(rep)
    problems = _problems(rep, reps)
    if problems:
        lines += ["## Notes", ""] + [f"- {p}" for p in problems[:50]] + [""]
    if figures:
        lines += _figure_lines(rep, out)
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
