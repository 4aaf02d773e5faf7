"""`record`: record the sep topic graph into a rosbag2 bag (MCAP by default, sqlite3 selectable).

    record --out BAG_DIR [--topics T ...] [--storage mcap|sqlite3] [--namespace slab]
           [--stop-after-idle S] [--no-stop-at-end] [--max-duration S] [--ready-file PATH] [--ros-args ...]

What rosbag2's `ros2 bag record` does, for installs without rosbag2 (PyPI wheels): raw
subscriptions (`raw=True`: the CDR bytes go into the bag untouched, no deserialization),
one rosbag2 connection per topic with the Jazzy message definition (rosbags typestore
`Stores.ROS2_JAZZY`), serialization `cdr`, and the QoS profiles the publishers offer.
Bag timestamps (log time) are receive times in ns (the middleware's reception timestamp,
system clock; the callback time when the middleware gives none).

Not slowing the loop: the subscription callback only appends (topic, time, bytes) to a
queue; a writer thread serializes into the bag. The recorder runs in its own process.

Robustness:
* SIGINT / SIGTERM (Ctrl-C) stop the recording and close the bag cleanly (metadata.yaml).
* The writer flushes the open MCAP chunk (or commits the sqlite3 transaction) whenever the
  queue runs dry and `--flush-interval` (default 0.1 s) has passed, so a bag cut off by a
  crash (SIGKILL) keeps everything up to about the last flush: `analyze --allow-truncated`
  (or `sep_control.bags.bag_io.read_episode(..., allow_truncated=True)`) reads it, and
  `bag_io.repair_bag` rewrites it as a complete bag for other tools.
* Stops by itself when the episode ends: `--final-grace` seconds after the plant's final
  measurement (step N = n_steps of the scenario topic's payload, stamp N dt with the plant's
  dt) arrives (disable with --no-stop-at-end), after `--stop-after-idle` seconds without
  messages, or after `--max-duration`.

Topics: by default every contract topic of `sep_plant.topics` (`topics.RECORDED`), including
the image topics that only grid plants publish; a topic nobody publishes is simply absent
from the bag.

Start-up: volatile topics are only recorded from the moment the publisher and the recorder
have matched; `--ready-file PATH` is created once every awaited topic is matched (all recorded
topics, or those of --ready-topics; optional topics (`topics.OPTIONAL`, the images) only
while they have a publisher), so an orchestrator (the main job, tests) starts the episode
after it and the bag holds step 0.

QoS: contract topics are subscribed reliable/volatile with a deep keep-last queue (the
scenario topic transient_local, to get the plant's latched scenario); if every publisher
of a topic offers best effort, the subscription is re-created best effort (as rosbag2 does).
"""
from __future__ import annotations

import argparse
import importlib
import queue
import signal
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from sep_plant import topics as T

EXIT_BAD_INPUT = 2
_STOP = object()
_INF_SEC, _INF_NSEC = 2147483647, 4294967295


def recording_topics(namespace: str = T.NAMESPACE, names: tuple[str, ...] = T.RECORDED
                     ) -> dict[str, tuple[str, bool]]:
    """{fully qualified topic: (ROS type, transient_local)} of the contract topics to record."""
    return {full: (spec.type_name, spec.qos.transient_local) for full, spec in T.contract_topics(namespace, names).items()}


def optional_topics(namespace: str = T.NAMESPACE) -> set[str]:
    """Fully qualified names of the contract topics that only some plants publish."""
    return {T.topic_name(n, namespace) for n in T.OPTIONAL}


def _qos_to_rosbags(profile):
    """rclpy QoSProfile -> rosbags Qos (enum values coincide)."""
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


