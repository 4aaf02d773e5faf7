"""metrics (docs/method.md), shared by evaluation, benchmarks and bag analysis.

Arrays are batched: a leading run axis is optional everywhere. Field trajectories are
F (..., N+1, n_field) for k = 0..N, inputs U (..., N, n_u) for k = 0..N-1; the objective
(target f*, weights q_k, band, band window) is a `sep_plant.problem.Objective`.

A recipe's objective (`Objective.holds`) has several hold segments s = (k_s0, k_s1, band_s): a
run is in band when |f_{k,i} - f*_{k,i}| <= band_s for every node and every step of EVERY hold,
and the metrics add `segments`, per hold: in_band (share of runs in band over that hold),
max_dev (the largest |f - f*| over the hold, runs and nodes) and max_dev_p99 (the 99 % quantile
over the runs of each run's largest |f - f*| over the hold).
Pure numpy: no ROS import.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from sep_plant.plants.backend import namespace, to_host
from sep_plant.problem import Objective
from sep_plant.scenario import json_default

#: keys of the machine-readable results (docs/method.md); mean_dev_start/end: at the band
#: window's first and last step
JSON_KEYS = ("cost_mean", "cost_std", "in_band", "rms", "mean_dev_start", "mean_dev_end", "n_runs",
             "coverage_2sigma", "deadline_misses", "rejected_messages", "latency_p50_s", "latency_p99_s")


def nominal_cost(F: np.ndarray, U: np.ndarray, obj: Objective) -> np.ndarray:
    """J = sum_{k=1..N} q_k mean_i (f_{k,i} - f*_i)^2 + r_u sum_{k=0..N-1} |u_k|^2: `Objective.cost`, the
    one place J is written (its step-by-step form, for `MetricsAccumulator`, is beside it)."""
    return obj.cost(F, U)


def _window(F: np.ndarray, obj: Objective, k0: int | None = None, k1: int | None = None) -> np.ndarray:
    """f_k - f*_k over steps k0..k1 (the band window by default)."""
    if k0 is None:
        k0, k1 = obj.window
    return F[..., k0:k1 + 1, :] - obj.targets(k0, k1)


def in_band(F: np.ndarray, obj: Objective) -> np.ndarray:
    """True where the whole field stays in [f*_k - band_s, f*_k + band_s] for every k of every
    hold s (the band window with `band` without a recipe)."""
    ok = None
    for k0, k1, band in obj.segments:
        seg = np.all(np.abs(_window(F, obj, k0, k1)) <= band, axis=(-2, -1))
        ok = seg if ok is None else ok & seg
    return ok


def segment_max_dev(F: np.ndarray, obj: Objective) -> np.ndarray:
    """Each run's largest |f - f*| over each hold: (S, ...) for the S holds."""
    return np.stack([np.max(np.abs(_window(F, obj, k0, k1)), axis=(-2, -1)) for k0, k1, _ in obj.segments])


def segment_summary(max_dev: np.ndarray, obj: Objective) -> list[dict[str, Any]]:
    """The per-hold metrics from each run's largest deviation per hold, max_dev (S, M)."""
    out = []
    for (k0, k1, band), d in zip(obj.segments, np.atleast_2d(max_dev)):
        out.append({"k_start": int(k0), "k_end": int(k1), "band": float(band),
                    "in_band": float(np.mean(d <= band)), "max_dev": float(np.max(d)),
                    "max_dev_p99": float(np.percentile(d, 99))})
    return out


def rms_in_window(F: np.ndarray, obj: Objective) -> np.ndarray:
    """RMS(f - f*) over the band window and all nodes."""
    return np.sqrt(np.mean(_window(F, obj) ** 2, axis=(-2, -1)))


def mean_deviation(F_runs: np.ndarray, F_nom: np.ndarray, k: int) -> float:
    """max_i |mean over runs of f_k - nominal f_k|."""
    return float(np.max(np.abs(np.mean(F_runs[:, k], axis=0) - F_nom[k])))


