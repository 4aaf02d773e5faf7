"""Recorded-bag analysis (Python API): metrics (docs/method.md) from rosbag2 bags of the topic graph.

    rep = analyze("episode_bag", design="design.npz")    # one episode
    rep.metrics["in_band"], rep.episode.F, rep.err ...
    agg = aggregate(["bag_000", "bag_001", ...], design="design.npz")   # many seeded episodes
    agg.metrics["cost_mean"], agg.rows                      # like the offline Monte Carlo table

Works for any plant: the objective (target field, weights, band, band window) is the design's
(`design.objective`, nominal `design.nominal.field`) or, without a design, the bag's scenario
resolved on the clouds' node coordinates (`Objective.of(scenario.problem, xyz)`).

The metrics and their definitions are in `sep_control.bags.bag_metrics` (docs/method.md#metrics);
this module adds what compares the bag with the design:

* model_mismatch: how the plant the episode ran on differed from the design's model (a
  sim-to-real rehearsal, docs/robustness.md): plant keys and the perturbation of its actuators
  and sensors, from the bag's scenario message against the design (`sep_plant.truth.plant_differences`),
  else what the controllers reported on /diagnostics (run with allow_model_mismatch); [] when
  none. Such an episode is measured against the design's objective and nominal, the goal the
  controllers had, without --allow-mismatch.

Progress: `analyze` and `aggregate` take ``on_progress(steps_done, steps_total)``, called in
run-steps (one bag of N steps is N run-steps; ``steps_total`` None while unknown).

Pure: no rclpy, no matplotlib (figures are in `sep_control.bags.figures`, the Markdown report in
`sep_control.bags.report`).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from sep_control.bags.bag_metrics import episode_metrics, pooled_metrics
from sep_control.bags.reader import Episode, read_episode
from sep_control.bags.storage import BagError
from sep_plant.problem import Objective, ProblemError
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario
from sep_plant.truth import plant_differences


#: ``on_progress(steps_done, steps_total)`` in run-steps; steps_total None while unknown
ProgressHook = Callable[[int, int | None], None]


class AnalysisError(RuntimeError):
    """The bags cannot be analysed as asked (scenario mismatch, inconsistent bags)."""


@dataclass
class EpisodeReport:
    """Metrics and arrays of one recorded episode."""

    name: str
    episode: Episode
    scenario: Scenario | None          # scenario the metrics were computed with
    design: Any | None                 # sep_estimator.design.Design or None
    objective: Objective | None        # objective of the metrics (None: no scenario or no field)
    F_nom: np.ndarray | None           # (N+1, n_field) nominal field (from the design)
    metrics: dict[str, Any]
    err: np.ndarray                    # (N+1, n_field) F_hat - F (NaN where either is missing)
    latency_cmd_s: np.ndarray          # per step with both messages
    latency_est_s: np.ndarray
    mismatch: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def model_mismatch(self) -> list[str]:
        """How the episode's plant differed from the design's model (the module docstring), kept
        in ``metrics['model_mismatch']``."""
        return self.metrics["model_mismatch"]

    @property
    def inputs(self) -> np.ndarray:
        """Applied inputs (commands where the applied ones are missing)."""
        e = self.episode
        return np.where(np.isfinite(e.u), e.u, e.u_cmd)

    @property
    def info(self) -> PlantInfo | None:
        """The plant's description: the bag's, else the design's."""
        if self.episode.info is not None:
            return self.episode.info
        return self.design.info if self.design is not None else None

    @property
    def xyz(self) -> np.ndarray | None:
        """Node coordinates (n_field, 3): the clouds', else the design's when the widths agree."""
        if self.episode.xyz is not None:
            return self.episode.xyz
        d = self.design
        if d is not None and d.field_xyz.shape[0] == self.episode.n_field:
            return d.field_xyz
        return None


@dataclass
class AggregateReport:
    """Statistics over many episodes (one row per episode plus the pooled metrics)."""

    reports: list[EpisodeReport]
    scenario: Scenario | None
    design: Any | None
    objective: Objective | None
    metrics: dict[str, Any]
    rows: dict[str, dict[str, Any]]     # episode name -> its metrics
    notes: list[str] = field(default_factory=list)


