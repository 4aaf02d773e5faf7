"""Decoding a raw bag's contract messages (pure: no rclpy): topic grouping, stamps, per-step
parsing and the payload parsers of the contract types (docs/reference/topics.md).

Topic keys are the contract names of `sep_plant.topics` ('measurements', '/clock', ...); sep
0.1's names are mapped through the one table `sep_plant.topics.LEGACY_TOPICS` (`topics.key_of`).
Messages are deserialized with rosbags' Jazzy typestore; an undecodable or malformed message is
collected by the `Decoder` (one note in the episode), never raised. `sep_control.bags.reader`
assembles the arrays.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sep_control.bags.storage import BagError, RawBag, read_raw
from sep_plant import topics as T
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario, ScenarioError, parse_scenario_message

#: JointState topics and the array that carries their values
VECTOR_TOPICS = {T.MEASUREMENTS: "position", T.COMMAND: "effort", T.APPLIED_INPUT: "effort",
                 T.STATE_ESTIMATE: "position"}
#: per-step topics with one message per input step k = 0..N-1 (the others have k = 0..N)
INPUT_TOPICS = (T.COMMAND, T.APPLIED_INPUT)
IMAGE_TOPICS = tuple(t.name for t in T.TOPICS if t.type_name == T.IMAGE)
#: topics whose serialized message starts with a stamp (header.stamp, or Clock.clock)
STAMPED_TOPICS = tuple(t.name for t in T.TOPICS if t.per_step) + (T.CLOCK, T.DIAGNOSTICS)

_STAMP = struct.Struct("<iI").unpack_from
NO_MESSAGES = np.zeros(0, dtype=np.int64)


class Decoder:
    """CDR deserialization with the Jazzy typestore; undecodable or malformed messages are
    collected in `bad` (reported as one note), never raised."""

    def __init__(self, raw: RawBag):
        from rosbags.typesys import Stores, get_typestore

        self.raw = raw
        self.ts = get_typestore(Stores.ROS2_JAZZY)
        self.bad: list[str] = []

    def topic(self, i: int) -> str:
        return self.raw.connections[int(self.raw.conn_ids[i])].topic

    def __call__(self, i: int, msgtype: str) -> Any | None:
        try:
            return self.ts.deserialize_cdr(self.raw.data[i], msgtype)
        except Exception as exc:  # noqa: BLE001 - report, never a traceback
            self.reject(i, f"undecodable ({type(exc).__name__})")
            return None

    def reject(self, i: int, why: str) -> None:
        self.bad.append(f"{self.topic(i)} message {i}: {why}")


@dataclass
class Messages:
    """A bag's contract messages: indices per topic key, header stamps, the step grid."""

    raw: RawBag
    decode: Decoder
    index: dict[str, np.ndarray]      # topic key -> message indices in file order
    stamps: dict[str, np.ndarray]     # topic key -> header stamps [ns] of those messages
    origin: int                       # earliest log time [ns]
    dt: float = 0.0                   # the step grid (set by `episode.resolve_timing`): dt [s],
    step_ns: int = 0                  # dt [ns],
    n_steps: int = 0                  # N

    def of(self, key: str) -> np.ndarray:
        return self.index.get(key, NO_MESSAGES)


@dataclass
class PerStep:
    """The parsed messages of one per-step topic."""

    values: dict[int, Any]            # step k -> parsed value (a repeated step keeps the last)
    recv_ns: np.ndarray               # (N+1,) receive time relative to the origin; NaN: none
    off_grid: int                     # messages off the step grid or outside the topic's steps


