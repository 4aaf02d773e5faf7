"""The recorder's bag writer (pure: no rclpy): serialized messages from a queue into a rosbag2
bag with rosbags' Writer, on a thread of its own, so that subscription callbacks only enqueue.

`BagSink` is fed by `sep_control.ros.record_node` (raw subscriptions: the CDR bytes go into the
bag untouched), one rosbag2 connection per topic with the Jazzy message definition (rosbags
typestore `Stores.ROS2_JAZZY`), serialization ``cdr`` and the QoS profiles the publishers offer.

Crash safety: whenever the queue runs dry and `flush_interval` has passed, the open MCAP chunk
is closed and flushed (sqlite3: the transaction committed), so a bag cut off by SIGKILL keeps
everything up to about the last flush (`sep_control.bags.reader.read_episode(...,
allow_truncated=True)` reads it, `sep_control.bags.repair.repair_bag` completes it).

End of episode: the sink watches the scenario topic (N and dt of the plant) and the
measurements' header stamps; `final_seen` is set when the measurement of step N has arrived (of
the plant's last episode, when the scenario messages announce several: one bag holds them all).
"""
from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable

from sep_control.bags.messages import cdr_stamp_ns, cdr_string
from sep_plant import topics as T

_STOP = object()
_INF_SEC, _INF_NSEC = 2147483647, 4294967295


