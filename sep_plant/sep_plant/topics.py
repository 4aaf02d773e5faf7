"""The topic contract (docs/reference/topics.md) as plain data: one definition for the nodes, the recorder
and the bag reader. No ROS import; `sep_plant.ros.contract` builds the rclpy side from it.

Topics (relative names resolve in the node's namespace, ``sep`` by default; /clock and
/diagnostics are absolute). The names say what a topic carries, for every plant:

=======================  ================================  =====================================
topic                    type                              content
=======================  ================================  =====================================
/clock                   rosgraph_msgs/msg/Clock           simulated time k dt (plant)
measurements             sensor_msgs/msg/JointState        position = y_k; names = the plant's outputs
command                  sensor_msgs/msg/JointState        effort = u_k; names = the plant's inputs
applied_input            sensor_msgs/msg/JointState        effort = inputs applied at step k
state_estimate           sensor_msgs/msg/JointState        position = ROM estimate a_hat_k (a_0..) and
                                                           disturbance estimate d_hat_k (d_0..)
field_estimate           sensor_msgs/msg/PointCloud2       x, y, z, <field>, <field>_std
field                    sensor_msgs/msg/PointCloud2       true field (std 0)
field_image              sensor_msgs/msg/Image             true field as a 32FC1 image (grid plants)
field_estimate_image     sensor_msgs/msg/Image             estimated field as a 32FC1 image
scenario                 std_msgs/msg/String               the plant's scenario as JSON (latched)
/diagnostics             diagnostic_msgs/msg/DiagnosticArray  node health
=======================  ================================  =====================================

Stamps: a message of step k carries header.stamp = k dt on the simulated clock, computed in
integer nanoseconds as k * round(dt * 1e9) (no float drift over long episodes), and the
plant's frame id (its optional ``frame_id`` attribute, ``sep`` by default). A received stamp is step k when it lies within `STAMP_TOLERANCE` (0.1 %) of dt of
k dt (250 us at dt = 0.25 s); anything else is rejected as off the step grid.

PointCloud2 layout (fixed; little endian): height 1, width n_field, five FLOAT64 fields
x, y, z, <field_name>, <field_name>_std at offsets 0, 8, 16, 24, 32 (e.g. temperature,
temperature_std for the heat plants); point_step 40, row_step 40 n_field, is_dense. x, y, z
are the node coordinates in metres.

sep 0.1 wrote the slab's names for every plant (namespace ``slab``, topics ``heat_command`` and
``heat_applied``); `LEGACY_TOPICS` is the one table that maps them, so bags recorded with them
are read as they always were (`key_of`, `detect_namespace`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NAMESPACE = "sep"
#: frame id of every message when the plant declares none (`PlantInfo.frame_id`)
FRAME_ID = "sep"

CLOCK = "/clock"
DIAGNOSTICS = "/diagnostics"
MEASUREMENTS = "measurements"
COMMAND = "command"
APPLIED_INPUT = "applied_input"
STATE_ESTIMATE = "state_estimate"
FIELD_ESTIMATE = "field_estimate"
FIELD = "field"
FIELD_IMAGE = "field_image"
FIELD_ESTIMATE_IMAGE = "field_estimate_image"
SCENARIO = "scenario"

JOINT_STATE = "sensor_msgs/msg/JointState"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
STRING = "std_msgs/msg/String"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"


@dataclass(frozen=True)
class QosSpec:
    """A QoS profile as data (KEEP_LAST history)."""

    depth: int
    reliable: bool = True
    transient_local: bool = False


LOOP = QosSpec(10)                                  # control loop: reliable, volatile, depth 10
VIEW = QosSpec(50)                                  # field clouds / images (offered reliably)
LATCHED = QosSpec(1, transient_local=True)          # scenario


@dataclass(frozen=True)
class TopicSpec:
    name: str          # relative to the namespace, or absolute (leading '/')
    type_name: str     # ROS 2 type name as in a rosbag2 metadata file
    qos: QosSpec       # as published
    per_step: bool     # one message per step k (stamped k dt)


TOPICS: tuple[TopicSpec, ...] = (
    TopicSpec(CLOCK, CLOCK_TYPE, LOOP, False),
    TopicSpec(MEASUREMENTS, JOINT_STATE, LOOP, True),
    TopicSpec(COMMAND, JOINT_STATE, LOOP, True),
    TopicSpec(APPLIED_INPUT, JOINT_STATE, LOOP, True),
    TopicSpec(STATE_ESTIMATE, JOINT_STATE, LOOP, True),
    TopicSpec(FIELD_ESTIMATE, POINT_CLOUD2, VIEW, True),
    TopicSpec(FIELD, POINT_CLOUD2, VIEW, True),
    TopicSpec(FIELD_IMAGE, IMAGE, VIEW, True),
    TopicSpec(FIELD_ESTIMATE_IMAGE, IMAGE, VIEW, True),
    TopicSpec(DIAGNOSTICS, DIAGNOSTIC_ARRAY, LOOP, False),
    TopicSpec(SCENARIO, STRING, LATCHED, False),
)
BY_NAME = {t.name: t for t in TOPICS}
#: every contract topic is recorded; the images (grid plants only) repeat the clouds for viewers,
#: so the analysis does not miss them when absent
RECORDED = tuple(t.name for t in TOPICS)
OPTIONAL = (FIELD_IMAGE, FIELD_ESTIMATE_IMAGE)


#: name prefixes of the state_estimate entries: the ROM state, the disturbance states
STATE_PREFIX, DISTURBANCE_PREFIX = "a_", "d_"


def state_labels(n_r: int, n_d: int = 0) -> list[str]:
    """Names of the state_estimate entries: a_0 .. a_{n_r-1}, then d_0 .. d_{n_d-1} (the
    disturbance estimates of a design with disturbance states)."""
    return [f"{STATE_PREFIX}{i}" for i in range(n_r)] + [f"{DISTURBANCE_PREFIX}{i}" for i in range(n_d)]


def topic_name(name: str, namespace: str = NAMESPACE) -> str:
    """Fully qualified name of a contract topic (absolute names are returned unchanged)."""
    if name.startswith("/"):
        return name
    ns = namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


#: sep 0.1's topic names -> the contract's (its namespace was ``slab``)
LEGACY_TOPICS = {"heat_command": COMMAND, "heat_applied": APPLIED_INPUT}
LEGACY_NAMESPACE = "slab"


def key_of(full_name: str, namespace: str = NAMESPACE) -> str | None:
    """The contract name ('measurements', '/clock', ...) of a fully qualified topic, or None;
    sep 0.1's names (`LEGACY_TOPICS`) map to theirs."""
    for t in TOPICS:
        if full_name == topic_name(t.name, namespace):
            return t.name
    for old, new in LEGACY_TOPICS.items():
        if full_name == topic_name(old, namespace):
            return new
    return None


