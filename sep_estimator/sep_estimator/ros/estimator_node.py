"""`estimator`: the time-varying Kalman filter on the ROM as a ROS 2 node (docs/reference/topics.md).

A thin node around `sep_estimator.estimator_core.EstimatorCore` (the filter with its episode
logic: gaps, restarts, late inputs, NIS); here: parameters, topics, message checks, diagnostics.

Subscribes measurements (y_k), applied_input (inputs the plant applied at step k),
command (the commanded inputs, used only when the applied ones are late) and
scenario (checked against the design file); publishes state_estimate (z_hat_k: the ROM
estimate a_hat_k, names a_0..a_{n_r-1}, then the disturbance estimates d_hat_k, names
d_0..d_{n_d-1}, when the design has disturbance states), field_estimate (T_nom_k + G_k a_hat_k with its per-node std, the
contract PointCloud2; for grid plants also field_estimate_image) and /diagnostics. The
estimate and field messages are built only while somebody subscribes to them.

Per step: measurement y_k -> ``update(k, y_k - ybar_k)`` (or ``skip(k)`` if the measurement
is rejected) -> publish the estimate; the time update ``predict(k, u_k - ubar_k)`` runs as
soon as the applied input of step k arrives, off the measurement-to-command path.

Inputs that arrive late: if y_{k+1} arrives before applied_input of step k, the filter predicts
with the commanded input of step k if it has it (in a healthy loop it equals the applied one),
else with the nominal (du = 0); if the applied input then arrives and differs, the estimate is
corrected exactly (the correction B_k (du_applied - du_used) passed through the update of step
k+1) when it arrives within that step, and counted as uncorrected otherwise.

Bad measurements (NaN/Inf, wrong length, unknown names) are rejected and counted, and the
filter predicts without that update (``skip``), so the LQR still gets an estimate of step k.
Stale, duplicate or off-grid stamps are rejected and counted without touching the filter.
Missing steps (a gap) are skipped.  A node that starts (or restarts) mid-episode at step k > 0
calls ``restart_at(k)`` (estimate = nominal, open-loop covariance) and goes on.

NIS consistency: the normalized innovation squared of every update; its mean over the last 50
updates is reported with the 99 % interval for a consistent filter (WARN outside it).
"""
from __future__ import annotations

import sys

import numpy as np

from sep_plant import gate
from sep_plant.protocol import clip_inputs
from sep_plant.ros import contract as c
from sep_plant.ros.base import SampleWindow, StartError, declare, fmt_s, steady
from sep_plant.ros.process import NodeProcess, node_main

from sep_estimator.disturbance import summary as disturbance_summary
from sep_estimator.estimator_core import EstimatorCore
from sep_estimator.ltv import FIELD_PRECISIONS
from sep_estimator.ros.designed_node import DESIGNED_NODE_PARAMETERS, DesignedNode, scenario_summary

PARAMETERS = """parameters (--ros-args -p NAME:=VALUE or --params-file $(ros2 pkg prefix sep_estimator)/share/sep_estimator/config/estimator.yaml):
  design_file (str, required)      design file written by `sep design`
  scenario_file (str, '')          refuse to start unless the design matches this scenario
  wait_for_scenario_s (float, 0)   wait for the plant's scenario and check it first
  allow_model_mismatch (bool, false)  run on a plant whose keys or actuator/sensor perturbation
                                   differ from the design's (logged, reported as model_mismatch)
  publish_field_estimate (bool, true)
  field_precision (str, auto)      float32: the field reconstruction Phi (g_k a_hat) from a float32
                                   copy of Phi (~1e-7 relative round-off; a half to a third of the
                                   time on large grids, where the product is memory-bound); float64;
                                   auto: float32 from a Phi of 8 MB on (65 536 nodes x r_f 16),
                                   float64 below; messages stay float64""" + DESIGNED_NODE_PARAMETERS


