"""DESIGN.md §3 metrics, shared by evaluation, benchmarks and bag analysis.

Arrays are batched: a leading run axis is optional everywhere. Trajectories are
T (..., N+1, n_x) for k = 0..N, inputs U (..., N, n_u) for k = 0..N-1.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from sep_plant.scenario import Scenario

#: keys of the machine-readable results (DESIGN.md §3)
JSON_KEYS = ("cost_mean", "cost_std", "in_band", "rms", "mean_dev_37_5", "mean_dev_62_5", "n_runs",
             "coverage_2sigma", "deadline_misses", "rejected_messages", "latency_p50_s", "latency_p99_s")
CONTROLLERS = ("open_loop", "rom_lqg", "oracle_lqg")


def nominal_cost(T: np.ndarray, U: np.ndarray, s: Scenario) -> np.ndarray:
    """J = sum_{k=1..N} q_k mean_i (T_{k,i} - T*)^2 + r_u sum_{k=0..N-1} |u_k|^2."""
    q = s.q_weights()[1:]
    field = np.einsum("k,...k->...", q, np.mean((T[..., 1:, :] - s.t_target) ** 2, axis=-1))
    return field + s.r_u * np.sum(U**2, axis=(-2, -1))


def in_band(T: np.ndarray, s: Scenario) -> np.ndarray:
    """True where the whole field stays in [T* - band, T* + band] for every k in [k_band, N]."""
    return np.all(np.abs(T[..., s.k_band:, :] - s.t_target) <= s.band, axis=(-2, -1))


def rms_in_window(T: np.ndarray, s: Scenario) -> np.ndarray:
    """RMS(T - T*) over k in [k_band, N] and all nodes."""
    return np.sqrt(np.mean((T[..., s.k_band:, :] - s.t_target) ** 2, axis=(-2, -1)))


def step_at(s: Scenario, t: float) -> int:
    """Step index of time t (clipped to [0, N])."""
    return int(min(max(round(t / s.dt), 0), s.n_steps))


def mean_deviation(T_runs: np.ndarray, T_nom: np.ndarray, k: int) -> float:
    """max_i |mean over runs of T_k - nominal T_k|."""
    return float(np.max(np.abs(np.mean(T_runs[:, k], axis=0) - T_nom[k])))


def coverage_2sigma(err: np.ndarray, std: np.ndarray) -> float:
    """Share of entries with |err| <= 2 std (about 0.95 for a consistent filter)."""
    return float(np.mean(np.abs(err) <= 2.0 * std))


def summarize(T_runs: np.ndarray, U_runs: np.ndarray, T_nom: np.ndarray, s: Scenario,
              extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The §3 closed-loop metrics for a batch of runs (T_runs (M, N+1, n_x), U_runs (M, N, n_u))."""
    J = nominal_cost(T_runs, U_runs, s)
    out: dict[str, Any] = {
        "cost_mean": float(np.mean(J)),
        "cost_std": float(np.std(J)),
        "in_band": float(np.mean(in_band(T_runs, s))),
        "rms": float(np.mean(rms_in_window(T_runs, s))),
        "mean_dev_37_5": mean_deviation(T_runs, T_nom, step_at(s, 37.5)),
        "mean_dev_62_5": mean_deviation(T_runs, T_nom, step_at(s, 62.5)),
        "n_runs": int(T_runs.shape[0]),
    }
    if extra:
        out.update(extra)
    return out


class MetricsAccumulator:
    """The `summarize` metrics computed step by step, without storing (M, N+1, n_x) trajectories.

    Feed `add_state(k, T_k)` for k = 0..N and `add_input(k, u_k)` for k = 0..N-1 (batched over
    M runs); `result()` equals `summarize` on the stacked arrays. Memory O(M + N n_x), so a
    Monte Carlo on a large grid does not need M N n_x numbers.
    """

    def __init__(self, s: Scenario, T_nom: np.ndarray, runs: int):
        self.s, self.T_nom, self.M = s, T_nom, runs
        self.q = s.q_weights()
        self.cost = np.zeros(runs)
        self.band_ok = np.ones(runs, dtype=bool)
        self.sq_sum = np.zeros(runs)
        self.k_marks = [(step_at(s, 37.5), "mean_dev_37_5"), (step_at(s, 62.5), "mean_dev_62_5")]
        self.mean_dev: dict[str, float] = {}
        self.mean_traj = np.zeros_like(T_nom)

    def add_state(self, k: int, T_k: np.ndarray) -> None:
        s = self.s
        err = T_k - s.t_target
        sq = np.mean(err**2, axis=-1)
        if k >= 1:
            self.cost += self.q[k] * sq
        if k >= s.k_band:
            self.band_ok &= np.all(np.abs(err) <= s.band, axis=-1)
            self.sq_sum += sq
        mean_k = np.mean(T_k, axis=0)
        self.mean_traj[k] = mean_k
        for k_mark, name in self.k_marks:
            if k == k_mark:
                self.mean_dev[name] = float(np.max(np.abs(mean_k - self.T_nom[k])))

    def add_input(self, k: int, u_k: np.ndarray) -> None:
        self.cost += self.s.r_u * np.sum(u_k**2, axis=-1)

    def result(self, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        n_win = self.s.n_steps + 1 - self.s.k_band
        out: dict[str, Any] = {
            "cost_mean": float(np.mean(self.cost)),
            "cost_std": float(np.std(self.cost)),
            "in_band": float(np.mean(self.band_ok)),
            "rms": float(np.mean(np.sqrt(self.sq_sum / n_win))),
            "mean_dev_37_5": self.mean_dev.get("mean_dev_37_5"),
            "mean_dev_62_5": self.mean_dev.get("mean_dev_62_5"),
            "n_runs": int(self.M),
        }
        if extra:
            out.update(extra)
        return out


def format_table(rows: Mapping[str, Mapping[str, Any]], keys: Iterable[str] | None = None) -> str:
    """Plain-text table: one row per controller/episode, one column per metric."""
    keys = list(keys) if keys is not None else [k for k in JSON_KEYS if any(k in r for r in rows.values())]
    head = ["name"] + keys
    body = [[name] + [_fmt(r.get(k)) for k in keys] for name, r in rows.items()]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body)]
    line = lambda cells: "  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(b) for b in body])


def write_json(path: str | Path, rows: Mapping[str, Mapping[str, Any]]) -> None:
    """One object per controller/episode: {"name": ..., <§3 keys>}."""
    data = [{"name": name, **{k: v for k, v in r.items()}} for name, r in rows.items()]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2, default=_json_default) + "\n")


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.2e}"
    return str(v)


def _json_default(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    raise TypeError(f"not JSON serializable: {type(v).__name__}")