def open_bag(path: str | Path, allow_truncated: bool) -> tuple[RawBag, str]:
    """The raw bag and the name errors use; refuses truncated (unless allowed) and empty bags."""
    raw = read_raw(path)
    name = str(raw.path if Path(path).is_file() else Path(path))
    if not raw.complete and not allow_truncated:
        raise BagError(f"{name}: truncated bag: " + "; ".join(raw.notes) +
                       ". Analyse what was recovered with --allow-truncated")
    if not len(raw):
        raise BagError(f"{name}: no messages" + (" recovered: " + "; ".join(raw.notes) if raw.notes else "")
                       + "; nothing to analyse")
    return raw, name


def group_by_topic(raw: RawBag, namespace: str) -> tuple[dict[str, np.ndarray], list[str]]:
    """Message indices per contract topic key (file order), and the topics that are ignored:
    outside the contract, or recorded with another type than the contract's."""
    keys: dict[int, str] = {}
    ignored: set[str] = set()
    for cid in np.unique(raw.conn_ids).tolist():
        c = raw.connections[cid]
        key = T.key_of(c.topic, namespace)
        if key is None:
            ignored.add(c.topic)
        elif c.msgtype and c.msgtype != T.BY_NAME[key].type_name:
            ignored.add(f"{c.topic} ({c.msgtype})")
        else:
            keys[cid] = key
    index: dict[str, np.ndarray] = {}
    for key in sorted(set(keys.values())):
        cids = [cid for cid, k in keys.items() if k == key]
        index[key] = np.flatnonzero(np.isin(raw.conn_ids, cids))
    return index, sorted(ignored)


def cdr_string(data: bytes) -> str:
    """The text of a serialized std_msgs/String (CDR: 4-byte header, uint32 length with the
    terminating NUL, then the text): the scenario topic's payload."""
    (n,) = struct.unpack_from("<I", data, 4)
    return data[8:8 + n - 1].decode()


def cdr_stamp_ns(data: bytes) -> int | None:
    """Stamp [ns] of a serialized message that starts with a builtin_interfaces/Time (after the
    4-byte CDR encapsulation: int32 sec, uint32 nanosec); None for one too short to hold it."""
    if len(data) < 12:
        return None
    sec, nsec = _STAMP(data, 4)
    return sec * 1_000_000_000 + nsec


def header_stamps(raw: RawBag, idx: np.ndarray) -> np.ndarray:
    """Stamps [ns] (`cdr_stamp_ns`) of the messages `idx`; 0 for a message too short to hold one."""
    out = np.zeros(len(idx), dtype=np.int64)
    for j, i in enumerate(idx.tolist()):
        out[j] = cdr_stamp_ns(raw.data[i]) or 0
    return out


def index_messages(raw: RawBag, namespace: str) -> tuple[Messages, list[str]]:
    """The contract messages of `raw` in `namespace` (with their header stamps), and the
    ignored topics."""
    index, ignored = group_by_topic(raw, namespace)
    stamps = {k: header_stamps(raw, index[k]) for k in STAMPED_TOPICS if k in index}
    return Messages(raw, Decoder(raw), index, stamps, origin=int(raw.log_times.min())), ignored


def read_scenario(msgs: Messages, notes: list[str]) -> tuple[Scenario, PlantInfo, dict[str, list[float]]] | None:
    """(scenario, plant description, perturbation) of the plant from the last readable scenario
    message (sep 0.1's flat slab JSON too; perturbation {} when the message carries none, as for
    every unperturbed plant), or None. All three come from the same message; one that does not
    parse is noted once as '<topic> message unreadable (<reason>)'."""
    found = None
    for i in msgs.of(T.SCENARIO).tolist():
        msg = msgs.decode(i, T.STRING)
        if msg is None:
            continue
        try:
            found = parse_scenario_message(msg.data)
        except (ScenarioError, ValueError) as exc:
            notes.append(f"{msgs.decode.topic(i)} message unreadable ({exc})")
    return found


