"""Rewriting a truncated bag as a complete one (pure: no rclpy; rosbags' Writer)."""
from __future__ import annotations

from pathlib import Path

from sep_control.bags.storage import RawConnection, read_raw


def _offered_qos(c: RawConnection) -> list:
    """The connection's offered QoS profiles as rosbags Qos (none when unreadable)."""
    from rosbags.rosbag2.metadata import parse_qos

    text = c.metadata.get("offered_qos_profiles", "")
    if not text:
        return []
    try:
        return parse_qos(text)
    except Exception:  # noqa: BLE001 - QoS metadata is informative only
        return []


def repair_bag(path: str | Path, out: str | Path, storage: str = "mcap") -> Path:
    """Rewrite a (possibly truncated) bag as a complete rosbag2 bag holding every message that
    can be recovered, so that tools needing the summary / metadata.yaml (rosbags' AnyReader,
    ``ros2 bag``) open it. Message bytes and log times are copied unchanged.

    Parameters
    ----------
    path : str or Path
        The bag to read (`sep_control.bags.storage.read_raw`: truncation is tolerated).
    out : str or Path
        The new bag directory (must not exist).
    storage : {'mcap', 'sqlite3'}
        Storage plugin of the new bag.

    Returns
    -------
    Path
        `out`.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    raw = read_raw(path)
    ts = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(Path(out), version=9, storage_plugin=plugin) as w:
        conns = {}
        for cid, c in raw.connections.items():
            # types outside the Jazzy store keep the bag's own definition (hash unknown: zeros)
            kw = ({"typestore": ts} if c.msgtype in ts.fielddefs
                  else {"msgdef": c.msgdef, "rihs01": "RIHS01_" + "0" * 64})
            conns[cid] = w.add_connection(c.topic, c.msgtype, serialization_format=c.encoding or "cdr",
                                          offered_qos_profiles=_offered_qos(c), **kw)
        for cid, t, data in zip(raw.conn_ids.tolist(), raw.log_times.tolist(), raw.data):
            w.write(conns[cid], t, data)
    return Path(out)