def detect_namespace(full_names: list[str] | set[str]) -> str | None:
    """The namespace of a graph from the topic names it has (a bag's): the one whose
    ``measurements`` topic is there (the default namespace first, then sep 0.1's, then any
    other), or None when there is none."""
    found = sorted(n.rsplit("/", 1)[0].strip("/") for n in full_names
                   if n.endswith("/" + MEASUREMENTS) and n.count("/") >= 1)
    for ns in (NAMESPACE, LEGACY_NAMESPACE):
        if ns in found:
            return ns
    return found[0] if found else None


def contract_topics(namespace: str = NAMESPACE, names: tuple[str, ...] = RECORDED) -> dict[str, TopicSpec]:
    """{fully qualified topic: spec} of the given contract topics (default: what is recorded)."""
    return {topic_name(n, namespace): BY_NAME[n] for n in names}


# --------------------------------------------------------------------------- stamps
#: a stamp is step k when |stamp - k dt| <= STAMP_TOLERANCE * dt
STAMP_TOLERANCE = 1e-3


def dt_ns(dt: float) -> int:
    """The step length in integer nanoseconds."""
    return int(round(dt * 1e9))


def stamp_ns(k: int, dt: float) -> int:
    """Simulated time of step k in nanoseconds: k * round(dt * 1e9)."""
    return int(k) * dt_ns(dt)