def reports_of(rep: EpisodeReport | AggregateReport) -> list[EpisodeReport]:
    """The episode reports of an aggregate, or [rep] for one episode."""
    return rep.reports if isinstance(rep, AggregateReport) else [rep]


def _load_design(design):
    """A `Design` from a path (a `Design` or None passes through)."""
    if design is None or not isinstance(design, (str, Path)):
        return design
    from sep_estimator.design_file import load_design

    return load_design(design)


def scenario_differences(ep: Episode, design) -> list[str]:
    """Where the bag's plant (type, keys, horizon) differs from the design's ([] without a
    design or without a scenario in the bag)."""
    if design is None or ep.scenario is None or ep.scenario_source != "bag":
        return []
    return design.scenario.plant_mismatches(ep.scenario)


def reported_mismatch(ep: Episode) -> list[str]:
    """The model mismatch the controllers reported on /diagnostics (their ``model_mismatch``
    values, JSON lists; the union in order of appearance)."""
    out: list[str] = []
    for d in ep.diagnostics.values():
        try:
            items = json.loads(d.get("model_mismatch") or "[]")
        except json.JSONDecodeError:
            items = [d["model_mismatch"]]
        out += [str(i) for i in (items if isinstance(items, list) else [items]) if str(i) not in out]
    return out


def model_mismatch(ep: Episode, design, reported: list[str]) -> list[str]:
    """How the episode's plant differed from the design's model: the bag's scenario (and
    perturbation) against the design when both are there, else what the controllers reported."""
    if design is None or ep.scenario is None or ep.scenario_source != "bag" \
            or ep.scenario.plant_type != design.scenario.plant_type:
        return list(reported)
    return plant_differences(design.scenario, ep.scenario, ep.perturbation)


def _fits(obj: Objective, ep: Episode) -> bool:
    return obj.n_steps == ep.n_steps and obj.target.shape[-1] == ep.n_field


def scenario_objective(ep: Episode, notes: list[str]) -> Objective | None:
    """The objective of the bag's scenario on the clouds' node coordinates (None, noted, when
    the bag has no scenario or no clouds, or the target does not fit the field)."""
    if ep.scenario is None:
        notes.append("no scenario: cost, band and RMS metrics need the scenario (pass --design)")
        return None
    if ep.xyz is None:
        notes.append("no field clouds: the objective's target cannot be placed on the field's nodes")
        return None
    try:
        obj = Objective.of(ep.scenario.problem, ep.xyz, ep.dt)
    except ProblemError as exc:
        notes.append(f"the scenario's objective does not fit the recorded field: {exc}")
        return None
    return obj if _fits(obj, ep) else None


def objective_and_nominal(ep: Episode, design, diff: list[str], notes: list[str]
                          ) -> tuple[Scenario | None, Objective | None, np.ndarray | None]:
    """(scenario, objective, nominal field) the metrics use: the design's when it matches the
    bag, else the bag's own scenario (the design's nominal only where its shape fits)."""
    if design is not None and not diff:
        obj = design.objective if _fits(design.objective, ep) else None
        F_nom = design.nominal.field if design.nominal.field.shape == ep.F.shape else None
        return design.scenario, obj, F_nom
    obj = scenario_objective(ep, notes)
    F_nom = None
    if design is not None:
        notes.append("scenario mismatch: " + "; ".join(diff))
        if design.nominal.field.shape == ep.F.shape:
            F_nom = design.nominal.field
    return ep.scenario, obj, F_nom


def _episode_name(bag_path: Path, name: str | None) -> str:
    if name:
        return name
    return bag_path.stem if bag_path.is_file() else bag_path.name


