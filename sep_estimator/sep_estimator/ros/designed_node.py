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

import numpy as np

from sep_plant.ros import contract as c
from sep_plant.ros.base import NodeBase, StartError, StopError, declare, steady
from sep_plant.ros.process import spin_once

_DESIGN_CACHE: dict[str, object] = {}


def load_design_checked(path: str):
    """Load a design file (cached per path within the process); StartError with a clear message
    when there is none or it is unreadable (the plant is checked by `check_scenario_file`)."""
    from sep_estimator.design_file import DesignFileError, load_design

    if not path:
        raise StartError('parameter design_file is required (create one with '
                         '`sep design --scenario SCENARIO --out FILE`, then -p design_file:=FILE)')
    try:
        design = _DESIGN_CACHE.get(path) or load_design(path)
    except DesignFileError as exc:
        raise StartError(f'design_file: {exc}') from None
    _DESIGN_CACHE[path] = design
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
        from sep_plant.scenario import parse_scenario_message

        topic = self.sub_scenario.topic_name
        try:
            plant, info, perturbation = parse_scenario_message(msg.data)
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
        if changed:
            self._log_mismatch(f'the plant scenario on {self.sub_scenario.topic_name}')
        if not self.plant_scenario_checked and not diffs:
            self.log.info(f'plant scenario on {self.sub_scenario.topic_name} matches the design')
        self.plant_scenario_checked = True

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
