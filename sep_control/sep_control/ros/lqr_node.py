"""`lqr`: the time-varying LQR tracking law (or the ROM-MPC) as a ROS 2 node (docs/reference/topics.md).

u_k = clip(ubar_k + K_k a_hat_k, u_min, u_max) for every state estimate a_hat_k received on
state_estimate, published on command stamped k. With ``controller:=mpc`` the
command is the first move of the box-constrained MPC on the design's ROM (`sep_control.control.mpc`):
the LQR law itself whenever no limit binds, an OSQP solve when one does, and the clipped LQR
command when that solve fails or runs past ``mpc_time_budget_s`` (counted on /diagnostics).

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

from sep_plant.ros import contract as c
from sep_plant import gate
from sep_plant.ros.base import (SampleWindow, StartError, declare, fmt_s, limit_blas_threads, make_executor,
                                 parse_front, run_node, sim_time_default, steady)
from sep_estimator.ros.designed_node import DesignedNode, scenario_summary, spin_episode

from sep_control.design.gains import command
from sep_control.control.mpc import DEFAULT_BUDGET_S, DEFAULT_HORIZON

PARAMETERS = """parameters (--ros-args -p NAME:=VALUE or --params-file $(ros2 pkg prefix sep_control)/share/sep_control/config/lqr.yaml):
  design_file (str, required)      design file written by `design`
  scenario_file (str, '')          refuse to start unless the design matches this scenario
  wait_for_scenario_s (float, 0)   wait for the plant's scenario and check it first
  controller (str, lqr)            lqr | mpc (box-constrained MPC on the ROM, input limits planned for)
  mpc_horizon (int, 20)            mpc: horizon H in steps
  mpc_time_budget_s (float, 0.02)  mpc: a QP slower than this falls back to the clipped LQR command
  estimate_timeout_s (float, 0.5)  send the nominal input if no estimate of step k arrives
                                   this long (steady clock) after measurement k  (0 = never)
  exit_at_end (bool, true)         exit 0 after the last step (k = N)
  diagnostics_period_s (float, 1)  /diagnostics period
  summary_file (str, '')           end-of-episode summary JSON
  use_sim_time (bool, true)        time from the plant's /clock"""


