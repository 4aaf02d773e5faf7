"""The topic contract on the ROS side: QoS profiles and message builders/parsers.

The contract itself (names, types, QoS as data, stamps, cloud layout) is `sep_plant.topics`
(no ROS import), shared with the recorder and the bag reader; this module turns it into rclpy
objects. Every node takes its topic names, QoS profiles and message layouts from here.

QoS, chosen on purpose:

* **Control loop** (measurements, command, applied_input, state_estimate): RELIABLE,
  VOLATILE, KEEP_LAST depth 10.  A lost sample would stall a lockstep episode (the plant waits
  for the command of step k) or silently cost a control update; reliability on localhost costs
  nothing measurable (see bench/bench_latency.py).  Depth 10: a subscriber that falls a few
  steps behind still gets every step in order; a stale one is then refused by its step gate.
  VOLATILE: a late joiner must not act on old steps.
* **Field clouds and images**: the publisher offers RELIABLE, KEEP_LAST depth 50. Nothing in
  the loop reads them: they are for viewers and bags.  A reliable *offer* matches both kinds of
  subscriber: the recorder subscribes reliably (a bag should hold every step, so its metrics
  equal the live run's), while viewers (RViz, Foxglove), where loss is fine, subscribe with the
  sensor-data profile (`VIEWER_QOS`, best effort, depth 5) and never slow the writer.
* **/diagnostics**: RELIABLE, VOLATILE, depth 10, like diagnostic_updater.
* **scenario**: RELIABLE, TRANSIENT_LOCAL, depth 1 (latched): the plant publishes its scenario
  once; nodes started later (a restarted estimator, the recorder) still receive it and can
  refuse a design file made for another plant.
* **/clock**: the plant publishes RELIABLE depth 10; rclpy's time source subscribes best
  effort depth 1 (the latest time is all that matters), which matches.

This module imports rclpy and the message packages; the pure checks of message content
(lengths, names, finiteness, stamp order) are in `sep_plant.gate` (no ROS import).
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
from sensor_msgs.msg import Image, JointState, PointCloud2, PointField
from std_msgs.msg import Header, String

from sep_plant import topics as T
from sep_plant.topics import (CLOCK, DIAGNOSTICS, FIELD, FIELD_ESTIMATE, FIELD_ESTIMATE_IMAGE, FIELD_IMAGE,  # noqa: F401
                     FRAME_ID, APPLIED_INPUT, COMMAND, MEASUREMENTS, NAMESPACE, SCENARIO, STATE_ESTIMATE,
                     dt_ns, stamp_ns, state_labels)

_CLASSES = {T.JOINT_STATE: JointState, T.POINT_CLOUD2: PointCloud2, T.IMAGE: Image, T.STRING: String,
            T.CLOCK_TYPE: Clock, T.DIAGNOSTIC_ARRAY: DiagnosticArray}

#: contract name -> message class
TOPIC_TYPES = {t.name: _CLASSES[t.type_name] for t in T.TOPICS}


def qos(spec: T.QosSpec) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=spec.depth,
                      reliability=ReliabilityPolicy.RELIABLE if spec.reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if spec.transient_local
                      else DurabilityPolicy.VOLATILE)


#: QoS of every contract topic as *published* (subscribers use the same, except viewers)
TOPIC_QOS = {t.name: qos(t.qos) for t in T.TOPICS}
LOOP_QOS = qos(T.LOOP)
FIELD_QOS = qos(T.VIEW)
SCENARIO_QOS = qos(T.LATCHED)
DIAGNOSTICS_QOS = TOPIC_QOS[DIAGNOSTICS]
CLOCK_QOS = TOPIC_QOS[CLOCK]
#: for subscribers of the field clouds and images that only display them (loss is fine)
VIEWER_QOS = qos_profile_sensor_data


# --------------------------------------------------------------------------- stamps
def stamp(k: int, dt: float) -> Time:
    """builtin_interfaces/Time of step k."""
    ns = stamp_ns(k, dt)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(k: int, dt: float, frame_id: str = FRAME_ID) -> Header:
    return Header(stamp=stamp(k, dt), frame_id=frame_id)


def time_ns(t: Time) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def step_of_stamp(t: Time | int, dt: float) -> int | None:
    """Step k of a stamp (a Time or integer nanoseconds), or None when off the step grid
    (`sep_plant.topics.step_of_stamp`: one tolerance, 0.1 % of dt)."""
    return T.step_of_stamp(t if isinstance(t, int) else time_ns(t), dt_ns(dt))


def clock_msg(k: int, dt: float) -> Clock:
    return Clock(clock=stamp(k, dt))


# ----------------------------------------------------------------------- JointState
def joint_state(k: int, dt: float, names: Sequence[str], *, position=None, effort=None,
                frame_id: str = FRAME_ID) -> JointState:
    """A JointState of step k: `position` or `effort` filled (the other arrays empty)."""
    msg = JointState()
    msg.header = header(k, dt, frame_id)
    msg.name = list(names)
    if position is not None:
        msg.position = np.asarray(position, dtype=np.float64).ravel()
    if effort is not None:
        msg.effort = np.asarray(effort, dtype=np.float64).ravel()
    return msg


# ---------------------------------------------------------------------- PointCloud2
class CloudBuilder:
    """Builds the contract PointCloud2 of one plant's field (layout fixed once)."""

    def __init__(self, xyz: np.ndarray, field_name: str, frame_id: str = FRAME_ID):
        self.xyz = np.asarray(xyz, dtype=np.float64)
        self.frame_id = frame_id
        self.fields = [PointField(name=n, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                       for i, n in enumerate(T.cloud_fields(field_name))]

    def build(self, k: int, dt: float, values: np.ndarray, std: np.ndarray | None = None) -> PointCloud2:
        n = self.xyz.shape[0]
        msg = PointCloud2()
        msg.header = header(k, dt, self.frame_id)
        msg.height = 1
        msg.width = n
        msg.fields = self.fields
        msg.is_bigendian = False
        msg.point_step = T.POINT_STEP
        msg.row_step = T.POINT_STEP * n
        msg.data = T.cloud_payload(self.xyz, values, std)
        msg.is_dense = True
        return msg


# --------------------------------------------------------------------------- images
def field_image(k: int, dt: float, values: np.ndarray, grid_shape: tuple[int, ...],
                frame_id: str = FRAME_ID) -> Image:
    """sensor_msgs/Image 32FC1 of a grid field (the middle slice of a 3-D grid)."""
    img = T.image_of_field(values, grid_shape)
    msg = Image()
    msg.header = header(k, dt, frame_id)
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = '32FC1'
    msg.is_bigendian = 0
    msg.step = 4 * msg.width
    msg.data = img.astype('<f4').tobytes()
    return msg


# ---------------------------------------------------------------------- scenario JSON
def scenario_msg(scenario_json: str) -> String:
    return String(data=scenario_json)


# ------------------------------------------------------------------------ diagnostics
#: diagnostic levels as ints (DiagnosticStatus stores them as one byte)
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass
class Health:
    """One node's health for /diagnostics."""

    name: str                       # e.g. 'sep_plant: plant' (node name)
    hardware_id: str = 'sep'
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


def diagnostics(stamp_time: Time, statuses: Iterable[Health], frame_id: str = FRAME_ID) -> DiagnosticArray:
    """A DiagnosticArray with one DiagnosticStatus per `Health`."""
    arr = DiagnosticArray()
    arr.header = Header(stamp=stamp_time, frame_id=frame_id)
    for h in statuses:
        st = DiagnosticStatus()
        st.level = bytes([int(h.level)])
        st.name = h.name
        st.message = h.message
        st.hardware_id = h.hardware_id
        st.values = [KeyValue(key=str(k), value=_fmt_value(v)) for k, v in (h.values or {}).items()]
        arr.status.append(st)
    return arr
