"""`sep record`: record the sep topic graph into a rosbag2 bag (MCAP by default, sqlite3 selectable).

    sep record --out BAG_DIR [--topics T ...] [--storage mcap|sqlite3] [--namespace NS]
               [--stop-after-idle S] [--no-stop-at-end] [--max-duration S] [--ready-file PATH] [--ros-args ...]

What rosbag2's `ros2 bag record` does, for installs without rosbag2 (PyPI wheels): raw
subscriptions (`raw=True`: the CDR bytes go into the bag untouched, no deserialization) feed
the ROS-free writer `sep_control.bags.writer.BagSink` (rosbags' Writer: one rosbag2
connection per topic with the Jazzy message definition, serialization ``cdr``, the QoS
profiles the publishers offer). Bag timestamps (log time) are receive times in ns (the
middleware's reception timestamp, system clock; the callback time when the middleware gives
none).

Not slowing the loop: the subscription callback only appends (topic, time, bytes) to a
queue; the sink's writer thread serializes into the bag. The recorder runs in its own process.

Robustness:
* SIGINT / SIGTERM (Ctrl-C) stop the recording and close the bag cleanly (metadata.yaml).
* The writer flushes the open MCAP chunk (or commits the sqlite3 transaction) whenever the
  queue runs dry and `--flush-interval` (default 0.1 s) has passed, so a bag cut off by a
  crash (SIGKILL) keeps everything up to about the last flush: `sep analyze --allow-truncated`
  (or `sep_control.bags.reader.read_episode(..., allow_truncated=True)`) reads it, and
  `sep_control.bags.repair.repair_bag` rewrites it as a complete bag for other tools.
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
while they have a publisher), so an orchestrator (the demo, tests) starts the episode
after it and the bag holds step 0.

Lifecycle: the recorder (node ``sep_recorder``) is a managed node. With the parameter
``autostart`` (default true) it configures and activates at start, as before. With
``-p autostart:=false`` it waits unconfigured for the standard lifecycle services
(``/sep_recorder/change_state`` ...): configure creates the bag (refused when it cannot: the
transition fails and the log says why) and the subscriptions; activate records; deactivate stops
recording (messages that arrive while inactive are dropped, counted in the log line of cleanup);
cleanup closes the bag (metadata written) and removes the subscriptions; shutdown ends the
process (exit 0). The stop conditions (end of episode, idle, duration) apply while configured.

QoS: contract topics are subscribed reliable/volatile with a deep keep-last queue (the
scenario topic transient_local, to get the plant's latched scenario); if every publisher
of a topic offers best effort, the subscription is re-created best effort (as rosbag2 does).
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import time
from pathlib import Path

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from sep_control.bags.writer import BagSink
from sep_plant import topics as T
from sep_plant.ros.lifecycle import autostart

PROG = "sep record"
EXIT_BAD_INPUT = 2


def recording_topics(namespace: str = T.NAMESPACE, names: tuple[str, ...] = T.RECORDED
                     ) -> dict[str, tuple[str, bool]]:
    """{fully qualified topic: (ROS type, transient_local)} of the contract topics to record."""
    return {full: (spec.type_name, spec.qos.transient_local)
            for full, spec in T.contract_topics(namespace, names).items()}


def optional_topics(namespace: str = T.NAMESPACE) -> set[str]:
    """Fully qualified names of the contract topics that only some plants publish."""
    return {T.topic_name(n, namespace) for n in T.OPTIONAL}


def _msg_class(msgtype: str):
    """The rclpy message class of a ROS type name ('sensor_msgs/msg/JointState')."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class Recorder(LifecycleNode):
    """Raw subscriptions feeding a `BagSink`, topic discovery and the matched-topics check; a
    managed (lifecycle) node (see the module's docstring).

    Parameters
    ----------
    make_sink : callable
        () -> BagSink, started: where the received messages go (`sink.types` is filled here);
        called by the configure transition (an exception fails it).
    topics : dict, optional
        {fully qualified topic: (ROS type or '', transient_local)}; default: the recorded
        contract topics (`recording_topics`). A topic without type (outside the contract,
        given with --topics) gets its type from the graph.
    namespace : str
        Namespace of the contract topics.
    node_name : str
        The node's name.
    """

    def __init__(self, make_sink, topics: dict[str, tuple[str, bool]] | None = None,
                 namespace: str = T.NAMESPACE, node_name: str = "sep_recorder"):
        super().__init__(node_name)
        self.make_sink = make_sink
        self.topics, self.namespace = topics, namespace
        self.autostart = self.declare_parameter("autostart", True).value
        self.sink: BagSink | None = None
        self.config_error: str | None = None
        self.active = self.shut_down = False
        self.dropped = 0                    # messages that came while inactive
        self._starting = False

    def start(self) -> None:
        """autostart: configure and activate now; a refused configure raises RuntimeError(why)."""
        autostart(self, lambda: RuntimeError(self.config_error) if self.config_error else None,
                  lambda flag: setattr(self, "_starting", flag))

    # ------------------------------------------------------------ lifecycle
    def on_configure(self, state) -> TransitionCallbackReturn:
        try:
            self.sink = sink = self.make_sink()
        except Exception as exc:  # noqa: BLE001 - the transition fails and says why
            self.config_error = f"cannot create the bag: {exc}"
            if not self._starting:
                self.get_logger().error(f"configure failed, staying unconfigured: {self.config_error}")
            return TransitionCallbackReturn.FAILURE
        self.config_error = None
        sink.qos_lookup = self.qos_lookup
        self.optional = optional_topics(self.namespace)
        self.wanted = dict(self.topics) if self.topics is not None else recording_topics(self.namespace)
        self.subs: dict[str, object] = {}
        self.best_effort: set[str] = set()
        self.offered: dict[str, list] = {}
        self.matched: set[str] = set()
        for topic, (msgtype, tl) in list(self.wanted.items()):
            if msgtype:
                self._subscribe(topic, msgtype, tl, reliable=True)
        self.timer = self.create_timer(0.5, self._discover)
        self.match_timer = self.create_timer(0.05, self._check_matched)
        self.get_logger().info(f"recording {len(self.wanted)} topics to {sink.out} ({sink.storage})")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state) -> TransitionCallbackReturn:
        self.active = True
        if not self._starting:
            self.get_logger().info("activated: recording")
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state) -> TransitionCallbackReturn:
        self.active = False
        self.get_logger().info("deactivated: not recording")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state) -> TransitionCallbackReturn:
        self.close()
        self.get_logger().info(f"cleaned up: bag closed ({self.dropped} messages dropped while inactive)")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state) -> TransitionCallbackReturn:
        self.active, self.shut_down = False, True
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state) -> TransitionCallbackReturn:
        self.active = False
        return TransitionCallbackReturn.SUCCESS

    def configured(self) -> bool:
        return hasattr(self, "subs")

    def close(self) -> None:
        """Close the bag (first: its writer thread asks `qos_lookup` while it drains the queue),
        then remove the subscriptions and timers."""
        if not hasattr(self, "subs"):
            return
        if self.sink is not None:
            self.sink.close()
        for sub in self.subs.values():
            if sub is not None:
                self.destroy_subscription(sub)
        self.destroy_timer(self.timer)
        self.destroy_timer(self.match_timer)
        del self.subs

    def _subscribe(self, topic: str, msgtype: str, transient: bool, reliable: bool) -> None:
        """(Re-)create the raw subscription of `topic`; its callback only queues the bytes."""
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                         reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE)
        put = self.sink.put
        now = time.time_ns

        def cb(data, info, _topic=topic):
            if self.active:
                put(_topic, info.get("received_timestamp") or now(), data)
            else:
                self.dropped += 1

        old = self.subs.pop(topic, None)
        if old is not None:
            self.destroy_subscription(old)
        self.sink.types[topic] = msgtype
        self.subs[topic] = self.create_subscription(_msg_class(msgtype), topic, cb, qos, raw=True)

    def _check_matched(self) -> None:
        """Note topics whose subscription is matched with at least one publisher."""
        for topic, sub in self.subs.items():
            if sub is not None and topic not in self.matched and sub.get_publisher_count() > 0:
                self.matched.add(topic)

    def all_matched(self, topics=None) -> bool:
        """Every awaited topic (default: all recorded) is matched; an optional topic is only
        awaited while it has a publisher (the slab publishes no images)."""
        want = set(topics) if topics is not None else set(self.wanted)
        want -= {t for t in want & self.optional if t not in self.matched and self.count_publishers(t) == 0}
        return want <= self.matched

    def qos_lookup(self, topic: str) -> list:
        """The QoS profiles the publishers of `topic` offer (for the bag's metadata)."""
        found = self.offered.get(topic)
        if not found:
            found = [i.qos_profile for i in self.get_publishers_info_by_topic(topic)]
        return found

    def _discover(self) -> None:
        """Subscribe to wanted topics whose type the graph now tells; note offered QoS and
        switch to best effort where every publisher offers only that."""
        names = dict(self.get_topic_names_and_types())
        for topic, (msgtype, tl) in self.wanted.items():
            if topic not in self.subs:
                types = names.get(topic)
                if types:
                    self._subscribe_discovered(topic, types[0], tl)
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if infos:
                self.offered[topic] = [i.qos_profile for i in infos]
                if topic not in self.best_effort and all(
                        i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
                    self.get_logger().info(f"{topic}: publishers offer best effort; subscribing best effort")
                    self.best_effort.add(topic)
                    self._subscribe(topic, msgtype, tl, reliable=False)

    def _subscribe_discovered(self, topic: str, msgtype: str, tl: bool) -> None:
        try:
            self._subscribe(topic, msgtype, tl, reliable=True)
            self.wanted[topic] = (msgtype, tl)
        except (ImportError, AttributeError, ValueError) as exc:
            self.get_logger().warn(f"cannot record {topic} ({msgtype}): {exc}")
            self.wanted[topic] = ("", tl)
            self.subs[topic] = None


def build_parser() -> argparse.ArgumentParser:
    """The command line of `sep record` (ROS arguments after --ros-args are split off first)."""
    p = argparse.ArgumentParser(
        prog=PROG,
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


def _requested_topics(args: argparse.Namespace) -> dict[str, tuple[str, bool]] | None:
    """{full topic: (type, transient_local)} of --topics (types of contract topics filled in),
    or None for the default set."""
    if not args.topics:
        return None
    contract = recording_topics(args.namespace)
    return {full: contract.get(full, ("", False)) for full in (T.topic_name(t, args.namespace) for t in args.topics)}


def _stop_reason(args: argparse.Namespace, sink: BagSink, now: float, t0: float) -> str | None:
    """Why the recording stops now (writer error, episode end, idle, duration), or None."""
    if sink.error is not None:
        return f"writer error: {sink.error}"
    if not args.no_stop_at_end and sink.final_seen is not None and now - sink.final_seen >= args.final_grace:
        return "episode ended (final step recorded)"
    if args.stop_after_idle is not None and sink.last_msg is not None and now - sink.last_msg >= args.stop_after_idle:
        return f"idle for {args.stop_after_idle:g} s"
    if args.max_duration is not None and now - t0 >= args.max_duration:
        return f"max duration {args.max_duration:g} s"
    return None


def _record(node: Recorder, args: argparse.Namespace, stop: threading.Event) -> str | None:
    """Spin `node` until a stop condition while it is configured, or its shutdown transition
    (None: stopped by a signal); writes --ready-file once the awaited topics are matched."""
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    t0 = time.monotonic()
    ready_topics = [T.topic_name(t, args.namespace) for t in args.ready_topics] if args.ready_topics else None
    ready_done = not args.ready_file
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.05)
        if node.shut_down:
            return "shut down (lifecycle)"
        if not node.configured():
            continue
        if not ready_done and node.all_matched(ready_topics):
            ready_done = True
            Path(args.ready_file).write_text(f"{len(node.matched)} topics matched\n")
            node.get_logger().info(f"ready: {len(node.matched)} topics matched ({args.ready_file})")
        reason = _stop_reason(args, node.sink, time.monotonic(), t0)
        if reason is not None:
            return reason
    return None


def main(argv: list[str] | None = None) -> int:
    """Run the recorder; 0 after a clean stop, 2 on bad input, 1 when the writer failed."""
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    args = build_parser().parse_args(argv)
    out = Path(args.out)
    if out.exists():
        print(f"{PROG}: error: {out} exists already; choose a new bag directory", file=sys.stderr)
        return EXIT_BAD_INPUT
    topics = _requested_topics(args)
    stop = threading.Event()
    signalled: list[str] = []

    def on_signal(signum, _frame):
        signalled.append(signal.Signals(signum).name)
        stop.set()

    def make_sink() -> BagSink:
        sink = BagSink(out, args.storage, args.flush_interval, namespace=args.namespace)
        try:
            sink.start()
        except BaseException:
            sink.close()
            raise
        return sink

    rclpy.init(args=["--ros-args", *ros_args[1:]] if ros_args else None,
               signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    node = None
    reason = None
    try:
        node = Recorder(make_sink, topics, args.namespace)
        if node.autostart:
            try:
                node.start()
            except RuntimeError as exc:
                print(f"{PROG}: error: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
        reason = _record(node, args, stop)
    finally:
        # the bag first: its writer thread still asks the node for QoS profiles (`qos_lookup`)
        # while it drains the queue; close() reports a writer that did not finish (sink.error)
        if node is not None:
            node.close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return _report(reason or (signalled[0] if signalled else "stopped"), node.sink if node else None, out)


def _report(reason: str, sink: BagSink | None, out: Path) -> int:
    """Print what was written (stdout) and a writer error (stderr); the exit code."""
    if sink is None:
        print(f"{PROG}: {reason}; never configured, no bag written", flush=True)
        return 0
    counts = ", ".join(f"{t}: {n}" for t, n in sorted(sink.counted().items())) or "no messages"
    print(f"{PROG}: {reason}; wrote {sink.total} messages to {out} ({counts})", flush=True)
    if sink.error is not None:
        print(f"{PROG}: error: {sink.error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
