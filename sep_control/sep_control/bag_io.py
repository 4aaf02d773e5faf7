"""Reading recorded rosbag2 bags of the sep topic graph into numpy arrays (pure: no rclpy).

A bag is a rosbag2 directory (``metadata.yaml`` plus one ``.mcap`` or ``.db3`` file), a
directory holding such a storage file without ``metadata.yaml`` (a recording cut off by a
crash), or a lone ``.mcap`` / ``.db3`` file. The storage file is parsed directly:

* MCAP: a sequential record scan (no summary section, no index needed), so a file without
  footer (SIGKILL, power loss) is read up to its last complete chunk; a record that runs past
  the end of the file marks the bag as *truncated* and what came before is kept.
* sqlite3: the rosbag2 schema (``topics`` and ``messages`` tables) through the sqlite3 module.

`read_episode` turns the contract topics (DESIGN.md §4) into an `Episode`: per-step arrays
indexed by the step k = header.stamp / dt, per-topic receive times (the bag's log time, i.e.
the recorder's clock) and header stamps, the last diagnostics values and the plant's scenario.
Missing topics are listed in ``Episode.missing``; topics outside the contract are ignored.
A corrupt bag raises `BagError` naming the file and what could be recovered; a truncated
one does too unless ``allow_truncated=True``.
"""
from __future__ import annotations

import math
import sqlite3
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from sep_plant.scenario import Scenario, ScenarioError

#: contract topics (DESIGN.md §4): name relative to the namespace (a leading '/' means
#: absolute), ROS 2 type, and whether the publisher offers transient_local durability.
CONTRACT: tuple[tuple[str, str, bool], ...] = (
    ("/clock", "rosgraph_msgs/msg/Clock", False),
    ("measurements", "sensor_msgs/msg/JointState", False),
    ("heat_command", "sensor_msgs/msg/JointState", False),
    ("heat_applied", "sensor_msgs/msg/JointState", False),
    ("state_estimate", "sensor_msgs/msg/JointState", False),
    ("field_estimate", "sensor_msgs/msg/PointCloud2", False),
    ("field", "sensor_msgs/msg/PointCloud2", False),
    ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", False),
    ("scenario", "std_msgs/msg/String", True),
)

#: per-step JointState topics and the array they fill
STEP_TOPICS = ("measurements", "heat_command", "heat_applied", "state_estimate", "field", "field_estimate")

POINT_FIELDS = ("x", "y", "z", "temperature", "temperature_std")


class BagError(RuntimeError):
    """The bag cannot be read (corrupt, truncated, not a bag); the message names the file and
    what was recovered."""


def topic_name(rel: str, namespace: str = "slab") -> str:
    """Fully qualified topic name of a contract topic."""
    if rel.startswith("/"):
        return rel
    ns = namespace.strip("/")
    return f"/{ns}/{rel}" if ns else f"/{rel}"


def contract_topics(namespace: str = "slab") -> dict[str, tuple[str, bool]]:
    """{fully qualified topic: (msgtype, transient_local)} of the contract."""
    return {topic_name(rel, namespace): (typ, tl) for rel, typ, tl in CONTRACT}


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
        except Exception as exc:  # noqa: BLE001 - any parse problem: fall back to a file scan
            storage, files = "", []
            bad_meta = f"unreadable metadata.yaml ({type(exc).__name__})"
        else:
            bad_meta = ""
        if len(files) > 1:
            raise BagError(f"{p}: split bags ({len(files)} files) are not supported; merge them first")
        if files and (p / files[0]).is_file():
            f = p / files[0]
            if f.suffix in (".zstd", ".lz4"):
                raise BagError(f"{f}: file-compressed bags are not supported; record without compression")
            return f, ("sqlite3" if f.suffix == ".db3" or storage == "sqlite3" else "mcap"), True
        if bad_meta:
            pass  # fall through to the directory scan below
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
@dataclass
class TopicTimes:
    """Per-message receive times (bag log time, ns, recorder clock) and header stamps (ns)."""

    recv_ns: np.ndarray
    stamp_ns: np.ndarray


