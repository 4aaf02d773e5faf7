"""What every ROS 2 node of sep shares (plant, estimator, lqr, lqg): the command-line front
(`parse_front`), parameters with descriptors (`declare`), exit codes and start/stop errors
(`StartError`, `StopError`, `Shutdown`: from `sep_plant.ros.lifecycle`), executors, BLAS thread
limits, timing stats (`SampleWindow`, `percentiles`), the summary file (`write_summary_json`),
publisher flushing, and `NodeBase` (an rclpy managed (lifecycle) node with /diagnostics,
rejection reporting and the end-of-episode summary).
How a node process starts, spins and stops (`run_node`, `NodeProcess`, the middleware
watchdogs) is in `sep_plant.ros.process`.
ROS-side module (imports rclpy); the pure algorithm modules never import it.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from sep_plant.ros import contract as c
from sep_plant.ros.lifecycle import Managed, Shutdown, StartError, StopError, managed_node
from sep_plant.scenario import json_default

# Process exit codes of the nodes (docs/reference/cli.md).
EXIT_OK = 0
EXIT_FAILURE = 1          # unexpected error (traceback logged)
EXIT_CONFIG = 2           # bad parameter, missing/corrupt/mismatched design or scenario file
# EXIT_TIMEOUT = 3        lockstep: no command / no peer in time (sep_plant.plant_episode)
EXIT_INTERRUPTED = 130    # Ctrl-C / SIGTERM before the episode ended

ROS_ARGS_HELP = ("ROS arguments follow --ros-args, e.g. --ros-args --params-file FILE "
                 "-p NAME:=VALUE -r __ns:=/NAMESPACE --log-level debug")

#: at most this often a rejected message triggers an immediate /diagnostics message
REJECTION_DIAGNOSTICS_PERIOD_S = 0.2


EXECUTORS = ('events', 'single')


def parse_front(prog: str, description: str, argv: Sequence[str] | None,
                add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
                parameters: str = '') -> tuple[argparse.Namespace, list[str]]:
    """argparse front for a node: non-ROS options parsed here (``--help`` prints usage and
    exits 0), everything after ``--ros-args`` passed on to rclpy.  Returns (options, args for
    rclpy.init)."""
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(parameters + '\n\n' if parameters else '') + ROS_ARGS_HELP)
    parser.add_argument('--executor', choices=EXECUTORS, default=os.environ.get('SEP_EXECUTOR', 'events'),
                        help="rclpy executor: 'events' (rclpy.experimental.EventsExecutor, C++ "
                             "event queue, the low-latency default) or 'single' "
                             "(SingleThreadedExecutor); env SEP_EXECUTOR sets the default")
    if add_arguments:
        add_arguments(parser)
    return parser.parse_args(remove_ros_args(args=argv)[1:]), argv


def make_executor(kind: str = 'events'):
    """A single-threaded executor of the given kind (falls back to SingleThreadedExecutor when
    this rclpy has no EventsExecutor)."""
    from rclpy.executors import SingleThreadedExecutor
    if kind == 'events':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:  # pragma: no cover - older rclpy
            pass
    return SingleThreadedExecutor()


def limit_blas_threads(n: int = 1):
    """Limit BLAS/OpenMP pools to `n` threads for this process (the per-step linear algebra
    of the nodes is tiny: extra threads only add wake-up latency).  Returns the controller."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a pinned requirement
        return None
    return threadpool_limits(limits=n)