class LqrNode(DesignedNode):
    role = 'lqr'

    def __init__(self, design=None, standalone: bool = True):
        """standalone: subscribe to state estimates and run the watchdog (the `lqr` executable);
        in `lqg` the estimator calls ``on_estimate`` directly in the same callback."""
        from rclpy.clock import Clock, ClockType

        super().__init__('lqr', design)
        node = self.node
        self.timeout = declare(node, 'estimate_timeout_s', 0.5,
                               'nominal fallback when no estimate arrives this long after the '
                               'measurement of a step (0 = never)', lo=0.0, hi=3600.0)
        self.controller = declare(node, 'controller', 'lqr', 'lqr | mpc', constraints='one of: lqr, mpc')
        if self.controller not in ('lqr', 'mpc'):
            raise StartError(f"parameter controller must be 'lqr' or 'mpc', got {self.controller!r}")
        horizon = declare(node, 'mpc_horizon', DEFAULT_HORIZON, 'mpc: horizon in steps', lo=1, hi=100000)
        budget = declare(node, 'mpc_time_budget_s', DEFAULT_BUDGET_S, 'mpc: QP time budget (then the clipped LQR command)',
                         lo=1e-5, hi=60.0)
        d = self.design
        self.mpc = None
        self.warm = None
        if self.controller == 'mpc':
            from sep_control.control.mpc import RomMPC

            t0 = steady()
            self.mpc = RomMPC(d.lqg, d.problem, d.nominal.u, horizon=int(horizon), time_budget_s=float(budget))
            self.log.info(f'mpc: horizon {self.mpc.H}, {self.mpc.H * self.info.n_u} moves, condensed in '
                          f'{fmt_s(steady() - t0)}, QP budget {fmt_s(float(budget))}')
        self.input_names = list(self.info.input_names)
        self.labels = c.state_labels(d.n_r)
        self.u_nom, self.K = d.nominal.u, d.lqg.K
        self.lo, self.hi = d.problem.limits(self.info.n_u)
        self.rej = gate.RejectionLog()
        self.sent = np.zeros(self.N + 1, dtype=bool)   # a command (or, for k = N, nothing) done
        self.current = -1                              # newest step announced by a measurement
        self.last_est = -1
        self.n_commands = self.n_fallbacks = self.n_late = 0
        self.fallback_steps: list[int] = []
        self.compute_s = SampleWindow()
        self.on_command = None                         # lqg: tell the estimator the command
        self.pub_cmd = node.create_publisher(c.TOPIC_TYPES[c.COMMAND], c.COMMAND, c.LOOP_QOS)
        self.standalone = standalone
        self.timer = None
        if standalone:
            self.sub_est = node.create_subscription(c.TOPIC_TYPES[c.STATE_ESTIMATE], c.STATE_ESTIMATE,
                                                    self._on_estimate_msg, c.LOOP_QOS)
            if self.timeout > 0:
                self.sub_y = node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS,
                                                      self._on_measurement, c.LOOP_QOS)
                self.timer = node.create_timer(self.timeout, self._on_timeout,
                                               clock=Clock(clock_type=ClockType.STEADY_TIME),
                                               autostart=False)
        self.log.info(f'lqr: design file {self.design_file} (n_r={d.n_r}; {scenario_summary(d)}), '
                      + (f'estimate_timeout_s {self.timeout:g}' if standalone else 'in-process estimator')
                      + f', namespace {node.get_namespace()}')

    # ----------------------------------------------------------------- core
    def on_estimate(self, k: int, a_hat: np.ndarray, t_recv: float | None = None) -> None:
        """Command for step k from the estimate a_hat (n_r,)."""
        t0 = steady() if t_recv is None else t_recv
        self.last_k = max(self.last_k, k)
        if k >= self.N:
            self.sent[self.N] = True
            self.done = True
            return
        if self.sent[k]:
            self.n_late += 1
            self.log.warning(f'estimate of step {k} arrived after the nominal fallback was sent',
                             throttle_duration_sec=1.0)
            return
        if self.mpc is not None:
            fb = self.mpc.stats.fallbacks
            u, z = self.mpc.command(k, a_hat, self.warm)
            self.warm = self.mpc.shift(z)
            if self.mpc.stats.fallbacks > fb:
                self.log.warning(f'mpc: step {k} fell back to the clipped LQR command '
                                 f'({self.mpc.stats.fallbacks} fallbacks so far: '
                                 f'{self.mpc.stats.fallback_reasons})', throttle_duration_sec=1.0)
        else:
            u = command(self.u_nom[k], self.K[k], a_hat, self.lo, self.hi)
        self._send(k, u)
        self.n_commands += 1
        self.compute_s.append(steady() - t0)

    def _send(self, k: int, u: np.ndarray) -> None:
        self.sent[k] = True
        self.pub_cmd.publish(c.joint_state(k, self.dt, self.input_names, effort=u, frame_id=self.frame_id))
        if self.on_command is not None:
            self.on_command(k, u)
        if self.timer is not None and k == self.current:
            self.timer.cancel()

    # ---------------------------------------------------- standalone inputs
    def _on_estimate_msg(self, msg) -> None:
        t = steady()
        k, rej = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if rej is None:
            rej = gate.check_horizon(k, self.N)
        if rej is None:
            rej = gate.check_step(k, expected=max(self.last_est + 1, 0), last=self.last_est,
                                  allow_ahead=True)
        a = None
        if rej is None:
            a, rej = gate.check_vector(msg.name, msg.position, self.labels, 'state_estimate position')
        if rej is not None:
            self.reject('state_estimate', rej, self.rej)
            return
        self.last_est = k
        self.on_estimate(k, a, t)

    def _on_measurement(self, msg) -> None:
        k, rej = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if rej is not None or not 0 <= k <= self.N or k <= self.current:
            return
        self.current = k
        self.last_k = max(self.last_k, k)
        if not self.sent[k]:
            self.timer.reset()   # for k = N: ends the episode if its estimate never comes

    def _on_timeout(self) -> None:
        self.timer.cancel()
        k = self.current
        if k < 0 or self.sent[k]:
            return
        if k == self.N:
            self.sent[k] = self.done = True
            self.log.warning(f'no state estimate of the last step {k}: ending the episode')
            return
        u = np.clip(self.u_nom[k], self.lo, self.hi)
        self._send(k, u)
        self.n_fallbacks += 1
        self.fallback_steps.append(k)
        self.log.warning(f'no state estimate of step {k} within estimate_timeout_s = {self.timeout:g} s: '
                         f'sent the nominal input ({self.n_fallbacks} fallbacks so far)',
                         throttle_duration_sec=1.0)
        self.publish_diagnostics()

    # --------------------------------------------------------------- report
    def health(self) -> c.Health:
        comp = self.compute_s.percentiles()
        problems = []
        if self.n_fallbacks:
            problems.append(f'{self.n_fallbacks} nominal fallbacks (no estimate in time)')
        if self.rej.total:
            problems.append(f'{self.rej.total} rejected estimates')
        mpc = self._mpc_values()
        if mpc.get('mpc_fallbacks'):
            problems.append(f"{mpc['mpc_fallbacks']} MPC fallbacks to the clipped LQR")
        return c.Health(name=self.node.get_fully_qualified_name(), hardware_id='sep_lqr',
                        level=c.WARN if problems else c.OK, message='; '.join(problems) or 'ok',
                        values={'step': self.last_k, 'n_steps': self.N, 'commands': self.n_commands,
                                'fallbacks': self.n_fallbacks, 'late_estimates': self.n_late,
                                'rejected_messages': self.rej.total,
                                'rejected_by_reason': self.rej.as_dict(),
                                'last_rejection': str(self.rej.last or ''),
                                'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99'],
                                'controller': self.controller, **mpc,
                                'design_file': self.design_file})

    def _mpc_values(self) -> dict:
        if self.mpc is None:
            return {}
        st = self.mpc.stats.as_dict()
        return {'mpc_horizon': self.mpc.H, 'mpc_unconstrained_steps': st['unconstrained'], 'mpc_qp_steps': st['qp'],
                'mpc_fallbacks': st['fallbacks'], 'mpc_fallback_reasons': st['fallback_reasons'],
                'mpc_qp_p50_s': st['qp_p50_s'], 'mpc_qp_p99_s': st['qp_p99_s']}

    def summary(self, status: str) -> dict:
        comp = self.compute_s.percentiles()
        return {'node': 'lqr', 'status': status, 'design_file': self.design_file,
                'steps': self.last_k, 'n_steps': self.N, 'commands': self.n_commands,
                'fallbacks': self.n_fallbacks, 'fallback_steps': self.fallback_steps,
                'late_estimates': self.n_late, 'rejected_messages': self.rej.total,
                'rejected_by_reason': self.rej.as_dict(),
                'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99'],
                'controller': self.controller, **self._mpc_values()}

    def summary_line(self, s: dict) -> str:
        mpc = (f", mpc: {s['mpc_qp_steps']} QPs (p99 {fmt_s(s['mpc_qp_p99_s'])}), {s['mpc_fallbacks']} "
               f"fallbacks" if s.get('controller') == 'mpc' else '')
        return (f"{s['commands']} commands ({s.get('controller', 'lqr')}), {s['fallbacks']} nominal fallbacks, "
                f"{s['late_estimates']} late estimates, {s['rejected_messages']} rejected, compute p50 "
                f"{fmt_s(s['compute_p50_s'])} p99 {fmt_s(s['compute_p99_s'])}{mpc}")

    def publishers(self):
        return [self.pub_cmd, self.pub_diag]


class _Process:
    def __init__(self, executor: str):
        self.lqr = LqrNode()
        self.executor = make_executor(executor)
        self.executor.add_node(self.lqr.node)

    def run(self) -> int:
        rc = spin_episode(self.executor, [self.lqr])
        self.finish('completed')
        return rc

    def finish(self, status: str, error: str | None = None) -> None:
        self.lqr.finish(status, error)

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        self.lqr.destroy_node()


def main(argv: list[str] | None = None) -> int:
    opts, args = parse_front('lqr', 'Time-varying LQR node (sep_control): heater commands from '
                          'slab/state_estimate, nominal fallback when estimates are late.',
                          argv, None, PARAMETERS)
    limit_blas_threads(1)
    return run_node(lambda a: _Process(opts.executor), sim_time_default(args), 'lqr')


if __name__ == '__main__':
    sys.exit(main())