def tolerance_ns(step_ns: int) -> int:
    return max(1, int(step_ns * STAMP_TOLERANCE))


def step_of_stamp(ns: int, step_ns: int) -> int | None:
    """Step k of a stamp of `ns` nanoseconds on the grid k * step_ns, or None when it is off the
    grid by more than the tolerance or negative."""
    k = (ns + step_ns // 2) // step_ns
    if k < 0 or abs(ns - k * step_ns) > tolerance_ns(step_ns):
        return None
    return int(k)


def steps_of_stamps(ns: np.ndarray, step_ns: int) -> np.ndarray:
    """`step_of_stamp` for an array of stamps (-1 where off the grid)."""
    k = np.floor_divide(ns + step_ns // 2, step_ns).astype(np.int64)
    k[(k < 0) | (np.abs(ns - k * step_ns) > tolerance_ns(step_ns))] = -1
    return k


# ---------------------------------------------------------------------- point clouds
POINT_STEP = 40
FLOAT64 = 8          # sensor_msgs/PointField datatype


def cloud_fields(field_name: str) -> tuple[str, ...]:
    """Channel names of the contract PointCloud2 of a field called `field_name`."""
    return ("x", "y", "z", field_name, f"{field_name}_std")


def cloud_payload(xyz: np.ndarray, values: np.ndarray, std: np.ndarray | None = None) -> bytes:
    """The PointCloud2 data bytes: (n, 5) little-endian float64 rows x, y, z, value, std."""
    n = xyz.shape[0]
    buf = np.empty((n, 5), dtype="<f8")
    buf[:, :3] = xyz
    buf[:, 3] = np.ravel(values)
    buf[:, 4] = 0.0 if std is None else np.ravel(std)
    return buf.tobytes()


class CloudLayoutError(ValueError):
    """A PointCloud2 does not have the contract layout."""


def check_cloud_layout(names: list[str], datatypes: list[int], offsets: list[int], point_step: int,
                       height: int, bigendian: bool, width: int, n_bytes: int) -> None:
    """Raise CloudLayoutError unless the cloud has the contract layout (any field name)."""
    if len(names) != 5 or names[:3] != ["x", "y", "z"] or names[4] != f"{names[3]}_std":
        raise CloudLayoutError(f"fields {names}, expected x, y, z, <field>, <field>_std")
    if any(t != FLOAT64 for t in datatypes) or list(offsets) != [0, 8, 16, 24, 32]:
        raise CloudLayoutError(f"fields must be FLOAT64 at offsets 0, 8, 16, 24, 32 (got types {datatypes}, "
                               f"offsets {offsets})")
    if bigendian or point_step != POINT_STEP or height != 1:
        raise CloudLayoutError("expected little endian, height 1, point_step 40")
    if n_bytes != width * POINT_STEP:
        raise CloudLayoutError(f"data has {n_bytes} bytes, expected {width * POINT_STEP}")


def parse_cloud_payload(data: bytes, width: int) -> np.ndarray:
    """(width, 5) float64 rows of a contract PointCloud2 payload (layout checked by the caller)."""
    return np.frombuffer(bytes(data), dtype="<f8").reshape(width, 5)


# --------------------------------------------------------------------------- images
def image_of_field(values: np.ndarray, grid_shape: tuple[int, ...]) -> np.ndarray:
    """The field as a 2-D float32 image: a 2-D grid as it is (rows = first axis), the middle
    slice along the last axis of a 3-D grid, a 1-D field as one row."""
    g = np.asarray(values, dtype=np.float32).reshape(grid_shape)
    if g.ndim == 1:
        return g[None, :]
    if g.ndim == 3:
        return np.ascontiguousarray(g[:, :, g.shape[2] // 2])
    return g