def read_per_step(msgs: Messages, key: str, parse: Callable[[Any], Any]) -> PerStep:
    """Decode and parse every message of a per-step topic at its step k (k = 0..N, or 0..N-1
    for the inputs). Messages off the step grid are counted; a message `parse` refuses
    (ValueError) is reported through the decoder."""
    rows = msgs.n_steps if key in INPUT_TOPICS else msgs.n_steps + 1
    idx = msgs.of(key)
    ks = T.steps_of_stamps(msgs.stamps.get(key, NO_MESSAGES), msgs.step_ns)
    recv = np.full(msgs.n_steps + 1, np.nan)
    values: dict[int, Any] = {}
    off_grid = 0
    for i, k in zip(idx.tolist(), ks.tolist()):
        if not 0 <= k < rows:
            off_grid += 1
            continue
        msg = msgs.decode(i, T.BY_NAME[key].type_name)
        if msg is None:
            continue
        try:
            values[k] = parse(msg)
        except ValueError as exc:
            msgs.decode.reject(i, str(exc))
            continue
        recv[k] = float(msgs.raw.log_times[i] - msgs.origin)   # exact: relative times stay below 2**53 ns
    return PerStep(values, recv, off_grid)


# ------------------------------------------------------------------ payload parsers
def joint_values(msg: Any, attr: str, n: int | None) -> np.ndarray:
    """The `attr` array (position / effort) of a JointState; `n` values when n is given."""
    v = np.asarray(getattr(msg, attr), dtype=float)
    if n is not None and v.size != n:
        raise ValueError(f"{v.size} {attr} values, expected {n}")
    return v


def cloud_points(msg: Any, n: int | None) -> tuple[str, np.ndarray]:
    """(field name, (width, 5) rows x, y, z, value, std) of a contract PointCloud2 (any field
    name; `n` points when n is given)."""
    names = [f.name for f in msg.fields]
    data = np.asarray(msg.data, dtype=np.uint8)
    T.check_cloud_layout(names, [f.datatype for f in msg.fields], [f.offset for f in msg.fields],
                         msg.point_step, msg.height, bool(msg.is_bigendian), msg.width, data.size)
    if n is not None and msg.width != n:
        raise ValueError(f"cloud with {msg.width} points, expected {n}")
    return names[3], T.parse_cloud_payload(data.tobytes(), msg.width)


def image_pixels(msg: Any) -> np.ndarray:
    """(height, width) float32 pixels of a 32FC1 sensor_msgs/Image (rows may be padded: `step`)."""
    if msg.encoding != "32FC1":
        raise ValueError(f"image encoding {msg.encoding!r}, expected 32FC1")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < 4 * w or data.size != h * step:
        raise ValueError(f"image data of {data.size} bytes does not fit {h} rows of step {step} for width {w}")
    dtype = ">f4" if msg.is_bigendian else "<f4"
    return data.reshape(h, step)[:, :4 * w].copy().view(dtype).astype(np.float32)


def read_diagnostics(msgs: Messages, notes: list[str]) -> tuple[dict[str, dict[str, str]], dict[str, int]]:
    """Last key/values per diagnostic status name, and deadline_misses / rejected_messages (and
    the MPC's mpc_qp_steps / mpc_fallbacks) summed over the statuses (nodes) that report them."""
    diags: dict[str, dict[str, str]] = {}
    for i in msgs.of(T.DIAGNOSTICS).tolist():
        msg = msgs.decode(i, T.DIAGNOSTIC_ARRAY)
        if msg is None:
            continue
        for st in msg.status:
            d = diags.setdefault(st.name or st.hardware_id or "?", {})
            for kv in st.values:
                d[kv.key] = kv.value
    totals: dict[str, int] = {}
    for key in ("deadline_misses", "rejected_messages", "mpc_qp_steps", "mpc_fallbacks"):
        vals = []
        for d in diags.values():
            if key in d:
                try:
                    vals.append(int(float(d[key])))
                except ValueError:
                    notes.append(f"diagnostics {key} = {d[key]!r} is not a number")
        if vals:
            totals[key] = int(sum(vals))
    return diags, totals
