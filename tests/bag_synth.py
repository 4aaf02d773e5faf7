"""Synthetic bags of the sep topic contract (DESIGN.md §4), for the bag/analysis tests.

`synthetic_episode` rolls out a tiny scenario on the real simulator with known inputs and
noise; `write_bag` serializes it with the Jazzy typestore exactly in the contract layout and
writes a rosbag2 bag with rosbags' Writer. Receive (log) times are synthetic and known, so
latencies are known exactly.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from sep_plant.scenario import Scenario
from sep_plant.slab import SlabSimulator

TS = get_typestore(Stores.ROS2_JAZZY)
T0_NS = 1_700_000_000_000_000_000    # recorder clock origin of the synthetic receive times
LAT_CMD_NS = 700_000                 # measurement k -> heat_command k (0.7 ms)
LAT_EST_NS = 300_000                 # measurement k -> state_estimate k / field_estimate k

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=19)


def small_scenario(**kw) -> Scenario:
    return Scenario(**{**SMALL, **kw})


@dataclass
class SynthEpisode:
    scenario: Scenario
    T: np.ndarray          # (N+1, n_x)
    u_cmd: np.ndarray      # (N, n_u)
    u: np.ndarray          # (N, n_u)  applied (here clipped == commanded)
    y: np.ndarray          # (N+1, n_y)
    T_hat: np.ndarray      # (N+1, n_x)
    T_std: np.ndarray      # (N+1, n_x)
    a_hat: list            # N+1 arrays of growing length
    T_nom: np.ndarray      # (N+1, n_x)
    u_nom: np.ndarray      # (N, n_u)
    diag: dict = field(default_factory=lambda: {"deadline_misses": 3, "rejected_messages": 2})


def synthetic_episode(s: Scenario | None = None, seed: int = 0) -> SynthEpisode:
    s = s or small_scenario()
    rng = np.random.default_rng(seed)
    sim = SlabSimulator(s)
    N = s.n_steps
    u_nom = np.full((N, s.n_u), 2.0)
    T_nom = sim.rollout(sim.initial_state(), u_nom)[0]
    u_cmd = u_nom + 0.2 * rng.standard_normal((N, s.n_u))
    w = s.w_std * rng.standard_normal((N, s.n_u))
    T = sim.rollout(sim.initial_state(), u_cmd, w[None])[0]
    y = T[:, s.sensor_nodes()] + s.v_std * rng.standard_normal((N + 1, s.n_y))
    T_std = 0.5 + 0.1 * rng.random((N + 1, s.n_x))
    T_hat = T + T_std * rng.standard_normal((N + 1, s.n_x))
    a_hat = [rng.standard_normal(min(k * s.n_u, 8)) for k in range(N + 1)]
    return SynthEpisode(s, T, u_cmd, u_cmd.copy(), y, T_hat, T_std, a_hat, T_nom, u_nom)


def _stamp(k: int, s: Scenario):
    ns = k * int(round(s.dt * 1e9))
    return TS.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(k, s):
    return TS.types["std_msgs/msg/Header"](stamp=_stamp(k, s), frame_id="slab")


def joint_state(k, s, names, position=(), effort=()):
    JS = TS.types["sensor_msgs/msg/JointState"]
    msg = JS(header=_header(k, s), name=list(names), position=np.asarray(position, float),
             velocity=np.zeros(0), effort=np.asarray(effort, float))
    return TS.serialize_cdr(msg, "sensor_msgs/msg/JointState")


def cloud(k, s, T, std):
    PC = TS.types["sensor_msgs/msg/PointCloud2"]
    PF = TS.types["sensor_msgs/msg/PointField"]
    fields = [PF(name=n, offset=8 * i, datatype=8, count=1)
              for i, n in enumerate(("x", "y", "z", "temperature", "temperature_std"))]
    pts = np.zeros((s.n_x, 5))
    pts[:, 0] = s.grid()
    pts[:, 3] = T
    pts[:, 4] = std
    data = np.frombuffer(pts.astype("<f8").tobytes(), dtype=np.uint8)
    msg = PC(header=_header(k, s), height=1, width=s.n_x, fields=fields, is_bigendian=False,
             point_step=40, row_step=40 * s.n_x, data=data, is_dense=True)
    return TS.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2")


def clock(k, s):
    return TS.serialize_cdr(TS.types["rosgraph_msgs/msg/Clock"](clock=_stamp(k, s)), "rosgraph_msgs/msg/Clock")


def diagnostics(k, s, values: dict, name="plant"):
    D = TS.types
    st = D["diagnostic_msgs/msg/DiagnosticStatus"](
        level=0, name=name, message="ok", hardware_id="slab",
        values=[D["diagnostic_msgs/msg/KeyValue"](key=kk, value=str(v)) for kk, v in {**values, "step": k}.items()])
    arr = D["diagnostic_msgs/msg/DiagnosticArray"](header=_header(k, s), status=[st])
    return TS.serialize_cdr(arr, "diagnostic_msgs/msg/DiagnosticArray")


def string(text):
    return TS.serialize_cdr(TS.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String")


def _qos(transient=False):
    z = QosTime(0, 0)
    return Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if transient else QosDurability.VOLATILE,
               z, z, QosLiveliness.AUTOMATIC, z, False)


TYPES = {
    "/clock": "rosgraph_msgs/msg/Clock",
    "/slab/measurements": "sensor_msgs/msg/JointState",
    "/slab/heat_command": "sensor_msgs/msg/JointState",
    "/slab/heat_applied": "sensor_msgs/msg/JointState",
    "/slab/state_estimate": "sensor_msgs/msg/JointState",
    "/slab/field_estimate": "sensor_msgs/msg/PointCloud2",
    "/slab/field": "sensor_msgs/msg/PointCloud2",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "/slab/scenario": "std_msgs/msg/String",
}


def episode_messages(ep: SynthEpisode, skip=(), extra_topics=False):
    """[(topic, log_time_ns, cdr bytes)] of one episode in receive order."""
    s = ep.scenario
    N = s.n_steps
    dt_ns = int(round(s.dt * 1e9))
    out = [("/slab/scenario", T0_NS - 1_000_000, string(s.to_json()))]
    for k in range(N + 1):
        t = T0_NS + k * dt_ns
        out.append(("/clock", t - 10_000, clock(k, s)))
        out.append(("/slab/field", t - 5_000, cloud(k, s, ep.T[k], np.zeros(s.n_x))))
        out.append(("/slab/measurements", t, joint_state(k, s, s.sensor_labels(), position=ep.y[k])))
        out.append(("/slab/state_estimate", t + LAT_EST_NS,
                    joint_state(k, s, [f"a_{i}" for i in range(len(ep.a_hat[k]))], position=ep.a_hat[k])))
        out.append(("/slab/field_estimate", t + LAT_EST_NS + 1000, cloud(k, s, ep.T_hat[k], ep.T_std[k])))
        if k < N:
            out.append(("/slab/heat_command", t + LAT_CMD_NS,
                        joint_state(k, s, s.heater_labels(), effort=ep.u_cmd[k])))
            out.append(("/slab/heat_applied", t + LAT_CMD_NS + 50_000,
                        joint_state(k, s, s.heater_labels(), effort=ep.u[k])))
        if k % 10 == 0 or k == N:
            frac = k / N
            out.append(("/diagnostics", t + 900_000,
                        diagnostics(k, s, {kk: int(round(v * frac)) for kk, v in ep.diag.items()})))
        if extra_topics:
            out.append(("/rosout_like/extra", t + 1, string(f"noise {k}")))
            out.append(("/slab/unknown", t + 2, string("x")))
    return [(t, ns, bytes(d)) for t, ns, d in out if t not in skip]


def write_bag(path: Path, ep: SynthEpisode, storage="mcap", skip=(), extra_topics=False,
              chunk_per_step=False) -> Path:
    """Write `ep` as a bag; chunk_per_step: close an MCAP chunk after every step (as the
    recorder's periodic flushes do), so a cut file keeps every earlier step."""
    msgs = episode_messages(ep, skip=skip, extra_topics=extra_topics)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, _t, _d in msgs:
            if topic not in conns:
                typ = TYPES.get(topic, "std_msgs/msg/String")
                conns[topic] = w.add_connection(topic, typ, typestore=TS,
                                                offered_qos_profiles=[_qos(topic == "/slab/scenario")])
        for topic, t, data in msgs:
            w.write(conns[topic], t, data)
            if chunk_per_step and storage == "mcap" and topic == "/slab/heat_applied":
                w.storage.close_chunk()
    return path


def fake_design(ep: SynthEpisode, n_r: int = 4):
    """A structurally valid design file content for `ep`'s scenario (nominal = ep's nominal)."""
    from sep_estimator.design_file import Design

    s = ep.scenario
    N, nx, nu, ny = s.n_steps, s.n_x, s.n_u, s.n_y
    z = np.zeros
    return Design(scenario=s, u_nom=ep.u_nom, y_nom=ep.T_nom[:, s.sensor_nodes()], T_nom=ep.T_nom,
                  belief_mean=ep.T_nom.copy(), belief_std=z((N + 1, nx)),
                  rom_dims=np.minimum(np.arange(N + 1) * nu, n_r).astype(np.int64),
                  A=z((N, n_r, n_r)), B=z((N, n_r, nu)), C=z((N + 1, ny, n_r)), G=z((N + 1, nx, n_r)),
                  K=z((N, nu, n_r)), L=z((N + 1, n_r, ny)), P_post=z((N + 1, n_r, n_r)),
                  field_std=z((N + 1, nx)), hankel_sv=z((N + 1, 3)), meta={"synthetic": True})
