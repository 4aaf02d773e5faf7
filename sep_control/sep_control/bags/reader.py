"""A recorded episode as numpy arrays (pure: no rclpy): `read_episode` and `Episode`.

`read_episode` turns the contract topics (`sep_plant.topics`, docs/reference/topics.md) of any
plant into an `Episode`: per-step arrays indexed by the step k of header.stamp
(`topics.steps_of_stamps`, one tolerance for the whole product), per-topic receive times (the
bag's log time, i.e. the recorder's clock) and header stamps, the last diagnostics values, and
the plant's scenario and description (`PlantInfo`) from the scenario topic. Point clouds are
accepted with any field name (x, y, z, <field>, <field>_std); the optional 32FC1 image topics
of grid plants are read when present. Missing required topics are listed in
``Episode.missing``; topics outside the contract are ignored. Bags of sep 0.1 (namespace
``slab``, topics ``heat_command`` / ``heat_applied``, flat slab scenario JSON) are read too,
through `sep_plant.topics.LEGACY_TOPICS`. A corrupt bag raises `BagError` naming the file and
what could be recovered; a truncated one does too unless ``allow_truncated=True``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sep_control.bags.messages import (IMAGE_TOPICS, NO_MESSAGES, VECTOR_TOPICS, Messages, PerStep, cloud_points,
                                       image_pixels, index_messages, joint_values, open_bag, read_diagnostics,
                                       read_per_step, read_scenario)
from sep_control.bags.storage import BagError
from sep_plant import topics as T
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario, ScenarioError


@dataclass
class TopicTimes:
    """Per-message receive times (bag log time, ns, recorder clock) and header stamps (ns)."""

    recv_ns: np.ndarray
    stamp_ns: np.ndarray


@dataclass
class Episode:
    """One recorded episode as arrays; step k rows are NaN where the bag has no message.
    Topic keys are the contract names of `sep_plant.topics` ('measurements', '/clock', ...)."""

    path: Path
    scenario: Scenario | None
    info: PlantInfo | None    # the plant's description (None: no scenario in the bag or given)
    dt: float
    n_steps: int
    y: np.ndarray             # (N+1, n_y)      measurements
    u_cmd: np.ndarray         # (N, n_u)        command
    u: np.ndarray             # (N, n_u)        applied_input
    a_hat: np.ndarray         # (N+1, n_a)      state_estimate (NaN padded; n_a = longest estimate)
    a_dim: np.ndarray         # (N+1,) int      length of the estimate at step k (-1: none)
    F: np.ndarray             # (N+1, n_field)  true field (field cloud)
    F_hat: np.ndarray         # (N+1, n_field)  field estimate
    F_std: np.ndarray         # (N+1, n_field)  field estimate std
    xyz: np.ndarray | None    # (n_field, 3)    node coordinates from the point clouds
    field_name: str | None    # the clouds' field channel, e.g. 'temperature'
    images: dict[str, dict[int, np.ndarray]]  # image topic key -> step -> (height, width) float32
    step_recv_ns: dict[str, np.ndarray]   # per-step topic key -> (N+1,) receive time per step, ns since
                                          # recv_origin_ns (float, exact; NaN: no message)
    times: dict[str, TopicTimes]          # topic key -> all messages' receive times and stamps
    diagnostics: dict[str, dict[str, str]]  # status name -> last key/values
    diag_totals: dict[str, int]           # deadline_misses, rejected_messages summed over statuses
    counts: dict[str, int]                # messages per contract topic key
    missing: list[str]                    # required contract topics with no message (full names)
    ignored_topics: list[str]             # topics outside the contract (or of another type)
    recv_origin_ns: int = 0               # earliest log time in the bag (recorder clock)
    complete: bool = True                 # False: truncated bag (only with allow_truncated)
    notes: list[str] = field(default_factory=list)
    scenario_source: str = "bag"          # 'bag', 'argument' or 'inferred'
    perturbation: dict[str, list[float]] = field(default_factory=dict)  # the plant's actuator/sensor
                                          # perturbation from its scenario message ({}: none)
    estimate_names: list[str] = field(default_factory=list)   # names of the longest state_estimate

    @property
    def n_field(self) -> int:
        return int(self.F.shape[1])

    @property
    def d_hat(self) -> np.ndarray:
        """(N+1, n_d) the disturbance estimates d_hat_k (NaN where a step has none): the
        state_estimate entries named d_0, d_1, ..., which `sep_plant.topics.state_labels` puts
        last, so they are the last n_d entries of every estimate whatever its length; (N+1, 0)
        without disturbance states."""
        n_d = sum(name.startswith(T.DISTURBANCE_PREFIX) for name in self.estimate_names)
        out = np.full((self.a_hat.shape[0], n_d), np.nan)
        rows = np.flatnonzero(self.a_dim >= n_d) if n_d else np.zeros(0, dtype=int)
        if rows.size:
            cols = self.a_dim[rows, None] - n_d + np.arange(n_d)
            out[rows] = self.a_hat[rows[:, None], cols]
        return out

    def steps_with(self, key: str) -> np.ndarray:
        """Steps k that have a message on topic `key`."""
        return np.flatnonzero(np.isfinite(self.step_recv_ns[key]))


# ------------------------------------------------------------------------- the step grid
def infer_timing(msgs: Messages, name: str) -> tuple[float, int]:
    """dt and N of a bag without a scenario, from the stamps of measurements and field clouds:
    dt = the smallest positive stamp difference, N = the last stamp / dt."""
    st = np.unique(np.concatenate([msgs.stamps.get(k, NO_MESSAGES) for k in (T.MEASUREMENTS, T.FIELD)]))
    diffs = np.diff(st)
    diffs = diffs[diffs > 0]
    if not diffs.size:
        raise BagError(f"{name}: no scenario and too few stamped measurements to infer the time step; "
                       "pass the design file (--design)")
    return float(diffs.min()) * 1e-9, int(round(st[-1] / diffs.min()))


def resolve_timing(msgs: Messages, found: tuple[Scenario, PlantInfo] | None, scenario: Scenario | None,
                   info: PlantInfo | None, name: str, notes: list[str]
                   ) -> tuple[Scenario | None, PlantInfo | None, str]:
    """(scenario, plant description, source) of the episode, and its step grid set on `msgs`:
    `found`, the bag's scenario topic ('bag'), else the given scenario ('argument'; `info`
    defaults to `scenario.info`, which builds the plant), else dt and N inferred from stamps
    ('inferred')."""
    source = "bag"
    if found is None and scenario is not None:
        if info is None:
            try:
                info = scenario.info
            except ScenarioError as exc:
                raise BagError(f"{name}: no scenario in the bag and the one given cannot describe the plant "
                               f"({exc})") from None
        found, source = (scenario, info), "argument"
    if found is not None:
        scen, info = found
        dt, n_steps = info.dt, scen.problem.n_steps
    else:
        scen, info, source = None, None, "inferred"
        dt, n_steps = infer_timing(msgs, name)
        notes.append(f"no scenario in the bag: dt = {dt:g} s and N = {n_steps} inferred from stamps")
    msgs.dt, msgs.step_ns, msgs.n_steps = dt, T.dt_ns(dt), n_steps
    return scen, info, source


# ------------------------------------------------------------------------------ arrays
def stack_rows(values: dict[int, np.ndarray], rows: int, width: int) -> np.ndarray:
    """(rows, width) array of per-step vectors (NaN where a step has none, or past a vector's end)."""
    out = np.full((rows, width), np.nan)
    for k, v in values.items():
        out[k, :len(v)] = v
    return out


def field_arrays(clouds: dict[int, tuple[str, np.ndarray]], rows: int, n_field: int, notes: list[str]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, str | None]:
    """(values, std, xyz, field name) of the per-step clouds of one field topic; clouds of
    another width than `n_field` are skipped (noted)."""
    vals = np.full((rows, n_field), np.nan)
    std = np.full((rows, n_field), np.nan)
    xyz, name = None, None
    skipped = 0
    for k, (fname, pts) in clouds.items():
        if pts.shape[0] != n_field:
            skipped += 1
            continue
        vals[k], std[k] = pts[:, 3], pts[:, 4]
        if xyz is None:
            xyz, name = pts[:, :3].copy(), fname
    if skipped:
        notes.append(f"{skipped} point clouds with another number of points than {n_field} skipped")
    return vals, std, xyz, name


def _longest(*found: dict[int, np.ndarray]) -> int:
    """Length of the longest recorded vector (a dimension when the plant is not described)."""
    return max((len(v) for vals in found for v in vals.values()), default=0)


class _EstimateNames:
    """A state_estimate parser that keeps the names of the longest estimate seen."""

    def __init__(self):
        self.names: list[str] = []

    def __call__(self, msg) -> np.ndarray:
        v = joint_values(msg, "position", None)
        if v.size >= len(self.names):
            self.names = [str(n) for n in msg.name]
        return v


def read_vectors(msgs: Messages, info: PlantInfo | None) -> tuple[dict[str, PerStep], dict[str, Any]]:
    """The JointState topics per step, and the Episode arrays y, u_cmd, u, a_hat, a_dim (state
    estimates vary in length: the ROM order grows) and the estimate's names."""
    n_y, n_u = (None, None) if info is None else (info.n_y, info.n_u)
    dims = {T.MEASUREMENTS: n_y, T.COMMAND: n_u, T.APPLIED_INPUT: n_u, T.STATE_ESTIMATE: None}
    names = _EstimateNames()
    vec = {key: read_per_step(msgs, key, names if key == T.STATE_ESTIMATE else
                              functools.partial(joint_values, attr=attr, n=dims[key]))
           for key, attr in VECTOR_TOPICS.items()}
    n_y = n_y if n_y is not None else _longest(vec[T.MEASUREMENTS].values)
    n_u = n_u if n_u is not None else _longest(vec[T.COMMAND].values, vec[T.APPLIED_INPUT].values)
    N = msgs.n_steps
    est = vec[T.STATE_ESTIMATE].values
    a_dim = np.full(N + 1, -1, dtype=np.int64)
    for k, v in est.items():
        a_dim[k] = len(v)
    return vec, {"y": stack_rows(vec[T.MEASUREMENTS].values, N + 1, n_y),
                 "u_cmd": stack_rows(vec[T.COMMAND].values, N, n_u),
                 "u": stack_rows(vec[T.APPLIED_INPUT].values, N, n_u),
                 "a_hat": stack_rows(est, N + 1, max(int(a_dim.max()), 0)), "a_dim": a_dim,
                 "estimate_names": names.names}


def read_fields(msgs: Messages, info: PlantInfo | None, notes: list[str]
                ) -> tuple[dict[str, PerStep], dict[str, Any]]:
    """The field clouds per step, and the Episode arrays F, F_hat, F_std, xyz, field_name. Every
    cloud has the plant's width (without a description: the first cloud's)."""
    n_field = info.n_field if info is not None else None
    clouds = {key: read_per_step(msgs, key, functools.partial(cloud_points, n=n_field))
              for key in (T.FIELD, T.FIELD_ESTIMATE)}
    if n_field is None:
        n_field = next((pts.shape[0] for c in clouds.values() for _, pts in c.values.values()), 0)
    rows = msgs.n_steps + 1
    F, _, xyz_f, name_f = field_arrays(clouds[T.FIELD].values, rows, n_field, notes)
    F_hat, F_std, xyz_e, name_e = field_arrays(clouds[T.FIELD_ESTIMATE].values, rows, n_field, notes)
    field_name = name_f or name_e
    if info is not None and field_name is not None and field_name != info.field_name:
        notes.append(f"the point clouds carry {field_name!r}, the plant's field is {info.field_name!r}")
    return clouds, {"F": F, "F_hat": F_hat, "F_std": F_std, "xyz": xyz_f if xyz_f is not None else xyz_e,
                    "field_name": field_name}


def read_images(msgs: Messages) -> dict[str, PerStep]:
    """The optional 32FC1 image topics that the bag has, per step."""
    return {key: read_per_step(msgs, key, image_pixels) for key in IMAGE_TOPICS if key in msgs.index}


# ~64 lines: 32 of them the public function's numpydoc docstring
def read_episode(path: str | Path, scenario: Scenario | None = None, info: PlantInfo | None = None, *,
                 namespace: str | None = None, allow_truncated: bool = False) -> Episode:
    """Read a bag of one episode into arrays indexed by step k.

    The bag's own scenario (and plant description) wins; `scenario` and `info` (e.g. a
    design's) are used when the bag carries none; without either, dt and N are inferred from
    the stamps. Scenarios are compared in `sep_control.bags.analysis.analyze`.

    Parameters
    ----------
    path : str or Path
        A rosbag2 directory (MCAP or sqlite3), or a lone ``.mcap`` / ``.db3`` file.
    scenario : Scenario, optional
        Used when the bag has no scenario topic (``Episode.scenario_source == 'argument'``).
    info : PlantInfo, optional
        The plant's description with `scenario`; default ``scenario.info`` (builds the plant).
    namespace : str, optional
        Namespace of the contract topics; None: the bag's own
        (`sep_plant.topics.detect_namespace`: ``sep``, or sep 0.1's ``slab``, whose topic names
        are read through `sep_plant.topics.LEGACY_TOPICS`).
    allow_truncated : bool, default False
        Read what was recovered from a bag cut off by a crash instead of raising.

    Returns
    -------
    Episode
        Per-step arrays (NaN where a step has no message), receive times, diagnostics, the
        missing and ignored topics, and reader notes.

    Raises
    ------
    BagError
        Not a bag, corrupt, empty, truncated (unless `allow_truncated`), or no step grid.
    """
    raw, name = open_bag(path, allow_truncated)
    return episode_of_raw(raw, name, Path(path), scenario, info, namespace)


def episode_of_raw(raw, name: str, path: Path, scenario: Scenario | None = None, info: PlantInfo | None = None,
                   namespace: str | None = None) -> Episode:
    """`read_episode` of an opened raw bag (or one episode's part of it: `sep_control.bags.episodes`)."""
    if namespace is None:
        namespace = T.detect_namespace({c.topic for c in raw.connections.values()}) or T.NAMESPACE
    notes = list(raw.notes)
    msgs, ignored = index_messages(raw, namespace)
    in_bag = read_scenario(msgs, notes)
    scen, info, source = resolve_timing(msgs, in_bag[:2] if in_bag else None, scenario, info, name, notes)
    vec, vectors = read_vectors(msgs, info)
    clouds, fields = read_fields(msgs, info, notes)
    images = read_images(msgs)
    per_step = {**vec, **clouds, **images}
    off_grid = sum(p.off_grid for p in per_step.values())
    if off_grid:
        notes.append(f"{off_grid} messages with stamps off the step grid or outside k = 0..N ignored")
    diags, totals = read_diagnostics(msgs, notes)
    if msgs.decode.bad:
        notes.append(f"{len(msgs.decode.bad)} undecodable or malformed messages skipped "
                     f"(first: {msgs.decode.bad[0]})")
    counts = {t.name: int(msgs.of(t.name).size) for t in T.TOPICS}
    return Episode(
        path=path, scenario=scen, info=info, dt=msgs.dt, n_steps=msgs.n_steps, **vectors, **fields,
        images={key: p.values for key, p in images.items()},
        step_recv_ns={key: p.recv_ns for key, p in per_step.items()},
        times={key: TopicTimes(raw.log_times[idx], msgs.stamps.get(key, NO_MESSAGES))
               for key, idx in msgs.index.items() if key != T.SCENARIO},
        diagnostics=diags, diag_totals=totals, counts=counts,
        missing=[T.topic_name(t.name, namespace) for t in T.TOPICS
                 if not counts[t.name] and t.name not in T.OPTIONAL],
        ignored_topics=ignored, recv_origin_ns=msgs.origin, complete=raw.complete, notes=notes,
        scenario_source=source, perturbation=in_bag[2] if in_bag else {})
