"""`plant`: any plant of the plant protocol as a ROS 2 node (docs/reference/topics.md); the slab by default.

Publishes /clock (simulated time k*dt), measurements (y_k), applied_input (u applied
at step k), field (true field as a PointCloud2 with the nodes' x, y, z), for grid plants
field_image (32FC1; the middle slice of a 3-D grid), scenario (its scenario and plant
description as JSON, latched) and /diagnostics; subscribes command.  One episode of N
steps per process, then exit 0.  The plant is checked against the protocol before step 0.

Per step k = 0..N: publish /clock and y_k = h(x_k) + v_k; if k < N get the command u_k, apply
clip(u_k), publish it on applied_input, publish the field f(x_k), x_{k+1} = f(x_k, u, w_k).  The
noise of (seed, run) is run `run` of `noise_sequences(problem, info, seed, runs)`, the numbers the
offline Monte Carlo uses for that run, so a lockstep episode reproduces it exactly.  The field
messages are built only while somebody subscribes to them.

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

from sep_plant.ros import contract as c
from sep_plant import gate
from sep_plant.ros.base import (EXIT_OK, EpisodeError, StartError, Throttle, declare, fmt_s, limit_blas_threads,
                        flush_publishers, log_rejection, make_executor, parse_front, percentiles, run_node, steady,
                        write_json)
from sep_plant.protocol import clip_inputs

MODES = ('lockstep', 'realtime')

PARAMETERS = """parameters (set with --ros-args -p NAME:=VALUE or --params-file $(ros2 pkg prefix sep_plant)/share/sep_plant/config/plant.yaml):
  scenario_file (str, '')          scenario YAML; '' = the shipped reference scenario
  mode (str, lockstep)             lockstep | realtime
  real_time_factor (float, 10)     realtime: steps every dt / real_time_factor  [0.01, 1000]
  seed (int, 0), run (int, 0)      noise = run `run` of the Monte Carlo with seed `seed`
  command_timeout_s (float, 10)    lockstep: wait this long for the command of each step
  publish_field (bool, true)       publish the true field on field
  wait_for_subscribers (int, 1)    matched measurement subscribers needed before step 0
  wait_for_field_subscribers (int, 0)  matched field subscribers needed before step 0
  start_timeout_s (float, 30)      give up (exit 3) if they do not appear in time
  start_delay_s (float, 0.2)       settle time after they appeared (endpoint matching)
  diagnostics_period_s (float, 1)  /diagnostics period (also sent on a rejection, at most 5 Hz)
  summary_file (str, '')           write the end-of-episode summary as JSON
  trajectory_file (str, '')        write F (N+1,n_field), U (N,n_u), Y (N+1,n_y) as .npz (kept
                                   in memory only when set)"""

#: at most this often a rejected message triggers an immediate /diagnostics message
REJECTION_DIAGNOSTICS_PERIOD_S = 0.2


class PlantNode:
    """The plant; wraps an rclpy Node (created in __init__)."""

    def __init__(self, args: list[str], summary_json: str | None = None, executor: str = 'events'):
        from rclpy.node import Node

        from sep_plant.conformance import check_plant
        from sep_plant.noise import noise_sequences
        from sep_plant.protocol import PlantError, PlantInfo
        from sep_plant.scenario import ScenarioError, load_scenario, scenario_payload

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
            scen = load_scenario(p['scenario_file'] or None)
            plant = scen.plant
            check_plant(plant, scen.problem.channels('u_init', int(plant.n_u)), name=scen.plant_type)
        except (ScenarioError, PlantError) as exc:
            raise StartError(f"bad scenario_file {p['scenario_file'] or '<reference>'}: {exc}") from None
        self.scenario, self.plant, self.problem = scen, plant, scen.problem
        self.info = info = PlantInfo.of(plant)
        self.dt = info.dt
        w, v = noise_sequences(self.problem, info, p['seed'], [p['run']])
        self.w, self.v = w[0], v[0]
        self.lo, self.hi = self.problem.limits(info.n_u)
        self.cloud = c.CloudBuilder(plant.field_coordinates(), info.field_name, info.frame_id)
        self.input_names = list(info.input_names)
        self.sensors = list(info.output_names)
        self.dt_ns = c.dt_ns(info.dt)
        self.N = self.problem.n_steps
        self.payload = scenario_payload(scen, info)

        self.pub_y = node.create_publisher(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS, c.LOOP_QOS)
        self.pub_u = node.create_publisher(c.TOPIC_TYPES[c.APPLIED_INPUT], c.APPLIED_INPUT, c.LOOP_QOS)
        self.pub_field = node.create_publisher(c.TOPIC_TYPES[c.FIELD], c.FIELD, c.FIELD_QOS)
        self.pub_image = (node.create_publisher(c.TOPIC_TYPES[c.FIELD_IMAGE], c.FIELD_IMAGE, c.FIELD_QOS)
                          if info.grid_shape else None)
        self.pub_scen = node.create_publisher(c.TOPIC_TYPES[c.SCENARIO], c.SCENARIO, c.SCENARIO_QOS)
        from rosgraph_msgs.msg import Clock
        from diagnostic_msgs.msg import DiagnosticArray
        self.pub_clock = node.create_publisher(Clock, c.CLOCK, c.CLOCK_QOS)
        self.pub_diag = node.create_publisher(DiagnosticArray, c.DIAGNOSTICS, c.DIAGNOSTICS_QOS)
        self.sub_cmd = node.create_subscription(c.TOPIC_TYPES[c.COMMAND], c.COMMAND,
                                                self._on_command, c.LOOP_QOS)
        self.executor = make_executor(executor)
        self.executor_kind = executor
        self.executor.add_node(node)

        # episode state
        self.k = 0
        self.last_cmd_step = -1
        self.pending: np.ndarray | None = None     # accepted command for step self.k
        self.held = np.zeros(info.n_u)            # last applied (zeros before the first command)
        self.rejections = gate.RejectionLog()
        self.diag_throttle = Throttle(REJECTION_DIAGNOSTICS_PERIOD_S)
        self.deadline_misses = 0
        self.t_pub = np.full(self.N + 1, np.nan)   # wall time y_k was published
        self.t_cmd = np.full(self.N, np.nan)       # wall time command k arrived
        keep = bool(p['trajectory_file'])          # the trajectory is kept only when asked for
        self.F = np.empty((self.N + 1, info.n_field)) if keep else None
        self.U = np.empty((self.N, info.n_u)) if keep else None
        self.Y = np.empty((self.N + 1, info.n_y)) if keep else None
        self.finished = False
        self._next_diag = 0.0
        self._t_start = None
        self._t_end = None

        self.log.info(
            f"plant: {scen.plant_type}, scenario {p['scenario_file'] or '<reference>'} (n_x={info.n_x}, "
            f"n_field={info.n_field}, n_u={info.n_u}, n_y={info.n_y}, dt={info.dt:g} s, N={self.N}), "
            f"mode {p['mode']}"
            + (f" at real_time_factor {p['real_time_factor']:g} (a step every "
               f"{fmt_s(info.dt / p['real_time_factor'])})" if p['mode'] == 'realtime' else
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
            u, rej = gate.check_vector(msg.name, msg.effort, self.input_names, 'command effort')
        if rej is not None:
            self._reject(rej)
            return
        self.last_cmd_step = k
        self.pending = u
        self.t_cmd[k] = t

    def _reject(self, rej: gate.Rejection) -> None:
        log_rejection(self.log, self.rejections, rej, f'rejected command at step {self.k}')
        if self.diag_throttle.ready():
            self._publish_diagnostics()

    # ---------------------------------------------------------------- output
    def _publish_step(self, k: int, x: np.ndarray) -> None:
        """/clock k, then y_k: the controllers' clock reads k*dt when y_k arrives.  The field
        (analysis only) is published later by `_publish_field`, off the measurement-to-command
        path: serializing n_field points here would delay taking the command."""
        y = self.plant.observe(x)[0] + self.v[k]
        if self.Y is not None:
            self.Y[k] = y
            self.F[k] = self.plant.field(x)[0]
        msg = c.joint_state(k, self.dt, self.sensors, position=y, frame_id=self.info.frame_id)
        self.pub_clock.publish(c.clock_msg(k, self.dt))
        self.t_pub[k] = steady()
        self.pub_y.publish(msg)

    def _publish_field(self, k: int, x: np.ndarray) -> None:
        """The true field as a cloud (and an image for grid plants), built only when subscribed."""
        if not self.p['publish_field']:
            return
        cloud = self.pub_field.get_subscription_count() > 0
        image = self.pub_image is not None and self.pub_image.get_subscription_count() > 0
        if cloud or image:
            f = self.plant.field(x)[0]
            if cloud:
                self.pub_field.publish(self.cloud.build(k, self.dt, f))
            if image:
                self.pub_image.publish(c.field_image(k, self.dt, f, self.info.grid_shape, self.info.frame_id))

    def health(self) -> c.Health:
        lat = percentiles(self._latencies())
        level, msg = c.OK, 'ok'
        if self.deadline_misses or self.rejections.total:
            level = c.WARN
            msg = f'{self.deadline_misses} deadline misses, {self.rejections.total} rejected commands'
        return c.Health(name=f'{self.node.get_fully_qualified_name()}', hardware_id=f'{self.scenario.plant_type}_plant',
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
            self.pub_diag.publish(c.diagnostics(c.stamp(self.k, self.dt), [self.health()], self.info.frame_id))
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
        # with subscribers required, also a command publisher (a command sent before
        # its writer matched our reader would be lost)
        ok = lambda: (self.pub_y.get_subscription_count() >= need_y
                      and self.pub_field.get_subscription_count() >= need_f
                      and (need_y == 0 or self.sub_cmd.get_publisher_count() >= 1))
        if need_y or need_f:
            self.log.info(f'waiting for {need_y} measurement subscriber(s)'
                          + (f', {need_f} field subscriber(s)' if need_f else '')
                          + ' and a command publisher')
        if not self._spin_until(t_end, ok):
            raise EpisodeError(
                f"no controller: {self.pub_y.get_subscription_count()} of {need_y} measurement "
                f"subscribers, {self.sub_cmd.get_publisher_count()} command publishers and "
                f"{self.pub_field.get_subscription_count()} of {need_f} field "
                f"subscribers after start_timeout_s = {self.p['start_timeout_s']:g} s "
                f"(is the estimator/lqg running in namespace {self.node.get_namespace()} with "
                f"the same ROS_DOMAIN_ID?)")
        self._spin_until(steady() + self.p['start_delay_s'])

    def run(self) -> int:
        self.pub_scen.publish(c.scenario_msg(self.payload))
        self._publish_diagnostics()
        self._wait_for_peers()
        realtime = self.p['mode'] == 'realtime'
        period = self.dt / self.p['real_time_factor']
        x = self.plant.initial_state(1)
        self._t_start = t0 = steady()
        self.log.info(f'episode start: {self.N} steps')
        for k in range(self.N + 1):
            self.k = k
            self._publish_step(k, x)
            if k == self.N:
                self._publish_field(k, x)
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
                        f"lockstep: no valid command stamped step {k} (t = {k * self.dt:g} s) "
                        f"within command_timeout_s = {self.p['command_timeout_s']:g} s{why}; is the "
                        f"lqg (or estimator + lqr) running on {self.node.get_namespace()}?")
                u = self.pending
            u_app = clip_inputs(u, self.lo, self.hi)
            self.pending = None
            self.held = u_app
            if self.U is not None:
                self.U[k] = u_app
            self.pub_u.publish(c.joint_state(k, self.dt, self.input_names, effort=u_app, frame_id=self.info.frame_id))
            self._publish_field(k, x)
            x = self.plant.step(x, u_app[None], self.w[k][None])
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
                'scenario_file': self.p['scenario_file'], 'plant': self.scenario.plant_type,
                'namespace': self.node.get_namespace()}

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
            np.savez(path, F=self.F[:n + 1], U=self.U[:n], Y=self.Y[:n + 1],
                     scenario=np.frombuffer(self.payload.encode(), dtype=np.uint8),
                     seed=self.p['seed'], run=self.p['run'])
        # Let reliable subscribers receive the last messages before the writers go away.
        flush_publishers([pub for pub in (self.pub_y, self.pub_field, self.pub_image, self.pub_u, self.pub_clock,
                                          self.pub_diag) if pub is not None])

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        self.node.destroy_node()


def main(argv: list[str] | None = None) -> int:
    def add(parser):
        parser.add_argument('--summary-json', metavar='PATH',
                            help='write the end-of-episode summary as JSON (same as -p summary_file:=PATH)')

    opts, args = parse_front('plant', 'Simulated plant (sep_plant; the heat slab by default, any plant '
                             'of the plant protocol via scenario_file): the plant node of the sep closed loop.',
                             argv, add, PARAMETERS)
    limit_blas_threads(1)
    return run_node(lambda a: PlantNode(a, opts.summary_json, opts.executor), args, 'plant')


if __name__ == '__main__':
    sys.exit(main())
