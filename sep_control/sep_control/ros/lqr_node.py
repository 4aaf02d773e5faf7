"""`lqr`: the time-varying LQR tracking law (or the ROM-MPC) as a ROS 2 node (docs/reference/topics.md).

u_k = clip(ubar_k + K_k z_hat_k, u_min, u_max) for every state estimate z_hat_k received on
state_estimate (the ROM estimate a_hat_k and, with disturbance states, the disturbance estimates
d_hat_k: K_k is the augmented ROM's LQR, docs/method.md), published on command stamped k. With ``controller:=rom_mpc`` the
command is the first move of the box-constrained MPC on the design's ROM (`sep_control.control.mpc`):
the LQR law itself whenever no limit binds, an OSQP solve when one does, and the clipped LQR
command when that solve fails or runs past ``mpc_time_budget_s`` (counted on /diagnostics).
The old values ``lqr`` and ``mpc`` of ``controller`` still work (a deprecation warning is logged).

A thin node around `sep_control.control.loop.ControlLoopCore` (which step gets which command)
and the control law (`sep_control.control.controllers`), the same objects the offline Monte
Carlo steps; here: parameters, topics, message checks, the watchdog timer, diagnostics.

No estimate in time: the node watches measurements (only their stamps) to know that step
k has begun; if no valid estimate of step k arrives within ``estimate_timeout_s`` (steady
clock) it sends the nominal input ubar_k, logs it and counts a fallback.  An estimate that then
arrives for that step is counted as late and dropped (the plant already has a command).  Set
``estimate_timeout_s`` below the plant's period in real time (the demo uses 40 % of
dt / real_time_factor) and well above the estimator's latency in lockstep.

Bad estimates (wrong length/names, NaN/Inf, off-grid/stale/duplicate stamps) are rejected and
counted on /diagnostics; the watchdog then covers the step.
"""
from __future__ import annotations

import sys

import numpy as np

from sep_plant import gate
from sep_plant.ros import contract as c
from sep_plant.ros.base import SampleWindow, StartError, declare, fmt_s, steady
from sep_plant.ros.process import NodeProcess, node_main
from sep_estimator.disturbance import summary as disturbance_summary
from sep_estimator.ros.designed_node import DESIGNED_NODE_PARAMETERS, DesignedNode, scenario_summary

from sep_control.control.controllers import (CONTROLLER_ALIASES, NODE_CONTROLLERS, Controller, MpcOptions,
                                             make_controller, resolve_controller_name)
from sep_control.control.loop import ControlLoopCore
from sep_control.control.mpc import DEFAULT_BUDGET_S, DEFAULT_HORIZON

#: the control-law parameters (help text), shared by the lqr and lqg executables
CONTROLLER_PARAMETERS = """
  controller (str, rom_lqg)        rom_lqg | rom_mpc (box-constrained MPC on the ROM, input limits
                                   planned for); lqr, mpc: deprecated spellings of the two
  mpc_horizon (int, 20)            rom_mpc: horizon H in steps
  mpc_time_budget_s (float, 0.02)  rom_mpc: a QP slower than this falls back to the clipped LQR command"""

PARAMETERS = """parameters (--ros-args -p NAME:=VALUE or --params-file $(ros2 pkg prefix sep_control)/share/sep_control/config/lqr.yaml):
  design_file (str, required)      design file written by `sep design`
  scenario_file (str, '')          refuse to start unless the design matches this scenario
  wait_for_scenario_s (float, 0)   wait for the plant's scenario and check it first
  allow_model_mismatch (bool, false)  run on a plant whose keys or actuator/sensor perturbation
                                   differ from the design's (logged, reported as model_mismatch)""" + CONTROLLER_PARAMETERS + """
  estimate_timeout_s (float, 0.5)  send the nominal input if no estimate of step k arrives
                                   this long (steady clock) after measurement k  (0 = never)""" + DESIGNED_NODE_PARAMETERS


def declare_controller(node, design, log) -> Controller:
    """The control law of the parameters controller, mpc_horizon and mpc_time_budget_s."""
    value = declare(node, 'controller', 'rom_lqg', 'rom_lqg | rom_mpc',
                    constraints=f"one of: {', '.join(NODE_CONTROLLERS)} (deprecated: "
                                f"{', '.join(CONTROLLER_ALIASES)})")
    try:
        name, old = resolve_controller_name(value, NODE_CONTROLLERS)
    except ValueError as exc:
        raise StartError(f'parameter controller {exc}') from None
    if old is not None:
        log.warning(f'parameter controller: {old!r} is deprecated, use {name!r}')
    horizon = declare(node, 'mpc_horizon', DEFAULT_HORIZON, 'rom_mpc: horizon in steps', lo=1, hi=100000)
    budget = declare(node, 'mpc_time_budget_s', DEFAULT_BUDGET_S,
                     'rom_mpc: QP time budget (then the clipped LQR command)', lo=1e-5, hi=60.0)
    t0 = steady()
    law = make_controller(name, design.lqg, design.problem, design.nominal.u,
                          MpcOptions(horizon=int(horizon), time_budget_s=float(budget)))
    if name == 'rom_mpc':
        log.info(f'rom_mpc: horizon {law.horizon}, {law.horizon * design.info.n_u} moves, condensed in '
                 f'{fmt_s(steady() - t0)}, QP budget {fmt_s(float(budget))}')
    return law