def rosbags_qos(profile: Any):
    """An rclpy QoSProfile (or any object with its attributes) as a rosbags Qos; the enum values
    coincide, infinite durations become rosbag2's (2147483647 s, 4294967295 ns)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def dur(d):
        ns = getattr(d, "nanoseconds", 0)
        if ns >= 2**63 - 1 or ns < 0:
            return QosTime(_INF_SEC, _INF_NSEC)
        return QosTime(*divmod(int(ns), 1_000_000_000))

    def enum(cls, v, default):
        try:
            return cls(int(v))
        except (ValueError, TypeError):
            return default

    return Qos(enum(QosHistory, profile.history, QosHistory.UNKNOWN), int(profile.depth),
               enum(QosReliability, profile.reliability, QosReliability.UNKNOWN),
               enum(QosDurability, profile.durability, QosDurability.UNKNOWN),
               dur(profile.deadline), dur(profile.lifespan),
               enum(QosLiveliness, profile.liveliness, QosLiveliness.UNKNOWN),
               dur(profile.liveliness_lease_duration), bool(profile.avoid_ros_namespace_conventions))


def flush(writer) -> None:
    """Make what a rosbags Writer wrote so far durable against a crash of this process."""
    st = writer.storage
    chunk = getattr(st, "chunk", None)
    if chunk is not None and hasattr(st, "close_chunk"):      # rosbags McapWriter
        if chunk.msgs:
            st.close_chunk()
        st.bio.flush()
    elif hasattr(st, "conn"):                                 # rosbags Sqlite3Writer
        st.conn.commit()


class BagSink:
    """A rosbags Writer fed from a queue by a writer thread.

    `put` is what subscription callbacks call: one `SimpleQueue.put` (C, lock-free for the
    caller). A topic's connection is created at its first message, with the type in
    ``types[topic]`` (set by the recorder before subscribing) and the QoS profiles returned by
    `qos_lookup(topic)`.

    Parameters
    ----------
    out : str or Path
        Bag directory to create (must not exist).
    storage : {'mcap', 'sqlite3'}
        Storage plugin.
    flush_interval : float
        Seconds between crash-safety flushes while messages flow.
    qos_lookup : callable, optional
        topic -> offered QoS profiles (rclpy QoSProfile); default none.
    namespace : str
        Namespace of the contract topics (the scenario and measurements watched for the end).
    """

    def __init__(self, out: str | Path, storage: str = "mcap", flush_interval: float = 0.1,
                 qos_lookup: Callable[[str], list] | None = None, namespace: str = T.NAMESPACE):
        self.out = Path(out)
        self.storage = storage
        self.flush_interval = flush_interval
        self.qos_lookup = qos_lookup or (lambda topic: [])
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.last_msg: float | None = None    # monotonic time of the last message
        self.final_seen: float | None = None  # monotonic time the final step's measurement arrived
        self.n_steps: int | None = None
        self.last_meas_ns = -1                # latest measurement stamp seen
        self.dt_ns: int | None = None
        self.final_topic = T.topic_name(T.MEASUREMENTS, namespace)
        self.scenario_topic = T.topic_name(T.SCENARIO, namespace)
        self.error: BaseException | None = None
        #: guards `counts` (written by the writer thread, read by the recorder's thread)
        self.lock = threading.Lock()
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._opened = threading.Event()
        self._conns: dict[str, object] = {}
        self._typestore = None
        self._thread = threading.Thread(target=self._run, name="bag-writer", daemon=True)

    # called from subscription callbacks
    def put(self, topic: str, t_ns: int, data: bytes) -> None:
        """Queue one serialized message of `topic` received at `t_ns` (ns, the bag's log time)."""
        self._q.put((topic, t_ns, data))

    def start(self) -> None:
        """Open the bag on the writer thread; raises what opening raised (e.g. `out` exists)."""
        self._thread.start()
        self._opened.wait(30)
        if self.error is not None:
            raise self.error

    def close(self, timeout: float = 30.0) -> bool:
        """Write what is queued, close the bag (summary, metadata.yaml) and end the thread.
        False, with `error` set, when the thread has not ended within `timeout` seconds (the bag
        may then lack its summary: `sep_control.bags.repair.repair_bag` completes it)."""
        self._q.put(_STOP)
        if self._thread.ident is None:
            return True                      # never started
        self._thread.join(timeout)
        if self._thread.is_alive():
            if self.error is None:
                self.error = TimeoutError(f"the bag writer did not finish {self.out} within {timeout:g} s "
                                          f"({self._q.qsize()} messages still queued): the bag may be incomplete")
            return False
        return True

    def counted(self) -> dict[str, int]:
        """A copy of the messages written per topic (taken under `lock`)."""
        with self.lock:
            return dict(self.counts)

    @property
    def total(self) -> int:
        with self.lock:
            return sum(self.counts.values())

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        writer = self._open_writer()
        if writer is None:
            return
        try:
            self._loop(writer)
        except BaseException as exc:  # noqa: BLE001 - keep the bag closable, report at the end
            self.error = exc
        finally:
            self._drain(writer)
            writer.close()           # writes the summary and metadata.yaml

    def _open_writer(self):
        """The open rosbags Writer, or None with `error` set; `start` waits for this."""
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        try:
            self._typestore = get_typestore(Stores.ROS2_JAZZY)
            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer(self.out, version=9, storage_plugin=plugin)
            writer.open()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller of start()
            self.error = exc
            writer = None
        self._opened.set()
        return writer

    def _loop(self, writer) -> None:
        """Write queued messages until `close`; flush when the queue runs dry (at most every
        `flush_interval` seconds)."""
        last_flush = time.monotonic()
        dirty = False
        while True:
            try:
                item = self._q.get(timeout=self.flush_interval)
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            if item is not None:
                self._write(writer, *item)
                dirty = True
            if dirty and self._q.empty() and time.monotonic() - last_flush >= self.flush_interval:
                flush(writer)
                dirty = False
                last_flush = time.monotonic()

    def _write(self, writer, topic: str, t_ns: int, data: bytes) -> None:
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = writer.add_connection(
                topic, self.types[topic], typestore=self._typestore, serialization_format="cdr",
                offered_qos_profiles=self._offered(topic))
        writer.write(conn, t_ns, data)
        now = time.monotonic()
        with self.lock:
            self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_msg = now
        self._observe(topic, data, now)

    def _drain(self, writer) -> None:
        """Write what is still queued on topics that have a connection (nothing after an error)."""
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return
            if item is _STOP or self.error is not None:
                continue
            topic, t_ns, data = item
            if topic in self._conns:
                writer.write(self._conns[topic], t_ns, data)
                with self.lock:
                    self.counts[topic] = self.counts.get(topic, 0) + 1

    def _offered(self, topic: str) -> list:
        try:
            return [rosbags_qos(p) for p in self.qos_lookup(topic)]
        except Exception:  # noqa: BLE001 - QoS metadata is informative only
            return []

    # ------------------------------------------------------------------ end of episode
    def _observe(self, topic: str, data: bytes, now: float) -> None:
        """Track N and dt (scenario topic) and the latest measurement stamp; set `final_seen`."""
        if topic == self.scenario_topic:
            self._note_scenario(data)
        elif topic == self.final_topic and (stamp := cdr_stamp_ns(data)) is not None:
            self.last_meas_ns = max(self.last_meas_ns, stamp)
        # the scenario may arrive after the final measurement (discovery order)
        if self.final_seen is None and self._final_step_recorded():
            self.final_seen = now

    def _note_scenario(self, data: bytes) -> None:
        """N and dt from the scenario topic's payload (`messages.cdr_string`); with an episode
        entry, the end is the last episode's."""
        try:
            from sep_plant.scenario import scenario_message_parts

            scenario, info, _, episode = scenario_message_parts(cdr_string(data))
        except Exception:  # noqa: BLE001 - then only idle/signal/duration stop the recording
            return
        self.n_steps, self.dt_ns = scenario.problem.n_steps, T.dt_ns(info.dt)
        if episode is not None:
            # several episodes in one bag: the end is step N of the plant's last episode (never
            # for a plant that plays until stopped); an episode's measurements start anew
            self.last_meas_ns = -1
            if episode["of"] == 0 or episode["index"] < episode["of"] - 1:
                self.n_steps = None

    def _final_step_recorded(self) -> bool:
        """Whether the measurement of step N (of the recorded scenario) has arrived."""
        if self.n_steps is None or self.dt_ns is None or self.last_meas_ns < 0:
            return False
        k = T.step_of_stamp(self.last_meas_ns, self.dt_ns)
        return k is not None and k >= self.n_steps