@dataclass
class Episode:
    """One recorded episode as arrays; step k rows are NaN where the bag has no message."""

    path: Path
    scenario: Scenario | None
    dt: float
    n_steps: int
    y: np.ndarray             # (N+1, n_y)  measurements
    u_cmd: np.ndarray         # (N, n_u)    heat_command
    u: np.ndarray             # (N, n_u)    heat_applied
    a_hat: np.ndarray         # (N+1, n_a)  state_estimate (NaN padded; n_a = longest estimate)
    a_dim: np.ndarray         # (N+1,) int  length of the estimate at step k (-1: none)
    T: np.ndarray             # (N+1, n_x)  true field
    T_hat: np.ndarray         # (N+1, n_x)  field estimate
    T_std: np.ndarray         # (N+1, n_x)  field estimate std
    x: np.ndarray | None      # (n_x,)      node positions from the point clouds
    step_recv_ns: dict[str, np.ndarray]   # topic key -> (N+1,) receive time per step, ns since
                                          # recv_origin_ns (float, exact; NaN: no message)
    times: dict[str, TopicTimes]          # topic key -> all messages' receive times and stamps
    diagnostics: dict[str, dict[str, str]]  # status name -> last key/values
    diag_totals: dict[str, int]           # deadline_misses, rejected_messages summed over statuses
    counts: dict[str, int]                # messages per contract topic key
    missing: list[str]                    # contract topics with no message
    ignored_topics: list[str]             # topics outside the contract
    recv_origin_ns: int = 0               # earliest log time in the bag (recorder clock)
    complete: bool = True                 # False: truncated bag (only with allow_truncated)
    notes: list[str] = field(default_factory=list)
    scenario_source: str = "bag"          # 'bag', 'argument' or 'inferred'

    def steps_with(self, key: str) -> np.ndarray:
        """Steps k that have a message on topic `key`."""
        return np.flatnonzero(np.isfinite(self.step_recv_ns[key]))

    @property
    def last_step(self) -> int:
        """Last step with a measurement or field (-1 when none)."""
        ks = [self.steps_with(k) for k in ("measurements", "field") if k in self.step_recv_ns]
        ks = [k[-1] for k in ks if k.size]
        return int(max(ks)) if ks else -1


def _key(topic: str, namespace: str) -> str | None:
    for rel, _typ, _tl in CONTRACT:
        if topic == topic_name(rel, namespace):
            return rel.strip("/")
    return None


_STAMP = struct.Struct("<iI").unpack_from