class BagSink:
    """A rosbags Writer fed from a queue by a writer thread.

    `put` is what subscription callbacks call: one `SimpleQueue.put` (C, lock-free for the
    caller). Connections are created lazily at a topic's first message with the QoS profiles
    returned by `qos_lookup(topic)`.
    """

    def __init__(self, out: str | Path, storage: str = "mcap", flush_interval: float = 0.1,
                 qos_lookup: Callable[[str], list] | None = None, namespace: str = T.NAMESPACE):
        self.out = Path(out)
        self.storage = storage
        self.flush_interval = flush_interval
        self.qos_lookup = qos_lookup or (lambda topic: [])
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.first_msg: float | None = None   # monotonic time of the first / last message
        self.last_msg: float | None = None
        self.final_seen: float | None = None  # monotonic time the final step's measurement arrived
        self.n_steps: int | None = None
        self.last_meas_ns = -1                # latest measurement stamp seen
        self.dt_ns: int | None = None
        self.final_topic = T.topic_name(T.MEASUREMENTS, namespace)
        self.scenario_topic = T.topic_name(T.SCENARIO, namespace)
        self.error: BaseException | None = None
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._opened = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bag-writer", daemon=True)

    # called from subscription callbacks
    def put(self, topic: str, t_ns: int, data: bytes) -> None:
        self._q.put((topic, t_ns, data))

    def start(self) -> None:
        self._thread.start()
        self._opened.wait(30)
        if self.error is not None:
            raise self.error

    def close(self, timeout: float = 30.0) -> None:
        self._q.put(_STOP)
        self._thread.join(timeout)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        try:
            ts = get_typestore(Stores.ROS2_JAZZY)
            plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
            writer = Writer(self.out, version=9, storage_plugin=plugin)
            writer.open()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller of start()
            self.error = exc
            self._opened.set()
            return
        self._opened.set()
        conns: dict[str, object] = {}
        last_flush = time.monotonic()
        dirty = False
        try:
            while True:
                try:
                    item = self._q.get(timeout=self.flush_interval)
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                if item is not None:
                    topic, t_ns, data = item
                    conn = conns.get(topic)
                    if conn is None:
                        msgtype = self.types[topic]
                        conn = conns[topic] = writer.add_connection(
                            topic, msgtype, typestore=ts, serialization_format="cdr",
                            offered_qos_profiles=self._offered(topic))
                    writer.write(conn, t_ns, data)
                    dirty = True
                    now = time.monotonic()
                    self.counts[topic] = self.counts.get(topic, 0) + 1
                    if self.first_msg is None:
                        self.first_msg = now
                    self.last_msg = now
                    if topic == self.scenario_topic:
                        self._note_scenario(data)
                    elif topic == self.final_topic and len(data) >= 12:
                        sec, nsec = struct.unpack_from("<iI", data, 4)
                        self.last_meas_ns = max(self.last_meas_ns, sec * 1_000_000_000 + nsec)
                    # the scenario may arrive after the final measurement (discovery order)
                    if self.final_seen is None and self._final_step_recorded():
                        self.final_seen = now
                if dirty and self._q.empty() and time.monotonic() - last_flush >= self.flush_interval:
                    _flush(writer)
                    dirty = False
                    last_flush = time.monotonic()
        except BaseException as exc:  # noqa: BLE001 - keep the bag closable, report at the end
            self.error = exc
        finally:
            # drain what is still queued, then close (writes the summary and metadata.yaml)
            while True:
                try:
                    item = self._q.get_nowait()
                except queue.Empty:
                    break
                if item is _STOP or self.error is not None:
                    continue
                topic, t_ns, data = item
                if topic in conns:
                    writer.write(conns[topic], t_ns, data)
                    self.counts[topic] = self.counts.get(topic, 0) + 1
            writer.close()

    def _offered(self, topic: str) -> list:
        try:
            return [_qos_to_rosbags(p) for p in self.qos_lookup(topic)]
        except Exception:  # noqa: BLE001 - QoS metadata is informative only
            return []

    def _note_scenario(self, data: bytes) -> None:
        """N and dt from the scenario topic's payload (CDR std_msgs/String: uint32 length with
        the terminating NUL, then the text)."""
        try:
            from sep_plant.scenario import parse_scenario_payload

            (n,) = struct.unpack_from("<I", data, 4)
            scenario, info = parse_scenario_payload(data[8:8 + n - 1].decode())
            self.n_steps, self.dt_ns = scenario.problem.n_steps, T.dt_ns(info.dt)
        except Exception:  # noqa: BLE001 - then only idle/signal/duration stop the recording
            pass

    def _final_step_recorded(self) -> bool:
        """Whether the measurement of step N (of the recorded scenario) has arrived."""
        if self.n_steps is None or self.dt_ns is None or self.last_meas_ns < 0:
            return False
        k = T.step_of_stamp(self.last_meas_ns, self.dt_ns)
        return k is not None and k >= self.n_steps