class LqrNode(DesignedNode):
    role = 'lqr'

    def __init__(self, peer=None, standalone: bool = True):
        """standalone: subscribe to state estimates and run the watchdog (the `lqr` executable);
        in `lqg` the estimator (`peer`, whose design this node uses) calls ``on_estimate``
        directly in the same callback."""
        super().__init__('lqr', peer)
        self.standalone = standalone
        self.on_command = None                         # lqg: tell the estimator the command

    def configure(self) -> None:
        """The design (`DesignedNode.configure`), the control law, the topics."""
        super().configure()
        node, d, standalone = self.node, self.design, self.standalone
        self.timeout = declare(node, 'estimate_timeout_s', 0.5,
                               'nominal fallback when no estimate arrives this long after the '
                               'measurement of a step (0 = never)', lo=0.0, hi=3600.0)
        self.timer = None
        self._build_law()
        self.rej = gate.RejectionLog()
        self.compute_s = SampleWindow()
        self.pub_cmd = node.create_publisher(c.TOPIC_TYPES[c.COMMAND], c.COMMAND, c.LOOP_QOS)
        self.timer = self._watch_inputs() if standalone else None
        self.log.info(f'lqr: design file {self.design_file} (n_r={d.n_r}, disturbance states '
                      f'{disturbance_summary(d.disturbance)}; {scenario_summary(d)}), '
                      f'controller {self.law.name}, '
                      + (f'estimate_timeout_s {self.timeout:g}' if standalone else 'in-process estimator')
                      + f', namespace {node.get_namespace()}')

    def _build_law(self) -> None:
        """The control law of the design in use and a fresh episode."""
        d = self.design
        self.law = declare_controller(self.node, d, self.log)
        self.input_names = list(self.info.input_names)
        self.labels = c.state_labels(d.n_r, d.lqg.n_d)
        self.reset_episode()

    def reset_episode(self) -> None:
        """A fresh episode of the control law (which step got its command; the MPC's warm start)."""
        if hasattr(self.law, 'reset'):
            self.law.reset()
        d = self.design
        self.core = ControlLoopCore(self.law, d.nominal.u, *d.problem.limits(self.info.n_u))
        self.last_est = -1
        if self.timer is not None:
            self.timer.cancel()

    def adopt_design(self, design) -> None:
        super().adopt_design(design)
        self._build_law()

    def episode_counters(self) -> dict:
        return self.core.counters()

    def _watch_inputs(self):
        """Subscribe to state estimates and, with a timeout, to measurements; the watchdog timer."""
        from rclpy.clock import Clock, ClockType

        node = self.node
        self.sub_est = node.create_subscription(c.TOPIC_TYPES[c.STATE_ESTIMATE], c.STATE_ESTIMATE,
                                                self._on_estimate_msg, c.LOOP_QOS)
        if self.timeout <= 0:
            return None
        self.sub_y = node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS,
                                              self._on_measurement, c.LOOP_QOS)
        return node.create_timer(self.timeout, self._on_timeout, clock=Clock(clock_type=ClockType.STEADY_TIME),
                                 autostart=False)

    # ----------------------------------------------------------------- core
    def on_estimate(self, k: int, a_hat: np.ndarray, t_recv: float | None = None) -> None:
        """Command for step k from the filter's estimate z_hat = [a_hat; d_hat] (n_r + n_d,)."""
        if not self.active:              # inactive: no commands
            return
        t0 = steady() if t_recv is None else t_recv
        out = self.core.estimate(k, a_hat)
        self.last_k = self.core.last_k
        if out.end:
            self.end_of_episode()
            return
        if out.late:
            self.log.warning(f'estimate of step {k} arrived after the nominal fallback was sent',
                             throttle_duration_sec=1.0)
            return
        if out.law_fallback:
            st = self.law.stats
            self.log.warning(f'rom_mpc: step {k} fell back to the clipped LQR command ({st.fallbacks} '
                             f'fallbacks so far: {st.fallback_reasons})', throttle_duration_sec=1.0)
        self._send(k, out.u)
        self.compute_s.append(steady() - t0)

    def _send(self, k: int, u: np.ndarray) -> None:
        self.pub_cmd.publish(c.joint_state(k, self.dt, self.input_names, effort=u, frame_id=self.frame_id))
        if self.on_command is not None:
            self.on_command(k, u)
        if self.timer is not None and k == self.core.current:
            self.timer.cancel()

    # ---------------------------------------------------- standalone inputs
    def _on_estimate_msg(self, msg) -> None:
        if not self.taking(msg):
            return
        t = steady()
        j, _ = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if j is not None:
            self.stale_step(j, self.last_est)       # the plant began its next episode
        k, a, rej = gate.check_message(c.time_ns(msg.header.stamp), self.dt_ns, self.N, msg.name, msg.position,
                                       self.labels, 'state_estimate position',
                                       order=(max(self.last_est + 1, 0), self.last_est, True))
        if rej is not None:
            self.reject('state_estimate', rej, self.rej)
            return
        self.last_est = k
        self.on_estimate(k, a, t)

    def _on_measurement(self, msg) -> None:
        if not self.taking(msg):
            return
        k, rej = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if rej is None:
            self.stale_step(k, self.core.current)   # the plant began its next episode
        if rej is None and self.core.measurement(k):
            self.timer.reset()   # for k = N: ends the episode if its estimate never comes
        self.last_k = self.core.last_k

    def _on_timeout(self) -> None:
        self.timer.cancel()
        if not self.active:
            return
        out = self.core.timeout()
        if out is None:
            return
        if out.end:
            self.log.warning(f'no state estimate of the last step {out.k}: ending the episode')
            self.end_of_episode()
            return
        self._send(out.k, out.u)
        self.log.warning(f'no state estimate of step {out.k} within estimate_timeout_s = {self.timeout:g} s: '
                         f'sent the nominal input ({self.core.n_fallbacks} fallbacks so far)',
                         throttle_duration_sec=1.0)
        self.publish_diagnostics()

    # --------------------------------------------------------------- report
    def _values(self) -> dict:
        """The counts of the summary and of /diagnostics."""
        comp = self.compute_s.percentiles()
        return {'n_steps': self.N, **self.core.counters(), 'rejected_messages': self.rej.total,
                'rejected_by_reason': self.rej.as_dict(), 'compute_p50_s': comp['p50'],
                'compute_p99_s': comp['p99'], 'controller': self.law.name,
                **(self.law.stats.as_dict() if self.law.stats is not None else {}),
                'design_file': self.design_file, 'model_mismatch': self.model_mismatch}

    def health(self) -> c.Health:
        v = self._values()
        problems = []
        if v['fallbacks']:
            problems.append(f"{v['fallbacks']} nominal fallbacks (no estimate in time)")
        if self.rej.total:
            problems.append(f'{self.rej.total} rejected estimates')
        if v.get('mpc_fallbacks'):
            problems.append(f"{v['mpc_fallbacks']} MPC fallbacks to the clipped LQR")
        return c.Health(name=self.node.get_fully_qualified_name(), hardware_id='sep_lqr',
                        level=c.WARN if problems else c.OK, message='; '.join(problems) or 'ok',
                        values={'step': self.last_k, **v, 'last_rejection': str(self.rej.last or '')})

    def summary(self, status: str) -> dict:
        return {'node': 'lqr', 'status': status, 'steps': self.last_k, **self._values(),
                'fallback_steps': self.core.fallback_steps, **self.episode_summary()}

    def summary_line(self, s: dict) -> str:
        mpc = (f", mpc: {s['mpc_qp_steps']} QPs (p99 {fmt_s(s['mpc_qp_p99_s'])}), {s['mpc_fallbacks']} "
               f"fallbacks" if s['controller'] == 'rom_mpc' else '')
        return (f"{s['commands']} commands ({s['controller']}), {s['fallbacks']} nominal fallbacks, "
                f"{s['late_estimates']} late estimates, {s['rejected_messages']} rejected, compute p50 "
                f"{fmt_s(s['compute_p50_s'])} p99 {fmt_s(s['compute_p99_s'])}{mpc}" + self.mismatch_note(s))

    def publishers(self):
        return [self.pub_cmd, self.pub_diag]


def main(argv: list[str] | None = None) -> int:
    return node_main('lqr', 'Time-varying LQR node (sep_control): commands from state_estimate, '
                     'the nominal input when an estimate is late.', argv, PARAMETERS,
                     lambda opts: NodeProcess([LqrNode()], opts.executor))


if __name__ == '__main__':
    sys.exit(main())
