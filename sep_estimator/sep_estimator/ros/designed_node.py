"""What the design-driven ROS 2 nodes (estimator, lqr) add to `sep_plant.ros.base.NodeBase`:
the design file, loaded once per process and checked against the scenario.

A node refuses to start (StartError, exit code 2) when its design file is missing, corrupt, or
made for another plant than the one given by the ``scenario_file`` parameter or published by
the plant on scenario (latched); the message names every mismatching value
(docs/reference/design-file.md). With ``allow_model_mismatch:=true`` (the sim-to-real
rehearsal, docs/robustness.md) a plant that differs only in plant keys or in a perturbation of
its actuators and sensors is accepted: the node logs the differences, reports them as
``model_mismatch`` on /diagnostics and in its summary (`sep_estimator.model_mismatch`).
ROS-side module (imports rclpy).
"""
from __future__ import annotations

import os
from collections import OrderedDict

import numpy as np

from sep_plant.ros import contract as c
from sep_plant.ros.base import NodeBase, StartError, StopError, append_json_line, declare, steady
from sep_plant.ros.process import spin_once

from sep_estimator.episode_switch import EpisodeSwitch

#: loaded designs of this process by file identity (`_file_key`), the most recent last
_DESIGN_CACHE: 'OrderedDict[tuple, object]' = OrderedDict()
#: designs kept (a long-running node swapping designs keeps only the recent ones)
DESIGN_CACHE_SIZE = 4

# The --help lines of the parameters every designed node (estimator, lqr, lqg) has.
DESIGNED_NODE_PARAMETERS = """
  autostart (bool, true)           configure and activate at start; false: a managed node that waits
                                   for its lifecycle transitions (docs/reference/parameters.md)
  exit_at_end (bool, true)         exit 0 after the last step (k = N; of the plant's last episode)
  next_design_file (str, '')       set at run time: the design for the next episode, checked at once
                                   as design_file at start (a refused one is reported, the old kept)
  episode_log_file (str, '')       append one JSON line per episode served
  diagnostics_period_s (float, 1)  /diagnostics period
  summary_file (str, '')           end-of-episode summary JSON
  use_sim_time (bool, true)        time from the plant's /clock"""


def _file_key(path: str) -> tuple:
    """A design file's identity: path, mtime, size and inode (a file rewritten in place or
    replaced by another under the same name is loaded anew)."""
    try:
        st = os.stat(path)
    except OSError:
        return (path,)
    return (path, st.st_mtime_ns, st.st_size, st.st_ino)


def load_design_checked(path: str, what: str = 'design_file'):
    """Load a design file (cached by path, mtime, size and inode within the process); StartError
    with a clear message when there is none or it is unreadable (the plant is checked by
    `check_scenario_file`)."""
    from sep_estimator.design_file import DesignFileError, load_design

    if not path:
        raise StartError(f'parameter {what} is required (create one with '
                         f'`sep design --scenario SCENARIO --out FILE`, then -p {what}:=FILE)')
    key = _file_key(path)
    design = _DESIGN_CACHE.get(key) if len(key) > 1 else None
    if design is None:
        try:
            design = load_design(path)
        except DesignFileError as exc:
            raise StartError(f'{what}: {exc}') from None
    _DESIGN_CACHE[key] = design
    _DESIGN_CACHE.move_to_end(key)
    while len(_DESIGN_CACHE) > DESIGN_CACHE_SIZE:
        _DESIGN_CACHE.popitem(last=False)
    return design


def check_scenario_file(design, path: str, scenario_file: str, allow_model_mismatch: bool = False) -> list[str]:
    """The model mismatch between the design and the plant of `scenario_file` ('' : none, []);
    StartError when the design may not run on that plant (`sep_estimator.model_mismatch`)."""
    from sep_estimator.design_file import DesignFileError
    from sep_estimator.model_mismatch import model_mismatch
    from sep_plant.scenario import ScenarioError, load_scenario

    if not scenario_file:
        return []
    try:
        plant = load_scenario(scenario_file)
    except ScenarioError as exc:
        raise StartError(f'bad scenario_file: {exc}') from None
    try:
        return model_mismatch(design, plant, allow=allow_model_mismatch, where=f'design file {path}')
    except DesignFileError as exc:
        raise StartError(f'{exc} (scenario_file {scenario_file})') from None