def declare(node, name: str, default: Any, description: str, *, read_only: bool = True,
            lo: float | int | None = None, hi: float | int | None = None,
            constraints: str = '') -> Any:
    """Declare a parameter with a ParameterDescriptor (type from `default`, optional range) and
    return its value.  Range/type violations raise StartError naming the parameter."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import ParameterException

    if node.has_parameter(name):        # declared by an earlier configure (lifecycle): its value
        value = node.get_parameter(name).value
        return float(value) if isinstance(default, float) and isinstance(value, int) else value
    desc = ParameterDescriptor(name=name, description=description, read_only=read_only,
                               additional_constraints=constraints)
    if isinstance(default, bool):
        pass
    elif isinstance(default, int) and (lo is not None or hi is not None):
        desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
    elif isinstance(default, float) and (lo is not None or hi is not None):
        desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                        step=0.0)]
    try:
        value = node.declare_parameter(name, default, desc).value
    except ParameterException as exc:
        rng = f' (allowed range [{lo}, {hi}])' if lo is not None else ''
        raise StartError(f'bad parameter {name}: {exc}{rng}') from None
    if isinstance(default, float) and isinstance(value, int):
        value = float(value)
    return value


def percentiles(samples: Sequence[float]) -> dict[str, float | None]:
    """p50/p99/max of a list of seconds (None when empty)."""
    if len(samples) == 0:
        return {'p50': None, 'p99': None, 'max': None, 'n': 0}
    a = np.asarray(samples, dtype=float)
    return {'p50': float(np.percentile(a, 50)), 'p99': float(np.percentile(a, 99)),
            'max': float(a.max()), 'n': int(a.size)}


def fmt_s(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return 'n/a'
    return f'{v * 1e3:.3f} ms' if v >= 1e-3 else f'{v * 1e6:.0f} us'


def write_summary_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write a node's summary `obj` as JSON to `path` atomically (a temporary file renamed)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + '.tmp')
    tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=json_default) + '\n')
    tmp.replace(p)
    return p


def append_json_line(path: str | os.PathLike, record: dict) -> None:
    """Append `record` as one JSON line to `path` (a node's episode_log_file)."""
    with open(path, 'a') as fh:
        fh.write(json.dumps(record, sort_keys=True, default=json_default) + '\n')


def sim_time_default(args: list[str], value: bool = True) -> list[str]:
    """rclpy args with ``use_sim_time`` defaulting to `value` (a user's own
    ``-p use_sim_time:=...`` or params file given later still wins)."""
    return [args[0], '--ros-args', '-p', f'use_sim_time:={str(value).lower()}', '--', *args[1:]]


def flush_publishers(publishers, budget_s: float = 0.5) -> bool:
    """Wait (at most `budget_s` in total) until reliable subscribers acknowledged everything
    published: the last messages of an episode reach bags and peers before the writers go.
    Samples are delivered on publish on one host; acknowledgements can lag by a heartbeat
    period, hence a bounded wait rather than an unbounded one."""
    from rclpy.duration import Duration
    t_end = time.perf_counter() + budget_s
    ok = True
    for pub in publishers:
        left = t_end - time.perf_counter()
        if left <= 0:
            return False
        try:
            ok = pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))) and ok
        except Exception:  # noqa: BLE001 - context already shut down (Ctrl-C)
            return False
    return ok


def steady() -> float:
    return time.perf_counter()


class SampleWindow:
    """The last `size` samples (seconds) for percentiles, plus the count and maximum of all:
    memory stays bounded however long a node runs."""

    def __init__(self, size: int = 4096):
        from collections import deque

        self._d: 'deque[float]' = deque(maxlen=size)
        self.n = 0
        self.max: float | None = None

    def append(self, v: float) -> None:
        self._d.append(v)
        self.n += 1
        self.max = v if self.max is None or v > self.max else self.max

    def __len__(self) -> int:
        return len(self._d)

    def percentiles(self) -> dict[str, float | None]:
        out = percentiles(self._d)
        out['n'], out['max'] = self.n, self.max
        return out


class Throttle:
    """At most one event per `period` seconds (steady clock): rate-limits the diagnostics sent
    on rejected messages, so a storm of bad messages cannot flood /diagnostics or the loop."""

    def __init__(self, period: float):
        self.period = period
        self._next = 0.0

    def ready(self) -> bool:
        now = steady()
        if now < self._next:
            return False
        self._next = now + self.period
        return True