# ~68 lines: 37 of them the public function's numpydoc docstring
def analyze(bag_path: str | Path, design=None, *, allow_mismatch: bool = False, allow_truncated: bool = False,
            namespace: str | None = None, name: str | None = None,
            on_progress: ProgressHook | None = None) -> EpisodeReport:
    """Metrics (docs/method.md) and arrays of one recorded episode.

    Parameters
    ----------
    bag_path : str or Path
        A rosbag2 directory (MCAP or sqlite3) or a lone ``.mcap`` / ``.db3`` file.
    design : Design, str, Path or None
        A `sep_estimator.design.Design` or the path of a design file
        (docs/reference/design-file.md): its objective and nominal f_nom, u_nom. None: the
        objective of the bag's scenario on the clouds' node coordinates, no nominal comparisons.
    allow_mismatch : bool, default False
        Analyse a bag of another plant than the design's (flagged in ``mismatch``) instead of
        raising.
    allow_truncated : bool, default False
        Analyse what was recovered from a truncated bag instead of raising.
    namespace : str, optional
        Namespace of the contract topics; None: the bag's own (``sep``, or sep 0.1's ``slab``).
    name : str, optional
        The episode's name in tables (default: the bag's directory or file stem).
    on_progress : callable, optional
        ``on_progress(steps_done, steps_total)`` in run-steps: (0, N or None) before reading,
        (N, N) after; default None (silent).

    Returns
    -------
    EpisodeReport
        ``metrics`` (keys of `sep_control.evaluation.metrics.JSON_KEYS` plus the bag's: latency
        percentiles, field_nees, field_rmse, controller, ...; None where the bag lacks what a
        metric needs), the episode's arrays, the estimation error F_hat - F and the latencies.

    Raises
    ------
    BagError
        The bag cannot be read (see `sep_control.bags.reader.read_episode`).
    AnalysisError
        The bag's plant differs from the design's and `allow_mismatch` is False.
    """
    design = _load_design(design)
    bag_path = Path(bag_path)
    if on_progress is not None:
        on_progress(0, design.n_steps if design is not None else None)
    ep = read_episode(bag_path, scenario=design.scenario if design is not None else None,
                      info=design.info if design is not None else None,
                      namespace=namespace, allow_truncated=allow_truncated)
    rep = analyze_episode(ep, design, allow_mismatch=allow_mismatch, name=_episode_name(bag_path, name))
    if on_progress is not None:
        on_progress(ep.n_steps, ep.n_steps)
    return rep


def analyze_episode(ep: Episode, design, *, allow_mismatch: bool = False, name: str = "") -> EpisodeReport:
    """`analyze` of an episode already read (a bag's, or one episode of a multi-episode bag:
    `sep_control.bags.episodes`); `design` loaded (or None)."""
    bag_path = ep.path
    reported = reported_mismatch(ep)
    diff = scenario_differences(ep, design)
    if reported and all(d.startswith("plant.") for d in diff):
        diff = []                  # a rehearsal: the design's goal applies on the other plant
    elif diff and not allow_mismatch:
        raise AnalysisError(f"{bag_path}: the bag was recorded with another scenario than the design file: "
                            + "; ".join(diff) + ". Use the design file of that plant, or --allow-mismatch "
                            "to analyse it anyway (nominal comparisons are then skipped where shapes differ)")
    notes = list(ep.notes)
    scen, obj, F_nom = objective_and_nominal(ep, design, diff, notes)
    m, mnotes, (lat_cmd, lat_est) = episode_metrics(ep, obj, F_nom)
    if diff:
        m["scenario_mismatch"] = diff
    m["model_mismatch"] = model_mismatch(ep, design, reported)
    if ep.missing:
        notes.append("missing topics: " + ", ".join(ep.missing))
    return EpisodeReport(name=name or _episode_name(bag_path, None), episode=ep, scenario=scen, design=design,
                         objective=obj, F_nom=F_nom, metrics=m, err=ep.F_hat - ep.F, latency_cmd_s=lat_cmd,
                         latency_est_s=lat_est, mismatch=diff, notes=notes + mnotes)


