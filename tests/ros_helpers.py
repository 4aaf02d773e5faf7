"""Readers of contract messages that only the tests need (the nodes build these messages,
`sep_plant.ros.contract`; the bag reader decodes them without ROS, `sep_plant.topics`)."""
from __future__ import annotations

import numpy as np

from sep_plant import topics as T
from sep_plant.topics import CloudLayoutError  # noqa: F401  (raised by parse_field_cloud)


def topic(name: str, namespace: str = T.NAMESPACE) -> str:
    """Fully qualified name of a contract topic (absolute names are returned unchanged)."""
    return T.topic_name(name, namespace)


def all_topics(namespace: str = T.NAMESPACE) -> dict[str, str]:
    """Fully qualified topic name -> ROS type name, for every topic of the contract."""
    return {T.topic_name(t.name, namespace): t.type_name for t in T.TOPICS}


def parse_field_cloud(msg) -> dict[str, np.ndarray]:
    """Arrays x, y, z, <field>, <field>_std of a contract PointCloud2 (layout checked)."""
    names = [f.name for f in msg.fields]
    T.check_cloud_layout(names, [f.datatype for f in msg.fields], [f.offset for f in msg.fields],
                         msg.point_step, msg.height, msg.is_bigendian, msg.width, len(msg.data))
    arr = T.parse_cloud_payload(msg.data, msg.width)
    return {name: arr[:, i].copy() for i, name in enumerate(names)}


def diagnostic_values(status) -> dict[str, str]:
    """key -> value of a diagnostic_msgs/DiagnosticStatus."""
    return {kv.key: kv.value for kv in status.values}


def level_of(status) -> int:
    """The level of a DiagnosticStatus as an int (it is stored as one byte)."""
    lv = status.level
    return lv[0] if isinstance(lv, (bytes, bytearray)) else int(lv)