class EstimatorNode(DesignedNode):
    role = 'estimator'

    def __init__(self, subscribe_command: bool = True, on_estimate=None):
        super().__init__('estimator')
        self.subscribe_command = subscribe_command
        self.on_estimate = on_estimate           # direct hook (lqg): f(k, z_hat (n_r + n_d,)) -> None

    def configure(self) -> None:
        """The design (`DesignedNode.configure`), the filter, the topics, the warm-up."""
        super().configure()
        node, subscribe_command = self.node, self.subscribe_command
        self.publish_field = declare(node, 'publish_field_estimate', True,
                                     'publish field_estimate (reconstructed field with std)')
        self.field_precision = declare(node, 'field_precision', 'auto',
                                       'field reconstruction arithmetic: float64, float32 (half the memory '
                                       'traffic on large grids; ~1e-7 relative round-off; messages stay float64), '
                                       'or auto (float32 from a field basis of 8 MB on)',
                                       constraints="one of: auto, float64, float32")
        if self.field_precision not in FIELD_PRECISIONS:
            raise StartError(f"bad parameter field_precision: {self.field_precision!r}, expected one of "
                             f"{list(FIELD_PRECISIONS)}")
        d = self.design
        self._build_filter()
        self.rej = gate.RejectionLog()
        self.compute_s = SampleWindow()
        self.n_estimates_published = 0

        self.pub_est = node.create_publisher(c.TOPIC_TYPES[c.STATE_ESTIMATE], c.STATE_ESTIMATE, c.LOOP_QOS)
        self.pub_field = node.create_publisher(c.TOPIC_TYPES[c.FIELD_ESTIMATE], c.FIELD_ESTIMATE, c.FIELD_QOS)
        self.pub_image = (node.create_publisher(c.TOPIC_TYPES[c.FIELD_ESTIMATE_IMAGE], c.FIELD_ESTIMATE_IMAGE,
                                                c.FIELD_QOS) if self.info.grid_shape else None)
        # applied_input before measurements: when both are ready, the executor takes them in
        # creation order, so u_k is used before y_{k+1} is processed
        self.sub_u = node.create_subscription(c.TOPIC_TYPES[c.APPLIED_INPUT], c.APPLIED_INPUT,
                                              self._on_applied, c.LOOP_QOS)
        self.sub_y = node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS,
                                              self._on_measurement, c.LOOP_QOS)
        self.sub_cmd = (node.create_subscription(c.TOPIC_TYPES[c.COMMAND], c.COMMAND,
                                                 self._on_command, c.LOOP_QOS)
                        if subscribe_command else None)
        rank = getattr(d.rom.G, 'rank', None)
        self.log.info(f'estimator: design file {self.design_file} (n_r={d.n_r}, disturbance states '
                      f'{disturbance_summary(d.disturbance)}; {scenario_summary(d)}), '
                      f'field reconstruction {self.core.field_precision}'
                      f"{' (auto)' if self.field_precision == 'auto' else ''}"
                      f"{f' on a field basis of rank {rank}' if rank is not None else ''}, "
                      f'namespace {node.get_namespace()}, use_sim_time '
                      f"{node.get_parameter('use_sim_time').value}")

    def _build_filter(self) -> None:
        """The filter of the design in use, the names of its messages, the warm-up."""
        d = self.design
        self.reset_episode()
        self.sensors = list(self.info.output_names)
        self.input_names = list(self.info.input_names)
        self.labels = c.state_labels(d.n_r, d.lqg.n_d)
        self.cloud = c.CloudBuilder(d.field_xyz, self.info.field_name, self.frame_id)
        self._warm_up()

    def reset_episode(self) -> None:
        """A fresh filter (the prior of step 0) for the next episode."""
        nom = self.design.nominal
        self.core = EstimatorCore(self.design.lqg, nom.u, nom.y, nom.field, field_precision=self.field_precision)

    def adopt_design(self, design) -> None:
        super().adopt_design(design)
        self._build_filter()

    def episode_counters(self) -> dict:
        return self.core.counters()

    def _warm_up(self) -> None:
        """Run every per-step code path once on throwaway objects (first calls into numpy,
        LAPACK and the message type support are slow), so step 0 meets a real-time deadline."""
        from rclpy.serialization import serialize_message

        d = self.design
        core = EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field,
                             field_precision=self.field_precision)
        a, _ = core.measurement(0, d.nominal.y[0])
        lo, hi = d.problem.limits(self.info.n_u)
        clip_inputs(d.nominal.u[0] + a @ d.lqg.K[0].T, lo, hi)   # the LQR law's ops
        f, std = core.field_estimate()
        core.applied(0, d.nominal.u[0])
        core.measurement(2, None)                            # gap + skip: the off-schedule paths
        core.field_estimate()
        gate.check_vector(self.sensors, d.nominal.y[0], self.sensors)
        for msg in (c.joint_state(0, self.dt, self.labels, position=a),
                    c.joint_state(0, self.dt, self.input_names, effort=d.nominal.u[0]),
                    self.cloud.build(0, self.dt, f, std)):
            serialize_message(msg)

    # -------------------------------------------------------------- helpers
    def _step_of(self, msg, what: str, last_step: int) -> int | None:
        k, rej = gate.check_stamp(c.time_ns(msg.header.stamp), self.dt_ns, last_step)
        if rej is not None:
            self.reject(what, rej, self.rej)
            return None
        return k

    # -------------------------------------------------------------- inputs
    def _on_measurement(self, msg) -> None:
        if not self.taking(msg):                  # inactive (or the scenario not yet checked): not taken
            return
        t = steady()
        k = self._step_of(msg, 'measurement', self.N)
        if k is None:
            return
        self.stale_step(k, self.last_k)          # the plant began its next episode
        y, bad = gate.check_vector(msg.name, msg.position, self.sensors, 'measurement position')
        restarts = self.core.restarts
        a, rej = self.core.measurement(k, y)
        if rej is not None:                    # stale or duplicate: the filter is untouched
            self.reject('measurement', rej, self.rej, k)
            return
        if bad is not None:                    # malformed: the filter skipped the update
            self.reject('measurement', bad, self.rej, k)
        if self.core.restarts > restarts:
            self.log.warning(f'joining the episode at step {k}: restart_at({k}) '
                             '(estimate = nominal, open-loop covariance)')
        self.last_k = k
        self._emit(k, a, t)

    def _emit(self, k: int, a: np.ndarray, t_recv: float) -> None:
        if self.on_estimate is not None:       # lqg: the command goes out first
            self.on_estimate(k, a)
        # everything below is for other processes and viewers: built only when somebody listens
        if self.pub_est.get_subscription_count() > 0:
            self.pub_est.publish(c.joint_state(k, self.dt, self.labels, position=a, frame_id=self.frame_id))
            self.n_estimates_published += 1
        self.compute_s.append(steady() - t_recv)
        cloud = self.publish_field and self.pub_field.get_subscription_count() > 0
        image = self.publish_field and self.pub_image is not None and self.pub_image.get_subscription_count() > 0
        if cloud or image:
            f, std = self.core.field_estimate()
            if cloud:
                self.pub_field.publish(self.cloud.build(k, self.dt, f, std))
            if image:
                self.pub_image.publish(c.field_image(k, self.dt, f, self.info.grid_shape, self.frame_id))
        self.core.finish_step()
        if k == self.N:
            self.end_of_episode()

    def _on_applied(self, msg) -> None:
        if not self.taking(msg):                  # inactive (or the scenario not yet checked): not taken
            return
        j, u, rej = gate.check_message(c.time_ns(msg.header.stamp), self.dt_ns, self.N - 1, msg.name, msg.effort,
                                       self.input_names, 'applied_input effort')
        if rej is None:
            rej = self.core.applied(j, u)
        if rej is not None:
            self.reject('applied_input', rej, self.rej, j)

    def _on_command(self, msg) -> None:
        if not self.taking(msg):                  # inactive (or the scenario not yet checked): not taken
            return
        j, _ = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if j is None or not 0 <= j < self.N:
            return  # the plant gates commands; here they are only a fallback for late inputs
        u, rej = gate.check_vector(msg.name, msg.effort, self.input_names)
        if rej is None:
            self.note_command(j, u)

    def note_command(self, j: int, u: np.ndarray) -> None:
        """The command of step j (from the LQR in the same process, or command)."""
        self.core.commanded(j, u)

    # -------------------------------------------------------------- report
    def health(self) -> c.Health:
        nis = self.core.nis_stats()
        comp = self.compute_s.percentiles()
        level, message = c.OK, 'ok'
        problems = []
        if self.rej.total:
            problems.append(f'{self.rej.total} rejected messages')
        if nis['nis_consistent'] is False:
            problems.append(f"NIS mean {nis['nis_recent_mean']:.2f} outside "
                            f"[{nis['nis_recent_interval_99'][0]:.2f}, {nis['nis_recent_interval_99'][1]:.2f}]")
        if problems:
            level, message = c.WARN, '; '.join(problems)
        return c.Health(name=self.node.get_fully_qualified_name(), hardware_id='sep_estimator',
                        level=level, message=message, values={
                            'step': self.last_k, 'n_steps': self.N, **self.core.counters(),
                            'rejected_messages': self.rej.total,
                            'rejected_by_reason': self.rej.as_dict(),
                            'last_rejection': str(self.rej.last or ''),
                            **nis, 'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99'],
                            'design_file': self.design_file, 'model_mismatch': self.model_mismatch})

    def summary(self, status: str) -> dict:
        comp = self.compute_s.percentiles()
        return {'node': 'estimator', 'status': status, 'design_file': self.design_file,
                'steps': self.last_k, 'n_steps': self.N, **self.core.counters(),
                'rejected_messages': self.rej.total, 'rejected_by_reason': self.rej.as_dict(),
                'state_estimates_published': self.n_estimates_published,
                **self.core.nis_stats(), 'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99'],
                'model_mismatch': self.model_mismatch, **self.episode_summary()}

    def summary_line(self, s: dict) -> str:
        nis = 'n/a' if s['nis_mean'] is None else f"{s['nis_mean']:.2f} (expected {s['nis_expected']})"
        return (f"{s['updates']} updates, {s['skipped_updates']} skipped, {s['missing_measurements']} missing, "
                f"{s['rejected_messages']} rejected, {s['restarts']} restarts, mean NIS {nis}, "
                f"compute p50 {fmt_s(s['compute_p50_s'])} p99 {fmt_s(s['compute_p99_s'])}" + self.mismatch_note(s))

    def publishers(self):
        return [p for p in (self.pub_est, self.pub_field, self.pub_image, self.pub_diag) if p is not None]


def main(argv: list[str] | None = None) -> int:
    return node_main('estimator', 'ROM Kalman filter node (sep_estimator): estimates the ROM state and '
                     'the field from measurements.', argv, PARAMETERS,
                     lambda opts: NodeProcess([EstimatorNode()], opts.executor))


if __name__ == '__main__':
    sys.exit(main())
