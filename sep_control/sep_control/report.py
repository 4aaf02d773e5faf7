"""Markdown + PNG report of analysed bags (the paper's figures rebuilt from recorded topics).

Figures (matplotlib, Agg backend, written next to report.md):
* field.png: closed-loop field vs nominal at 37.5 s and 62.5 s (band [T* - 3, T* + 3] shaded);
* estimation.png: field-estimate error with its 2-sigma bounds at x = 0.4 L and 0.9 L;
* inputs.png: heater inputs (applied) vs nominal.
For many episodes every run is drawn thin, their mean thick, and the table has one row per
episode plus the pooled row.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from sep_control import metrics as M
from sep_control.analyze import AggregateReport, EpisodeReport
from sep_control.figures import pyplot, save_figure

LATENCY_NOTE = ("latency = receive time of slab/heat_command k minus receive time of slab/measurements k, "
                "both in the recorder's clock (bag log time)")


def _reports(rep) -> list[EpisodeReport]:
    return rep.reports if isinstance(rep, AggregateReport) else [rep]


def _x(r: EpisodeReport) -> np.ndarray:
    e = r.episode
    if e.x is not None:
        return e.x
    if r.scenario is not None and r.scenario.n_x == e.T.shape[1]:
        return r.scenario.grid()
    return np.arange(e.T.shape[1], dtype=float)


def fig_field(rep, path: Path) -> Path | None:
    reps = _reports(rep)
    s = reps[0].scenario
    if s is None or not np.isfinite(reps[0].episode.T).any():
        return None
    plt = pyplot()
    design = reps[0].design
    x = _x(reps[0])
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, t in zip(axes, (37.5, 62.5)):
        k = M.step_at(s, t)
        ax.axhspan(s.t_target - s.band, s.t_target + s.band, color="0.9", label=f"{s.t_target:g} ± {s.band:g} F")
        T = np.stack([r.episode.T[k] for r in reps])
        for row in T:
            ax.plot(x, row, color="C0", lw=0.6 if len(reps) > 1 else 1.5, alpha=0.35 if len(reps) > 1 else 1)
        if len(reps) > 1:
            ax.plot(x, np.nanmean(T, axis=0), color="C0", lw=2, label=f"mean of {len(reps)} runs")
        else:
            ax.lines[-1].set_label("closed loop (bag)")
        if design is not None and design.T_nom.shape[1] == len(x) and k < design.T_nom.shape[0]:
            ax.plot(x, design.T_nom[k], "k--", lw=1.2, label="nominal")
        ax.set_title(f"t = {k * s.dt:g} s (k = {k})")
        ax.set_xlabel("x / L")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("T [F]")
    axes[0].legend(loc="lower right", fontsize=8)
    return save_figure(fig, path)


def fig_estimation(rep, path: Path) -> Path | None:
    reps = _reports(rep)
    r0 = reps[0]
    if not np.isfinite(r0.err).any():
        return None
    plt = pyplot()
    x = _x(r0)
    L = r0.scenario.length if r0.scenario is not None else (x[-1] + (x[1] - x[0]))
    dt = r0.episode.dt
    t = np.arange(r0.err.shape[0]) * dt
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, frac in zip(axes, (0.4, 0.9)):
        i = int(np.argmin(np.abs(x - frac * L)))
        for j, r in enumerate(reps):
            lw, a = (0.6, 0.35) if len(reps) > 1 else (1.2, 1.0)
            ax.plot(t, r.err[:, i], color="C1", lw=lw, alpha=a, label="error T_hat - T" if j == 0 else None)
        std = np.nanmean(np.stack([r.episode.T_std[:, i] for r in reps]), axis=0)
        ax.fill_between(t, -2 * std, 2 * std, color="C0", alpha=0.2, label="± 2 sigma")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(f"x = {x[i]:.3g} (≈ {frac:g} L)")
        ax.set_xlabel("t [s]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("estimation error [F]")
    axes[0].legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def fig_inputs(rep, path: Path) -> Path | None:
    reps = _reports(rep)
    r0 = reps[0]
    U = np.stack([r.inputs for r in reps])
    if not np.isfinite(U).any():
        return None
    plt = pyplot()
    design = r0.design
    t = np.arange(U.shape[1]) * r0.episode.dt
    fig, ax = plt.subplots(figsize=(10, 4))
    for j in range(U.shape[2]):
        c = f"C{j % 10}"
        if len(reps) > 1:
            for row in U[:, :, j]:
                ax.plot(t, row, color=c, lw=0.4, alpha=0.25)
        ax.step(t, np.nanmean(U[:, :, j], axis=0), where="post", color=c, lw=1.5, label=f"heater_{j}")
        if design is not None and design.u_nom.shape[0] == U.shape[1] and j < design.u_nom.shape[1]:
            ax.step(t, design.u_nom[:, j], where="post", color=c, ls="--", lw=1)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("heater input")
    ax.set_title("applied inputs (solid" + (", mean over runs" if len(reps) > 1 else "") + ") vs nominal (dashed)")
    ax.grid(alpha=0.3)
    ax.legend(ncol=min(U.shape[2], 5), fontsize=8)
    return save_figure(fig, path)


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


def write_report(rep, out_dir: str | Path, figures: bool = True) -> Path:
    """Write report.md (+ PNGs) for an `EpisodeReport` or `AggregateReport`; returns report.md."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reps = _reports(rep)
    agg = isinstance(rep, AggregateReport)
    lines = [f"# sep bag analysis: {'%d episodes' % len(reps) if agg else reps[0].name}", ""]
    lines.append("Bags: " + ", ".join(f"`{r.episode.path}`" for r in reps[:10]) +
                 (f" and {len(reps) - 10} more" if len(reps) > 10 else ""))
    s = reps[0].scenario
    if s is not None:
        lines.append(f"Scenario: n_x = {s.n_x}, dt = {s.dt:g} s, N = {s.n_steps}, band {s.t_target:g} ± {s.band:g} F "
                     f"from k = {s.k_band} (source: {reps[0].episode.scenario_source})")
    d = reps[0].design
    lines.append("Design file: " + ("given (nominal comparisons included)" if d is not None else
                                    "none (no nominal comparisons; pass --design)"))
    lines += ["", "## Metrics", "", markdown_table(metrics_rows(rep)), "", f"- {LATENCY_NOTE}.",
              "- coverage_2sigma: share of node-steps k >= 1 with |T_hat - T| <= 2 std; field_nees: mean "
              "((T_hat - T)/std)^2 (about 1 when consistent).",
              "- deadline_misses / rejected_messages: last /diagnostics values (summed over episodes).", ""]
    problems = []
    for r in reps:
        e = r.episode
        if e.missing:
            problems.append(f"`{r.name}`: missing topics {', '.join(e.missing)}")
        if not e.complete:
            problems.append(f"`{r.name}`: truncated bag, analysed what was recovered")
        if r.mismatch:
            problems.append(f"`{r.name}`: SCENARIO MISMATCH with the design file: {'; '.join(r.mismatch)}")
        for n in r.notes:
            if not n.startswith("missing topics"):
                problems.append(f"`{r.name}`: {n}")
        if e.ignored_topics:
            problems.append(f"`{r.name}`: ignored topics outside the contract: {', '.join(e.ignored_topics)}")
    if agg:
        problems += rep.notes
    if problems:
        lines += ["## Notes", ""] + [f"- {p}" for p in problems[:50]] + [""]
    if figures:
        lines += ["## Figures", ""]
        for fn, title, fname in ((fig_field, "Closed-loop field vs nominal", "field.png"),
                                 (fig_estimation, "Estimation error with 2-sigma bounds", "estimation.png"),
                                 (fig_inputs, "Heater inputs vs nominal", "inputs.png")):
            p = fn(rep, out / fname)
            if p is None:
                lines.append(f"- {title}: not drawn (the bag lacks the topics it needs)")
            else:
                lines += [f"### {title}", "", f"![{title}]({fname})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