def read_episode(path: str | Path, scenario: Scenario | None = None, *, namespace: str = "slab",
                 allow_truncated: bool = False) -> Episode:
    """Read a bag of one episode. `scenario` is used when the bag carries none (else the bag's
    own scenario wins; compare with the design in `analyze`)."""
    from rosbags.typesys import Stores, get_typestore

    raw = read_raw(path)
    name = str(raw.path if Path(path).is_file() else Path(path))
    if not raw.complete and not allow_truncated:
        raise BagError(f"{name}: truncated bag: " + "; ".join(raw.notes) +
                       ". Analyse what was recovered with --allow-truncated")
    if not len(raw):
        raise BagError(f"{name}: no messages" + (" recovered: " + "; ".join(raw.notes) if raw.notes else "")
                       + "; nothing to analyse")
    ts = get_typestore(Stores.ROS2_JAZZY)
    contract = contract_topics(namespace)
    by_key: dict[str, list[int]] = {}
    ignored = set()
    for i, cid in enumerate(raw.conn_ids.tolist()):
        c = raw.connections[cid]
        key = _key(c.topic, namespace)
        if key is None or (c.msgtype and c.msgtype != contract[c.topic][0]):
            ignored.add(c.topic if key is None else f"{c.topic} ({c.msgtype})")
            continue
        by_key.setdefault(key, []).append(i)
    notes = list(raw.notes)
    bad: list[str] = []

    def decode(i: int, msgtype: str):
        try:
            return ts.deserialize_cdr(raw.data[i], msgtype)
        except Exception as exc:  # noqa: BLE001 - report, never a traceback
            bad.append(f"{raw.connections[int(raw.conn_ids[i])].topic} message {i} ({type(exc).__name__})")
            return None

    # scenario (transient_local, once; take the last valid one)
    scen, source = None, "bag"
    for i in by_key.get("scenario", []):
        msg = decode(i, "std_msgs/msg/String")
        if msg is None:
            continue
        try:
            scen = Scenario.from_json(msg.data)
        except (ScenarioError, ValueError) as exc:
            notes.append(f"slab/scenario message unreadable ({exc})")
    if scen is None and scenario is not None:
        scen, source = scenario, "argument"

    # stamps of the per-step topics (parsed from the CDR header: int32 sec, uint32 nanosec)
    stamps: dict[str, np.ndarray] = {}
    for key in STEP_TOPICS + ("clock", "diagnostics"):
        idx = by_key.get(key, [])
        st = np.empty(len(idx), dtype=np.int64)
        for j, i in enumerate(idx):
            d = raw.data[i]
            sec, nsec = _STAMP(d, 4) if len(d) >= 12 else (0, 0)
            st[j] = sec * 1_000_000_000 + nsec
        stamps[key] = st
    if scen is not None:
        dt, n_steps = scen.dt, scen.n_steps
    else:  # infer the step from the stamps
        st = np.unique(np.concatenate([stamps[k] for k in ("measurements", "field") if stamps[k].size] or
                                      [np.zeros(0, np.int64)]))
        diffs = np.diff(st)
        diffs = diffs[diffs > 0]
        if not diffs.size:
            raise BagError(f"{name}: no scenario and too few stamped measurements to infer the time step; "
                           "pass the design file (--design)")
        dt = float(diffs.min()) * 1e-9
        n_steps = int(round(st[-1] / diffs.min()))
        source = "inferred"
        notes.append(f"no scenario in the bag: dt = {dt:g} s and N = {n_steps} inferred from stamps")
    dt_ns = int(round(dt * 1e9))
    N = n_steps

    def step_of(st: np.ndarray) -> np.ndarray:
        k = np.rint(st / dt_ns).astype(np.int64)
        off = np.abs(st - k * dt_ns) > max(1, dt_ns // 1000)
        k[off] = -1
        return k

    origin = int(raw.log_times.min()) if raw.log_times.size else 0
    recv = raw.log_times
    times = {key: TopicTimes(recv[np.asarray(by_key.get(key, []), dtype=np.int64)], stamps.get(key, np.zeros(0, np.int64)))
             for key in by_key if key != "scenario"}
    step_recv = {}
    off_grid = 0

    def fill(key: str, rows: int, getter) -> tuple[np.ndarray | None, int]:
        nonlocal off_grid
        idx = by_key.get(key, [])
        ks = step_of(stamps[key])
        sr = np.full(N + 1, np.nan)
        vals: dict[int, np.ndarray] = {}
        for j, i in enumerate(idx):
            k = int(ks[j])
            if not 0 <= k < rows:
                off_grid += 1
                continue
            msg = decode(i, contract[raw.connections[int(raw.conn_ids[i])].topic][0])
            if msg is None:
                continue
            v = getter(msg)
            if v is None:
                continue
            vals[k] = v          # a repeated step keeps the last message
            sr[k] = float(recv[i] - origin)   # exact: relative times stay below 2**53 ns
        step_recv[key] = sr
        if not vals:
            return None, 0
        width = max(len(v) if v.ndim == 1 else v.shape[0] for v in vals.values())
        return vals, width

    def stack(vals, rows, width, shape_tail=()):
        out = np.full((rows, width) + shape_tail, np.nan)
        if vals:
            for k, v in vals.items():
                out[k, :len(v)] = v
        return out

    def js(attr):
        return lambda m: np.asarray(getattr(m, attr), dtype=float)

    def cloud(m):
        names = [f.name for f in m.fields]
        if m.point_step != 40 or names[:5] != list(POINT_FIELDS) or any(f.datatype != 8 for f in m.fields[:5]) \
                or m.is_bigendian or m.height != 1:
            bad.append(f"point cloud with unexpected layout (fields {names}, point_step {m.point_step})")
            return None
        a = np.frombuffer(np.asarray(m.data, dtype=np.uint8).tobytes(), dtype="<f8")
        if a.size != 5 * m.width:
            bad.append(f"point cloud data size {a.size * 8} != width {m.width} x 40")
            return None
        return a.reshape(m.width, 5)

    y_v, ny = fill("measurements", N + 1, js("position"))
    uc_v, nu1 = fill("heat_command", N, js("effort"))
    u_v, nu2 = fill("heat_applied", N, js("effort"))
    a_v, na = fill("state_estimate", N + 1, js("position"))
    f_v, nx1 = fill("field", N + 1, cloud)
    fe_v, nx2 = fill("field_estimate", N + 1, cloud)
    n_y = scen.n_y if scen else ny
    n_u = scen.n_u if scen else max(nu1, nu2)
    n_x = scen.n_x if scen else max(nx1, nx2)
    y = stack(y_v, N + 1, n_y)
    u_cmd = stack(uc_v, N, n_u)
    u = stack(u_v, N, n_u)
    a_hat = stack(a_v, N + 1, na)
    a_dim = np.full(N + 1, -1, dtype=np.int64)
    for k, v in (a_v or {}).items():
        a_dim[k] = len(v)
    T = np.full((N + 1, n_x), np.nan)
    T_hat = np.full((N + 1, n_x), np.nan)
    T_std = np.full((N + 1, n_x), np.nan)
    xs = None
    for vals, tgt, std in ((f_v, T, None), (fe_v, T_hat, T_std)):
        for k, pts in (vals or {}).items():
            if pts.shape[0] != n_x:
                bad.append(f"field with {pts.shape[0]} points at step {k}, expected {n_x}")
                continue
            tgt[k] = pts[:, 3]
            if std is not None:
                std[k] = pts[:, 4]
            if xs is None:
                xs = pts[:, 0].copy()
    if off_grid:
        notes.append(f"{off_grid} messages with stamps off the step grid or outside k = 0..N ignored")

    # diagnostics: last value per status name and key
    diags: dict[str, dict[str, str]] = {}
    for i in by_key.get("diagnostics", []):
        msg = decode(i, "diagnostic_msgs/msg/DiagnosticArray")
        if msg is None:
            continue
        for st in msg.status:
            d = diags.setdefault(st.name or st.hardware_id or "?", {})
            for kv in st.values:
                d[kv.key] = kv.value
    totals = {}
    for key in ("deadline_misses", "rejected_messages"):
        vals = []
        for d in diags.values():
            if key in d:
                try:
                    vals.append(int(float(d[key])))
                except ValueError:
                    notes.append(f"diagnostics {key} = {d[key]!r} is not a number")
        if vals:
            totals[key] = int(sum(vals))
    if bad:
        notes.append(f"{len(bad)} undecodable or malformed messages skipped (first: {bad[0]})")
    counts = {rel.strip("/"): len(by_key.get(rel.strip("/"), [])) for rel, _t, _l in CONTRACT}
    missing = [topic_name(rel, namespace) for rel, _t, _l in CONTRACT if not counts[rel.strip("/")]]
    return Episode(path=Path(path), scenario=scen, dt=dt, n_steps=N, y=y, u_cmd=u_cmd, u=u, a_hat=a_hat,
                   a_dim=a_dim, T=T, T_hat=T_hat, T_std=T_std, x=xs, step_recv_ns=step_recv, times=times,
                   diagnostics=diags, diag_totals=totals, counts=counts, missing=missing,
                   ignored_topics=sorted(ignored), recv_origin_ns=origin, complete=raw.complete, notes=notes,
                   scenario_source=source)


def field_points(T: np.ndarray, std: np.ndarray | None, x: np.ndarray) -> np.ndarray:
    """PointCloud2 payload of the contract layout: (n_x, 5) float64 x, y=0, z=0, T, std."""
    pts = np.zeros((len(x), 5))
    pts[:, 0] = x
    pts[:, 3] = T
    if std is not None:
        pts[:, 4] = std
    return np.ascontiguousarray(pts, dtype="<f8")


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
