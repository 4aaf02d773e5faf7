"""Reading recorded rosbag2 bags of the sep topic graph into numpy arrays (pure: no rclpy).

A bag is a rosbag2 directory (``metadata.yaml`` plus one ``.mcap`` or ``.db3`` file), a
directory holding such a storage file without ``metadata.yaml`` (a recording cut off by a
crash), or a lone ``.mcap`` / ``.db3`` file. The storage file is parsed directly:

* MCAP: a sequential record scan (no summary section, no index needed), so a file without
  footer (SIGKILL, power loss) is read up to its last complete chunk; a record that runs past
  the end of the file marks the bag as *truncated* and what came before is kept.
* sqlite3: the rosbag2 schema (``topics`` and ``messages`` tables) through the sqlite3 module.

`read_episode` turns the contract topics (`sep_plant.topics`, docs/reference/topics.md) of any plant into
an `Episode`: per-step arrays indexed by the step k of header.stamp (`topics.steps_of_stamps`,
one tolerance for the whole product), per-topic receive times (the bag's log time, i.e. the
recorder's clock) and header stamps, the last diagnostics values, and the plant's scenario
and description (`PlantInfo`) from the scenario topic. Point clouds are accepted with any
field name (x, y, z, <field>, <field>_std); the optional 32FC1 image topics of grid plants are
read when present. Missing required topics are listed in ``Episode.missing``; topics outside
the contract are ignored. Bags of sep 0.1 (flat slab scenario JSON) are read too.
A corrupt bag raises `BagError` naming the file and what could be recovered; a truncated one
does too unless ``allow_truncated=True``.
"""
from __future__ import annotations

import functools
import sqlite3
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from sep_plant import topics as T
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario, ScenarioError, parse_scenario_payload


class BagError(RuntimeError):
    """The bag cannot be read (corrupt, truncated, not a bag); the message names the file and
    what was recovered."""


# --------------------------------------------------------------------------- raw bag layer
@dataclass
class RawConnection:
    id: int
    topic: str
    msgtype: str
    msgdef: str = ""
    encoding: str = "cdr"
    metadata: dict[str, str] = field(default_factory=dict)   # MCAP channel metadata (offered QoS)


@dataclass
class RawBag:
    """Connections and messages of one storage file, in file order."""

    path: Path                        # the storage file
    storage: str                      # 'mcap' or 'sqlite3'
    connections: dict[int, RawConnection]
    conn_ids: np.ndarray              # (M,) connection id per message
    log_times: np.ndarray             # (M,) int64 ns
    data: list[bytes]                 # (M,) serialized messages
    complete: bool = True             # False: file ends early (no footer / cut record)
    has_metadata: bool = True         # metadata.yaml present
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.data)


def locate_storage(path: str | Path) -> tuple[Path, str, bool]:
    """(storage file, storage id, metadata.yaml present) of a bag path."""
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag (expected a rosbag2 directory or a .mcap/.db3 file)")
    if p.is_file():
        if p.suffix == ".mcap":
            return p, "mcap", (p.parent / "metadata.yaml").is_file()
        if p.suffix == ".db3":
            return p, "sqlite3", (p.parent / "metadata.yaml").is_file()
        if p.name == "metadata.yaml":
            return locate_storage(p.parent)
        raise BagError(f"{p}: not a bag (expected a rosbag2 directory, a .mcap or a .db3 file)")
    meta = p / "metadata.yaml"
    if meta.is_file():
        import yaml

        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = str(info.get("storage_identifier", "")).lower()
            files = list(info.get("relative_file_paths") or [])
        except Exception:  # noqa: BLE001 - any parse problem: fall back to the directory scan below
            storage, files = "", []
        if len(files) > 1:
            raise BagError(f"{p}: split bags ({len(files)} files) are not supported; merge them first")
        if files and (p / files[0]).is_file():
            f = p / files[0]
            if f.suffix in (".zstd", ".lz4"):
                raise BagError(f"{f}: file-compressed bags are not supported; record without compression")
            return f, ("sqlite3" if f.suffix == ".db3" or storage == "sqlite3" else "mcap"), True
    found = sorted(p.glob("*.mcap")) + sorted(p.glob("*.db3"))
    if not found:
        raise BagError(f"{p}: no .mcap or .db3 file in this directory: not a bag")
    if len(found) > 1:
        raise BagError(f"{p}: several storage files ({', '.join(f.name for f in found)}); "
                       "split bags are not supported")
    f = found[0]
    return f, ("mcap" if f.suffix == ".mcap" else "sqlite3"), meta.is_file()


