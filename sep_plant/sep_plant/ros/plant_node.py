"""`plant`: any plant of the plant protocol as a ROS 2 node (docs/reference/topics.md); the
reference scenario's plant by default.

Publishes /clock (simulated time k*dt), measurements (y_k), applied_input (u applied
at step k), field (true field as a PointCloud2 with the nodes' x, y, z), for grid plants
field_image (32FC1; the middle slice of a 3-D grid), scenario (its scenario and plant
description as JSON, latched) and /diagnostics; subscribes command.  One episode of N
steps per process, then exit 0; with the parameter ``episodes`` K != 1, K episodes one after the
other (0: until stopped), episode i playing Monte Carlo run ``run + i``, each announced by a new
scenario message with an ``"episode"`` entry (the controllers reset on it; a lockstep episode
whose command does not come is cut off and the next one starts).  The plant is checked against
the protocol before step 0.

A thin node around `sep_plant.plant_episode.PlantEpisode` (the episode: lockstep or real-time
stepping, command gating, limits, the noise of (seed, run), latencies); here: parameters,
topics, waiting for the peers, logs, diagnostics, the summary and trajectory files.

Modes:
* lockstep (default): after y_k, wait (up to command_timeout_s) for a valid command stamped k;
  on timeout log which step and why, exit EXIT_TIMEOUT (3).  Deterministic, as fast as the
  controller answers.
* realtime: steps on a steady-clock schedule every dt / real_time_factor.  A command for step k
  that has not arrived by the tick is a deadline miss: the last applied command is held (zeros
  before the first command: the plant does not know the nominal; the LQR's own fallback to the
  nominal covers a missing estimate).

Perturbation (a model-mismatch rehearsal, docs/robustness.md): the parameters input_gain,
input_offset and sensor_bias wrap the scenario's plant in `sep_plant.perturb.PerturbedPlant`
(u_applied = g (u + w) + b, y = h(x) + s); the non-neutral values go out with the scenario
(and on /diagnostics and in the summary), so controllers and bag analyses see them.

Bad commands (NaN/Inf, wrong length, unknown names, stamps off the step grid, stale, duplicate,
for a future step) are rejected, counted per reason, logged and reported on /diagnostics.
The field messages are built only while somebody subscribes to them.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from sep_plant.plant_episode import MODES, CommandTimeout, EpisodeError, PlantEpisode
from sep_plant.noise import DEFAULT_SEED
from sep_plant.ros import contract as c
from sep_plant.ros.base import (EXIT_OK, NodeBase, Shutdown, StartError, append_json_line, declare,
                                flush_publishers, fmt_s, percentiles, steady)
from sep_plant.ros.process import NodeProcess, node_main, spin_once

PARAMETERS = f"""parameters (set with --ros-args -p NAME:=VALUE or --params-file $(ros2 pkg prefix sep_plant)/share/sep_plant/config/plant.yaml):
  scenario_file (str, '')          scenario YAML; '' = the shipped reference scenario
  mode (str, lockstep)             lockstep | realtime
  real_time_factor (float, 10)     realtime: steps every dt / real_time_factor  [0.01, 1000]
  seed (int, {DEFAULT_SEED}), run (int, 0)      noise = run `run` of the Monte Carlo with seed `seed`
  episodes (int, 1)                episodes played one after the other in this process (0 = until
                                   stopped); episode i plays run `run + i` and is announced by a new
                                   scenario message with an "episode" entry
  episode_log_file (str, '')       append one JSON line per episode (index, run, status, steps, ...)
  command_timeout_s (float, 10)    lockstep: wait this long for the command of each step
  publish_field (bool, true)       publish the true field on field
  wait_for_subscribers (int, 1)    matched measurement subscribers needed before step 0
  wait_for_field_subscribers (int, 0)  matched field subscribers needed before step 0
  wait_for_scenario_subscribers (int, 0)  matched scenario subscribers needed before step 0 (each
                                   holds the announcement before y_0: a recorder of several
                                   episodes, whose bag is split at the announcements)
  start_timeout_s (float, 30)      give up (exit 3) if they do not appear in time
  start_delay_s (float, 0.2)       settle time after they appeared (endpoint matching)
  autostart (bool, true)            configure and activate at start; false: wait unconfigured for the
                                   lifecycle transitions (ros2 lifecycle set /sep/plant configure ...)
  diagnostics_period_s (float, 1)  /diagnostics period (also sent on a rejection, at most 5 Hz)
  summary_file (str, '')           write the end-of-episode summary as JSON
  trajectory_file (str, '')        write F (N+1,n_field), U (N,n_u), Y (N+1,n_y) as .npz (kept
                                   in memory only when set)
  input_gain (double or double[], 1)    actuator gain g: u_applied = g (u + w) + b (a model
  input_offset (double or double[], 0)  mismatch of the actuators, sep_plant.perturb; one value or
  sensor_bias (double or double[], 0)   one per input) and sensor bias s: y = h(x) + s + v (one value
                                   or one per output); published with the scenario (docs/robustness.md)"""


def declare_parameters(node) -> dict:
    """The plant's own parameters (summary_file and diagnostics_period_s: `NodeBase`)."""
    p = {'scenario_file': declare(node, 'scenario_file', '', "scenario YAML file; '' = reference"),
         'mode': declare(node, 'mode', 'lockstep', 'lockstep | realtime', constraints='one of: lockstep, realtime'),
         'real_time_factor': declare(node, 'real_time_factor', 10.0, 'realtime mode: simulated seconds per wall second',
                                     lo=0.01, hi=1000.0),
         'seed': declare(node, 'seed', DEFAULT_SEED, 'noise seed (Monte Carlo seed)', lo=0, hi=2**31 - 1),
         'run': declare(node, 'run', 0, 'run index within the seed', lo=0, hi=10**6),
         'command_timeout_s': declare(node, 'command_timeout_s', 10.0, 'lockstep: seconds to wait for each command',
                                      lo=0.001, hi=86400.0),
         'publish_field': declare(node, 'publish_field', True, 'publish the true field'),
         'wait_for_subscribers': declare(node, 'wait_for_subscribers', 1,
                                         'matched measurement subscribers needed to start', lo=0, hi=1000),
         'wait_for_field_subscribers': declare(node, 'wait_for_field_subscribers', 0,
                                               'matched field subscribers needed to start', lo=0, hi=1000),
         'wait_for_scenario_subscribers': declare(node, 'wait_for_scenario_subscribers', 0,
                                                  'matched scenario subscribers needed to start (each holds '
                                                  'the announcement before y_0)', lo=0, hi=1000),
         'start_timeout_s': declare(node, 'start_timeout_s', 30.0, 'seconds to wait for subscribers',
                                    lo=0.0, hi=86400.0),
         'start_delay_s': declare(node, 'start_delay_s', 0.2, 'settle time after the subscribers appeared',
                                  lo=0.0, hi=60.0),
         'trajectory_file': declare(node, 'trajectory_file', '', 'true trajectory .npz'),
         'episodes': declare(node, 'episodes', 1, 'episodes to play in this process (episode i plays run run+i; '
                             '0 = until stopped)', lo=0, hi=10**9),
         'episode_log_file': declare(node, 'episode_log_file', '', 'one JSON line per episode played')}
    if p['mode'] not in MODES:
        raise StartError(f"bad parameter mode: {p['mode']!r}, expected one of {list(MODES)}")
    return p