def _unique_rows(reports: Sequence[EpisodeReport]) -> dict[str, dict[str, Any]]:
    """Episode name -> metrics; repeated names get '#1', '#2', ..."""
    seen: dict[str, int] = {}
    rows: dict[str, dict[str, Any]] = {}
    for r in reports:
        n = r.name
        if n in seen:
            seen[n] += 1
            n = f"{n}#{seen[n]}"
        else:
            seen[n] = 0
        rows[n] = r.metrics
    return rows


def _check_same_scenario(reports: Sequence[EpisodeReport]) -> None:
    """Refuse to pool bags of different plants or horizons."""
    first = reports[0]
    s = first.scenario
    for r in reports[1:]:
        if (r.scenario is None) != (s is None):
            diff = ["scenario missing"]
        else:
            diff = s.plant_mismatches(r.scenario) if s is not None else []
        if diff:
            raise AnalysisError(f"{r.episode.path}: recorded with another scenario than {first.episode.path} "
                                f"({'; '.join(diff)}); aggregate bags of one scenario")


def _analyze_all(items: Sequence[str | Path | EpisodeReport], design, on_progress: ProgressHook | None,
                 **kw) -> list[EpisodeReport]:
    """`analyze` every bag (reports pass through), reporting run-steps: the total is the number
    of bags times N (the design's, else the first bag's; pooled bags share one scenario)."""
    n_steps = design.n_steps if design is not None else None
    total = len(items) * n_steps if n_steps is not None else None
    done = 0
    if on_progress is not None:
        on_progress(done, total)
    reports = []
    for p in items:
        r = p if isinstance(p, EpisodeReport) else analyze(p, design, **kw)
        reports.append(r)
        done += r.episode.n_steps
        if on_progress is not None:
            total = max(total if total is not None else len(items) * r.episode.n_steps, done)
            on_progress(done, total)
    return reports


def aggregate(paths: Iterable[str | Path] | Sequence[EpisodeReport], design=None, *, allow_mismatch: bool = False,
              allow_truncated: bool = False, namespace: str | None = None,
              on_progress: ProgressHook | None = None) -> AggregateReport:
    """Pooled statistics of many episodes, comparable to the offline Monte Carlo table.

    Cost mean/std, in-band fraction, mean RMS and mean-trajectory deviations over the runs
    (`sep_control.evaluation.metrics.summarize`, over the episodes that have the field and
    inputs at every step), 2-sigma coverage over all node-steps, latency percentiles over all
    steps, deadline misses and rejected messages summed over the episodes.

    Parameters
    ----------
    paths : iterable of str, Path or EpisodeReport
        The bags (as for `analyze`), or reports already made by `analyze`.
    design : Design, str, Path or None
        As for `analyze`; loaded once.
    allow_mismatch, allow_truncated : bool, default False
        As for `analyze`.
    namespace : str, optional
        As for `analyze`.
    on_progress : callable, optional
        ``on_progress(steps_done, steps_total)`` in run-steps, after each bag (and once with 0
        before the first); steps_total is the number of bags times N, None until N is known;
        default None (silent).

    Returns
    -------
    AggregateReport
        ``metrics`` (pooled), ``rows`` (episode name -> its metrics; repeated names get '#1',
        '#2', ...) and the per-episode ``reports``.

    Raises
    ------
    BagError
        A bag cannot be read.
    AnalysisError
        No bags, bags of different scenarios, or a scenario mismatch with the design.
    """
    design = _load_design(design)
    reports = _analyze_all(list(paths), design, on_progress, allow_mismatch=allow_mismatch,
                           allow_truncated=allow_truncated, namespace=namespace)
    if not reports:
        raise AnalysisError("no bags to aggregate")
    _check_same_scenario(reports)
    first = reports[0]
    notes: list[str] = []
    out = pooled_metrics(reports, first.objective, first.F_nom, notes)
    return AggregateReport(reports=reports, scenario=first.scenario, design=design, objective=first.objective,
                           metrics=out, rows=_unique_rows(reports), notes=notes)


__all__ = ["AnalysisError", "BagError", "EpisodeReport", "AggregateReport", "ProgressHook", "analyze", "analyze_episode",
           "aggregate", "model_mismatch", "reported_mismatch", "reports_of"]
