"""Recorded-bag analysis (Python API): DESIGN.md §3 metrics from rosbag2 bags of the topic graph.

    rep = analyze("episode_bag", design="design.npz")    # one episode
    rep.metrics["in_band"], rep.episode.T, rep.err ...
    agg = aggregate(["bag_000", "bag_001", ...], design="design.npz")   # many seeded episodes
    agg.metrics["cost_mean"], agg.rows                      # like the offline Monte Carlo table

Definitions (everything computed from the bag alone, plus the design for nominal comparisons):

* cost, in_band, rms, mean_dev_37_5 / mean_dev_62_5: `sep_control.metrics` on the recorded
  true field (slab/field) and the inputs the plant applied (slab/heat_applied; the commands
  when the bag has no heat_applied). For one episode mean_dev_* is max_i |T_k,i - Tnom_k,i|.
* coverage_2sigma: share of node-steps k = 1..N (as `montecarlo.simulate`) with |T_hat - T| <= 2 std (slab/field_estimate
  vs slab/field); field_nees: mean of ((T_hat - T) / std)^2 over node-steps with std > 0
  (about 1 for a consistent filter).
* latency (measurement-to-command): receive time of heat_command k minus receive time of
  measurement k, both in the recorder's clock (the bag's log time, which the recorder takes
  from the middleware's reception timestamp), for every k that has both; p50/p99 in seconds.
  The same for the estimate (state_estimate k - measurement k). Receive times include the
  recorder's own transport delay, which cancels in the difference up to jitter.
* episode_wall_s / episode_sim_s: receive-time span and stamp span of the measurements
  (real-time factor = sim / wall).
* deadline_misses, rejected_messages: the last /diagnostics values, summed over the status
  entries (nodes) that report them.

Pure: no rclpy, no matplotlib (figures are in `sep_control.report`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from sep_plant.scenario import Scenario, mismatches
from sep_control import metrics as M
from sep_control.bag_io import BagError, Episode, read_episode


class AnalysisError(RuntimeError):
    """The bags cannot be analysed as asked (scenario mismatch, inconsistent bags)."""


@dataclass
class EpisodeReport:
    """Metrics and arrays of one recorded episode."""

    name: str
    episode: Episode
    scenario: Scenario | None          # scenario the metrics were computed with
    design: Any | None                 # sep_estimator.design_file.Design or None
    metrics: dict[str, Any]
    err: np.ndarray                    # (N+1, n_x) T_hat - T (NaN where either is missing)
    latency_cmd_s: np.ndarray          # per step with both messages
    latency_est_s: np.ndarray
    mismatch: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def inputs(self) -> np.ndarray:
        """Applied inputs (commands where the applied ones are missing)."""
        e = self.episode
        return np.where(np.isfinite(e.u), e.u, e.u_cmd)


@dataclass
class AggregateReport:
    """Statistics over many episodes (one row per episode plus the pooled metrics)."""

    reports: list[EpisodeReport]
    scenario: Scenario | None
    design: Any | None
    metrics: dict[str, Any]
    rows: dict[str, dict[str, Any]]     # episode name -> its metrics
    notes: list[str] = field(default_factory=list)

    @property
    def T_runs(self) -> np.ndarray:
        return np.stack([r.episode.T for r in self.reports])


def _load_design(design):
    if design is None or not isinstance(design, (str, Path)):
        return design
    from sep_estimator.design_file import load_design

    return load_design(design)


def _pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if a.size else None


def _check_scenario(ep: Episode, design, allow_mismatch: bool, name: str) -> list[str]:
    if design is None or ep.scenario is None or ep.scenario_source != "bag":
        return []
    diff = mismatches(design.scenario, ep.scenario)
    if diff and not allow_mismatch:
        raise AnalysisError(f"{name}: the bag was recorded with another scenario than the design file: "
                            + "; ".join(diff) + ". Use the design file of that plant, or --allow-mismatch "
                            "to analyse it anyway (nominal comparisons are then skipped where shapes differ)")
    return diff


def episode_metrics(ep: Episode, s: Scenario | None, T_nom: np.ndarray | None) -> tuple[dict, list[str], np.ndarray]:
    """§3 metrics of one episode (None where the bag lacks what a metric needs)."""
    notes: list[str] = []
    out: dict[str, Any] = {k: None for k in M.JSON_KEYS}
    out["n_runs"] = 1
    U = np.where(np.isfinite(ep.u), ep.u, ep.u_cmd)
    T = ep.T
    if s is not None and T.shape == (s.n_steps + 1, s.n_x):
        if np.all(np.isfinite(T[1:])) and np.all(np.isfinite(U)) and U.shape == (s.n_steps, s.n_u):
            J = float(M.nominal_cost(T, U, s))
            out["cost_mean"], out["cost_std"] = J, 0.0
        else:
            notes.append("cost not computed: field or inputs missing at some step")
        if np.all(np.isfinite(T[s.k_band:])):
            out["in_band"] = float(M.in_band(T, s))
            out["rms"] = float(M.rms_in_window(T, s))
        else:
            notes.append("in_band/rms not computed: field missing in the band window")
        if T_nom is not None and T_nom.shape == T.shape:
            for key, t in (("mean_dev_37_5", 37.5), ("mean_dev_62_5", 62.5)):
                k = M.step_at(s, t)
                if np.all(np.isfinite(T[k])):
                    out[key] = M.mean_deviation(T[None], T_nom, k)
    err = ep.T_hat - ep.T
    ok = np.isfinite(err) & np.isfinite(ep.T_std)
    ok[0] = False                        # k >= 1, as the offline Monte Carlo (T_0 is known exactly)
    if ok.any():
        out["coverage_2sigma"] = M.coverage_2sigma(err[ok], ep.T_std[ok])
        pos = ok & (ep.T_std > 0)
        out["field_nees"] = float(np.mean((err[pos] / ep.T_std[pos]) ** 2)) if pos.any() else None
        out["field_rmse"] = float(np.sqrt(np.mean(err[ok] ** 2)))
    sr = ep.step_recv_ns
    meas = sr.get("measurements")
    lat_cmd = lat_est = np.zeros(0)
    if meas is not None:
        if "heat_command" in sr:
            d = sr["heat_command"][:-1] - meas[:-1] if len(sr["heat_command"]) == len(meas) else np.zeros(0)
            lat_cmd = d[np.isfinite(d)] * 1e-9
        if "state_estimate" in sr:
            d = sr["state_estimate"] - meas
            lat_est = d[np.isfinite(d)] * 1e-9
    out["latency_p50_s"] = _pct(lat_cmd, 50)
    out["latency_p99_s"] = _pct(lat_cmd, 99)
    out["latency_max_s"] = float(lat_cmd.max()) if lat_cmd.size else None
    out["latency_estimate_p50_s"] = _pct(lat_est, 50)
    out["latency_estimate_p99_s"] = _pct(lat_est, 99)
    tt = ep.times.get("measurements")
    if tt is not None and tt.recv_ns.size > 1:
        dr = (tt.recv_ns - tt.recv_ns[0]) * 1e-9
        ds = (tt.stamp_ns - tt.stamp_ns[0]) * 1e-9
        out["episode_wall_s"] = float(dr[-1])
        out["episode_sim_s"] = float(ds[-1])
    out["deadline_misses"] = ep.diag_totals.get("deadline_misses")
    out["rejected_messages"] = ep.diag_totals.get("rejected_messages")
    out["steps_recorded"] = int(np.sum(np.isfinite(sr["measurements"]))) if meas is not None else 0
    out["complete"] = bool(ep.complete and not ep.missing)
    return out, notes, (lat_cmd, lat_est)


def analyze(bag_path: str | Path, design=None, *, allow_mismatch: bool = False, allow_truncated: bool = False,
            namespace: str = "slab", name: str | None = None) -> EpisodeReport:
    """Metrics and arrays of one bag. `design`: a `Design`, a path to a design file, or None
    (then nominal comparisons are skipped). A bag of another plant than the design raises
    `AnalysisError` unless `allow_mismatch`."""
    design = _load_design(design)
    bag_path = Path(bag_path)
    name = name or bag_path.stem if bag_path.is_file() else (name or bag_path.name)
    ep = read_episode(bag_path, scenario=design.scenario if design is not None else None,
                      namespace=namespace, allow_truncated=allow_truncated)
    diff = _check_scenario(ep, design, allow_mismatch, str(bag_path))
    notes = list(ep.notes)
    s = ep.scenario
    T_nom = None
    if design is not None:
        if not diff:
            s = design.scenario          # the design's objective (band, weights) defines the metrics
            T_nom = design.T_nom
        else:
            notes.append("scenario mismatch: " + "; ".join(diff))
            if design.T_nom.shape == ep.T.shape:
                T_nom = design.T_nom
    m, mnotes, (lat_cmd, lat_est) = episode_metrics(ep, s, T_nom)
    if diff:
        m["scenario_mismatch"] = diff
    if ep.missing:
        notes.append("missing topics: " + ", ".join(ep.missing))
    return EpisodeReport(name=name, episode=ep, scenario=s, design=design, metrics=m, err=ep.T_hat - ep.T,
                         latency_cmd_s=lat_cmd, latency_est_s=lat_est, mismatch=diff, notes=notes + mnotes)


def aggregate(paths: Iterable[str | Path] | Sequence[EpisodeReport], design=None, *, allow_mismatch: bool = False,
              allow_truncated: bool = False, namespace: str = "slab") -> AggregateReport:
    """Pooled statistics of many episodes, comparable to the offline Monte Carlo table:
    cost mean/std, in-band fraction, mean RMS and mean-trajectory deviations over the runs
    (`metrics.summarize`), 2-sigma coverage over all node-steps, latency percentiles over all
    steps, deadline misses and rejected messages summed over the episodes."""
    design = _load_design(design)
    reports: list[EpisodeReport] = []
    for p in paths:
        if isinstance(p, EpisodeReport):
            reports.append(p)
        else:
            reports.append(analyze(p, design, allow_mismatch=allow_mismatch, allow_truncated=allow_truncated,
                                   namespace=namespace))
    if not reports:
        raise AnalysisError("no bags to aggregate")
    names: dict[str, int] = {}
    rows: dict[str, dict[str, Any]] = {}
    for r in reports:
        n = r.name
        if n in names:
            names[n] += 1
            n = f"{n}#{names[n]}"
        else:
            names[n] = 0
        rows[n] = r.metrics
    s = reports[0].scenario
    for r in reports[1:]:
        if (r.scenario is None) != (s is None) or (s is not None and mismatches(s, r.scenario)):
            raise AnalysisError(f"{r.episode.path}: recorded with another scenario than {reports[0].episode.path} "
                                "(" + "; ".join(mismatches(s, r.scenario) if s and r.scenario else ["scenario missing"])
                                + "); aggregate bags of one scenario")
    notes: list[str] = []
    out: dict[str, Any] = {k: None for k in M.JSON_KEYS}
    out["n_runs"] = len(reports)
    full = [r for r in reports if s is not None and np.all(np.isfinite(r.episode.T[1:]))
            and np.all(np.isfinite(r.inputs))]
    if len(full) < len(reports):
        notes.append(f"{len(reports) - len(full)} of {len(reports)} episodes lack the field or inputs at some "
                     "step and are left out of the cost/band statistics")
    if full:
        T_runs = np.stack([r.episode.T for r in full])
        U_runs = np.stack([r.inputs for r in full])
        T_nom = design.T_nom if design is not None and design.T_nom.shape == T_runs.shape[1:] else None
        if T_nom is not None:
            out.update(M.summarize(T_runs, U_runs, T_nom, s))
        else:
            J = M.nominal_cost(T_runs, U_runs, s)
            out.update(cost_mean=float(np.mean(J)), cost_std=float(np.std(J)),
                       in_band=float(np.mean(M.in_band(T_runs, s))), rms=float(np.mean(M.rms_in_window(T_runs, s))))
        out["n_runs"] = len(full)
    err = np.concatenate([r.err[1:].ravel() for r in reports])
    std = np.concatenate([r.episode.T_std[1:].ravel() for r in reports])
    ok = np.isfinite(err) & np.isfinite(std)
    if ok.any():
        out["coverage_2sigma"] = M.coverage_2sigma(err[ok], std[ok])
        pos = ok & (std > 0)
        out["field_nees"] = float(np.mean((err[pos] / std[pos]) ** 2)) if pos.any() else None
        out["field_rmse"] = float(np.sqrt(np.mean(err[ok] ** 2)))
    lat = np.concatenate([r.latency_cmd_s for r in reports])
    late = np.concatenate([r.latency_est_s for r in reports])
    out["latency_p50_s"], out["latency_p99_s"] = _pct(lat, 50), _pct(lat, 99)
    out["latency_max_s"] = float(lat.max()) if lat.size else None
    out["latency_estimate_p50_s"], out["latency_estimate_p99_s"] = _pct(late, 50), _pct(late, 99)
    for key in ("deadline_misses", "rejected_messages"):
        vals = [r.metrics.get(key) for r in reports if r.metrics.get(key) is not None]
        out[key] = int(sum(vals)) if vals else None
    out["complete"] = all(r.metrics.get("complete") for r in reports)
    return AggregateReport(reports=reports, scenario=s, design=design, metrics=out, rows=rows, notes=notes)


__all__ = ["AnalysisError", "BagError", "EpisodeReport", "AggregateReport", "analyze", "aggregate",
           "episode_metrics"]