def read_raw(path: str | Path, topics: Iterable[str] | None = None) -> RawBag:
    """All messages of a bag (only `topics` if given). Truncation is reported, not raised;
    structural corruption raises `BagError`."""
    f, storage, has_meta = locate_storage(path)
    want = set(topics) if topics is not None else None
    raw = _read_mcap(f, want) if storage == "mcap" else _read_sqlite(f, want)
    raw.has_metadata = has_meta
    if not has_meta and Path(path).is_dir():
        raw.notes.append("metadata.yaml missing (recording not closed cleanly)")
    return raw


_MAGIC = b"\x89MCAP0\r\n"
_U16 = struct.Struct("<H").unpack_from
_U32 = struct.Struct("<I").unpack_from
_U64 = struct.Struct("<Q").unpack_from
_OP_LEN = struct.Struct("<BQ").unpack_from
_MSG_HDR = struct.Struct("<HIQQ").unpack_from


class _Cut(Exception):
    """A record runs past the end of its buffer."""


def _str(buf, off: int) -> tuple[str, int]:
    (n,) = _U32(buf, off)
    end = off + 4 + n
    if end > len(buf):
        raise _Cut
    return bytes(buf[off + 4:end]).decode("utf-8", "replace"), end


def _decompress(data: bytes, compression: str, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        try:
            from compression import zstd  # type: ignore[import-not-found]
        except ImportError:
            from backports import zstd  # type: ignore[import-not-found,no-redef]
        return zstd.decompress(data)
    if compression == "lz4":
        import lz4.frame  # type: ignore[import-untyped]

        return lz4.frame.decompress(data)
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _read_mcap(f: Path, want: set[str] | None) -> RawBag:
    try:
        buf = memoryview(f.read_bytes())
    except OSError as exc:
        raise BagError(f"{f}: cannot read ({exc})") from None
    n = len(buf)
    if n == 0:
        raise BagError(f"{f}: empty file (recording produced no data); nothing recovered")
    if bytes(buf[:8]) != _MAGIC:
        raise BagError(f"{f}: not an MCAP file (bad magic); nothing recovered")
    schemas: dict[int, tuple[str, str]] = {}
    conns: dict[int, RawConnection] = {}
    ids: list[int] = []
    times: list[int] = []
    data: list[bytes] = []
    state = {"complete": False}

    def records(b, off: int, end: int, top: bool):
        while off < end:
            if off + 9 > end:
                if not top:
                    raise ValueError("record header overruns its chunk")
                raise _Cut
            op, length = _OP_LEN(b, off)
            if 0x10 < op < 0x80 or op == 0:
                raise ValueError(f"invalid record opcode 0x{op:02x}")
            body = off + 9
            if body + length > end:
                if not top:
                    raise ValueError("record overruns its chunk")
                raise _Cut
            yield op, body, body + length
            off = body + length
            if top and op == 0x02:  # footer: the file is complete
                state["complete"] = True
                return

    def handle(b, op: int, s: int, e: int) -> None:
        if op == 0x05:  # message
            cid, _seq, log_time, _pub = _MSG_HDR(b, s)
            c = conns.get(cid)
            if c is not None and (want is None or c.topic in want):
                ids.append(cid)
                times.append(log_time)
                data.append(bytes(b[s + 22:e]))
        elif op == 0x03:  # schema
            (sid,) = _U16(b, s)
            name, o = _str(b, s + 2)
            enc, o = _str(b, o)
            (dl,) = _U32(b, o)
            schemas[sid] = (name, bytes(b[o + 4:o + 4 + dl]).decode("utf-8", "replace"))
        elif op == 0x04:  # channel
            cid, sid = struct.unpack_from("<HH", b, s)
            topic, o = _str(b, s + 4)
            enc, o = _str(b, o)
            (ml,) = _U32(b, o)
            meta, o, mend = {}, o + 4, o + 4 + ml
            while o < mend:
                key, o = _str(b, o)
                meta[key], o = _str(b, o)
            name, msgdef = schemas.get(sid, ("", ""))
            conns[cid] = RawConnection(cid, topic, name, msgdef, enc, meta)

    off = 8
    good_end = off
    kept_before = 0
    try:
        for op, s, e in records(buf, off, n, True):
            if op == 0x06:  # chunk: header then records
                _start, _end, usize, _crc = struct.unpack_from("<QQQI", buf, s)
                comp, o = _str(buf, s + 28)
                (clen,) = _U64(buf, o)
                if o + 8 + clen > e:
                    raise ValueError("chunk length exceeds its record")
                inner = _decompress(bytes(buf[o + 8:o + 8 + clen]), comp, usize)
                if len(inner) != usize:
                    raise ValueError("chunk size mismatch")
                if _crc and zlib.crc32(inner) != _crc:
                    raise ValueError("chunk CRC mismatch")
                for iop, is_, ie in records(inner, 0, len(inner), False):
                    handle(inner, iop, is_, ie)
            else:
                handle(buf, op, s, e)
            good_end = e
            kept_before = len(data)
    except _Cut:
        if n > 16 and bytes(buf[n - 8:]) == _MAGIC:   # a whole file whose records do not fit: corrupt
            raise BagError(f"{f}: corrupt MCAP: a record near byte {good_end} of {n} runs past the end of the "
                           f"file; {kept_before} messages were readable before it") from None
        # else truncated: keep what was complete
    except (struct.error, ValueError, UnicodeDecodeError, RuntimeError, OSError) as exc:
        raise BagError(f"{f}: corrupt MCAP record near byte {good_end} of {n} ({type(exc).__name__}: {exc}); "
                       f"{kept_before} messages were readable before it") from None
    # a record cut inside a chunk must not leave half a chunk behind
    del ids[kept_before:], times[kept_before:], data[kept_before:]
    raw = RawBag(path=f, storage="mcap", connections=conns, conn_ids=np.asarray(ids, dtype=np.int64),
                 log_times=np.asarray(times, dtype=np.int64), data=data, complete=state["complete"])
    if not raw.complete:
        raw.notes.append(f"MCAP file ends without footer at byte {n} (last complete record ends at byte "
                         f"{good_end}); {len(data)} messages recovered")
    return raw


def _read_sqlite(f: Path, want: set[str] | None) -> RawBag:
    try:
        con = sqlite3.connect(f"file:{f}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise BagError(f"{f}: cannot open sqlite3 bag ({exc}); nothing recovered") from None
    try:
        rows = con.execute("SELECT id, name, type, offered_qos_profiles FROM topics").fetchall()
        defs = {}
        try:
            defs = {t: d for t, d in con.execute(
                "SELECT topic_type, encoded_message_definition FROM message_definitions")}
        except sqlite3.Error:
            pass
        conns = {int(i): RawConnection(int(i), name, typ, defs.get(typ, ""), "cdr", {"offered_qos_profiles": q or ""})
                 for i, name, typ, q in rows}
        sel = [c.id for c in conns.values() if want is None or c.topic in want]
        msgs = con.execute(
            f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({','.join('?' * len(sel))}) "
            "ORDER BY id", sel).fetchall() if sel else []
        complete = True
        try:
            complete = con.execute("SELECT count(*) FROM metadata").fetchone()[0] > 0
        except sqlite3.Error:
            complete = True  # older schema without a metadata table
    except sqlite3.DatabaseError as exc:
        raise BagError(f"{f}: corrupt sqlite3 bag ({exc}); nothing recovered") from None
    finally:
        con.close()
    raw = RawBag(path=f, storage="sqlite3", connections=conns,
                 conn_ids=np.asarray([m[0] for m in msgs], dtype=np.int64),
                 log_times=np.asarray([m[1] for m in msgs], dtype=np.int64),
                 data=[bytes(m[2]) for m in msgs], complete=complete)
    if not complete:
        raw.notes.append(f"sqlite3 bag not closed (no metadata row); {len(msgs)} committed messages recovered")
    return raw


# --------------------------------------------------------------------------- episode layer
#: JointState topics and the array that carries their values
VECTOR_TOPICS = {T.MEASUREMENTS: "position", T.COMMAND: "effort", T.APPLIED_INPUT: "effort",
                 T.STATE_ESTIMATE: "position"}
#: per-step topics with one message per input step k = 0..N-1 (the others have k = 0..N)
INPUT_TOPICS = (T.COMMAND, T.APPLIED_INPUT)
IMAGE_TOPICS = tuple(t.name for t in T.TOPICS if t.type_name == T.IMAGE)
#: topics whose serialized message starts with a stamp (header.stamp, or Clock.clock)
STAMPED_TOPICS = tuple(t.name for t in T.TOPICS if t.per_step) + (T.CLOCK, T.DIAGNOSTICS)

_STAMP = struct.Struct("<iI").unpack_from
_NO_MESSAGES = np.zeros(0, dtype=np.int64)


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

    @property
    def n_field(self) -> int:
        return int(self.F.shape[1])

    def steps_with(self, key: str) -> np.ndarray:
        """Steps k that have a message on topic `key`."""
        return np.flatnonzero(np.isfinite(self.step_recv_ns[key]))

    @property
    def last_step(self) -> int:
        """Last step with a measurement or field (-1 when none)."""
        ks = [self.steps_with(k) for k in (T.MEASUREMENTS, T.FIELD) if k in self.step_recv_ns]
        ks = [k[-1] for k in ks if k.size]
        return int(max(ks)) if ks else -1


class _Decoder:
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
class _Messages:
    """A bag's contract messages: indices per topic key, header stamps, the step grid."""

    raw: RawBag
    decode: _Decoder
    index: dict[str, np.ndarray]      # topic key -> message indices in file order
    stamps: dict[str, np.ndarray]     # topic key -> header stamps [ns] of those messages
    origin: int                       # earliest log time [ns]
    dt: float = 0.0                   # the step grid (set by `resolve_timing`): dt [s],
    step_ns: int = 0                  # dt [ns],
    n_steps: int = 0                  # N

    def of(self, key: str) -> np.ndarray:
        return self.index.get(key, _NO_MESSAGES)


@dataclass
class _PerStep:
    """The parsed messages of one per-step topic."""

    values: dict[int, Any]            # step k -> parsed value (a repeated step keeps the last)
    recv_ns: np.ndarray               # (N+1,) receive time relative to the origin; NaN: none
    off_grid: int                     # messages off the step grid or outside the topic's steps


def _open(path: str | Path, allow_truncated: bool) -> tuple[RawBag, str]:
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


def header_stamps(raw: RawBag, idx: np.ndarray) -> np.ndarray:
    """Stamps [ns] of messages that start with a builtin_interfaces/Time (after the 4-byte CDR
    encapsulation: int32 sec, uint32 nanosec); 0 for a message too short to hold one."""
    out = np.zeros(len(idx), dtype=np.int64)
    for j, i in enumerate(idx.tolist()):
        d = raw.data[i]
        if len(d) >= 12:
            sec, nsec = _STAMP(d, 4)
            out[j] = sec * 1_000_000_000 + nsec
    return out


def read_scenario(msgs: _Messages, notes: list[str]) -> tuple[Scenario, PlantInfo] | None:
    """The plant's scenario and description from the scenario topic (the last readable
    message; sep 0.1's flat slab JSON too), or None."""
    found = None
    for i in msgs.of(T.SCENARIO).tolist():
        msg = msgs.decode(i, T.STRING)
        if msg is None:
            continue
        try:
            found = parse_scenario_payload(msg.data)
        except (ScenarioError, ValueError) as exc:
            notes.append(f"{msgs.decode.topic(i)} message unreadable ({exc})")
    return found


def infer_timing(msgs: _Messages, name: str) -> tuple[float, int]:
    """dt and N of a bag without a scenario, from the stamps of measurements and field clouds:
    dt = the smallest positive stamp difference, N = the last stamp / dt."""
    st = np.unique(np.concatenate([msgs.stamps.get(k, _NO_MESSAGES) for k in (T.MEASUREMENTS, T.FIELD)]))
    diffs = np.diff(st)
    diffs = diffs[diffs > 0]
    if not diffs.size:
        raise BagError(f"{name}: no scenario and too few stamped measurements to infer the time step; "
                       "pass the design file (--design)")
    return float(diffs.min()) * 1e-9, int(round(st[-1] / diffs.min()))


def read_per_step(msgs: _Messages, key: str, parse: Callable[[Any], Any]) -> _PerStep:
    """Decode and parse every message of a per-step topic at its step k (k = 0..N, or 0..N-1
    for the inputs). Messages off the step grid are counted; a message `parse` refuses
    (ValueError) is reported through the decoder."""
    rows = msgs.n_steps if key in INPUT_TOPICS else msgs.n_steps + 1
    idx = msgs.of(key)
    ks = T.steps_of_stamps(msgs.stamps.get(key, _NO_MESSAGES), msgs.step_ns)
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
    return _PerStep(values, recv, off_grid)


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


def read_diagnostics(msgs: _Messages, notes: list[str]) -> tuple[dict[str, dict[str, str]], dict[str, int]]:
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


def _longest(*found: dict[int, np.ndarray]) -> int:
    """Length of the longest recorded vector (a dimension when the plant is not described)."""
    return max((len(v) for vals in found for v in vals.values()), default=0)


def resolve_timing(msgs: _Messages, scenario: Scenario | None, info: PlantInfo | None, name: str,
                   notes: list[str]) -> tuple[Scenario | None, PlantInfo | None, str]:
    """(scenario, plant description, source) of the episode, and its step grid set on `msgs`:
    the bag's scenario topic ('bag'), else the given scenario ('argument'; `info` defaults to
    `scenario.info`, which builds the plant), else dt and N inferred from stamps ('inferred')."""
    found, source = read_scenario(msgs, notes), "bag"
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


def read_vectors(msgs: _Messages, info: PlantInfo | None) -> tuple[dict[str, _PerStep], dict[str, np.ndarray]]:
    """The JointState topics per step, and the Episode arrays y, u_cmd, u, a_hat, a_dim (state
    estimates vary in length: the ROM order grows)."""
    n_y, n_u = (None, None) if info is None else (info.n_y, info.n_u)
    dims = {T.MEASUREMENTS: n_y, T.COMMAND: n_u, T.APPLIED_INPUT: n_u, T.STATE_ESTIMATE: None}
    vec = {key: read_per_step(msgs, key, functools.partial(joint_values, attr=attr, n=dims[key]))
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
                 "a_hat": stack_rows(est, N + 1, max(int(a_dim.max()), 0)), "a_dim": a_dim}


def read_fields(msgs: _Messages, info: PlantInfo | None, notes: list[str]
                ) -> tuple[dict[str, _PerStep], dict[str, Any]]:
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


def read_images(msgs: _Messages) -> dict[str, _PerStep]:
    """The optional 32FC1 image topics that the bag has, per step."""
    return {key: read_per_step(msgs, key, image_pixels) for key in IMAGE_TOPICS if key in msgs.index}


def read_episode(path: str | Path, scenario: Scenario | None = None, info: PlantInfo | None = None, *,
                 namespace: str | None = None, allow_truncated: bool = False) -> Episode:
    """Read a bag of one episode. The bag's own scenario (and plant description) wins; `scenario`
    and `info` (e.g. a design's) are used when the bag carries none (`info` defaults to
    `scenario.info`, which builds the plant); without either, dt and N are inferred from the
    stamps. Compare scenarios in `analyze`. `namespace` None: the bag's own
    (`sep_plant.topics.detect_namespace`; sep 0.1's ``slab`` names are read through
    `sep_plant.topics.LEGACY_TOPICS`)."""
    raw, name = _open(path, allow_truncated)
    if namespace is None:
        namespace = T.detect_namespace({c.topic for c in raw.connections.values()}) or T.NAMESPACE
    notes = list(raw.notes)
    index, ignored = group_by_topic(raw, namespace)
    msgs = _Messages(raw, _Decoder(raw), index,
                     {k: header_stamps(raw, index[k]) for k in STAMPED_TOPICS if k in index},
                     origin=int(raw.log_times.min()))
    scen, info, source = resolve_timing(msgs, scenario, info, name, notes)
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
        path=Path(path), scenario=scen, info=info, dt=msgs.dt, n_steps=msgs.n_steps, **vectors, **fields,
        images={key: p.values for key, p in images.items()},
        step_recv_ns={key: p.recv_ns for key, p in per_step.items()},
        times={key: TopicTimes(raw.log_times[idx], msgs.stamps.get(key, _NO_MESSAGES))
               for key, idx in index.items() if key != T.SCENARIO},
        diagnostics=diags, diag_totals=totals, counts=counts,
        missing=[T.topic_name(t.name, namespace) for t in T.TOPICS
                 if not counts[t.name] and t.name not in T.OPTIONAL],
        ignored_topics=ignored, recv_origin_ns=msgs.origin, complete=raw.complete, notes=notes,
        scenario_source=source)


def repair_bag(path: str | Path, out: str | Path, storage: str = "mcap") -> Path:
    """Rewrite a (possibly truncated) bag as a complete rosbag2 bag at `out` holding every
    message that can be recovered, so that tools needing the summary/metadata.yaml (rosbags'
    AnyReader, ros2 bag) open it. Message bytes and log times are copied unchanged."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.metadata import parse_qos
    from rosbags.typesys import Stores, get_typestore

    raw = read_raw(path)
    ts = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(Path(out), version=9, storage_plugin=plugin) as w:
        conns = {}
        for cid, c in raw.connections.items():
            try:
                qos = parse_qos(c.metadata.get("offered_qos_profiles", "")) if c.metadata.get("offered_qos_profiles") else []
            except Exception:  # noqa: BLE001 - QoS metadata is informative only
                qos = []
            kw = {"typestore": ts} if c.msgtype in ts.fielddefs else {"msgdef": c.msgdef, "rihs01": "RIHS01_" + "0" * 64}
            conns[cid] = w.add_connection(c.topic, c.msgtype, serialization_format=c.encoding or "cdr",
                                          offered_qos_profiles=qos, **kw)
        for cid, t, data in zip(raw.conn_ids.tolist(), raw.log_times.tolist(), raw.data):
            w.write(conns[cid], t, data)
    return Path(out)