def _flush(writer) -> None:
    """Make what was written so far durable against a crash of this process."""
    st = writer.storage
    chunk = getattr(st, "chunk", None)
    if chunk is not None and hasattr(st, "close_chunk"):      # rosbags McapWriter
        if chunk.msgs:
            st.close_chunk()
        st.bio.flush()
    elif hasattr(st, "conn"):                                 # rosbags Sqlite3Writer
        st.conn.commit()


def _msg_class(msgtype: str):
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def make_recorder_node(sink: BagSink, topics: dict[str, tuple[str, bool]] | None, namespace: str = T.NAMESPACE,
                       node_name: str = "sep_recorder"):
    """The rclpy node: raw subscriptions feeding `sink`. `topics` None: the recorded contract
    topics (`recording_topics`). Topics outside the contract (given with --topics) get their
    type from the graph."""
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    contract = recording_topics(namespace)
    optional = optional_topics(namespace)

    class Recorder(Node):
        def __init__(self):
            super().__init__(node_name)
            self.wanted = dict(topics) if topics is not None else dict(contract)
            self.subs: dict[str, object] = {}
            self.best_effort: set[str] = set()
            self.offered: dict[str, list] = {}
            for topic, (msgtype, tl) in list(self.wanted.items()):
                if msgtype:
                    self._subscribe(topic, msgtype, tl, reliable=True)
            self.matched: set[str] = set()
            self.timer = self.create_timer(0.5, self._discover)
            self.match_timer = self.create_timer(0.05, self._check_matched)
            self.get_logger().info(f"recording {len(self.wanted)} topics to {sink.out} ({sink.storage})")

        def _subscribe(self, topic, msgtype, transient, reliable):
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)
            put = sink.put
            now = time.time_ns

            def cb(data, info, _topic=topic):
                put(_topic, info.get("received_timestamp") or now(), data)

            old = self.subs.pop(topic, None)
            if old is not None:
                self.destroy_subscription(old)
            sink.types[topic] = msgtype
            self.subs[topic] = self.create_subscription(_msg_class(msgtype), topic, cb, qos, raw=True)

        def _check_matched(self):
            """Note topics whose subscription is matched with at least one publisher."""
            for topic, sub in self.subs.items():
                if sub is not None and topic not in self.matched and sub.get_publisher_count() > 0:
                    self.matched.add(topic)

        def all_matched(self, topics=None) -> bool:
            """Every awaited topic (default: all recorded) is matched; an optional topic is only
            awaited while it has a publisher (the slab publishes no images)."""
            want = set(topics) if topics is not None else set(self.wanted)
            want -= {t for t in want & optional if t not in self.matched and self.count_publishers(t) == 0}
            return want <= self.matched

        def qos_lookup(self, topic):
            found = self.offered.get(topic)
            if not found:
                found = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
            return found

        def _discover(self):
            names = dict(self.get_topic_names_and_types())
            for topic, (msgtype, tl) in self.wanted.items():
                if topic not in self.subs:
                    types = names.get(topic)
                    if types:
                        try:
                            self._subscribe(topic, types[0], tl, reliable=True)
                            self.wanted[topic] = (types[0], tl)
                        except (ImportError, AttributeError, ValueError) as exc:
                            self.get_logger().warn(f"cannot record {topic} ({types[0]}): {exc}")
                            self.wanted[topic] = ("", tl)
                            self.subs[topic] = None
                    continue
                infos = self.get_publishers_info_by_topic(topic)
                if infos:
                    self.offered[topic] = [i.qos_profile for i in infos]
                    if topic not in self.best_effort and all(
                            i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
                        self.get_logger().info(f"{topic}: publishers offer best effort; subscribing best effort")
                        self.best_effort.add(topic)
                        self._subscribe(topic, msgtype, tl, reliable=False)

    return Recorder()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="record",
        description="Record the sep topic graph (docs/reference/topics.md) into a rosbag2 bag with the Jazzy message "
                    "definitions. ROS arguments go after --ros-args.")
    p.add_argument("--out", required=True, metavar="BAG_DIR", help="bag directory to create (must not exist)")
    p.add_argument("--topics", nargs="+", metavar="T",
                   help="topics to record (default: every contract topic of sep_plant.topics); relative names "
                        "are put in --namespace")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="storage plugin (default mcap)")
    p.add_argument("--namespace", default=T.NAMESPACE,
                   help=f"namespace of the contract topics (default {T.NAMESPACE})")
    p.add_argument("--stop-after-idle", type=float, default=None, metavar="S",
                   help="stop when no message arrived for S seconds (after the first one)")
    p.add_argument("--no-stop-at-end", action="store_true",
                   help="keep recording after the plant's final step (stop with Ctrl-C)")
    p.add_argument("--final-grace", type=float, default=1.0, metavar="S",
                   help="after the final step's measurement, record S more seconds (default 1)")
    p.add_argument("--max-duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--ready-file", metavar="PATH",
                   help="create PATH once every recorded topic (or those of --ready-topics) is matched with a "
                        "publisher (optional topics such as the images only while they have one): start the "
                        "episode after it appears so the bag holds step 0 of every topic")
    p.add_argument("--ready-topics", nargs="+", metavar="T",
                   help="topics that --ready-file waits for (default: all recorded topics)")
    p.add_argument("--flush-interval", type=float, default=0.1, metavar="S",
                   help="make data crash-safe at least every S seconds while messages flow (default 0.1)")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    if out.exists():
        print(f"record: error: {out} exists already; choose a new bag directory", file=sys.stderr)
        return EXIT_BAD_INPUT
    contract = recording_topics(args.namespace)
    topics = None
    if args.topics:
        topics = {}
        for t in args.topics:
            full = T.topic_name(t, args.namespace)
            topics[full] = contract.get(full, ("", False))

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    stop = threading.Event()
    reason = ["stopped"]

    def on_signal(signum, _frame):
        reason[0] = signal.Signals(signum).name
        stop.set()

    rclpy.init(args=["--ros-args", *ros_args[1:]] if ros_args else None,
               signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    node = None
    sink = BagSink(out, args.storage, args.flush_interval, namespace=args.namespace)
    try:
        try:
            sink.start()
        except Exception as exc:  # noqa: BLE001
            print(f"record: error: cannot create {out}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        node = make_recorder_node(sink, topics, args.namespace)
        sink.qos_lookup = node.qos_lookup
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        t0 = time.monotonic()
        ready_topics = None
        if args.ready_topics:
            ready_topics = [T.topic_name(t, args.namespace) for t in args.ready_topics]
        ready_done = not args.ready_file
        while not stop.is_set():
            executor.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if not ready_done and node.all_matched(ready_topics):
                ready_done = True
                Path(args.ready_file).write_text(f"{len(node.matched)} topics matched\n")
                node.get_logger().info(f"ready: {len(node.matched)} topics matched ({args.ready_file})")
            if sink.error is not None:
                reason[0] = f"writer error: {sink.error}"
                break
            if not args.no_stop_at_end and sink.final_seen is not None and now - sink.final_seen >= args.final_grace:
                reason[0] = "episode ended (final step recorded)"
                break
            if args.stop_after_idle is not None and sink.last_msg is not None \
                    and now - sink.last_msg >= args.stop_after_idle:
                reason[0] = f"idle for {args.stop_after_idle:g} s"
                break
            if args.max_duration is not None and now - t0 >= args.max_duration:
                reason[0] = f"max duration {args.max_duration:g} s"
                break
    finally:
        if node is not None:
            node.destroy_node()
        sink.close()
        if rclpy.ok():
            rclpy.shutdown()
    counts = ", ".join(f"{t}: {n}" for t, n in sorted(sink.counts.items())) or "no messages"
    print(f"record: {reason[0]}; wrote {sink.total} messages to {out} ({counts})", flush=True)
    if sink.error is not None:
        print(f"record: error: {sink.error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
