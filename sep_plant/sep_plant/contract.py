"""The topic contract of DESIGN.md §4 on the ROS side: names, QoS, message builders/parsers.

Every node of sep (plant, estimator, LQR, lqg, recorder, test collectors) takes its topic
names, QoS profiles and message layouts from here, so there is exactly one definition.
Bag readers that do not import ROS (helper tools using `rosbags`) decode the same layouts:
they are fixed below and documented field by field.

Topics (relative names resolve in the node's namespace, ``slab`` by default; remap the whole
graph with ``--ros-args -r __ns:=/other``; /clock and /diagnostics are absolute):

======================  ===========================  ==========================================
topic                   type                         content
======================  ===========================  ==========================================
/clock                  rosgraph_msgs/Clock          simulated time k*dt (plant)
slab/measurements       sensor_msgs/JointState       position = y_k [F]; names = sensor_i
slab/heat_command       sensor_msgs/JointState       effort = u_k; names = heater_j
slab/heat_applied       sensor_msgs/JointState       effort = inputs applied at step k
slab/state_estimate     sensor_msgs/JointState       position = ROM estimate a_hat_k; names a_i
slab/field_estimate     sensor_msgs/PointCloud2      x, y, z, temperature, temperature_std
slab/field              sensor_msgs/PointCloud2      true field (temperature_std = 0)
slab/scenario           std_msgs/String              the plant's scenario as JSON (latched)
/diagnostics            diagnostic_msgs/DiagnosticArray  node health
======================  ===========================  ==========================================

QoS, chosen on purpose:

* **Control loop** (measurements, heat_command, heat_applied, state_estimate): RELIABLE,
  VOLATILE, KEEP_LAST depth 10.  A lost sample would stall a lockstep episode (the plant waits
  for the command of step k) or silently cost a control update; reliability on localhost costs
  nothing measurable (see bench/bench_latency.py).  Depth 10: a subscriber that falls a few
  steps behind still gets every step in order; a stale one is then refused by its step gate.
  VOLATILE: a late joiner must not act on old steps.
* **Field clouds** (field, field_estimate): the publisher offers RELIABLE, KEEP_LAST depth 50.
  Nothing in the loop reads them: they are for viewers and bags.  A reliable *offer* matches
  both kinds of subscriber: the recorder subscribes reliably (a bag should hold every step,
  so its metrics equal the live run's), while viewers, where loss is fine, subscribe with the
  sensor-data profile (`FIELD_VIEWER_QOS`, best effort, depth 5) and never slow the writer.
* **/diagnostics**: RELIABLE, VOLATILE, depth 10, like diagnostic_updater.
* **slab/scenario**: RELIABLE, TRANSIENT_LOCAL, depth 1 (latched): the plant publishes its
  scenario once; nodes started later (a restarted estimator, the recorder) still receive it
  and can refuse a design file made for another plant.
* **/clock**: the plant publishes RELIABLE depth 10; rclpy's time source subscribes best
  effort depth 1 (the latest time is all that matters), which matches.

Stamps: a message of step k carries header.stamp = k*dt on the simulated clock, computed in
integer nanoseconds as k * round(dt * 1e9) (no float drift over long episodes), frame_id
``slab``.  `step_of_stamp` inverts it with a tolerance.

PointCloud2 layout (fixed; little endian): height 1, width n_x, fields
x, y, z, temperature, temperature_std, all FLOAT64 (datatype 8, count 1) at offsets
0, 8, 16, 24, 32; point_step 40, row_step 40 n_x, is_dense true, is_bigendian false.
x = node position [L units], y = z = 0; temperature [F]; temperature_std [F] (0 for the true
field).

This module imports rclpy and the message packages; the pure checks of message content
(lengths, names, finiteness, stamp order) are in `sep_estimator.gate` (no ROS import).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState, PointCloud2, PointField
from std_msgs.msg import Header, String

# ---------------------------------------------------------------------------- names
NAMESPACE = 'slab'
FRAME_ID = 'slab'

CLOCK = '/clock'
DIAGNOSTICS = '/diagnostics'
MEASUREMENTS = 'measurements'
HEAT_COMMAND = 'heat_command'
HEAT_APPLIED = 'heat_applied'
STATE_ESTIMATE = 'state_estimate'
FIELD_ESTIMATE = 'field_estimate'
FIELD = 'field'
SCENARIO = 'scenario'

#: relative topic name -> message type, for the contract topics in the node namespace
TOPIC_TYPES = {
    MEASUREMENTS: JointState,
    HEAT_COMMAND: JointState,
    HEAT_APPLIED: JointState,
    STATE_ESTIMATE: JointState,
    FIELD_ESTIMATE: PointCloud2,
    FIELD: PointCloud2,
    SCENARIO: String,
}

#: ROS type names (as in a rosbag2 metadata file) of every contract topic
TYPE_NAMES = {
    JointState: 'sensor_msgs/msg/JointState',
    PointCloud2: 'sensor_msgs/msg/PointCloud2',
    String: 'std_msgs/msg/String',
    Clock: 'rosgraph_msgs/msg/Clock',
    DiagnosticArray: 'diagnostic_msgs/msg/DiagnosticArray',
}


def topic(name: str, namespace: str = NAMESPACE) -> str:
    """Fully qualified name of a contract topic (absolute names are returned unchanged)."""
    if name.startswith('/'):
        return name
    ns = '/' + namespace.strip('/') if namespace.strip('/') else ''
    return f'{ns}/{name}'


def all_topics(namespace: str = NAMESPACE) -> dict[str, str]:
    """Fully qualified topic name -> ROS type name, for every topic of the contract."""
    out = {topic(n, namespace): TYPE_NAMES[t] for n, t in TOPIC_TYPES.items()}
    out[CLOCK] = TYPE_NAMES[Clock]
    out[DIAGNOSTICS] = TYPE_NAMES[DiagnosticArray]
    return out


def state_labels(n_r: int) -> list[str]:
    """Names of the ROM state estimate entries: a_0 .. a_{n_r-1}."""
    return [f'a_{i}' for i in range(n_r)]


# ------------------------------------------------------------------------------ QoS
LOOP_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
FIELD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: for subscribers of the field clouds that only display them (loss is fine)
FIELD_VIEWER_QOS = qos_profile_sensor_data
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
SCENARIO_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)

#: QoS of every contract topic as *published* (subscribers use the same, except viewers)
TOPIC_QOS = {
    MEASUREMENTS: LOOP_QOS, HEAT_COMMAND: LOOP_QOS, HEAT_APPLIED: LOOP_QOS,
    STATE_ESTIMATE: LOOP_QOS, FIELD_ESTIMATE: FIELD_QOS, FIELD: FIELD_QOS,
    SCENARIO: SCENARIO_QOS, CLOCK: CLOCK_QOS, DIAGNOSTICS: DIAGNOSTICS_QOS,
}


# --------------------------------------------------------------------------- stamps
def dt_ns(dt: float) -> int:
    """The step length in integer nanoseconds."""
    return int(round(dt * 1e9))


def stamp_ns(k: int, dt: float) -> int:
    """Simulated time of step k in nanoseconds: k * round(dt * 1e9)."""
    return int(k) * dt_ns(dt)


def stamp(k: int, dt: float) -> Time:
    """builtin_interfaces/Time of step k."""
    ns = stamp_ns(k, dt)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(k: int, dt: float) -> Header:
    return Header(stamp=stamp(k, dt), frame_id=FRAME_ID)


def time_ns(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def step_of_stamp(t: Time | int, dt: float, tol_ns: int | None = None) -> int | None:
    """Step k whose stamp is k*dt, or None when the stamp is not within `tol_ns` of a step
    (default tolerance: 1 % of dt) or is negative."""
    ns = t if isinstance(t, int) else time_ns(t)
    step = dt_ns(dt)
    if tol_ns is None:
        tol_ns = max(1, step // 100)
    if ns < -tol_ns:
        return None
    k = (ns + step // 2) // step
    if abs(ns - k * step) > tol_ns or k < 0:
        return None
    return int(k)


def clock_msg(k: int, dt: float) -> Clock:
    return Clock(clock=stamp(k, dt))


# ----------------------------------------------------------------------- JointState
def joint_state(k: int, dt: float, names: Sequence[str], *, position=None, effort=None) -> JointState:
    """A JointState of step k: `position` or `effort` filled (the other arrays empty)."""
    msg = JointState()
    msg.header = header(k, dt)
    msg.name = list(names)
    if position is not None:
        msg.position = np.asarray(position, dtype=np.float64).ravel()
    if effort is not None:
        msg.effort = np.asarray(effort, dtype=np.float64).ravel()
    return msg


def joint_values(msg: JointState, field: str) -> np.ndarray:
    """The `position` / `effort` / `velocity` array of a JointState as float64 numpy."""
    return np.asarray(getattr(msg, field), dtype=np.float64)


# ---------------------------------------------------------------------- PointCloud2
CLOUD_FIELDS = ('x', 'y', 'z', 'temperature', 'temperature_std')
CLOUD_POINT_STEP = 8 * len(CLOUD_FIELDS)
_CLOUD_DTYPE = np.dtype('<f8')
_POINT_FIELDS = [PointField(name=n, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                 for i, n in enumerate(CLOUD_FIELDS)]


def field_cloud(k: int, dt: float, x: np.ndarray, temperature: np.ndarray,
                std: np.ndarray | None = None) -> PointCloud2:
    """The fixed-layout PointCloud2 of a field at step k (std None -> zeros, the true field)."""
    n = x.shape[0]
    buf = np.empty((n, len(CLOUD_FIELDS)), dtype=_CLOUD_DTYPE)
    buf[:, 0] = x
    buf[:, 1:3] = 0.0
    buf[:, 3] = np.ravel(temperature)
    buf[:, 4] = 0.0 if std is None else np.ravel(std)
    msg = PointCloud2()
    msg.header = header(k, dt)
    msg.height = 1
    msg.width = n
    msg.fields = _POINT_FIELDS
    msg.is_bigendian = False
    msg.point_step = CLOUD_POINT_STEP
    msg.row_step = CLOUD_POINT_STEP * n
    msg.data = buf.tobytes()
    msg.is_dense = True
    return msg


class CloudLayoutError(ValueError):
    """A PointCloud2 does not have the contract layout."""


def parse_field_cloud(msg: PointCloud2) -> dict[str, np.ndarray]:
    """Arrays x, y, z, temperature, temperature_std of a contract PointCloud2 (layout checked)."""
    names = [f.name for f in msg.fields]
    if names != list(CLOUD_FIELDS):
        raise CloudLayoutError(f'fields {names}, expected {list(CLOUD_FIELDS)}')
    for i, f in enumerate(msg.fields):
        if f.datatype != PointField.FLOAT64 or f.offset != 8 * i or f.count != 1:
            raise CloudLayoutError(f'field {f.name}: datatype {f.datatype} offset {f.offset} '
                                   f'count {f.count}, expected FLOAT64 at {8 * i}')
    if msg.is_bigendian or msg.point_step != CLOUD_POINT_STEP or msg.height != 1:
        raise CloudLayoutError('expected little endian, height 1, point_step 40')
    n = msg.width
    if len(msg.data) != n * CLOUD_POINT_STEP:
        raise CloudLayoutError(f'data has {len(msg.data)} bytes, expected {n * CLOUD_POINT_STEP}')
    arr = np.frombuffer(bytes(msg.data), dtype=_CLOUD_DTYPE).reshape(n, len(CLOUD_FIELDS))
    return {name: arr[:, i].copy() for i, name in enumerate(CLOUD_FIELDS)}


# ---------------------------------------------------------------------- scenario JSON
def scenario_msg(scenario) -> String:
    return String(data=scenario.to_json())


def parse_scenario(msg: String):
    """The Scenario of a slab/scenario message (raises ScenarioError / ValueError if bad)."""
    from .scenario import Scenario
    return Scenario.from_json(msg.data)


# ------------------------------------------------------------------------ diagnostics
#: diagnostic levels as ints (DiagnosticStatus stores them as one byte)
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass
class Health:
    """One node's health for /diagnostics."""

    name: str                       # e.g. 'sep_plant: plant' (node name)
    hardware_id: str = 'slab'
    level: int = 0                  # OK / WARN / ERROR / STALE
    message: str = 'ok'
    values: Mapping[str, object] | None = None


def _fmt_value(v: object) -> str:
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else str(v)
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v)
    return str(v)


def diagnostics(stamp_time: Time, statuses: Iterable[Health]) -> DiagnosticArray:
    """A DiagnosticArray with one DiagnosticStatus per `Health`."""
    arr = DiagnosticArray()
    arr.header = Header(stamp=stamp_time, frame_id=FRAME_ID)
    for h in statuses:
        st = DiagnosticStatus()
        st.level = bytes([int(h.level)])
        st.name = h.name
        st.message = h.message
        st.hardware_id = h.hardware_id
        st.values = [KeyValue(key=str(k), value=_fmt_value(v)) for k, v in (h.values or {}).items()]
        arr.status.append(st)
    return arr


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """key -> value of a DiagnosticStatus."""
    return {kv.key: kv.value for kv in status.values}


def level_of(status: DiagnosticStatus) -> int:
    lv = status.level
    return lv[0] if isinstance(lv, (bytes, bytearray)) else int(lv)
