"""`plant`: the simulated heat slab as a ROS 2 node (DESIGN.md §4).

Publishes /clock (simulated time k*dt), slab/measurements (y_k), slab/heat_applied (u applied
at step k), slab/field (true field), slab/scenario (its scenario as JSON, latched) and
/diagnostics; subscribes slab/heat_command.  One episode of N steps per process, then exit 0.

Per step k = 0..N: publish /clock and y_k = h(T_k) + v_k; if k < N get the command u_k, apply
clip(u_k), publish it on heat_applied, publish the field T_k, T_{k+1} = f(T_k, u + w_k).  The noise
of (seed, run) is run `run` of `noise_sequences(scenario, seed, runs)`, the numbers the offline
Monte Carlo uses for that run, so a lockstep episode reproduces it exactly.

Modes:
* lockstep (default): after y_k, wait (up to command_timeout_s) for a valid command stamped k;
  on timeout log which step and why, exit EXIT_TIMEOUT (3).  Deterministic, as fast as the
  controller answers.
* realtime: steps on a steady-clock schedule every dt / real_time_factor.  A command for step k
  that has not arrived by the tick is a deadline miss: the last applied command is held (zeros
  before the first command: the plant does not know the nominal; the LQR's own fallback to the
  nominal covers a missing estimate).

Bad commands (NaN/Inf, wrong length, unknown names, stamps off the step grid, stale, duplicate,
for a future step) are rejected, counted per reason, logged and reported on /diagnostics.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from . import contract as c
from . import gate
from .slab import clip_inputs
from .node_util import (EXIT_OK, EpisodeError, StartError, declare, fmt_s, limit_blas_threads,
                        flush_publishers, make_executor, parse_front, percentiles, run_node, steady, write_json)

MODES = ('lockstep', 'realtime')

PARAMETERS = """parameters (set with --ros-args -p NAME:=VALUE or --params-file ros_ws/config/plant.yaml):
  scenario_file (str, '')          scenario YAML; '' = the shipped reference scenario
  mode (str, lockstep)             lockstep | realtime
  real_time_factor (float, 10)     realtime: steps every dt / real_time_factor  [0.01, 1000]
  seed (int, 0), run (int, 0)      noise = run `run` of the Monte Carlo with seed `seed`
  command_timeout_s (float, 10)    lockstep: wait this long for the command of each step
  publish_field (bool, true)       publish the true field on slab/field
  wait_for_subscribers (int, 1)    matched measurement subscribers needed before step 0
  wait_for_field_subscribers (int, 0)  matched slab/field subscribers needed before step 0
  start_timeout_s (float, 30)      give up (exit 3) if they do not appear in time
  start_delay_s (float, 0.2)       settle time after they appeared (endpoint matching)
  diagnostics_period_s (float, 1)  /diagnostics period (also sent on every rejection)
  summary_file (str, '')           write the end-of-episode summary as JSON
  trajectory_file (str, '')        write T (N+1,n_x), U (N,n_u), Y (N+1,n_y) as .npz"""


class PlantNode:
    """The plant; wraps an rclpy Node (created in __init__)."""

    def __init__(self, args: list[str], summary_json: str | None = None, executor: str = 'events'):
        from rclpy.node import Node

        from .noise import noise_sequences
        from .scenario import ScenarioError, load_scenario
        from .slab import SlabSimulator

        self.node = node = Node('plant', namespace=c.NAMESPACE)
        self.log = node.get_logger()
        p = {}
        p['scenario_file'] = declare(node, 'scenario_file', '', "scenario YAML file; '' = reference")
        p['mode'] = declare(node, 'mode', 'lockstep', 'lockstep | realtime',
                            constraints='one of: lockstep, realtime')
        p['real_time_factor'] = declare(node, 'real_time_factor', 10.0,
                                        'realtime mode: simulated seconds per wall second',
                                        lo=0.01, hi=1000.0)
        p['seed'] = declare(node, 'seed', 0, 'noise seed (Monte Carlo seed)', lo=0, hi=2**31 - 1)
        p['run'] = declare(node, 'run', 0, 'run index within the seed', lo=0, hi=10**6)
        p['command_timeout_s'] = declare(node, 'command_timeout_s', 10.0,
                                         'lockstep: seconds to wait for each command',
                                         lo=0.001, hi=86400.0)
        p['publish_field'] = declare(node, 'publish_field', True, 'publish the true field')
        p['wait_for_subscribers'] = declare(node, 'wait_for_subscribers', 1,
                                            'matched measurement subscribers needed to start',
                                            lo=0, hi=1000)
        p['wait_for_field_subscribers'] = declare(node, 'wait_for_field_subscribers', 0,
                                                  'matched field subscribers needed to start',
                                                  lo=0, hi=1000)
        p['start_timeout_s'] = declare(node, 'start_timeout_s', 30.0,
                                       'seconds to wait for subscribers', lo=0.0, hi=86400.0)
        p['start_delay_s'] = declare(node, 'start_delay_s', 0.2,
                                     'settle time after the subscribers appeared', lo=0.0, hi=60.0)
        p['diagnostics_period_s'] = declare(node, 'diagnostics_period_s', 1.0,
                                            '/diagnostics period (wall seconds)', lo=0.01, hi=3600.0)
        p['summary_file'] = declare(node, 'summary_file', '', 'end-of-episode summary JSON')
        p['trajectory_file'] = declare(node, 'trajectory_file', '', 'true trajectory .npz')
        if p['mode'] not in MODES:
            raise StartError(f"bad parameter mode: {p['mode']!r}, expected one of {list(MODES)}")
        if summary_json:
            p['summary_file'] = summary_json
        self.p = p
        try:
            s = load_scenario(p['scenario_file'] or None)
        except ScenarioError as exc:
            raise StartError(f'bad scenario_file: {exc}') from None
        self.s = s
        self.sim = SlabSimulator(s)
        w, v = noise_sequences(s, p['seed'], range(p['run'], p['run'] + 1))
        self.w, self.v = w[0], v[0]
        self.x_grid = s.grid()
        self.heaters = s.heater_labels()
        self.sensors = s.sensor_labels()
        self.dt_ns = c.dt_ns(s.dt)
        self.N = s.n_steps

        self.pub_y = node.create_publisher(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS, c.LOOP_QOS)
        self.pub_u = node.create_publisher(c.TOPIC_TYPES[c.HEAT_APPLIED], c.HEAT_APPLIED, c.LOOP_QOS)
        self.pub_field = node.create_publisher(c.TOPIC_TYPES[c.FIELD], c.FIELD, c.FIELD_QOS)
        self.pub_scen = node.create_publisher(c.TOPIC_TYPES[c.SCENARIO], c.SCENARIO, c.SCENARIO_QOS)
        from rosgraph_msgs.msg import Clock
        from diagnostic_msgs.msg import DiagnosticArray
        self.pub_clock = node.create_publisher(Clock, c.CLOCK, c.CLOCK_QOS)
        self.pub_diag = node.create_publisher(DiagnosticArray, c.DIAGNOSTICS, c.DIAGNOSTICS_QOS)
        self.sub_cmd = node.create_subscription(c.TOPIC_TYPES[c.HEAT_COMMAND], c.HEAT_COMMAND,
                                                self._on_command, c.LOOP_QOS)
        self.executor = make_executor(executor)
        self.executor_kind = executor
        self.executor.add_node(node)

        # episode state
        self.k = 0
        self.last_cmd_step = -1
        self.pending: np.ndarray | None = None     # accepted command for step self.k
        self.held = np.zeros(s.n_u)               # last applied (zeros before the first command)
        self.rejections = gate.RejectionLog()
        self.deadline_misses = 0
        self.t_pub = np.full(self.N + 1, np.nan)   # wall time y_k was published
        self.t_cmd = np.full(self.N, np.nan)       # wall time command k arrived
        self.T = np.empty((self.N + 1, s.n_x))
        self.U = np.empty((self.N, s.n_u))
        self.Y = np.empty((self.N + 1, s.n_y))
        self.finished = False
        self._next_diag = 0.0
        self._t_start = None
        self._t_end = None

        self.log.info(
            f"plant: scenario {p['scenario_file'] or '<reference>'} (n_x={s.n_x}, n_u={s.n_u}, "
            f"n_y={s.n_y}, dt={s.dt:g} s, N={s.n_steps}), mode {p['mode']}"
            + (f" at real_time_factor {p['real_time_factor']:g} (a step every "
               f"{fmt_s(s.dt / p['real_time_factor'])})" if p['mode'] == 'realtime' else
               f", command_timeout_s {p['command_timeout_s']:g}")
            + f", seed {p['seed']} run {p['run']}, namespace {node.get_namespace()}")

    # ------------------------------------------------------------------ input
    def _on_command(self, msg) -> None:
        t = steady()
        k, rej = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if rej is None:
            rej = gate.check_horizon(k, self.N - 1)
        if rej is None:
            rej = gate.check_step(k, expected=self.k, last=self.last_cmd_step, allow_ahead=False)
        u = None
        if rej is None:
            u, rej = gate.check_vector(msg.name, msg.effort, self.heaters, 'heat_command effort')
        if rej is not None:
            self._reject(rej)
            return
        self.last_cmd_step = k
        self.pending = u
        self.t_cmd[k] = t

    def _reject(self, rej: gate.Rejection) -> None:
        self.rejections.add(rej)
        self.log.warning(f'rejected heat_command at step {self.k}: {rej} '
                         f'({self.rejections.total} rejected so far)')
        self._publish_diagnostics()

    # ---------------------------------------------------------------- output
    def _publish_step(self, k: int, T: np.ndarray) -> None:
        """/clock k, then y_k: the controllers' clock reads k*dt when y_k arrives.  The field
        (analysis only) is published later by `_publish_field`, off the measurement-to-command
        path: serializing n_x points here would delay taking the command."""
        y = self.sim.observe(T) + self.v[k]
        self.Y[k] = y
        self.T[k] = T
        msg = c.joint_state(k, self.s.dt, self.sensors, position=y)
        self.pub_clock.publish(c.clock_msg(k, self.s.dt))
        self.t_pub[k] = steady()
        self.pub_y.publish(msg)

    def _publish_field(self, k: int, T: np.ndarray) -> None:
        if self.p['publish_field'] and self.pub_field.get_subscription_count() > 0:
            self.pub_field.publish(c.field_cloud(k, self.s.dt, self.x_grid, T))

    def health(self) -> c.Health:
        lat = percentiles(self._latencies())
        level, msg = c.OK, 'ok'
        if self.deadline_misses or self.rejections.total:
            level = c.WARN
            msg = f'{self.deadline_misses} deadline misses, {self.rejections.total} rejected commands'
        return c.Health(name=f'{self.node.get_fully_qualified_name()}', hardware_id='slab_plant',
                        level=level, message=msg, values={
                            'step': self.k, 'n_steps': self.N, 'mode': self.p['mode'],
                            'deadline_misses': self.deadline_misses,
                            'rejected_messages': self.rejections.total,
                            'rejected_by_reason': self.rejections.as_dict(),
                            'last_rejection': str(self.rejections.last or ''),
                            'latency_p50_s': lat['p50'], 'latency_p99_s': lat['p99'],
                            'seed': self.p['seed'], 'run': self.p['run']})

    def _publish_diagnostics(self) -> None:
        try:
            self.pub_diag.publish(c.diagnostics(c.stamp(self.k, self.s.dt), [self.health()]))
        except Exception:  # noqa: BLE001 - context gone during shutdown
            pass
        self._next_diag = steady() + self.p['diagnostics_period_s']

    def _latencies(self) -> np.ndarray:
        d = self.t_cmd - self.t_pub[:-1]
        return d[np.isfinite(d)]

    # ------------------------------------------------------------------- run
    def _spin_until(self, t_end: float, done=lambda: False) -> bool:
        """Spin callbacks until done() or the steady time t_end; returns done()."""
        while not done():
            now = steady()
            if now >= t_end:
                return done()
            if now >= self._next_diag:
                self._publish_diagnostics()
            self.executor.spin_once(timeout_sec=min(t_end - now, max(self._next_diag - now, 0.0)))
        return True

    def _wait_for_peers(self) -> None:
        need_y, need_f = self.p['wait_for_subscribers'], self.p['wait_for_field_subscribers']
        t_end = steady() + self.p['start_timeout_s']
        # with subscribers required, also a heat_command publisher (a command sent before
        # its writer matched our reader would be lost)
        ok = lambda: (self.pub_y.get_subscription_count() >= need_y
                      and self.pub_field.get_subscription_count() >= need_f
                      and (need_y == 0 or self.sub_cmd.get_publisher_count() >= 1))
        if need_y or need_f:
            self.log.info(f'waiting for {need_y} measurement subscriber(s)'
                          + (f', {need_f} field subscriber(s)' if need_f else '')
                          + ' and a heat_command publisher')
        if not self._spin_until(t_end, ok):
            raise EpisodeError(
                f"no controller: {self.pub_y.get_subscription_count()} of {need_y} measurement "
                f"subscribers, {self.sub_cmd.get_publisher_count()} heat_command publishers and "
                f"{self.pub_field.get_subscription_count()} of {need_f} field "
                f"subscribers after start_timeout_s = {self.p['start_timeout_s']:g} s "
                f"(is the estimator/lqg running in namespace {self.node.get_namespace()} with "
                f"the same ROS_DOMAIN_ID?)")
        self._spin_until(steady() + self.p['start_delay_s'])

    def run(self) -> int:
        self.pub_scen.publish(c.scenario_msg(self.s))
        self._publish_diagnostics()
        self._wait_for_peers()
        realtime = self.p['mode'] == 'realtime'
        period = self.s.dt / self.p['real_time_factor']
        T = self.sim.initial_state()
        self._t_start = t0 = steady()
        self.log.info(f'episode start: {self.N} steps')
        for k in range(self.N + 1):
            self.k = k
            self._publish_step(k, T)
            if k == self.N:
                self._publish_field(k, T)
                break
            have = lambda: self.pending is not None
            if realtime:
                self._spin_until(t0 + (k + 1) * period)      # the tick: steps on schedule
                if not have():
                    self.deadline_misses += 1
                    self.log.warning(f'deadline miss at step {k}: no valid command within '
                                     f'{fmt_s(period)}; holding the last applied input',
                                     throttle_duration_sec=1.0)
                    if self.deadline_misses == 1:
                        self._publish_diagnostics()
                u = self.pending if self.pending is not None else self.held
            else:
                if not self._spin_until(steady() + self.p['command_timeout_s'], have):
                    why = (f'; {self.rejections.total} command(s) rejected, last: {self.rejections.last}'
                           if self.rejections.total else '')
                    raise EpisodeError(
                        f"lockstep: no valid heat_command stamped step {k} (t = {k * self.s.dt:g} s) "
                        f"within command_timeout_s = {self.p['command_timeout_s']:g} s{why}; is the "
                        f"lqg (or estimator + lqr) running on {self.node.get_namespace()}?")
                u = self.pending
            u_app = clip_inputs(u, self.s)
            self.pending = None
            self.held = u_app
            self.U[k] = u_app
            self.pub_u.publish(c.joint_state(k, self.s.dt, self.heaters, effort=u_app))
            self._publish_field(k, T)
            T = self.sim.step(T, u_app, self.w[k])
        self.k = self.N
        self.finish('completed')
        return EXIT_OK

    # --------------------------------------------------------------- finish
    def summary(self, status: str) -> dict:
        lat = percentiles(self._latencies())
        steps = self.k if status != 'completed' else self.N
        wall = (self._t_end - self._t_start) if self._t_start and self._t_end else None
        return {'node': 'plant', 'status': status, 'mode': self.p['mode'],
                'real_time_factor': self.p['real_time_factor'] if self.p['mode'] == 'realtime' else None,
                'seed': self.p['seed'], 'run': self.p['run'], 'steps': steps, 'n_steps': self.N,
                'deadline_misses': self.deadline_misses,
                'rejected_messages': self.rejections.total,
                'rejected_by_reason': self.rejections.as_dict(),
                'latency_p50_s': lat['p50'], 'latency_p99_s': lat['p99'],
                'latency_max_s': lat['max'], 'wall_s': wall,
                'scenario_file': self.p['scenario_file'], 'namespace': self.node.get_namespace()}

    def finish(self, status: str, error: str | None = None) -> None:
        if self.finished:
            return
        self.finished = True
        self._t_end = steady()
        summ = self.summary(status)
        if error:
            summ['error'] = error
        self._publish_diagnostics()
        lat = percentiles(self._latencies())
        self.log.info(
            f"episode {status}: {summ['steps']}/{self.N} steps in "
            f"{(summ['wall_s'] or 0.0):.2f} s wall, {self.deadline_misses} deadline misses, "
            f"{self.rejections.total} rejected commands, measurement->command latency "
            f"p50 {fmt_s(lat['p50'])} p99 {fmt_s(lat['p99'])} max {fmt_s(lat['max'])}")
        if self.p['summary_file']:
            write_json(self.p['summary_file'], summ)
        if self.p['trajectory_file']:
            n = summ['steps']
            path = Path(self.p['trajectory_file'])
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, T=self.T[:n + 1], U=self.U[:n], Y=self.Y[:n + 1],
                     scenario=np.frombuffer(self.s.to_json().encode(), dtype=np.uint8),
                     seed=self.p['seed'], run=self.p['run'])
        # Let reliable subscribers receive the last messages before the writers go away.
        flush_publishers((self.pub_y, self.pub_field, self.pub_u, self.pub_clock, self.pub_diag))

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        self.node.destroy_node()


def main(argv: list[str] | None = None) -> int:
    def add(parser):
        parser.add_argument('--summary-json', metavar='PATH',
                            help='write the end-of-episode summary as JSON (same as -p summary_file:=PATH)')

    opts, args = parse_front('plant', 'Simulated heat slab (sep_plant): the plant node of the '
                             'sep closed loop.', argv, add, PARAMETERS)
    limit_blas_threads(1)
    return run_node(lambda a: PlantNode(a, opts.summary_json, opts.executor), args, 'plant')


if __name__ == '__main__':
    sys.exit(main())