def scenario_summary(design) -> str:
    i, p = design.info, design.problem
    lo, hi = p.limits(i.n_u)
    lim = f'[{lo.min():g}, {hi.max():g}]' if np.all(lo == lo[0]) and np.all(hi == hi[0]) else 'per input'
    return (f'plant {design.scenario.plant_type}, n_field={i.n_field}, n_u={i.n_u}, n_y={i.n_y}, '
            f'dt={i.dt:g} s, N={p.n_steps}, u in {lim}')


class DesignedNode(NodeBase):
    """A node driven by a design file (``self.design``): its parameters design_file,
    scenario_file, wait_for_scenario_s, exit_at_end, and the check of the plant's scenario."""

    def __init__(self, node_name: str, peer: 'DesignedNode | None' = None):
        """peer: a node of the same process whose design this one uses (the lqg's LQR uses its
        estimator's: configure the estimator first)."""
        super().__init__(node_name)
        self.peer = peer
        # the lqg's LQR follows its estimator's episodes (one switch, driven by the estimator)
        self.switch = peer.switch if peer is not None else EpisodeSwitch()
        self.followers: list[DesignedNode] = []   # nodes of this process that use this one's design (lqg)
        self.next_design = None                  # an accepted next_design_file, used from the next episode
        self.plant_scenario: tuple | None = None  # (scenario, info, perturbation) last published by the plant
        self.episodes_played = 0
        self.serving: int | None = None           # the episode the filter / controller state belongs to
        self.episode_over = False                # the episode's last step N is handled
        self.node.add_on_set_parameters_callback(self._on_set_parameters)

    def configure(self) -> None:
        """The parameters, the design file loaded and checked against scenario_file, the scenario
        subscription (StartError: refused)."""
        node = self.node
        self.design_file = declare(node, 'design_file', '', 'design file written by `design` (required)')
        self.scenario_file = declare(node, 'scenario_file', '',
                                     "optional: refuse to start unless the design matches this "
                                     "scenario file ('' = check only against scenario)")
        self.wait_for_scenario_s = declare(node, 'wait_for_scenario_s', 0.0,
                                           'wait this long at start for the plant scenario on '
                                           'scenario (0 = do not wait)', lo=0.0, hi=3600.0)
        self.exit_at_end = declare(node, 'exit_at_end', True, 'exit after the last step of the episode')
        self.allow_model_mismatch = declare(node, 'allow_model_mismatch', False,
                                            'run the design on a plant whose keys or actuator/sensor '
                                            'perturbation differ from the design\'s model (logged and '
                                            'reported as model_mismatch)')
        self.episode_log_file = declare(node, 'episode_log_file', '', 'one JSON line per episode served')
        declare(node, 'next_design_file', '', 'design file for the next episode (checked at once as at start; '
                "a refused one leaves the design in use)", read_only=False)
        self.design = self._peer_design() if self.peer is not None else load_design_checked(self.design_file)
        #: how the plant differs from the design's model (empty: it is the model)
        self.model_mismatch: list[str] = check_scenario_file(self.design, self.design_file, self.scenario_file,
                                                             self.allow_model_mismatch)
        self._log_mismatch(f'scenario_file {self.scenario_file}')
        self.info = self.design.info
        self.dt = self.info.dt
        self.frame_id = self.info.frame_id
        self.N = self.design.n_steps
        self.dt_ns = c.dt_ns(self.dt)
        self.plant_scenario_checked = False
        self.sub_scenario = node.create_subscription(c.TOPIC_TYPES[c.SCENARIO], c.SCENARIO,
                                                     self._on_scenario, c.SCENARIO_QOS)

    def _peer_design(self):
        peer = self.peer
        if not peer.configured:
            raise StartError(f'{peer.node.get_fully_qualified_name()} of this process is not configured: '
                             f'configure it first (this node uses its design)')
        if self.design_file != peer.design_file:
            self.log.warning(f'design_file of {self.role} ({self.design_file}) differs from the '
                             f'{peer.role}\'s; using the {peer.role}\'s ({peer.design_file})')
        return peer.design

    # ----------------------------------------------------------- scenario
    def _on_scenario(self, msg) -> None:
        from sep_estimator.design_file import DesignFileError
        from sep_estimator.model_mismatch import model_mismatch
        from sep_plant.scenario import scenario_message_parts

        topic = self.sub_scenario.topic_name
        try:
            plant, info, perturbation, episode = scenario_message_parts(msg.data)
        except ValueError as exc:
            self.fatal = self._scenario_refused(f'unreadable plant scenario on {topic}: {exc}')
            return
        try:
            diffs = model_mismatch(self.design, plant, info, perturbation, self.allow_model_mismatch,
                                   f'design file {self.design_file}')
        except DesignFileError as exc:
            self.fatal = self._scenario_refused(f'{exc} (plant scenario from {topic})')
            return
        changed = diffs != self.model_mismatch
        self.model_mismatch = diffs
        self.plant_scenario = (plant, info, perturbation)
        if changed:
            self._log_mismatch(f'the plant scenario on {self.sub_scenario.topic_name}')
        if not self.plant_scenario_checked and not diffs:
            self.log.info(f'plant scenario on {self.sub_scenario.topic_name} matches the design')
        self.plant_scenario_checked = True
        if episode is not None and self.peer is None:
            if self.switch.announce(episode['index'], episode['of'], busy=self.last_k >= 0 and not self.episode_over):
                self.start_episode()
            elif self.serving is None:
                self.serving = self.switch.index
                for f in self.followers:
                    f.serving = self.serving

    # ----------------------------------------------------------- episodes
    def taking(self, msg) -> bool:
        """Whether the node takes the message `msg`: active, and, with wait_for_scenario_s > 0, a
        first message of a step k > 0 only once the plant's scenario is received and checked (a node
        that joins a running multi-episode plant mid-episode learns from it which episode it joins; an
        episode begun at step 0 goes on as always)."""
        if not self.active or self.plant_scenario_checked or self.wait_for_scenario_s <= 0:
            return self.active
        from sep_plant import gate

        k, _ = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        return k == 0 or self.last_k >= 0       # held back: only a first message of a step k > 0

    def end_of_episode(self) -> None:
        """The episode's last step N is handled: the node is done (it exits with exit_at_end) unless
        the plant plays more episodes; then it resets for the next one if it was announced already."""
        self.episode_over = True
        if self.switch.last_episode():
            self.done = True
        elif self.peer is None and self.switch.take_pending():
            self.start_episode()

    def stale_step(self, k: int, last: int) -> None:
        """A message stamped k came where the node had handled step `last`: with a new episode
        announced and k <= last, the old episode was cut off and the plant began the new one:
        reset now (the message then belongs to the new episode)."""
        if k <= last and self.peer is None and self.switch.take_pending():
            self.start_episode()

    def start_episode(self, ended: int | None = None) -> None:
        """Reset for the episode `switch.index`: the old one's record to episode_log_file, the
        accepted next design adopted, the filter / controller anew (`reset_episode`); then the
        nodes that follow this one's design (the lqg's LQR)."""
        ended = self.serving if ended is None else ended
        self.log_episode(ended)
        if self.next_design is not None and self.peer is None:
            (self.design_file, design), self.next_design = self.next_design, None
            self.adopt_design(design)
        elif self.peer is not None and self.design is not self.peer.design:
            self.design_file = self.peer.design_file
            self.adopt_design(self.peer.design)
        self.reset_episode()
        self.last_k, self.episode_over, self.done = -1, False, False
        self.episodes_played += 1
        self.serving = self.switch.index
        self.log.info(f'episode {self.switch.index}: {self.role} reset (design file {self.design_file})')
        for f in self.followers:
            f.start_episode(ended)

    def on_finish(self, summ: dict) -> None:
        """The record of the episode the process ends in (a multi-episode plant)."""
        if self.switch.multi:
            self.log_episode(self.serving)

    def log_episode(self, index: int | None) -> None:
        """Append the record of the episode `index` that ends to episode_log_file (when set)."""
        if not self.episode_log_file:
            return
        rec = {'node': self.role, 'episode': index, 'design_file': self.design_file,
               'status': 'completed' if self.episode_over else ('cut_off' if self.last_k >= 0 else 'no_steps'),
               'last_step': self.last_k, 'pid': os.getpid(), **self.episode_counters()}
        append_json_line(self.episode_log_file, rec)

    def episode_summary(self) -> dict:
        """The summary's episode entries (a multi-episode plant only)."""
        return {'episode': self.switch.index, 'episodes_played': self.episodes_played + 1} if self.switch.multi else {}

    def episode_counters(self) -> dict:
        """The episode's counts for its record (subclasses: their core's counters)."""
        return {}

    def reset_episode(self) -> None:
        """A fresh filter / controller for the next episode (subclasses)."""

    def adopt_design(self, design) -> None:
        """Use `design` from now on (subclasses rebuild what depends on it)."""
        self.design = design
        self.info, self.dt, self.frame_id = design.info, design.info.dt, design.info.frame_id
        self.N, self.dt_ns = design.n_steps, c.dt_ns(design.info.dt)

    # ------------------------------------------------------- design swap
    def _on_set_parameters(self, params):
        """next_design_file: checked at once exactly as design_file at start (file, scenario_file,
        the plant's scenario); refused (the result says why, the log too) or kept for the next episode."""
        from rcl_interfaces.msg import SetParametersResult

        for prm in params:
            if prm.name != 'next_design_file' or not prm.value:
                continue
            if not self.configured:
                return SetParametersResult(successful=False, reason='next_design_file: the node is not configured '
                                           '(configure it with its design_file first)')
            try:
                self.next_design = (str(prm.value), self.check_next_design(str(prm.value)))
            except StartError as exc:
                why = f'next_design_file {prm.value} refused, keeping design file {self.design_file}: {exc}'
                self.log.error(why)
                return SetParametersResult(successful=False, reason=why)
            self.log.info(f'next_design_file {prm.value} accepted: used from the next episode')
        return SetParametersResult(successful=True)

    def check_next_design(self, path: str):
        """The design of `path` if it may replace the one in use: loaded and checked against
        scenario_file and the plant's scenario as at start, the same horizon and interface."""
        from sep_estimator.design_file import DesignFileError
        from sep_estimator.model_mismatch import model_mismatch

        if self.peer is not None:
            raise StartError(f'this node uses the design of {self.peer.node.get_fully_qualified_name()}: '
                             f'set next_design_file there')
        design = load_design_checked(path, 'next_design_file')
        check_scenario_file(design, path, self.scenario_file, self.allow_model_mismatch)
        if self.plant_scenario is not None:
            try:
                model_mismatch(design, *self.plant_scenario, self.allow_model_mismatch, f'design file {path}')
            except DesignFileError as exc:
                raise StartError(f'{exc} (plant scenario from {self.sub_scenario.topic_name})') from None
        if design.n_steps != self.N or design.info.dt != self.dt:
            raise StartError(f'design file {path}: N = {design.n_steps}, dt = {design.info.dt:g} s; the design '
                             f'in use has N = {self.N}, dt = {self.dt:g} s')
        return design

    def _scenario_refused(self, why: str) -> StartError:
        """Before the first step: a refusal to start. After steps were run (the plant's scenario
        changed mid-episode): a StopError that says so, at which step, and why."""
        if self.last_k < 0:
            return StartError(why)
        return StopError(f'the plant scenario changed mid-episode (after step {self.last_k}) and no longer '
                         f'fits the design, so this node stops commanding: {why}')

    @staticmethod
    def mismatch_note(summary: dict) -> str:
        """The end of a summary line: '; model mismatch: ...', or '' when the plant is the model."""
        diffs = summary.get('model_mismatch')
        return f"; model mismatch: {'; '.join(diffs)}" if diffs else ''

    def _log_mismatch(self, source: str) -> None:
        if self.model_mismatch:
            self.log.warning(f'model mismatch (allow_model_mismatch): {source} differs from the design\'s model: '
                             + '; '.join(self.model_mismatch))

    def prepare(self, executor) -> None:
        """Wait (up to wait_for_scenario_s, when > 0) for the plant's scenario and its check."""
        if self.wait_for_scenario_s <= 0:
            return
        t_end = steady() + self.wait_for_scenario_s
        while not self.plant_scenario_checked and self.fatal is None and steady() < t_end:
            spin_once(executor, 0.05)
        if self.fatal is not None:
            raise self.fatal
        if not self.plant_scenario_checked:
            raise StartError(f'no plant scenario on {self.sub_scenario.topic_name} within '
                             f'wait_for_scenario_s = {self.wait_for_scenario_s:g} s')


__all__ = ['DesignedNode', 'check_scenario_file', 'load_design_checked', 'scenario_summary']
