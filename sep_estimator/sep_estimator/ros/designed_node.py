"""Common part of the design-driven ROS 2 nodes (estimator, LQR): design file and scenario
checks, /diagnostics, the end-of-episode summary, and the spin loop used by the `estimator`,
`lqr` and `lqg` executables.

ROS-side module (imports rclpy).  A node refuses to start (StartError, exit code 2) when its
design file is missing, corrupt, or made for another plant than the one given by the
``scenario_file`` parameter or published by the plant on scenario (latched); the message
names every mismatching value.
"""
from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from sep_plant.ros import contract as c
from sep_plant.ros.base import (EXIT_OK, StartError, Throttle, declare, flush_publishers, fmt_s, log_rejection,
                                 steady, write_json)

#: at most this often a rejected message triggers an immediate /diagnostics message
REJECTION_DIAGNOSTICS_PERIOD_S = 0.2

_DESIGN_CACHE: dict[str, object] = {}


def load_design_checked(path: str, scenario_file: str = ''):
    """Load a design file (cached per path within the process) and check it against the
    scenario file if one is given; StartError with a clear message otherwise."""
    from sep_estimator.design_file import DesignFileError, check_matches, load_design
    from sep_plant.scenario import ScenarioError, load_scenario

    if not path:
        raise StartError('parameter design_file is required (create one with '
                         '`design --out FILE`, then -p design_file:=FILE)')
    try:
        design = _DESIGN_CACHE.get(path) or load_design(path)
    except DesignFileError as exc:
        raise StartError(f'design_file: {exc}') from None
    _DESIGN_CACHE[path] = design
    if scenario_file:
        try:
            plant = load_scenario(scenario_file)
        except ScenarioError as exc:
            raise StartError(f'bad scenario_file: {exc}') from None
        try:
            check_matches(design, plant, f'design file {path}')
        except DesignFileError as exc:
            raise StartError(f'{exc} (scenario_file {scenario_file})') from None
    return design


def scenario_summary(design) -> str:
    i, p = design.info, design.problem
    lo, hi = p.limits(i.n_u)
    lim = f'[{lo.min():g}, {hi.max():g}]' if np.all(lo == lo[0]) and np.all(hi == hi[0]) else 'per input'
    return (f'plant {design.scenario.plant_type}, n_field={i.n_field}, n_u={i.n_u}, n_y={i.n_y}, '
            f'dt={i.dt:g} s, N={p.n_steps}, u in {lim}')