def declare_perturbation(node, n_u: int, n_y: int) -> dict[str, list[float]]:
    """The parameters input_gain, input_offset, sensor_bias (a double or a double array each, any
    type accepted at declaration so that both work) as (n,) lists; StartError naming the parameter
    when a value is not a number or has the wrong length."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import ParameterException

    from sep_plant.perturb import NEUTRAL, PERTURBATIONS, PerturbationError, channel_values

    dims = {'n_u': n_u, 'n_y': n_y}
    out = {}
    for key, neutral in NEUTRAL.items():
        n = dims[PERTURBATIONS[key]]
        desc = ParameterDescriptor(name=key, read_only=True, dynamic_typing=True,
                                   description=f'{key}: a double for every channel or a double array of '
                                               f'{n} ({PERTURBATIONS[key]}); {neutral:g} = none')
        try:
            value = node.declare_parameter(key, float(neutral), desc).value
            out[key] = channel_values(key, list(value) if isinstance(value, (list, tuple)) or
                                      hasattr(value, 'tolist') else value, n).tolist()
        except (ParameterException, PerturbationError) as exc:
            raise StartError(f'bad parameter {key}: {exc}') from None
    return out


def load_checked_scenario(path: str):
    """The scenario of `path` ('' = the reference) with its plant checked against the protocol."""
    from sep_plant.conformance import check_plant
    from sep_plant.protocol import PlantError
    from sep_plant.scenario import ScenarioError, load_scenario

    try:
        scen = load_scenario(path or None)
        check_plant(scen.plant, scen.problem.channels('u_init', int(scen.plant.n_u)), name=scen.plant_type)
    except (ScenarioError, PlantError) as exc:
        raise StartError(f"bad scenario_file {path or '<reference>'}: {exc}") from None
    return scen


def perturbed(plant, perturbation: dict[str, list[float]]):
    """`plant` wrapped in a `sep_plant.perturb.PerturbedPlant` when a perturbation value is not
    neutral, else `plant` itself (the same object: nothing changes for an unperturbed plant)."""
    from sep_plant.perturb import NEUTRAL, PerturbedPlant

    if all(np.all(np.asarray(v) == NEUTRAL[k]) for k, v in perturbation.items()):
        return plant
    return PerturbedPlant.around(plant, **perturbation)


class EpisodeTally:
    """What the episodes of a multi-episode plant came to (the summary's ``episodes``)."""

    def __init__(self) -> None:
        self.by_status: dict[str, int] = {}
        self.deadline_misses = self.rejected_messages = 0

    def add(self, rec: dict) -> None:
        self.by_status[rec['status']] = self.by_status.get(rec['status'], 0) + 1
        self.deadline_misses += rec['deadline_misses']
        self.rejected_messages += rec['rejected_messages']

    def as_dict(self) -> dict:
        return {'played': sum(self.by_status.values()), 'by_status': dict(self.by_status),
                'deadline_misses': self.deadline_misses, 'rejected_messages': self.rejected_messages}


class PlantNode(NodeBase):
    """The plant node: a `PlantEpisode` with its topics."""

    role = 'plant'

    def __init__(self, summary_json: str | None = None):
        super().__init__('plant')
        if summary_json:
            self.summary_file = summary_json
        self.executor = None
        self.episode_started = False

    def configure(self) -> None:
        """Load and check the scenario and its plant, build the episode, create the topics."""
        if self.episode_started:
            raise StartError('this process has run its episode (one episode per plant process): shut it down '
                             'and start a new plant')
        self.p = p = declare_parameters(self.node)
        self.scenario = scen = load_checked_scenario(p['scenario_file'])
        self.plant = plant = perturbed(scen.plant, declare_perturbation(self.node, int(scen.plant.n_u),
                                                                        int(scen.plant.n_y)))
        self.perturbation = plant.perturbation() if plant is not scen.plant else {}
        self.episode = ep = self._new_episode(0)
        self.info, self.N = info, N = ep.info, ep.N
        self.dt, self.frame_id = info.dt, info.frame_id
        self.payload = self._payload(0)
        self.played = EpisodeTally()
        self.cloud = c.CloudBuilder(scen.plant.field_coordinates(), info.field_name, info.frame_id)
        self.input_names, self.sensors = list(info.input_names), list(info.output_names)
        self.t_end: float | None = None
        self.ignored_commands = 0           # commands that came while the plant was inactive
        self.safe_steps: list[int] = []     # steps that got the safe input (deactivated mid-step)
        self._create_topics()
        self.log.info(
            f"plant: {scen.plant_type}, scenario {p['scenario_file'] or '<reference>'} (n_x={info.n_x}, "
            f"n_field={info.n_field}, n_u={info.n_u}, n_y={info.n_y}, dt={info.dt:g} s, N={N}), mode {p['mode']}"
            + (f" at real_time_factor {p['real_time_factor']:g} (a step every {fmt_s(ep.period)})"
               if p['mode'] == 'realtime' else f", command_timeout_s {p['command_timeout_s']:g}")
            + f", seed {p['seed']} run {p['run']}, namespace {self.node.get_namespace()}"
            + (f"; perturbed: {plant!r}" if self.perturbation else ''))

    @property
    def multi(self) -> bool:
        """Whether this plant plays more than one episode (parameter episodes != 1)."""
        return self.p['episodes'] != 1

    def _new_episode(self, index: int) -> PlantEpisode:
        """Episode `index`: Monte Carlo run ``run + index`` of the seed."""
        p = self.p
        return PlantEpisode(self.plant, self.scenario.problem, seed=p['seed'], run=p['run'] + index, mode=p['mode'],
                            real_time_factor=p['real_time_factor'], command_timeout_s=p['command_timeout_s'],
                            keep_trajectory=bool(p['trajectory_file']), clock=steady)

    def _payload(self, index: int) -> str:
        """The scenario message of episode `index` (with its "episode" entry when multi)."""
        from sep_plant.scenario import episode_entry, scenario_payload

        p = self.p
        entry = episode_entry(index, p['episodes'], p['seed'], p['run'] + index) if self.multi else None
        return scenario_payload(self.scenario, self.episode.info, self.perturbation, entry)

    def _create_topics(self) -> None:
        from rosgraph_msgs.msg import Clock

        node = self.node
        self.pub_y = node.create_publisher(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS, c.LOOP_QOS)
        self.pub_u = node.create_publisher(c.TOPIC_TYPES[c.APPLIED_INPUT], c.APPLIED_INPUT, c.LOOP_QOS)
        self.pub_field = node.create_publisher(c.TOPIC_TYPES[c.FIELD], c.FIELD, c.FIELD_QOS)
        self.pub_image = (node.create_publisher(c.TOPIC_TYPES[c.FIELD_IMAGE], c.FIELD_IMAGE, c.FIELD_QOS)
                          if self.info.grid_shape else None)
        self.pub_scen = node.create_publisher(c.TOPIC_TYPES[c.SCENARIO], c.SCENARIO, c.SCENARIO_QOS)
        self.pub_clock = node.create_publisher(Clock, c.CLOCK, c.CLOCK_QOS)
        self.sub_cmd = node.create_subscription(c.TOPIC_TYPES[c.COMMAND], c.COMMAND, self._on_command, c.LOOP_QOS)

    # ------------------------------------------------------------------ input
    def _on_command(self, msg) -> None:
        t = steady()
        if not self.active:     # inactive: the actuators hold the safe input, commands are not taken
            self.ignored_commands += 1
            return
        rej = self.episode.command(c.time_ns(msg.header.stamp), msg.name, msg.effort, t)
        if rej is not None:
            self.report_rejection('command', rej, self.episode.rejections, self.episode.k)

    # ----------------------------------------------- the episode's sink (outputs)
    def clock(self, k: int) -> None:
        """/clock k before y_k: the controllers' clock reads k*dt when y_k arrives."""
        self.last_k = k
        self.pub_clock.publish(c.clock_msg(k, self.dt))

    def measurement(self, k: int, y: np.ndarray) -> None:
        self.pub_y.publish(c.joint_state(k, self.dt, self.sensors, position=y, frame_id=self.frame_id))

    def applied(self, k: int, u: np.ndarray) -> None:
        self.pub_u.publish(c.joint_state(k, self.dt, self.input_names, effort=u, frame_id=self.frame_id))

    def field(self, k: int, field: Callable[[], np.ndarray]) -> None:
        """The true field as a cloud (and an image for grid plants), built only when subscribed:
        published after the command was taken, off the measurement-to-command path."""
        if not self.p['publish_field']:
            return
        cloud = self.pub_field.get_subscription_count() > 0
        image = self.pub_image is not None and self.pub_image.get_subscription_count() > 0
        if cloud or image:
            f = field()
            if cloud:
                self.pub_field.publish(self.cloud.build(k, self.dt, f))
            if image:
                self.pub_image.publish(c.field_image(k, self.dt, f, self.info.grid_shape, self.frame_id))

    def deadline_miss(self, k: int, period: float) -> None:
        self.log.warning(f'deadline miss at step {k}: no valid command within {fmt_s(period)}; '
                         f'holding the last applied input', throttle_duration_sec=1.0)
        if self.episode.deadline_misses == 1:
            self.publish_diagnostics()

    # ------------------------------------------------------------------- run
    def _spin_until(self, t_end: float, done: Callable[[], bool] = lambda: False) -> bool:
        """Spin callbacks until done() or the steady time t_end; returns done()."""
        while not done():
            now = steady()
            if now >= t_end:
                return done()
            spin_once(self.executor, t_end - now)
        return True

    def _wait_for_peers(self, first: bool = True) -> None:
        """Wait for the subscribers and a command publisher, then settle start_delay_s; before a
        later episode (`first` false) only when they are not all there (a controller restarting)."""
        p = self.p
        need_y, need_f = p['wait_for_subscribers'], p['wait_for_field_subscribers']
        need_s = p['wait_for_scenario_subscribers']
        # with subscribers required, also a command publisher (a command sent before
        # its writer matched our reader would be lost)
        ok = lambda: (self.pub_y.get_subscription_count() >= need_y
                      and self.pub_field.get_subscription_count() >= need_f
                      and self.pub_scen.get_subscription_count() >= need_s
                      and (need_y == 0 or self.sub_cmd.get_publisher_count() >= 1))
        if not first and ok():
            return
        if need_y or need_f or need_s:
            self.log.info(f'waiting for {need_y} measurement subscriber(s)'
                          + (f', {need_f} field subscriber(s)' if need_f else '')
                          + (f', {need_s} scenario subscriber(s)' if need_s else '') + ' and a command publisher')
        if not self._spin_until(steady() + p['start_timeout_s'], ok):
            raise EpisodeError(
                f"peers missing: {self.pub_y.get_subscription_count()} of {need_y} measurement "
                f"subscribers, {self.sub_cmd.get_publisher_count()} command publishers, "
                f"{self.pub_field.get_subscription_count()} of {need_f} field and "
                f"{self.pub_scen.get_subscription_count()} of {need_s} scenario "
                f"subscribers after start_timeout_s = {p['start_timeout_s']:g} s "
                f"(are the estimator/lqg and the recorder running in namespace {self.node.get_namespace()} "
                f"with the same ROS_DOMAIN_ID?)")
        if need_s:      # a reader matched during the wait gets the (latched) announcement: acknowledged first
            flush_publishers([self.pub_scen], 1.0)
        self._spin_until(steady() + p['start_delay_s'])

    # ------------------------------------------------------------- lifecycle
    def _hold_while_inactive(self, where: str) -> float:
        """Spin while the node is not active (Shutdown when it is shut down); the seconds held."""
        if self.active:
            return 0.0
        t0 = steady()
        self.log.info(f'inactive: holding {where} until activated')
        while not self.active:
            if self.shut_down:
                raise Shutdown
            spin_once(self.executor, 0.05)
        return steady() - t0

    def before_step(self, k: int) -> None:
        """The episode's hold point before step k (`PlantEpisode.run`): while inactive the
        simulation holds here (no time passes, the actuators hold the safe input); realtime: the
        schedule is shifted by the time held."""
        held = self._hold_while_inactive(f'before step {k}')
        if held and self.episode.t_start is not None:
            self.episode.t_start += held

    def on_deactivated(self) -> None:
        """Deactivated mid-episode: the step in progress gets the safe input (the last applied
        input, zeros before the first command: the realtime deadline-miss hold) unless its
        command already came; the episode then holds before the next step (`before_step`)."""
        if not self.configured:
            return
        ep = self.episode
        if ep.t_start is None or ep.k >= self.N or ep.has_command():
            return
        safe = ep.held.copy()
        if ep.command(ep.k * ep.dt_ns, self.input_names, safe) is None:
            ep.t_cmd[ep.k] = np.nan         # not a command: no measurement->command latency
            self.safe_steps.append(ep.k)
            self.log.warning(f'deactivated at step {ep.k}: applying the safe input (the last applied input) '
                             f'{np.array2string(safe, precision=4)}; holding before step {ep.k + 1}')

    def run_episode(self, executor) -> int:
        """Wait until active, publish the scenario, wait for the peers, run the episode
        (NodeProcess's episode)."""
        self.executor = executor
        self._hold_while_inactive('before the episode')
        self.episode_started = True
        if self.multi:
            return self._play_episodes()
        self.pub_scen.publish(c.scenario_msg(self.payload))
        self.publish_diagnostics()
        self._wait_for_peers()
        self.log.info(f'episode start: {self.N} steps')
        try:
            self.episode.run(self._spin_until, self)
        except CommandTimeout as exc:
            raise EpisodeError(f'{exc}; is the lqg (or estimator + lqr) running on '
                               f'{self.node.get_namespace()}?', exc.exit_code) from None
        self.last_k = self.N
        return EXIT_OK

    # ------------------------------------------------------- several episodes
    def _play_episodes(self) -> int:
        """Episodes 0, 1, ... (`episodes` of them, or until stopped): each announced by the
        scenario message with its "episode" entry, each a fresh `PlantEpisode` of run run+i. A
        lockstep episode whose command does not come is cut off (status 'timeout', logged) and
        the next one starts; a controller that is gone is waited for (start_timeout_s, then exit 3)."""
        n, i = self.p['episodes'], 0
        while n == 0 or i < n:
            if i > 0:
                self.episode, self.payload = self._new_episode(i), self._payload(i)
            self._log_episode(i, *self._play(i))
            i += 1
        self.last_k = self.N
        return EXIT_OK

    def _play(self, i: int) -> tuple[str, float]:
        """Announce and run episode `i`; (its status, its wall-clock start)."""
        self.pub_scen.publish(c.scenario_msg(self.payload))
        # every reader holds the announcement before y_0 goes out: the controllers reset first
        flush_publishers([self.pub_scen], 1.0)
        self._wait_for_peers(first=i == 0)
        t_wall = time.time()
        status = 'completed'
        try:
            self.episode.run(self._spin_until, self)
        except CommandTimeout as exc:
            status = 'timeout'
            self.log.warning(f'episode {i} (run {self.episode.run_index}) cut off at step {self.episode.k}: {exc}; '
                             f'next episode', throttle_duration_sec=1.0)
        self.flush()     # the episode's last messages reach bags and peers before the next announcement
        return status, t_wall

    def _log_episode(self, i: int, status: str, t_wall: float) -> None:
        """Count episode `i` and append its record to episode_log_file (its trajectory file too)."""
        ep = self.episode
        steps = self.N if status == 'completed' else ep.k
        lat = percentiles(ep.latencies())
        rec = {'episode': i, 'seed': ep.seed, 'run': ep.run_index, 'status': status, 'steps': steps,
               'deadline_misses': ep.deadline_misses, 'rejected_messages': ep.rejections.total,
               'rejected_by_reason': ep.rejections.as_dict(), 'latency_p50_s': lat['p50'],
               'latency_p99_s': lat['p99'], 't_start': t_wall, 't_end': time.time()}
        self.played.add(rec)
        if self.p['episode_log_file']:
            append_json_line(self.p['episode_log_file'], rec)
        if self.p['trajectory_file']:
            path = Path(self.p['trajectory_file'])
            self._save_trajectory(path.with_name(f'{path.stem}.e{i}{path.suffix}'), steps)

    # --------------------------------------------------------------- report
    def health(self) -> c.Health:
        ep = self.episode
        lat = percentiles(ep.latencies())
        level, msg = c.OK, 'ok'
        if ep.deadline_misses or ep.rejections.total:
            level = c.WARN
            msg = f'{ep.deadline_misses} deadline misses, {ep.rejections.total} rejected commands'
        return c.Health(name=f'{self.node.get_fully_qualified_name()}', hardware_id=f'{self.scenario.plant_type}_plant',
                        level=level, message=msg, values={
                            'step': ep.k, 'n_steps': self.N, 'mode': self.p['mode'],
                            'deadline_misses': ep.deadline_misses,
                            'rejected_messages': ep.rejections.total,
                            'rejected_by_reason': ep.rejections.as_dict(),
                            'last_rejection': str(ep.rejections.last or ''),
                            'latency_p50_s': lat['p50'], 'latency_p99_s': lat['p99'],
                            'seed': self.p['seed'], 'run': ep.run_index, 'perturbation': self.perturbation,
                            **self._rate_values()})

    def _rate_values(self) -> dict:
        """rate_clips (channel-steps the rate limit clipped), only for a rate-limited problem."""
        return {'rate_clips': self.episode.rate_clips} if self.episode.problem.rate_limited else {}

    def summary(self, status: str) -> dict:
        ep, p = self.episode, self.p
        self.t_end = steady() if self.t_end is None else self.t_end
        lat = percentiles(ep.latencies())
        return {'node': 'plant', 'status': status, 'mode': p['mode'],
                'real_time_factor': p['real_time_factor'] if p['mode'] == 'realtime' else None,
                'seed': p['seed'], 'run': ep.run_index, 'steps': ep.k if status != 'completed' else self.N,
                'n_steps': self.N, 'deadline_misses': ep.deadline_misses,
                'rejected_messages': ep.rejections.total, 'rejected_by_reason': ep.rejections.as_dict(),
                'latency_p50_s': lat['p50'], 'latency_p99_s': lat['p99'], 'latency_max_s': lat['max'],
                'wall_s': self.t_end - ep.t_start if ep.t_start else None,
                'scenario_file': p['scenario_file'], 'plant': self.scenario.plant_type,
                'perturbation': self.perturbation, 'namespace': self.node.get_namespace(),
                'safe_input_steps': self.safe_steps, 'commands_while_inactive': self.ignored_commands,
                **({'episodes': self.played.as_dict()} if self.multi else {}), **self._rate_values()}

    def finish_label(self) -> str:
        return 'episode'

    def summary_line(self, s: dict) -> str:
        return (f"{s['steps']}/{self.N} steps in {(s['wall_s'] or 0.0):.2f} s wall, {s['deadline_misses']} deadline "
                f"misses, {s['rejected_messages']} rejected commands, measurement->command latency "
                f"p50 {fmt_s(s['latency_p50_s'])} p99 {fmt_s(s['latency_p99_s'])} max {fmt_s(s['latency_max_s'])}")

    def on_finish(self, summ: dict) -> None:
        """The trajectory file (when asked for)."""
        if not self.p['trajectory_file'] or self.multi:   # several episodes: one file each (`_log_episode`)
            return
        self._save_trajectory(Path(self.p['trajectory_file']), summ['steps'])

    def _save_trajectory(self, path: Path, steps: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **self.episode.trajectory(steps),
                 scenario=np.frombuffer(self.payload.encode(), dtype=np.uint8), seed=self.p['seed'],
                 run=self.episode.run_index)

    def publishers(self):
        return [self.pub_y, self.pub_field, self.pub_image, self.pub_u, self.pub_clock, self.pub_diag]


def main(argv: list[str] | None = None) -> int:
    def add(parser):
        parser.add_argument('--summary-json', metavar='PATH',
                            help='write the end-of-episode summary as JSON (same as -p summary_file:=PATH)')

    def build(opts) -> NodeProcess:
        plant = PlantNode(opts.summary_json)
        return NodeProcess([plant], opts.executor, episode=plant.run_episode)

    return node_main('plant', 'Simulated plant (sep_plant; the reference scenario\'s plant by default, any '
                     'plant of the plant protocol via scenario_file): the plant node of the sep closed loop.',
                     argv, PARAMETERS, build, add, sim_time=False)


if __name__ == '__main__':
    sys.exit(main())