# ------------------------------------------------------------------------------- nodes
class NodeBase(Managed):
    """An rclpy Node (``self.node``, namespace sep) with /diagnostics, rejection reporting and the
    end-of-episode summary.

    Subclasses set ``dt`` and ``frame_id`` (the stamps of /diagnostics), implement ``health()``,
    ``summary(status)`` and ``summary_line(summary)``, set ``done`` when their episode is over
    and put a StartError in ``fatal`` to stop the process; ``prepare(executor)`` runs before
    the episode, ``on_finish(summary)`` after the summary is written.

    The node is a managed (lifecycle) node (`sep_plant.ros.lifecycle.Managed`: ``configure()``,
    ``on_activated()``, ``on_deactivated()``, ``active``); with the parameter ``autostart``
    (default true) `NodeProcess` configures and activates it at once, as before.
    """

    role = 'node'

    def __init__(self, node_name: str):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.clock import Clock, ClockType

        self.node = node = managed_node(self, node_name, c.NAMESPACE)
        self.log = node.get_logger()
        self.autostart = declare(node, 'autostart', True, 'configure and activate at start (false: wait for '
                                 'the lifecycle transitions, e.g. ros2 lifecycle set NODE configure)')
        Managed.__init__(self)
        self.summary_file = declare(node, 'summary_file', '', 'end-of-episode summary JSON')
        self.diag_period = declare(node, 'diagnostics_period_s', 1.0,
                                   '/diagnostics period (wall seconds)', lo=0.01, hi=3600.0)
        self.dt, self.frame_id = 1.0, c.FRAME_ID
        self.last_k = -1                    # newest step seen (the stamp of /diagnostics)
        self.exit_at_end = True
        self.done = False
        self.fatal: StartError | None = None
        self.finished = False
        self.last_summary: dict = {}
        self.health_errors = 0              # failed health() calls (logged, see publish_diagnostics)
        self.diag_throttle = Throttle(REJECTION_DIAGNOSTICS_PERIOD_S)
        self.pub_diag = node.create_publisher(DiagnosticArray, c.DIAGNOSTICS, c.DIAGNOSTICS_QOS)
        self.diag_timer = node.create_timer(self.diag_period, self.publish_diagnostics,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))

    def prepare(self, executor) -> None:
        """Before the episode, with the executor spinning (default: nothing)."""

    # -------------------------------------------------------- diagnostics
    def health(self) -> c.Health:  # pragma: no cover - overridden
        return c.Health(name=self.node.get_fully_qualified_name())

    def publish_diagnostics(self) -> None:
        """Publish this node's `health()` on /diagnostics. A failing `health()` is a bug: it is
        logged (with its traceback the first time, then at most once a minute) and published as an
        ERROR status naming the exception, so /diagnostics goes on and says so. Only the publish
        itself may fail silently (the context is gone during shutdown)."""
        try:
            health = self.health() if self.ready() else c.Health(
                name=self.node.get_fully_qualified_name(), message=f'lifecycle state {self.state_label()}')
        except Exception as exc:  # noqa: BLE001 - reported, never silent
            health = self._health_failed(exc)
        try:
            self.pub_diag.publish(c.diagnostics(c.stamp(max(self.last_k, 0), self.dt), [health], self.frame_id))
        except Exception:  # noqa: BLE001 - context gone during shutdown
            pass

    def _health_failed(self, exc: Exception) -> c.Health:
        """Log a failed `health()` and the ERROR status published instead."""
        import traceback

        what = f'{type(exc).__name__}: {exc}'
        self.health_errors += 1
        if self.health_errors == 1:
            self.log.error(f'/diagnostics: health() failed: {what}\n{traceback.format_exc()}')
        else:
            self.log.error(f'/diagnostics: health() failed: {what} ({self.health_errors} times)',
                           throttle_duration_sec=60.0)
        return c.Health(name=self.node.get_fully_qualified_name(), level=c.ERROR,
                        message=f'health() failed: {what}')

    def reject(self, what: str, rej, rejections, k: int | None = None) -> None:
        """Count a rejected message in `rejections` (a gate.RejectionLog) and report it."""
        rejections.add(rej)
        self.report_rejection(what, rej, rejections, k)

    def report_rejection(self, what: str, rej, rejections, k: int | None = None) -> None:
        """Log a rejected message already counted in `rejections`: the first of each reason at
        once, later ones at most once a second; and send /diagnostics at once, at most every
        REJECTION_DIAGNOSTICS_PERIOD_S (a storm of bad messages costs neither memory nor the loop)."""
        line = f"rejected {what}{'' if k is None else f' (step {k})'}: {rej} ({rejections.total} rejected so far)"
        if rejections.counts[rej.category] == 1:
            self.log.warning(line)
        else:
            self.log.warning(line, throttle_duration_sec=1.0)
        if self.diag_throttle.ready():
            self.publish_diagnostics()

    # -------------------------------------------------------------- finish
    def summary(self, status: str) -> dict:  # pragma: no cover - overridden
        return {'node': self.role, 'status': status}

    def summary_line(self, summ: dict) -> str:  # pragma: no cover - overridden
        return str(summ)

    def finish(self, status: str = 'completed', error: str | None = None) -> dict:
        """The end of the episode: summary (with `error`), last /diagnostics, one log line, the
        summary file, then the publishers flushed. Once; returns the summary ({} later)."""
        if self.finished or not self.ready():
            return {}
        self.finished = True
        summ = self.summary(status)
        if error:
            summ['error'] = error
        self.last_summary = summ            # kept past a cleanup (the lqg's process summary)
        self.publish_diagnostics()
        self.log.info(f'{self.finish_label()} {status}: ' + self.summary_line(summ))
        if self.summary_file:
            write_summary_json(self.summary_file, summ)
        self.on_finish(summ)
        self.flush()
        return summ

    def finish_label(self) -> str:
        return self.role   # the word that starts the end-of-episode log line

    def on_finish(self, summ: dict) -> None:
        """After the summary is written, before the flush (default: nothing)."""

    def publishers(self) -> Iterable:
        return [self.pub_diag]

    def flush(self, budget_s: float = 0.5) -> None:
        """Let reliable subscribers receive the last messages before the writers go away."""
        flush_publishers([p for p in self.publishers() if p is not None], budget_s)

    def destroy_node(self) -> None:
        self.node.destroy_node()

