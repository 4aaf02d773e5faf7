"""Synthetic bags of the sep topic contract (`sep_plant.topics`), for the bag/analysis tests.

* `synthetic_episode` rolls out a small slab scenario on the real plant with known inputs and
  noise; `legacy_episode` is the same episode as sep 0.1 published it (flat slab scenario JSON);
* `grid_episode` is a made-up 2-D (or 3-D) grid plant (no simulator: a smooth field approaching
  its target) whose field is called ``phi`` and which also publishes the 32FC1 image topics.

`write_bag` serializes an episode with the Jazzy typestore exactly in the contract layout and
writes a rosbag2 bag with rosbags' Writer. Receive (log) times are synthetic and known, so
latencies are known exactly.

Topic names: the contract's (namespace ``sep``, ``command``, ``applied_input``, frame id ``sep``)
by default; ``naming="sep01"`` writes the same messages under sep 0.1's names (namespace
``slab``, ``heat_command``, ``heat_applied``, frame id ``slab``), as the real bag
tests/data/bag_sep01 has them.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from sep_plant import topics as T
from sep_plant.problem import Objective, Problem
from sep_plant.protocol import GridGeometry, PlantInfo, fields, outputs, rollout
from sep_plant.scenario import Scenario, scenario_payload

TS = get_typestore(Stores.ROS2_JAZZY)
T0_NS = 1_700_000_000_000_000_000    # recorder clock origin of the synthetic receive times
LAT_CMD_NS = 700_000                 # measurement k -> command k (0.7 ms)
LAT_EST_NS = 300_000                 # measurement k -> state_estimate k / field_estimate k

SMALL_PLANT = {"n_x": 20}
SMALL_PROBLEM = {"n_steps": 40, "band_window": (24, 40), "lqr_k_switch": 19}
#: full topic name -> ROS type of every contract topic (namespace sep)
TYPES = {name: spec.type_name for name, spec in T.contract_topics().items()}

#: sep 0.1's naming, spelled out here (not taken from `topics.LEGACY_TOPICS`) so that the tests
#: check the reader's table against what sep 0.1 wrote (tests/data/bag_sep01: these names)
SEP01_NAMESPACE = "slab"
SEP01_TOPICS = {T.COMMAND: "heat_command", T.APPLIED_INPUT: "heat_applied"}
SEP01_FRAME_ID = "slab"
NAMINGS = ("current", "sep01")


def topic_namer(naming: str = "current") -> Callable[[str], str]:
    """contract key -> full topic name in the given naming ('current' or 'sep01')."""
    if naming == "current":
        return T.topic_name
    if naming != "sep01":
        raise ValueError(f"naming must be one of {NAMINGS}, got {naming!r}")
    return lambda key: T.topic_name(SEP01_TOPICS.get(key, key), SEP01_NAMESPACE)


def frame_id_of(naming: str = "current") -> str:
    return SEP01_FRAME_ID if naming == "sep01" else T.FRAME_ID


#: full topic name -> ROS type in either naming
ALL_TYPES = {**TYPES, **{topic_namer("sep01")(spec.name): spec.type_name for spec in T.TOPICS}}


def small_scenario(**kw) -> Scenario:
    """The slab on 20 nodes over 40 steps (canonical). Keys of `Problem` change the problem, any
    other key the plant; a new n_steps without band_window uses the default window and switch."""
    plant, problem = dict(SMALL_PLANT), dict(SMALL_PROBLEM)
    if "n_steps" in kw and "band_window" not in kw:
        problem.pop("band_window")
        problem.pop("lqr_k_switch")
    for k, v in kw.items():
        (problem if k in Problem.__dataclass_fields__ else plant)[k] = v
    return Scenario("slab", plant, Problem(**problem)).canonical()


@dataclass
class SynthEpisode:
    scenario: Scenario
    info: PlantInfo
    xyz: np.ndarray        # (n_field, 3)
    F: np.ndarray          # (N+1, n_field) true field
    u_cmd: np.ndarray      # (N, n_u)
    u: np.ndarray          # (N, n_u)  applied (here == commanded)
    y: np.ndarray          # (N+1, n_y)
    F_hat: np.ndarray      # (N+1, n_field)
    F_std: np.ndarray      # (N+1, n_field)
    a_hat: list            # N+1 arrays of growing length
    F_nom: np.ndarray      # (N+1, n_field)
    u_nom: np.ndarray      # (N, n_u)
    y_nom: np.ndarray      # (N+1, n_y)
    payload: str = ""      # the scenario topic's JSON ("" : scenario_payload(scenario, info))
    images: bool = False   # publish field_image / field_estimate_image
    diag: dict = field(default_factory=lambda: {"deadline_misses": 3, "rejected_messages": 2})

    def __post_init__(self) -> None:
        if not self.payload:
            self.payload = scenario_payload(self.scenario, self.info)

    @property
    def objective(self) -> Objective:
        return Objective.of(self.scenario.problem, self.xyz)


def _estimates(rng, F: np.ndarray, n_u: int, std_lo: float, std_span: float, sensed=()):
    """Field estimates f + std * noise with a random std (a fifth of it at `sensed` nodes), and
    ROM estimates of growing length."""
    N = F.shape[0] - 1
    F_std = std_lo + std_span * rng.random(F.shape)
    F_std[:, list(sensed)] *= 0.2
    F_hat = F + F_std * rng.standard_normal(F.shape)
    a_hat = [rng.standard_normal(min(k * n_u, 8)) for k in range(N + 1)]
    return F_hat, F_std, a_hat


def synthetic_episode(s: Scenario | None = None, seed: int = 0) -> SynthEpisode:
    """One noisy slab episode around a constant nominal input, on the real plant."""
    s = s or small_scenario()
    rng = np.random.default_rng(seed)
    plant, info, p = s.plant, s.info, s.problem
    N = p.n_steps
    u_nom = np.full((N, info.n_u), 2.0)
    x0 = plant.initial_state(1)
    X_nom = rollout(plant, x0, u_nom)[0]
    u_cmd = u_nom + 0.2 * rng.standard_normal((N, info.n_u))
    w = p.channels("w_std", info.n_u) * rng.standard_normal((N, info.n_u))
    X = rollout(plant, x0, u_cmd, w[None])[0]
    F = fields(plant, X)
    y = outputs(plant, X) + p.channels("v_std", info.n_y) * rng.standard_normal((N + 1, info.n_y))
    F_hat, F_std, a_hat = _estimates(rng, F, info.n_u, 0.5, 0.1)
    return SynthEpisode(s, info, np.asarray(plant.field_coordinates(), dtype=float), F, u_cmd, u_cmd.copy(), y,
                        F_hat, F_std, a_hat, fields(plant, X_nom), u_nom, outputs(plant, X_nom))


def legacy_scenario_json(s: Scenario) -> str:
    """The flat slab scenario JSON that sep 0.1 published (band window [k_band, N])."""
    p = s.problem
    k_band, k_end = p.window
    assert s.plant_type == "slab" and k_end == p.n_steps, "sep 0.1 knew only the slab, band up to N"

    def enc(v):
        if isinstance(v, float) and math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return list(v) if isinstance(v, tuple) else v

    flat = {**dict(s.plant_config), "n_steps": p.n_steps, "t_target": p.target, "band": p.band, "k_band": k_band,
            "q_late": p.q_window, "q_early": p.q_outside, "r_u": p.r_u, "w_std": p.w_std, "v_std": p.v_std,
            "u_min": p.u_min, "u_max": p.u_max, "lqr_k_switch": p.k_switch, "lqr_q_late": p.lqr_q_late,
            "lqr_q_early": p.lqr_q_early, "lqr_r": p.lqr_r, "u_init": p.u_init}
    return json.dumps({k: enc(v) for k, v in flat.items()}, sort_keys=True)


def legacy_episode(s: Scenario | None = None, seed: int = 0) -> SynthEpisode:
    """A slab episode as a sep 0.1 plant published it: the flat scenario JSON alone."""
    ep = synthetic_episode(s, seed)
    return dataclasses.replace(ep, payload=legacy_scenario_json(ep.scenario))


def grid_scenario(shape: tuple[int, ...] = (6, 5), n_steps: int = 30) -> tuple[Scenario, PlantInfo, np.ndarray]:
    """A made-up grid plant (type ``synthetic_grid``: never built) with 3 inputs, 4 probes and a
    field ``phi`` on a regular grid; its target depends on x. Returns (scenario, info, xyz)."""
    n = int(np.prod(shape))
    info = PlantInfo(dt=0.1, n_x=n, n_u=3, n_y=4, n_field=n, input_names=("jet_a", "jet_b", "jet_c"),
                     output_names=tuple(f"probe_{i}" for i in range(4)), field_name="phi", field_unit="mol",
                     grid_shape=tuple(shape), field_is_state=True)
    axes = [np.linspace(0.0, 0.5, shape[0]), np.linspace(0.0, 0.4, shape[1])]
    if len(shape) == 3:
        axes.append(np.linspace(0.0, 0.2, shape[2]))
    xyz = GridGeometry(tuple(axes)).coordinates()
    k0 = int(round(0.6 * n_steps))
    problem = Problem(n_steps=n_steps, target="1 + 2 * x", band=0.3, band_window=(k0, n_steps),
                      lqr_k_switch=k0 - 4, w_std=0.1, v_std=0.05)
    scen = Scenario("synthetic_grid", {"shape": list(shape), "dt": info.dt}, problem)
    return scen, info, xyz


def grid_episode(shape: tuple[int, ...] = (6, 5), seed: int = 0, n_steps: int = 30) -> SynthEpisode:
    """A 2-D (3-D) grid-plant episode: the nominal field rises from 0 to the target, the
    closed-loop field wanders around it; with the image topics."""
    scen, info, xyz = grid_scenario(shape, n_steps)
    rng = np.random.default_rng(seed)
    N = n_steps
    target = scen.problem.target_field(xyz)
    rise = 1.0 - np.exp(-np.arange(N + 1) / (0.15 * N))
    F_nom = rise[:, None] * target[None, :]
    F = F_nom + 0.05 * np.cumsum(rng.standard_normal((N + 1, info.n_field)), axis=0) / np.sqrt(N)
    F[0] = F_nom[0]
    u_nom = np.ones((N, info.n_u))
    u_cmd = u_nom + 0.1 * rng.standard_normal((N, info.n_u))
    probes = np.linspace(0, info.n_field - 1, info.n_y).round().astype(int)
    y = F[:, probes] + 0.05 * rng.standard_normal((N + 1, info.n_y))
    F_hat, F_std, a_hat = _estimates(rng, F, info.n_u, 0.02, 0.01, sensed=probes)
    return SynthEpisode(scen, info, xyz, F, u_cmd, u_cmd.copy(), y, F_hat, F_std, a_hat, F_nom, u_nom,
                        F_nom[:, probes], images=True)


# ------------------------------------------------------------------------- messages
def _stamp(ns: int):
    return TS.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(ns: int, frame_id: str = T.FRAME_ID):
    return TS.types["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id=frame_id)


def joint_state(ns: int, names, position=(), effort=(), frame_id: str = T.FRAME_ID) -> bytes:
    JS = TS.types[T.JOINT_STATE]
    msg = JS(header=_header(ns, frame_id), name=list(names), position=np.asarray(position, float),
             velocity=np.zeros(0), effort=np.asarray(effort, float))
    return TS.serialize_cdr(msg, T.JOINT_STATE)


def cloud(ns: int, field_name: str, xyz: np.ndarray, values: np.ndarray, std: np.ndarray,
          frame_id: str = T.FRAME_ID) -> bytes:
    PC = TS.types[T.POINT_CLOUD2]
    PF = TS.types["sensor_msgs/msg/PointField"]
    pf = [PF(name=n, offset=8 * i, datatype=T.FLOAT64, count=1) for i, n in enumerate(T.cloud_fields(field_name))]
    n = xyz.shape[0]
    data = np.frombuffer(T.cloud_payload(xyz, values, std), dtype=np.uint8)
    msg = PC(header=_header(ns, frame_id), height=1, width=n, fields=pf, is_bigendian=False, point_step=T.POINT_STEP,
             row_step=T.POINT_STEP * n, data=data, is_dense=True)
    return TS.serialize_cdr(msg, T.POINT_CLOUD2)


def image(ns: int, values: np.ndarray, grid_shape: tuple[int, ...], frame_id: str = T.FRAME_ID) -> bytes:
    """A 32FC1 sensor_msgs/Image of a grid field (as `sep_plant.ros.contract.field_image`)."""
    img = T.image_of_field(values, grid_shape)
    h, w = img.shape
    msg = TS.types[T.IMAGE](header=_header(ns, frame_id), height=h, width=w, encoding="32FC1", is_bigendian=0,
                            step=4 * w, data=np.frombuffer(img.astype("<f4").tobytes(), dtype=np.uint8))
    return TS.serialize_cdr(msg, T.IMAGE)


def clock(ns: int) -> bytes:
    return TS.serialize_cdr(TS.types[T.CLOCK_TYPE](clock=_stamp(ns)), T.CLOCK_TYPE)


def diagnostics(ns: int, values: dict, step: int, name="plant", frame_id: str = T.FRAME_ID) -> bytes:
    D = TS.types
    st = D["diagnostic_msgs/msg/DiagnosticStatus"](
        level=0, name=name, message="ok", hardware_id="slab",
        values=[D["diagnostic_msgs/msg/KeyValue"](key=kk, value=str(v)) for kk, v in {**values, "step": step}.items()])
    arr = D[T.DIAGNOSTIC_ARRAY](header=_header(ns, frame_id), status=[st])
    return TS.serialize_cdr(arr, T.DIAGNOSTIC_ARRAY)


def string(text: str) -> bytes:
    return TS.serialize_cdr(TS.types[T.STRING](data=text), T.STRING)


def _qos(transient=False):
    z = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if transient else QosDurability.VOLATILE,
               z, z, QosLiveliness.AUTOMATIC, z, False)


def episode_messages(ep: SynthEpisode, skip=(), extra_topics=False,
                     stamp_shift_ns: Mapping[tuple[str, int], int] | None = None, naming: str = "current"):
    """[(topic, log_time_ns, cdr bytes)] of one episode in receive order. `stamp_shift_ns`:
    {(contract key, k): ns} moves the header stamp of that message off k dt. `naming`:
    'current' or 'sep01' (topic names and frame id; `skip` takes names of that naming)."""
    info = ep.info
    N = ep.scenario.problem.n_steps
    step = T.dt_ns(info.dt)
    shift = dict(stamp_shift_ns or {})
    name = topic_namer(naming)
    fid = frame_id_of(naming)

    def st(key, k):
        return k * step + shift.get((key, k), 0)

    out = [(name(T.SCENARIO), T0_NS - 1_000_000, string(ep.payload))]
    for k in range(N + 1):
        t = T0_NS + k * step
        out.append((T.CLOCK, t - 10_000, clock(st(T.CLOCK, k))))
        out.append((name(T.FIELD), t - 5_000, cloud(st(T.FIELD, k), info.field_name, ep.xyz, ep.F[k],
                                                     np.zeros(info.n_field), fid)))
        if ep.images:
            out.append((name(T.FIELD_IMAGE), t - 4_000, image(st(T.FIELD_IMAGE, k), ep.F[k], info.grid_shape, fid)))
        out.append((name(T.MEASUREMENTS), t, joint_state(st(T.MEASUREMENTS, k), info.output_names, position=ep.y[k],
                                                         frame_id=fid)))
        out.append((name(T.STATE_ESTIMATE), t + LAT_EST_NS,
                    joint_state(st(T.STATE_ESTIMATE, k), [f"a_{i}" for i in range(len(ep.a_hat[k]))],
                                position=ep.a_hat[k], frame_id=fid)))
        out.append((name(T.FIELD_ESTIMATE), t + LAT_EST_NS + 1000,
                    cloud(st(T.FIELD_ESTIMATE, k), info.field_name, ep.xyz, ep.F_hat[k], ep.F_std[k], fid)))
        if ep.images:
            out.append((name(T.FIELD_ESTIMATE_IMAGE), t + LAT_EST_NS + 2000,
                        image(st(T.FIELD_ESTIMATE_IMAGE, k), ep.F_hat[k], info.grid_shape, fid)))
        if k < N:
            out.append((name(T.COMMAND), t + LAT_CMD_NS,
                        joint_state(st(T.COMMAND, k), info.input_names, effort=ep.u_cmd[k], frame_id=fid)))
            out.append((name(T.APPLIED_INPUT), t + LAT_CMD_NS + 50_000,
                        joint_state(st(T.APPLIED_INPUT, k), info.input_names, effort=ep.u[k], frame_id=fid)))
        if k % 10 == 0 or k == N:
            frac = k / N
            out.append((T.DIAGNOSTICS, t + 900_000,
                        diagnostics(st(T.DIAGNOSTICS, k), {kk: int(round(v * frac)) for kk, v in ep.diag.items()}, k,
                                    frame_id=fid)))
        if extra_topics:
            out.append(("/rosout_like/extra", t + 1, string(f"noise {k}")))
            out.append((T.topic_name("unknown", SEP01_NAMESPACE if naming == "sep01" else T.NAMESPACE), t + 2,
                        string("x")))
    return [(tp, ns, bytes(d)) for tp, ns, d in out if tp not in skip]


def write_messages(path: Path, msgs, storage="mcap", chunk_after: str | None = None) -> Path:
    """Write [(topic, log time, cdr)] as a rosbag2 bag (contract topics of either naming get their
    contract type, others std_msgs/String); `chunk_after`: close an MCAP chunk after every
    message of that topic (as the recorder's periodic flushes do)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, _t, _d in msgs:
            if topic not in conns:
                transient = topic in (topic_namer(n)(T.SCENARIO) for n in NAMINGS)
                conns[topic] = w.add_connection(topic, ALL_TYPES.get(topic, T.STRING), typestore=TS,
                                                offered_qos_profiles=[_qos(transient)])
        for topic, t, data in msgs:
            w.write(conns[topic], t, data)
            if chunk_after is not None and storage == "mcap" and topic == chunk_after:
                w.storage.close_chunk()
    return path


def write_bag(path: Path, ep: SynthEpisode, storage="mcap", skip=(), extra_topics=False,
              chunk_per_step=False, stamp_shift_ns=None, naming: str = "current") -> Path:
    """Write `ep` as a bag; chunk_per_step: close an MCAP chunk after every step (as the
    recorder's periodic flushes do), so a cut file keeps every earlier step. `naming`: the
    contract's topic names ('current') or sep 0.1's ('sep01')."""
    msgs = episode_messages(ep, skip=skip, extra_topics=extra_topics, stamp_shift_ns=stamp_shift_ns, naming=naming)
    return write_messages(path, msgs, storage, topic_namer(naming)(T.APPLIED_INPUT) if chunk_per_step else None)


def fake_design(ep: SynthEpisode, n_r: int = 4):
    """A structurally valid `Design` for `ep`'s scenario (nominal = ep's nominal; zero ROM)."""
    from sep_estimator.design import Design, Nominal
    from sep_estimator.ltv import LQG, DenseFieldMap, KalmanSchedule, LTVModel

    info, p = ep.info, ep.scenario.problem
    N, nf, nu, ny = p.n_steps, info.n_field, info.n_u, info.n_y
    z = np.zeros
    model = LTVModel(A=z((N, n_r, n_r)), B=z((N, n_r, nu)), C=z((N + 1, ny, n_r)), G=DenseFieldMap(z((N + 1, nf, n_r))),
                     dims=np.minimum(np.arange(N + 1) * nu, n_r).astype(np.int64))
    W, V = p.noise_covariances(info.noise_dim, ny)
    P = z((N + 1, n_r, n_r))
    lqg = LQG("rom_lqg", model, z((N, nu, n_r)), KalmanSchedule(z((N + 1, n_r, ny)), P, P.copy()), W, V,
              z((N + 1, nf)))
    nominal = Nominal(ep.u_nom, ep.y_nom, ep.F_nom, ep.F_nom.copy(), z((N + 1, nf)))
    return Design(ep.scenario, info, ep.objective, ep.xyz, nominal, lqg, z((N + 1, 3)), {"synthetic": True})