class DesignedNode:
    """An rclpy Node (``self.node``) driven by a design file.

    Subclasses set ``self.done`` when their episode is over, put a StartError in
    ``self.fatal`` to stop the process (e.g. the plant's scenario does not match), and
    implement ``health()`` and ``summary()``.
    """

    role = 'node'

    def __init__(self, node_name: str, design=None):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.clock import Clock, ClockType
        from rclpy.node import Node

        self.node = node = Node(node_name, namespace=c.NAMESPACE)
        self.log = node.get_logger()
        self.design_file = declare(node, 'design_file', '', 'design file written by `design` (required)')
        self.scenario_file = declare(node, 'scenario_file', '',
                                     "optional: refuse to start unless the design matches this "
                                     "scenario file ('' = check only against scenario)")
        self.wait_for_scenario_s = declare(node, 'wait_for_scenario_s', 0.0,
                                           'wait this long at start for the plant scenario on '
                                           'slab/scenario (0 = do not wait)', lo=0.0, hi=3600.0)
        self.exit_at_end = declare(node, 'exit_at_end', True, 'exit after the last step of the episode')
        self.summary_file = declare(node, 'summary_file', '', 'end-of-episode summary JSON')
        self.diag_period = declare(node, 'diagnostics_period_s', 1.0,
                                   '/diagnostics period (wall seconds)', lo=0.01, hi=3600.0)
        self.design = design if design is not None else load_design_checked(
            self.design_file, self.scenario_file)
        self.info = self.design.info
        self.dt = self.info.dt
        self.frame_id = self.info.frame_id
        self.N = self.design.n_steps
        self.dt_ns = c.dt_ns(self.dt)
        self.diag_throttle = Throttle(REJECTION_DIAGNOSTICS_PERIOD_S)
        self.done = False
        self.fatal: StartError | None = None
        self.finished = False
        self.plant_scenario_checked = False
        self.t_start = steady()
        self.pub_diag = node.create_publisher(DiagnosticArray, c.DIAGNOSTICS, c.DIAGNOSTICS_QOS)
        self.sub_scenario = node.create_subscription(c.TOPIC_TYPES[c.SCENARIO], c.SCENARIO,
                                                     self._on_scenario, c.SCENARIO_QOS)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.diag_timer = node.create_timer(self.diag_period, self.publish_diagnostics,
                                            clock=self._steady)
        self.last_k = -1  # newest step seen (for diagnostics stamps)

    # ----------------------------------------------------------- scenario
    def _on_scenario(self, msg) -> None:
        from sep_estimator.design_file import DesignFileError, check_matches
        from sep_plant.scenario import parse_scenario_payload

        try:
            plant, _ = parse_scenario_payload(msg.data)
        except ValueError as exc:
            self.fatal = StartError(f'unreadable plant scenario on {self.sub_scenario.topic_name}: {exc}')
            return
        try:
            check_matches(self.design, plant, f'design file {self.design_file}')
        except DesignFileError as exc:
            self.fatal = StartError(f'{exc} (plant scenario from {self.sub_scenario.topic_name})')
            return
        if not self.plant_scenario_checked:
            self.log.info(f'plant scenario on {self.sub_scenario.topic_name} matches the design')
        self.plant_scenario_checked = True

    def wait_for_scenario(self, executor) -> None:
        if self.wait_for_scenario_s <= 0:
            return
        t_end = steady() + self.wait_for_scenario_s
        while not self.plant_scenario_checked and self.fatal is None and steady() < t_end:
            executor.spin_once(timeout_sec=0.05)
        if self.fatal is not None:
            raise self.fatal
        if not self.plant_scenario_checked:
            raise StartError(f'no plant scenario on {self.sub_scenario.topic_name} within '
                             f'wait_for_scenario_s = {self.wait_for_scenario_s:g} s')

    # -------------------------------------------------------- diagnostics
    def health(self) -> c.Health:  # pragma: no cover - overridden
        return c.Health(name=self.node.get_fully_qualified_name())

    def publish_diagnostics(self) -> None:
        try:
            self.pub_diag.publish(c.diagnostics(c.stamp(max(self.last_k, 0), self.dt),
                                                [self.health()], self.frame_id))
        except Exception:  # noqa: BLE001 - context gone during shutdown
            pass

    def reject(self, what: str, rej, log, k: int | None = None) -> None:
        """Count a rejected message, log it (throttled) and report it on /diagnostics (rate
        limited), so a storm of bad messages costs neither memory nor the loop."""
        log_rejection(self.log, log, rej, f"rejected {what}{'' if k is None else f' (step {k})'}")
        if self.diag_throttle.ready():
            self.publish_diagnostics()

    # -------------------------------------------------------------- finish
    def summary(self, status: str) -> dict:  # pragma: no cover - overridden
        return {'node': self.role, 'status': status}

    def summary_line(self, summ: dict) -> str:  # pragma: no cover - overridden
        return str(summ)

    def finish(self, status: str = 'completed', error: str | None = None) -> dict:
        if self.finished:
            return {}
        self.finished = True
        summ = self.summary(status)
        if error:
            summ['error'] = error
        self.publish_diagnostics()
        self.log.info(f'{self.role} {status}: ' + self.summary_line(summ))
        if self.summary_file:
            write_json(self.summary_file, summ)
        self.flush()
        return summ

    def publishers(self) -> Iterable:
        return [self.pub_diag]

    def flush(self, budget_s: float = 0.5) -> None:
        flush_publishers(self.publishers(), budget_s)

    def destroy_node(self) -> None:
        self.node.destroy_node()


def spin_episode(executor, nodes: Sequence[DesignedNode]) -> int:
    """Spin until every node's episode is done (when exit_at_end) or a node reports a fatal
    error (raised as StartError); returns EXIT_OK (the caller then finishes the nodes)."""
    for n in nodes:
        n.wait_for_scenario(executor)
    while True:
        for n in nodes:
            if n.fatal is not None:
                raise n.fatal
        if all(n.done and n.exit_at_end for n in nodes):
            break
        executor.spin_once(timeout_sec=0.2)
    return EXIT_OK


__all__ = ['DesignedNode', 'load_design_checked', 'scenario_summary', 'spin_episode', 'fmt_s']
