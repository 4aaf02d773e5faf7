"""Helpers shared by the ROS 2 nodes of sep (plant, estimator, LQR, lqg): command-line front,
parameter declaration with descriptors, process exit codes, BLAS thread limits, timing stats.

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
from typing import Any, Callable, Sequence

import numpy as np

# Process exit codes of the nodes (documented in the README).
EXIT_OK = 0
EXIT_FAILURE = 1          # unexpected error (traceback logged)
EXIT_CONFIG = 2           # bad parameter, missing/corrupt/mismatched design or scenario file
EXIT_TIMEOUT = 3          # lockstep: no command / no peer in time
EXIT_INTERRUPTED = 130    # Ctrl-C / SIGTERM before the episode ended

ROS_ARGS_HELP = ("ROS arguments follow --ros-args, e.g. --ros-args --params-file FILE "
                 "-p NAME:=VALUE -r __ns:=/NAMESPACE --log-level debug")


class StartError(Exception):
    """A node cannot start (bad parameter, bad file, mismatch): logged, exit code EXIT_CONFIG."""

    exit_code = EXIT_CONFIG


class EpisodeError(Exception):
    """The episode cannot go on (e.g. lockstep command timeout): logged, non-zero exit."""

    def __init__(self, message: str, exit_code: int = EXIT_TIMEOUT):
        super().__init__(message)
        self.exit_code = exit_code


def parse_front(prog: str, description: str, argv: Sequence[str] | None,
                add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
                parameters: str = '') -> tuple[argparse.Namespace, list[str]]:
    """argparse front for a node: non-ROS options parsed here (``--help`` prints usage and
    exits 0), everything after ``--ros-args`` passed on to rclpy.  Returns (options, args for
    rclpy.init)."""
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(parameters + '\n\n' if parameters else '') + ROS_ARGS_HELP)
    add_executor_option(parser)
    if add_arguments:
        add_arguments(parser)
    own = remove_ros_args(args=argv)[1:]
    opts = parser.parse_args(own)
    return opts, argv


EXECUTORS = ('events', 'single')


def add_executor_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--executor', choices=EXECUTORS,
                        default=os.environ.get('SEP_EXECUTOR', 'events'),
                        help="rclpy executor: 'events' (rclpy.experimental.EventsExecutor, C++ "
                             "event queue, the low-latency default) or 'single' "
                             "(SingleThreadedExecutor); env SEP_EXECUTOR sets the default")


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


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + '.tmp')
    tmp.write_text(json.dumps(obj, indent=2, sort_keys=True, default=_plain) + '\n')
    tmp.replace(p)
    return p


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(type(v).__name__)


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


#: seconds the start (rclpy.init and building the node: its DDS entities, the plant, the design
#: file) or the teardown after the episode (destroying the entities, rclpy.shutdown) may take
#: before the watchdog gives up (`_Watchdog`); SEP_STARTUP_WATCHDOG_S overrides the first, for
#: a plant whose construction is slow
STARTUP_WATCHDOG_S = 90.0
TEARDOWN_WATCHDOG_S = 15.0


def startup_watchdog_s() -> float:
    try:
        return max(1.0, float(os.environ.get('SEP_STARTUP_WATCHDOG_S', STARTUP_WATCHDOG_S)))
    except ValueError:
        return STARTUP_WATCHDOG_S


def enable_stack_dumps() -> None:
    """Python stacks of every thread on stderr (the node's log) on a crash, and on SIGUSR1
    without stopping: `kill -USR1 <pid>` shows where a node is (the demo does it to a child that
    has not finished in time)."""
    import faulthandler
    import signal

    faulthandler.enable(all_threads=True)
    if hasattr(signal, 'SIGUSR1'):
        faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)


class _Watchdog:
    """Bounds a phase that only the middleware can block (DDS participant creation or
    destruction): if `disarm()` is not called within `seconds`, every thread's Python stack goes
    to stderr (the node's log) with `what`, and the process exits with `code` at once.  A node
    whose episode is over and whose outputs are written must exit, not hang in a DDS teardown."""

    #: seconds after `seconds` at which faulthandler's own watchdog (a C thread that needs no GIL:
    #: a middleware call that blocks while holding the GIL starves the Python timer) ends the
    #: process too, with exit code 1
    BACKSTOP_S = 5.0

    def __init__(self, seconds: float, what: str, code: Callable[[], int]):
        import faulthandler
        import threading

        self._what, self._code = what, code
        self._timer = threading.Timer(seconds, self._fire)
        self._timer.daemon = True
        self._timer.start()
        faulthandler.dump_traceback_later(seconds + self.BACKSTOP_S, exit=True)

    def _fire(self) -> None:
        import faulthandler

        print(f'watchdog: {self._what}; thread stacks follow, exiting', file=sys.stderr, flush=True)
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001 - a closed stream must not stop the exit
                pass
        os._exit(self._code())

    def disarm(self) -> None:
        import faulthandler

        self._timer.cancel()
        faulthandler.cancel_dump_traceback_later()


def run_node(make: Callable[[list[str]], Any], args: list[str], logger_name: str) -> int:
    """rclpy.init, build the node with `make`, call its ``run()`` (returns an exit code), and
    always destroy it and shut rclpy down.  Start errors and episode errors are logged as one
    clear line; Ctrl-C / SIGTERM exit EXIT_INTERRUPTED after the node's ``interrupted()``.
    The start (rclpy.init and `make`) and the final teardown are bounded by watchdogs
    (`startup_watchdog_s()`, TEARDOWN_WATCHDOG_S): a middleware that blocks there ends the process
    with its stacks in the log, EXIT_TIMEOUT at start-up, the episode's own exit code at teardown.
    SIGUSR1 dumps the stacks at any time (`enable_stack_dumps`)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.logging import get_logger

    enable_stack_dumps()
    bound = startup_watchdog_s()
    start = _Watchdog(bound, f'{logger_name}: the node did not start within {bound:g} s (rclpy.init, '
                      f'its DDS entities, the plant or design file; SEP_STARTUP_WATCHDOG_S sets the bound)',
                      lambda: EXIT_TIMEOUT)
    node = None
    rc = EXIT_FAILURE
    try:
        try:
            rclpy.init(args=args)
            node = make(args)
        finally:
            start.disarm()
        rc = node.run()
    except StartError as exc:
        get_logger(logger_name).error(f'refusing to start: {exc}')
        rc = exc.exit_code
    except EpisodeError as exc:
        get_logger(logger_name).error(str(exc))
        if node is not None and hasattr(node, 'finish'):
            node.finish(status='error', error=str(exc))
        rc = exc.exit_code
    except (KeyboardInterrupt, ExternalShutdownException):
        if node is not None and hasattr(node, 'finish'):
            node.finish(status='interrupted')
        else:
            get_logger(logger_name).warning('interrupted')
        rc = EXIT_INTERRUPTED
    finally:
        stop = _Watchdog(TEARDOWN_WATCHDOG_S, f'{logger_name}: the ROS middleware did not shut down within '
                         f'{TEARDOWN_WATCHDOG_S:g} s (exit code {rc} kept)', lambda: rc)
        if node is not None:
            try:
                node.destroy_node()
            except Exception:  # noqa: BLE001 - shutdown must not mask the exit code
                pass
        if rclpy.ok():
            rclpy.shutdown()
        stop.disarm()
    return rc


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


def log_rejection(logger, rejections, rej, text: str) -> None:
    """Count a rejected message in `rejections` (a gate.RejectionLog) and log it: the first of
    each kind at once, later ones at most once a second (a storm of bad messages must not flood
    the log)."""
    rejections.add(rej)
    line = f'{text}: {rej} ({rejections.total} rejected so far)'
    if rejections.counts[rej.category] == 1:
        logger.warning(line)
    else:
        logger.warning(line, throttle_duration_sec=1.0)


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
