"""How a node process of sep starts, spins and stops: rclpy.init with sep's own signal handling,
the watchdogs that bound start-up and teardown, the spin loop of one or more nodes on one executor
(`NodeProcess`), and the executables' ``main`` (`node_main`). ROS-side module (imports rclpy).
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
from typing import Any, Callable, Sequence

from sep_plant.plant_episode import EXIT_TIMEOUT, EpisodeError
from sep_plant.ros.base import (EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, NodeBase, Shutdown, StartError,
                                StopError, limit_blas_threads, make_executor, parse_front, sim_time_default)


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


#: set by SIGINT / SIGTERM (`_on_signal`); the spin loops turn it into a KeyboardInterrupt
_INTERRUPT = threading.Event()
#: the longest a spin loop waits before it looks at `_INTERRUPT` again [s] (events wake it sooner)
POLL_S = 0.2


def _on_signal(signum, frame) -> None:
    # Only set a flag: rclpy's own handler chains to Python's, which raises KeyboardInterrupt
    # wherever the main thread is, and inside an executor's C++ callback that aborts the process
    # (pybind11 terminate, exit -6) instead of ending the episode cleanly.
    _INTERRUPT.set()


def spin_once(executor, timeout_sec: float) -> None:
    """`executor.spin_once` for at most `timeout_sec` (and at most POLL_S), then raise
    KeyboardInterrupt in Python code if SIGINT/SIGTERM came: every spin loop of the nodes uses it."""
    executor.spin_once(timeout_sec=max(0.0, min(timeout_sec, POLL_S)))
    if _INTERRUPT.is_set():
        raise KeyboardInterrupt


def run_node(make: Callable[[list[str]], Any], args: list[str], logger_name: str) -> int:
    """rclpy.init, build the process with `make` (a `NodeProcess`), call its ``run()`` (returns an
    exit code), and always destroy it and shut rclpy down. Start errors and episode errors are
    logged as one clear line; Ctrl-C / SIGTERM exit EXIT_INTERRUPTED after ``finish('interrupted')``.
    The start (rclpy.init and `make`) and the final teardown are bounded by watchdogs
    (`startup_watchdog_s()`, TEARDOWN_WATCHDOG_S): a middleware that blocks there ends the process
    with its stacks in the log, EXIT_TIMEOUT at start-up, the episode's own exit code at teardown.
    SIGUSR1 dumps the stacks at any time (`enable_stack_dumps`)."""
    import signal

    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.logging import get_logger
    from rclpy.signals import SignalHandlerOptions

    enable_stack_dumps()
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    bound = startup_watchdog_s()
    start = _Watchdog(bound, f'{logger_name}: the node did not start within {bound:g} s (rclpy.init, '
                      f'its DDS entities, the plant or design file; SEP_STARTUP_WATCHDOG_S sets the bound)',
                      lambda: EXIT_TIMEOUT)
    proc = None
    rc = EXIT_FAILURE
    try:
        try:
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
            proc = make(args)
        finally:
            start.disarm()
        rc = proc.run()
    except StartError as exc:
        get_logger(logger_name).error(f'{exc.lead}: {exc}')
        if isinstance(exc, StopError) and proc is not None:
            proc.finish(status='error', error=f'{exc.lead}: {exc}')
        rc = exc.exit_code
    except EpisodeError as exc:
        get_logger(logger_name).error(str(exc))
        if proc is not None:
            proc.finish(status='error', error=str(exc))
        rc = exc.exit_code
    except (KeyboardInterrupt, ExternalShutdownException):
        if proc is not None:
            proc.finish(status='interrupted')
        else:
            get_logger(logger_name).warning('interrupted')
        rc = EXIT_INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - any other error mid-episode: summary, then exit 1
        rc = _failed(proc, exc, logger_name)
    finally:
        _teardown(proc, rc, logger_name)
    return rc


def _failed(proc: Any, exc: Exception, logger_name: str) -> int:
    """An unexpected error (an FMU error in a step, a filter error): log it with its traceback,
    write the summary with status 'error' naming it (when the process was built), EXIT_FAILURE."""
    import traceback

    from rclpy.logging import get_logger

    what = f'{type(exc).__name__}: {exc}'
    get_logger(logger_name).error(f'unexpected error, stopping: {what}\n{traceback.format_exc()}')
    if proc is not None:
        try:
            proc.finish(status='error', error=what)
        except Exception as again:  # noqa: BLE001 - the first error is the one reported
            get_logger(logger_name).error(f'the summary could not be written: {type(again).__name__}: {again}')
    return EXIT_FAILURE


def _teardown(proc: Any, rc: int, logger_name: str) -> None:
    """Destroy the process's nodes and shut rclpy down, within TEARDOWN_WATCHDOG_S."""
    import rclpy

    stop = _Watchdog(TEARDOWN_WATCHDOG_S, f'{logger_name}: the ROS middleware did not shut down within '
                     f'{TEARDOWN_WATCHDOG_S:g} s (exit code {rc} kept)', lambda: rc)
    if proc is not None:
        try:
            proc.destroy_node()
        except Exception:  # noqa: BLE001 - shutdown must not mask the exit code
            pass
    if rclpy.ok():
        rclpy.shutdown()
    stop.disarm()


