"""Raw rosbag2 storage reading (pure: no rclpy): connections and serialized messages.

A bag is a rosbag2 directory (``metadata.yaml`` plus one ``.mcap`` or ``.db3`` file), a
directory holding such a storage file without ``metadata.yaml`` (a recording cut off by a
crash), or a lone ``.mcap`` / ``.db3`` file. The storage file is parsed directly:

* MCAP: a sequential record scan (no summary section, no index needed), so a file without
  footer (SIGKILL, power loss) is read up to its last complete chunk; a record that runs past
  the end of the file marks the bag as *truncated* (``RawBag.complete`` False) and what came
  before is kept.
* sqlite3: the rosbag2 schema (``topics`` and ``messages`` tables) through the sqlite3 module;
  a database without its ``metadata`` row was not closed and is reported as truncated.

Structural corruption raises `BagError` naming the file and how many messages were readable.
Decoding the contract topics into arrays is `sep_control.bags.reader`.
"""
from __future__ import annotations

import sqlite3
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np


class BagError(RuntimeError):
    """The bag cannot be read (corrupt, truncated, not a bag); the message names the file and
    what was recovered."""


@dataclass
class RawConnection:
    """One rosbag2 connection (topic, type, message definition, offered QoS metadata)."""

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


# ------------------------------------------------------------------------ locating
def _listed_storage(p: Path) -> tuple[Path, str] | None:
    """(storage file, storage id) named by a directory's metadata.yaml, or None when it names
    none that exists (or cannot be parsed: the caller then scans the directory)."""
    import yaml

    try:
        info = yaml.safe_load((p / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier", "")).lower()
        files = list(info.get("relative_file_paths") or [])
    except Exception:  # noqa: BLE001 - any parse problem: fall back to the directory scan
        return None
    if len(files) > 1:
        raise BagError(f"{p}: split bags ({len(files)} files) are not supported; merge them first")
    if not files or not (p / files[0]).is_file():
        return None
    f = p / files[0]
    if f.suffix in (".zstd", ".lz4"):
        raise BagError(f"{f}: file-compressed bags are not supported; record without compression")
    return f, ("sqlite3" if f.suffix == ".db3" or storage == "sqlite3" else "mcap")


def locate_storage(path: str | Path) -> tuple[Path, str, bool]:
    """(storage file, storage id 'mcap' or 'sqlite3', metadata.yaml present) of a bag path.

    Raises
    ------
    BagError
        The path does not exist or is not a bag (no storage file, several, split or
        file-compressed bags).
    """
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag (expected a rosbag2 directory or a .mcap/.db3 file)")
    if p.is_file():
        if p.suffix in (".mcap", ".db3"):
            return p, ("mcap" if p.suffix == ".mcap" else "sqlite3"), (p.parent / "metadata.yaml").is_file()
        if p.name == "metadata.yaml":
            return locate_storage(p.parent)
        raise BagError(f"{p}: not a bag (expected a rosbag2 directory, a .mcap or a .db3 file)")
    meta = p / "metadata.yaml"
    if meta.is_file():
        listed = _listed_storage(p)
        if listed is not None:
            return (*listed, True)
    found = sorted(p.glob("*.mcap")) + sorted(p.glob("*.db3"))
    if not found:
        raise BagError(f"{p}: no .mcap or .db3 file in this directory: not a bag")
    if len(found) > 1:
        raise BagError(f"{p}: several storage files ({', '.join(f.name for f in found)}); "
                       "split bags are not supported")
    f = found[0]
    return f, ("mcap" if f.suffix == ".mcap" else "sqlite3"), meta.is_file()


def read_raw(path: str | Path, topics: Iterable[str] | None = None) -> RawBag:
    """All messages of a bag, in file order.

    Parameters
    ----------
    path : str or Path
        A rosbag2 directory, or a lone ``.mcap`` / ``.db3`` file.
    topics : iterable of str, optional
        Fully qualified topic names to keep (default: every topic).

    Returns
    -------
    RawBag
        Truncation is reported (``complete`` False, a note), not raised.

    Raises
    ------
    BagError
        Not a bag, or structural corruption.
    """
    f, storage, has_meta = locate_storage(path)
    want = set(topics) if topics is not None else None
    raw = read_mcap(f, want) if storage == "mcap" else read_sqlite3(f, want)
    raw.has_metadata = has_meta
    if not has_meta and Path(path).is_dir():
        raw.notes.append("metadata.yaml missing (recording not closed cleanly)")
    return raw


# ---------------------------------------------------------------------------- MCAP
_MAGIC = b"\x89MCAP0\r\n"
_U16 = struct.Struct("<H").unpack_from
_U32 = struct.Struct("<I").unpack_from
_U64 = struct.Struct("<Q").unpack_from
_OP_LEN = struct.Struct("<BQ").unpack_from
_MSG_HDR = struct.Struct("<HIQQ").unpack_from
_CHUNK_HDR = struct.Struct("<QQQI").unpack_from
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06


class _Cut(Exception):
    """A record runs past the end of its buffer."""


def _str(buf, off: int) -> tuple[str, int]:
    """An MCAP string (uint32 length, UTF-8 bytes) at `off`, and the offset after it."""
    (n,) = _U32(buf, off)
    end = off + 4 + n
    if end > len(buf):
        raise _Cut
    return bytes(buf[off + 4:end]).decode("utf-8", "replace"), end


def _decompress(data: bytes, compression: str) -> bytes:
    """A chunk's records: zstd (Python 3.14's compression.zstd or backports.zstd), lz4 or none."""
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


def _records(b, off: int, end: int, top: bool) -> Iterator[tuple[int, int, int]]:
    """(opcode, body start, body end) of the records in b[off:end]. At the top level a record
    cut by the end of the file raises `_Cut` (truncation); inside a chunk it is corruption."""
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


class _McapScan:
    """One sequential scan of an MCAP file: a handler per record type fills the schemas, the
    connections and the kept messages; `good_end` / `kept` mark the last complete top-level
    record, so a cut inside a chunk drops the whole chunk."""

    def __init__(self, want: set[str] | None):
        self.want = want
        self.schemas: dict[int, tuple[str, str]] = {}
        self.conns: dict[int, RawConnection] = {}
        self.ids: list[int] = []
        self.times: list[int] = []
        self.data: list[bytes] = []
        self.complete = False
        self.good_end = 8
        self.kept = 0
        self.handlers = {_OP_SCHEMA: self.on_schema, _OP_CHANNEL: self.on_channel, _OP_MESSAGE: self.on_message}

    def run(self, buf) -> None:
        """Scan the top-level records after the magic, up to the footer or the end."""
        for op, s, e in _records(buf, 8, len(buf), True):
            if op == _OP_CHUNK:
                self.on_chunk(buf, s, e)
            else:
                self.handle(buf, op, s, e)
            self.good_end, self.kept = e, len(self.data)
            if op == _OP_FOOTER:          # the file is complete
                self.complete = True
                return

    def handle(self, b, op: int, s: int, e: int) -> None:
        h = self.handlers.get(op)
        if h is not None:
            h(b, s, e)

    def on_chunk(self, b, s: int, e: int) -> None:
        """Chunk header (start/end time, uncompressed size, CRC, compression), then records."""
        _start, _end, usize, crc = _CHUNK_HDR(b, s)
        comp, o = _str(b, s + 28)
        (clen,) = _U64(b, o)
        if o + 8 + clen > e:
            raise ValueError("chunk length exceeds its record")
        inner = _decompress(bytes(b[o + 8:o + 8 + clen]), comp)
        if len(inner) != usize:
            raise ValueError("chunk size mismatch")
        if crc and zlib.crc32(inner) != crc:
            raise ValueError("chunk CRC mismatch")
        for op, is_, ie in _records(inner, 0, len(inner), False):
            self.handle(inner, op, is_, ie)

    def on_schema(self, b, s: int, e: int) -> None:
        (sid,) = _U16(b, s)
        name, o = _str(b, s + 2)
        _enc, o = _str(b, o)
        (dl,) = _U32(b, o)
        self.schemas[sid] = (name, bytes(b[o + 4:o + 4 + dl]).decode("utf-8", "replace"))

    def on_channel(self, b, s: int, e: int) -> None:
        cid, sid = struct.unpack_from("<HH", b, s)
        topic, o = _str(b, s + 4)
        enc, o = _str(b, o)
        (ml,) = _U32(b, o)
        meta, o, mend = {}, o + 4, o + 4 + ml
        while o < mend:
            key, o = _str(b, o)
            meta[key], o = _str(b, o)
        name, msgdef = self.schemas.get(sid, ("", ""))
        self.conns[cid] = RawConnection(cid, topic, name, msgdef, enc, meta)

    def on_message(self, b, s: int, e: int) -> None:
        cid, _seq, log_time, _pub = _MSG_HDR(b, s)
        c = self.conns.get(cid)
        if c is not None and (self.want is None or c.topic in self.want):
            self.ids.append(cid)
            self.times.append(log_time)
            self.data.append(bytes(b[s + 22:e]))


def _load_mcap(f: Path):
    """The file's bytes; an unreadable, empty or non-MCAP file raises `BagError`."""
    try:
        buf = memoryview(f.read_bytes())
    except OSError as exc:
        raise BagError(f"{f}: cannot read ({exc})") from None
    if len(buf) == 0:
        raise BagError(f"{f}: empty file (recording produced no data); nothing recovered")
    if bytes(buf[:8]) != _MAGIC:
        raise BagError(f"{f}: not an MCAP file (bad magic); nothing recovered")
    return buf


def read_mcap(f: Path, want: set[str] | None) -> RawBag:
    """The messages of an MCAP file (topics in `want`, or all), up to its last complete
    top-level record when it was cut off."""
    buf = _load_mcap(f)
    n = len(buf)
    scan = _McapScan(want)
    try:
        scan.run(buf)
    except _Cut:
        if n > 16 and bytes(buf[n - 8:]) == _MAGIC:   # a whole file whose records do not fit: corrupt
            raise BagError(f"{f}: corrupt MCAP: a record near byte {scan.good_end} of {n} runs past the end of "
                           f"the file; {scan.kept} messages were readable before it") from None
        # else truncated: keep what was complete
    except (struct.error, ValueError, UnicodeDecodeError, RuntimeError, OSError) as exc:
        raise BagError(f"{f}: corrupt MCAP record near byte {scan.good_end} of {n} ({type(exc).__name__}: "
                       f"{exc}); {scan.kept} messages were readable before it") from None
    # a record cut inside a chunk must not leave half a chunk behind
    k = scan.kept
    raw = RawBag(path=f, storage="mcap", connections=scan.conns, conn_ids=np.asarray(scan.ids[:k], dtype=np.int64),
                 log_times=np.asarray(scan.times[:k], dtype=np.int64), data=scan.data[:k], complete=scan.complete)
    if not raw.complete:
        raw.notes.append(f"MCAP file ends without footer at byte {n} (last complete record ends at byte "
                         f"{scan.good_end}); {k} messages recovered")
    return raw


# -------------------------------------------------------------------------- sqlite3
def _sqlite_connections(con: sqlite3.Connection) -> dict[int, RawConnection]:
    """The topics table (with the message definitions when the schema has them)."""
    rows = con.execute("SELECT id, name, type, offered_qos_profiles FROM topics").fetchall()
    defs = {}
    try:
        defs = {t: d for t, d in con.execute("SELECT topic_type, encoded_message_definition FROM message_definitions")}
    except sqlite3.Error:
        pass
    return {int(i): RawConnection(int(i), name, typ, defs.get(typ, ""), "cdr", {"offered_qos_profiles": q or ""})
            for i, name, typ, q in rows}


def read_sqlite3(f: Path, want: set[str] | None) -> RawBag:
    """The committed messages of a rosbag2 sqlite3 database (topics in `want`, or all)."""
    try:
        con = sqlite3.connect(f"file:{f}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise BagError(f"{f}: cannot open sqlite3 bag ({exc}); nothing recovered") from None
    try:
        conns = _sqlite_connections(con)
        sel = [c.id for c in conns.values() if want is None or c.topic in want]
        msgs = con.execute(
            f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({','.join('?' * len(sel))}) "
            "ORDER BY id", sel).fetchall() if sel else []
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