def coverage_2sigma(err: np.ndarray, std: np.ndarray) -> float:
    """Share of entries with |err| <= 2 std (about 0.95 for a consistent filter)."""
    return float(np.mean(np.abs(err) <= 2.0 * std))


def summarize(F_runs: np.ndarray, U_runs: np.ndarray, F_nom: np.ndarray, obj: Objective,
              extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The closed-loop metrics (docs/method.md#metrics) for a batch of runs (F_runs (M, N+1, n_field), U_runs (M, N, n_u))."""
    J = nominal_cost(F_runs, U_runs, obj)
    k0, k1 = obj.window
    out: dict[str, Any] = {
        "cost_mean": float(np.mean(J)),
        "cost_std": float(np.std(J)),
        "in_band": float(np.mean(in_band(F_runs, obj))),
        "rms": float(np.mean(rms_in_window(F_runs, obj))),
        "mean_dev_start": mean_deviation(F_runs, F_nom, k0),
        "mean_dev_end": mean_deviation(F_runs, F_nom, k1),
        "n_runs": int(F_runs.shape[0]),
    }
    if obj.holds is not None:
        out["segments"] = segment_summary(segment_max_dev(F_runs, obj), obj)
    if extra:
        out.update(extra)
    return out


class MetricsAccumulator:
    """The `summarize` metrics computed step by step, without storing (M, N+1, n_field) trajectories.

    Feed `add_field(k, f_k)` for k = 0..N and `add_input(k, u_k)` for k = 0..N-1 (batched over
    M runs); `result()` equals `summarize` on the stacked arrays. Memory O(M + N n_field), so a
    Monte Carlo on a large grid does not need M N n_field numbers.
    """

    def __init__(self, obj: Objective, F_nom: np.ndarray, runs: int):
        self.obj, self.F_nom, self.M = obj, F_nom, runs
        self.cost = np.zeros(runs)
        self.band_ok = np.ones(runs, dtype=bool)
        self.sq_sum = np.zeros(runs)
        self.sum_traj = np.zeros_like(F_nom)
        # a recipe: each run's largest |f - f*| per hold (S, M), and the holds' steps
        self.seg_dev = np.zeros((len(obj.segments), runs)) if obj.holds is not None else None
        self._hold_of = {k: (s, band) for s, (k0, k1, band) in enumerate(obj.segments) for k in range(k0, k1 + 1)}

    def add_field(self, k: int, f_k: np.ndarray, rows: slice = slice(None)) -> None:
        """The field of step k of the runs `rows` (all by default; a chunk of them otherwise)."""
        obj = self.obj
        xp = namespace(f_k)
        if np.ndim(obj.target) > 1:            # f*_k per step (host or device)
            return self._add_steps_field(k, f_k, rows)
        if xp is not np:                       # a device field: reduced there, the sums come to the host
            return self._add_device_field(xp, k, f_k, rows)
        self._add_squared_error(k, obj.squared_error(f_k), rows)
        k0, k1 = obj.window
        if k0 <= k <= k1:
            self.band_ok[rows] &= np.all(np.abs(f_k - obj.target) <= obj.band, axis=-1)
        self.sum_traj[k] += np.sum(f_k, axis=0)

    def _add_squared_error(self, k: int, sq: np.ndarray, rows: slice) -> None:
        """Step k's share of the cost J and of the band window's rms from the runs' mean squared
        error over the nodes, sq = mean_i (f_k,i - f*_k,i)^2 (host numbers)."""
        if k >= 1:
            self.cost[rows] += self.obj.field_cost(k, sq)
        k0, k1 = self.obj.window
        if k0 <= k <= k1:
            self.sq_sum[rows] += sq

    def _add_steps_field(self, k: int, f_k, rows: slice) -> None:
        """`add_field` of a per-step target f*_k with holds (a recipe): the band test of the
        hold step k is in, the largest deviation per hold, the rms over the band window."""
        obj = self.obj
        xp = namespace(f_k)
        target = obj.target_at(k) if xp is np else xp.asarray(obj.target_at(k))
        err = f_k - target
        self._add_squared_error(k, to_host(xp.mean(err**2, axis=-1)), rows)
        if k in self._hold_of:
            s, band = self._hold_of[k]
            dev = to_host(xp.max(xp.abs(err), axis=-1))
            self.band_ok[rows] &= dev <= band
            if self.seg_dev is not None:
                self.seg_dev[s, rows] = np.maximum(self.seg_dev[s, rows], dev)
        self.sum_traj[k] += to_host(xp.sum(f_k, axis=0))

    def _add_device_field(self, xp, k: int, f_k, rows: slice) -> None:
        """`add_field` of a device array (`sep_control.evaluation.montecarlo`): the same sums, with
        the per-run ones (M numbers) and the summed field (n_field) copied to the host."""
        obj = self.obj
        target = obj.target if np.ndim(obj.target) == 0 else self._on(xp, "target", obj.target)
        band = obj.band if np.ndim(obj.band) == 0 else self._on(xp, "band", obj.band)
        err = f_k - target
        self._add_squared_error(k, to_host(xp.mean(err**2, axis=-1)), rows)
        k0, k1 = obj.window
        if k0 <= k <= k1:
            self.band_ok[rows] &= to_host(xp.all(xp.abs(err) <= band, axis=-1))
        self.sum_traj[k] += to_host(xp.sum(f_k, axis=0))

    def _on(self, xp, name: str, value):
        """A host constant's device copy, made once."""
        cache = self.__dict__.setdefault("_device", {})
        if name not in cache:
            cache[name] = xp.asarray(np.asarray(value, dtype=float))
        return cache[name]

    def add_input(self, k: int, u_k: np.ndarray, rows: slice = slice(None)) -> None:
        self.cost[rows] += self.obj.input_cost(u_k)

    def state(self) -> dict[str, np.ndarray]:
        """The per-run sums and the summed field (to merge a chunk's accumulator into another)."""
        out = {"cost": self.cost, "band_ok": self.band_ok, "sq_sum": self.sq_sum, "sum_traj": self.sum_traj}
        if self.seg_dev is not None:
            out["seg_dev"] = self.seg_dev
        return out

    def merge(self, part: Mapping[str, np.ndarray], rows: slice) -> None:
        """Add a chunk's `state()` for the runs `rows` (chunks merged in order: the same sums)."""
        self.cost[rows] += part["cost"]
        self.band_ok[rows] &= part["band_ok"]
        self.sq_sum[rows] += part["sq_sum"]
        self.sum_traj += part["sum_traj"]
        if self.seg_dev is not None:
            self.seg_dev[:, rows] = np.maximum(self.seg_dev[:, rows], part["seg_dev"])

    @property
    def mean_traj(self) -> np.ndarray:
        """(N+1, n_field) mean field over the runs."""
        return self.sum_traj / self.M

    def result(self, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        k0, k1 = self.obj.window
        mean = self.mean_traj
        out: dict[str, Any] = {
            "cost_mean": float(np.mean(self.cost)),
            "cost_std": float(np.std(self.cost)),
            "in_band": float(np.mean(self.band_ok)),
            "rms": float(np.mean(np.sqrt(self.sq_sum / (k1 - k0 + 1)))),
            "mean_dev_start": float(np.max(np.abs(mean[k0] - self.F_nom[k0]))),
            "mean_dev_end": float(np.max(np.abs(mean[k1] - self.F_nom[k1]))),
            "n_runs": int(self.M),
        }
        if self.seg_dev is not None:
            out["segments"] = segment_summary(self.seg_dev, self.obj)
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


def write_metrics_json(path: str | Path, rows: Mapping[str, Mapping[str, Any]]) -> None:
    """The metrics table as JSON (``--json`` of sep evaluate / analyze): a list of one object per
    controller/episode, {"name": ..., <the keys of docs/method.md#metrics>}."""
    data = [{"name": name, **{k: v for k, v in r.items()}} for name, r in rows.items()]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2, default=json_default) + "\n")


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.2e}"
    return str(v)