def node_main(prog: str, description: str, argv: Sequence[str] | None, parameters: str,
              build: Callable[[argparse.Namespace], 'NodeProcess'],
              add_arguments: Callable[[argparse.ArgumentParser], None] | None = None,
              sim_time: bool = True) -> int:
    """The ``main`` of a node executable: the command-line front (``--help`` lists `parameters`),
    BLAS limited to one thread, and `run_node` of the process `build(options)` makes
    (``use_sim_time`` defaulting to true when `sim_time`)."""
    opts, args = parse_front(prog, description, argv, add_arguments, parameters)
    limit_blas_threads(1)   # the per-step linear algebra is tiny: extra threads only add latency
    return run_node(lambda a: build(opts), sim_time_default(args) if sim_time else args, prog)


class NodeProcess:
    """One or more nodes on one executor in this process (what `run_node` runs).

    ``run()`` runs `episode(executor)` when given (a node that drives its own episode: the
    plant), else prepares the nodes and spins until every node's episode is done (those with
    exit_at_end) or one reports a fatal error (raised); then it finishes the nodes.

    Lifecycle: nodes with ``autostart`` are configured and activated here (a refusal raises its
    StartError, as at start before); the others wait for their transitions (a node is prepared
    once it is configured). When every node has been shut down (the shutdown transition), or an
    episode raises `Shutdown`, the process finishes with status 'shutdown' and exit code 0."""

    def __init__(self, nodes: Sequence[NodeBase], executor: str = 'events',
                 episode: Callable[[Any], int] | None = None):
        self.nodes = list(nodes)
        self.executor = make_executor(executor)
        for n in self.nodes:
            self.executor.add_node(n.node)
        self._episode = episode
        self.finished = False
        for n in self.nodes:
            if n.autostart:
                n.start()

    def run(self) -> int:
        try:
            rc = self._episode(self.executor) if self._episode is not None else self.spin()
        except Shutdown:
            self.finish('shutdown')
            return EXIT_OK
        self.finish('completed')
        return rc

    def spin(self) -> int:
        while True:
            for n in self.nodes:
                if n.ready() and not n.prepared:
                    n.prepared = True
                    n.prepare(self.executor)
                if n.fatal is not None:
                    raise n.fatal
            if all(n.done and n.exit_at_end for n in self.nodes):
                return EXIT_OK
            if all(n.shut_down for n in self.nodes):
                raise Shutdown
            spin_once(self.executor, POLL_S)

    def finish(self, status: str, error: str | None = None) -> None:
        if self.finished:
            return
        self.finished = True
        for n in self.nodes:
            n.finish(status, error)

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        for n in reversed(self.nodes):
            n.destroy_node()
