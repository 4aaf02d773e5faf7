"""Metrics of recorded episodes (docs/method.md#metrics) from their arrays: one episode, or pooled.

Definitions (everything computed from the bag alone, plus the design for nominal comparisons):

* cost, in_band, rms, mean_dev_start / mean_dev_end: `sep_control.evaluation.metrics` on the recorded
  true field (the field cloud) and the inputs the plant applied (applied_input; the commands
  when the bag has no applied_input). For one episode mean_dev_* is max_i |f_k,i - fnom_k,i| at
  the band window's first and last step.
* coverage_2sigma: share of node-steps k = 1..N (as `montecarlo.simulate`) with
  |f_hat - f| <= 2 std (field_estimate vs field); field_nees: mean of ((f_hat - f) / std)^2
  over node-steps with std > 0 (about 1 for a consistent filter); field_rmse.
* latency (measurement-to-command): receive time of command k minus receive time of
  measurement k, both in the recorder's clock (the bag's log time, which the recorder takes
  from the middleware's reception timestamp), for every k that has both; p50/p99 in seconds.
  The same for the estimate (state_estimate k - measurement k). Receive times include the
  recorder's own transport delay, which cancels in the difference up to jitter.
* episode_wall_s / episode_sim_s: receive-time span and stamp span of the measurements
  (real-time factor = sim / wall).
* deadline_misses, rejected_messages: the last /diagnostics values, summed over the status
  entries (nodes) that report them.
* d_hat_end: the disturbance estimates d_hat (the state_estimate entries d_0, d_1, ...) at the
  last step with an estimate; None without disturbance states (docs/method.md). For many episodes
  the pooled value is their mean.
* controller: rom_lqg or rom_mpc, from the LQR node's /diagnostics (None in bags of sep < 0.3,
  whose LQR did not report it: those ran the LQR); for rom_mpc also mpc_qp_steps and
  mpc_fallbacks (QPs solved, steps that fell back to the clipped LQR).

Pooled over many episodes (`pooled_metrics`): cost, band and RMS statistics over the episodes
that have the field and inputs at every step, coverage and latencies over all node-steps and
steps, the diagnostics counters summed.

Pure numpy: no rclpy (`sep_control.bags.analysis` reads the bags and calls these).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from sep_control.bags.reader import Episode
from sep_control.evaluation import metrics as M
from sep_plant import topics as T
from sep_plant.problem import Objective

if TYPE_CHECKING:
    from sep_control.bags.analysis import EpisodeReport


def _pct(a: np.ndarray, q: float) -> float | None:
    return float(np.percentile(a, q)) if a.size else None


def latencies(ep: Episode) -> tuple[np.ndarray, np.ndarray]:
    """(command, estimate) latencies [s] per step that has both messages: receive time of
    command k (state_estimate k) minus that of measurement k."""
    sr = ep.step_recv_ns
    meas = sr.get(T.MEASUREMENTS)
    lat_cmd = lat_est = np.zeros(0)
    if meas is None:
        return lat_cmd, lat_est
    if T.COMMAND in sr:
        d = sr[T.COMMAND][:-1] - meas[:-1]
        lat_cmd = d[np.isfinite(d)] * 1e-9
    if T.STATE_ESTIMATE in sr:
        d = sr[T.STATE_ESTIMATE] - meas
        lat_est = d[np.isfinite(d)] * 1e-9
    return lat_cmd, lat_est


def control_metrics(F: np.ndarray, U: np.ndarray, obj: Objective, F_nom: np.ndarray | None,
                    notes: list[str]) -> dict[str, Any]:
    """cost, in_band, rms and mean_dev_start/end of one episode (each only where the field and
    inputs it needs were recorded)."""
    out: dict[str, Any] = {}
    k0, k1 = obj.window
    if np.all(np.isfinite(F[1:])) and np.all(np.isfinite(U)):
        out["cost_mean"], out["cost_std"] = float(M.nominal_cost(F, U, obj)), 0.0
    else:
        notes.append("cost not computed: field or inputs missing at some step")
    if np.all(np.isfinite(F[k0:k1 + 1])):
        out["in_band"] = float(M.in_band(F, obj))
        out["rms"] = float(M.rms_in_window(F, obj))
    else:
        notes.append("in_band/rms not computed: field missing in the band window")
    if obj.holds is not None and all(np.all(np.isfinite(F[a:b + 1])) for a, b, _ in obj.holds):
        out["segments"] = M.segment_summary(M.segment_max_dev(F[None], obj), obj)   # a recipe: per hold
    if F_nom is not None:
        for key, k in (("mean_dev_start", k0), ("mean_dev_end", k1)):
            if np.all(np.isfinite(F[k])):
                out[key] = M.mean_deviation(F[None], F_nom, k)
    return out


def estimation_metrics(err: np.ndarray, std: np.ndarray) -> dict[str, Any]:
    """coverage_2sigma, field_nees, field_rmse over the node-steps that have error and std."""
    ok = np.isfinite(err) & np.isfinite(std)
    if not ok.any():
        return {}
    pos = ok & (std > 0)
    return {"coverage_2sigma": M.coverage_2sigma(err[ok], std[ok]),
            "field_nees": float(np.mean((err[pos] / std[pos]) ** 2)) if pos.any() else None,
            "field_rmse": float(np.sqrt(np.mean(err[ok] ** 2)))}


def latency_metrics(lat_cmd: np.ndarray, lat_est: np.ndarray) -> dict[str, Any]:
    return {"latency_p50_s": _pct(lat_cmd, 50), "latency_p99_s": _pct(lat_cmd, 99),
            "latency_max_s": float(lat_cmd.max()) if lat_cmd.size else None,
            "latency_estimate_p50_s": _pct(lat_est, 50), "latency_estimate_p99_s": _pct(lat_est, 99)}


def episode_metrics(ep: Episode, obj: Objective | None, F_nom: np.ndarray | None
                    ) -> tuple[dict[str, Any], list[str], tuple[np.ndarray, np.ndarray]]:
    """The metrics (docs/method.md#metrics) of one episode (None where the bag lacks what a metric needs), notes, and
    the (command, estimate) latencies."""
    notes: list[str] = []
    out: dict[str, Any] = {k: None for k in M.JSON_KEYS}
    out["n_runs"] = 1
    U = np.where(np.isfinite(ep.u), ep.u, ep.u_cmd)
    if obj is not None:
        if F_nom is not None and F_nom.shape != ep.F.shape:
            F_nom = None
        out.update(control_metrics(ep.F, U, obj, F_nom, notes))
    err = ep.F_hat - ep.F
    # k >= 1, as the offline Monte Carlo (the initial field is known exactly)
    out.update(estimation_metrics(err[1:], ep.F_std[1:]))
    lat_cmd, lat_est = latencies(ep)
    out.update(latency_metrics(lat_cmd, lat_est))
    tt = ep.times.get(T.MEASUREMENTS)
    if tt is not None and tt.recv_ns.size > 1:
        out["episode_wall_s"] = float((tt.recv_ns[-1] - tt.recv_ns[0]) * 1e-9)
        out["episode_sim_s"] = float((tt.stamp_ns[-1] - tt.stamp_ns[0]) * 1e-9)
    ctl = [d.get("controller") for d in ep.diagnostics.values() if d.get("controller")]
    out["controller"] = {"mpc": "rom_mpc", "lqr": "rom_lqg"}.get(ctl[0], ctl[0]) if ctl else None
    if out["controller"] == "rom_mpc":
        for key in ("mpc_qp_steps", "mpc_fallbacks"):
            out[key] = ep.diag_totals.get(key)
    out["deadline_misses"] = ep.diag_totals.get("deadline_misses")
    out["rejected_messages"] = ep.diag_totals.get("rejected_messages")
    out["d_hat_end"] = d_hat_end(ep)
    meas = ep.step_recv_ns.get(T.MEASUREMENTS)
    out["steps_recorded"] = int(np.sum(np.isfinite(meas))) if meas is not None else 0
    out["complete"] = bool(ep.complete and not ep.missing)
    return out, notes, (lat_cmd, lat_est)


def d_hat_end(ep: Episode) -> list[float] | None:
    """The disturbance estimates at the last step that has all of them (None: no disturbance
    states in the bag's state_estimate, or no such step)."""
    dh = ep.d_hat
    if not dh.shape[1]:
        return None
    full = np.flatnonzero(np.all(np.isfinite(dh), axis=1))
    return [float(v) for v in dh[full[-1]]] if full.size else None


def pooled_control_metrics(F_runs: np.ndarray, U_runs: np.ndarray, obj: Objective, F_nom: np.ndarray | None
                           ) -> dict[str, Any]:
    """`metrics.summarize` over complete episodes, F_runs (M, N+1, n_field) and U_runs (M, N, n_u)
    (cost, band and RMS only without a nominal of their shape)."""
    if F_nom is not None and F_nom.shape == F_runs.shape[1:]:
        return M.summarize(F_runs, U_runs, F_nom, obj)
    J = M.nominal_cost(F_runs, U_runs, obj)
    out = {"cost_mean": float(np.mean(J)), "cost_std": float(np.std(J)),
           "in_band": float(np.mean(M.in_band(F_runs, obj))), "rms": float(np.mean(M.rms_in_window(F_runs, obj))),
           "n_runs": len(F_runs)}
    if obj.holds is not None:
        out["segments"] = M.segment_summary(M.segment_max_dev(F_runs, obj), obj)
    return out


def pooled_metrics(reports: Sequence[EpisodeReport], obj: Objective | None, F_nom: np.ndarray | None,
                   notes: list[str]) -> dict[str, Any]:
    """The metrics of many episodes of one scenario (module docstring) against `obj` and `F_nom`
    (the first episode's); episodes left out of the cost statistics are noted in `notes`."""
    out: dict[str, Any] = {k: None for k in M.JSON_KEYS}
    out["n_runs"] = len(reports)
    full = [r for r in reports if obj is not None and r.episode.F.shape == reports[0].episode.F.shape
            and np.all(np.isfinite(r.episode.F[1:])) and np.all(np.isfinite(r.inputs))]
    if len(full) < len(reports):
        notes.append(f"{len(reports) - len(full)} of {len(reports)} episodes lack the field or inputs at some "
                     "step (or the objective) and are left out of the cost/band statistics")
    if full:
        out.update(pooled_control_metrics(np.stack([r.episode.F for r in full]), np.stack([r.inputs for r in full]),
                                          obj, F_nom))
    out.update(estimation_metrics(np.concatenate([r.err[1:].ravel() for r in reports]),
                                  np.concatenate([r.episode.F_std[1:].ravel() for r in reports])))
    out.update(latency_metrics(np.concatenate([r.latency_cmd_s for r in reports]),
                               np.concatenate([r.latency_est_s for r in reports])))
    for key in ("deadline_misses", "rejected_messages"):
        vals = [r.metrics.get(key) for r in reports if r.metrics.get(key) is not None]
        out[key] = int(sum(vals)) if vals else None
    ends = [r.metrics.get("d_hat_end") for r in reports]
    if ends and all(e is not None and len(e) == len(ends[0]) for e in ends):
        out["d_hat_end"] = [float(v) for v in np.mean(ends, axis=0)]
    out["complete"] = all(r.metrics.get("complete") for r in reports)
    out["model_mismatch"] = list(dict.fromkeys(d for r in reports for d in r.model_mismatch))
    return out


__all__ = ["control_metrics", "d_hat_end", "episode_metrics", "estimation_metrics", "latencies", "latency_metrics",
           "pooled_control_metrics", "pooled_metrics"]
