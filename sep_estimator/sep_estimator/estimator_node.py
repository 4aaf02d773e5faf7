"""`estimator`: the time-varying Kalman filter on the ROM as a ROS 2 node (DESIGN.md §4).

Subscribes slab/measurements (y_k), slab/heat_applied (inputs the plant applied at step k),
slab/heat_command (the commanded inputs, used only when the applied ones are late) and
slab/scenario (checked against the design file); publishes slab/state_estimate (a_hat_k,
names a_0..a_{n_r-1}), slab/field_estimate (T_nom_k + G_k a_hat_k with its per-node std, the
contract PointCloud2) and /diagnostics.

Per step: measurement y_k -> ``update(k, y_k - ybar_k)`` (or ``skip(k)`` if the measurement
is rejected) -> publish the estimate; the time update ``predict(k, u_k - ubar_k)`` runs as
soon as the applied input of step k arrives, off the measurement-to-command path.

Inputs that arrive late: if y_{k+1} arrives before heat_applied of step k, the filter predicts
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
from collections import deque

import numpy as np

from sep_plant import contract as c
from sep_plant import gate
from sep_plant.node_util import (fmt_s, limit_blas_threads, make_executor, parse_front, percentiles, run_node,
                                 sim_time_default, steady)

from .ros_common import DesignedNode, scenario_summary, spin_episode

PARAMETERS = """parameters (--ros-args -p NAME:=VALUE or --params-file ros_ws/config/estimator.yaml):
  design_file (str, required)      design file written by `design`
  scenario_file (str, '')          refuse to start unless the design matches this scenario
  wait_for_scenario_s (float, 0)   wait for the plant's slab/scenario and check it first
  publish_field_estimate (bool, true)
  exit_at_end (bool, true)         exit 0 after the last step (k = N)
  diagnostics_period_s (float, 1)  /diagnostics period
  summary_file (str, '')           end-of-episode summary JSON
  use_sim_time (bool, true)        time from the plant's /clock"""

NIS_WINDOW = 50


class EstimatorNode(DesignedNode):
    role = 'estimator'

    def __init__(self, design=None, subscribe_command: bool = True, on_estimate=None):
        from sep_estimator.tvkf import filter_from_design

        super().__init__('estimator', design)
        node = self.node
        self.publish_field = c_decl(node, 'publish_field_estimate', True,
                                    'publish slab/field_estimate (reconstructed field with std)')
        d = self.design
        self.kf = filter_from_design(d)
        self.sensors = self.s.sensor_labels()
        self.heaters = self.s.heater_labels()
        self.labels = c.state_labels(d.n_r)
        self.x_grid = self.s.grid()
        self.v_var = self.s.v_std ** 2
        self.on_estimate = on_estimate           # direct hook (lqg): f(k, a_hat (n_r,)) -> None
        self.started = False
        self.last_meas = -1
        self.applied = np.full((self.N, self.s.n_u), np.nan)
        self.commanded = np.full((self.N, self.s.n_u), np.nan)
        self.used_du: dict[int, np.ndarray] = {}  # step -> du used when the applied input was late
        self.meas_kind: dict[int, str] = {}       # step -> 'update' | 'skip' (for late corrections)
        self.rej = gate.RejectionLog()
        self.n_updates = self.n_skipped = self.n_gap = self.restarts = 0
        self.input_source = {'applied': 0, 'commanded': 0, 'nominal': 0}
        self.late_corrected = self.late_uncorrected = 0
        self.nis: deque[float] = deque(maxlen=NIS_WINDOW)
        self.nis_sum = 0.0
        self.nis_n = 0
        self.compute_s: list[float] = []
        self._prior = None
        # innovation covariance inverses S_k^-1 = (C_k P_{k|k-1} C_k' + V)^-1 of the schedule (NIS)
        C, Pp = d.C, self.kf.P_prior_sched
        self.S_inv = np.linalg.inv(C @ Pp @ C.transpose(0, 2, 1) + self.v_var * np.eye(self.s.n_y))

        self.pub_est = node.create_publisher(c.TOPIC_TYPES[c.STATE_ESTIMATE], c.STATE_ESTIMATE, c.LOOP_QOS)
        self.pub_field = node.create_publisher(c.TOPIC_TYPES[c.FIELD_ESTIMATE], c.FIELD_ESTIMATE, c.FIELD_QOS)
        # heat_applied before measurements: when both are ready, the executor takes them in
        # creation order, so u_k is used before y_{k+1} is processed
        self.sub_u = node.create_subscription(c.TOPIC_TYPES[c.HEAT_APPLIED], c.HEAT_APPLIED,
                                              self._on_applied, c.LOOP_QOS)
        self.sub_y = node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS,
                                              self._on_measurement, c.LOOP_QOS)
        self.sub_cmd = (node.create_subscription(c.TOPIC_TYPES[c.HEAT_COMMAND], c.HEAT_COMMAND,
                                                 self._on_command, c.LOOP_QOS)
                        if subscribe_command else None)
        self._warm_up()
        self.log.info(f'estimator: design file {self.design_file} (n_r={d.n_r}; {scenario_summary(self.s)}), '
                      f'namespace {node.get_namespace()}, use_sim_time '
                      f"{node.get_parameter('use_sim_time').value}")

    def _warm_up(self) -> None:
        """Run every per-step code path once on throwaway objects (first calls into numpy,
        LAPACK and the message type support are slow), so step 0 meets a real-time deadline."""
        from rclpy.serialization import serialize_message
        from sep_estimator.tvkf import filter_from_design

        d = self.design
        kf = filter_from_design(d)
        a = kf.update(0, np.zeros(self.s.n_y))
        np.clip(d.u_nom[0] + a @ d.K[0].T, self.s.u_min, self.s.u_max)   # the LQR law's ops
        kf.field_std(precomputed=d.field_std)
        kf.predict(0, np.zeros(self.s.n_u))
        kf.skip(1)
        kf.field_std()
        y = d.y_nom[0]
        gate.check_vector(self.sensors, y, self.sensors)
        for msg in (c.joint_state(0, self.s.dt, self.labels, position=a[0]),
                    c.joint_state(0, self.s.dt, self.heaters, effort=d.u_nom[0]),
                    c.field_cloud(0, self.s.dt, self.x_grid, d.T_nom[0] + d.G[0] @ a[0], d.field_std[0])):
            serialize_message(msg)
        C = d.C[0]
        np.linalg.solve(C @ kf.P @ C.T + self.v_var * np.eye(C.shape[0]), y)

    # -------------------------------------------------------------- helpers
    def _reject(self, what: str, rej: gate.Rejection, k: int | None = None) -> None:
        self.rej.add(rej)
        self.log.warning(f"rejected {what}{'' if k is None else f' (step {k})'}: {rej} "
                         f'({self.rej.total} rejected so far)')
        self.publish_diagnostics()

    def _step_of(self, msg, what: str, last_step: int) -> int | None:
        k, rej = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if rej is None:
            rej = gate.check_horizon(k, last_step)
        if rej is not None:
            self._reject(what, rej)
            return None
        return k

    def filter_step(self) -> int:
        """The step whose measurement the filter expects next."""
        return self.kf.k + 1 if self.kf.posterior else self.kf.k

    def _du(self, j: int) -> np.ndarray:
        """Input deviation of step j for the time update: applied, else commanded, else nominal."""
        if not np.isnan(self.applied[j, 0]):
            self.input_source['applied'] += 1
            return self.applied[j] - self.design.u_nom[j]
        if not np.isnan(self.commanded[j, 0]):
            self.input_source['commanded'] += 1
            du = self.commanded[j] - self.design.u_nom[j]
        else:
            self.input_source['nominal'] += 1
            du = np.zeros(self.s.n_u)
        self.used_du[j] = du
        return du

    def _advance_to(self, k: int) -> None:
        """Bring the filter to the prior of step k (restart, or skip/predict through a gap)."""
        if not self.started:
            self.started = True
            if k > 0:
                self.kf.restart_at(k)
                self.restarts += 1
                self.log.warning(f'joining the episode at step {k}: restart_at({k}) '
                                 '(estimate = nominal, open-loop covariance)')
            return
        while self.kf.k < k:
            j = self.kf.k
            if not self.kf.posterior:
                self.kf.skip(j)
                self.meas_kind[j] = 'skip'
                self.n_gap += 1
            self.kf.predict(j, self._du(j))

    # -------------------------------------------------------------- inputs
    def _on_measurement(self, msg) -> None:
        t = steady()
        k = self._step_of(msg, 'measurement', self.N)
        if k is None:
            return
        if self.started:
            rej = gate.check_step(k, expected=self.filter_step(), last=self.last_meas, allow_ahead=True)
            if rej is not None:
                self._reject('measurement', rej, k)
                return
        y, rej = gate.check_vector(msg.name, msg.position, self.sensors, 'measurement position')
        self.last_meas = k
        self.last_k = k
        self._advance_to(k)
        if rej is not None:
            self._reject('measurement', rej, k)
            a = self.kf.skip(k)
            self.meas_kind[k] = 'skip'
            self.n_skipped += 1
            self._prior = None
        else:
            self._prior = (k, self.kf.a.copy(), None if self.kf.on_schedule else self.kf.P.copy(), y)
            a = self.kf.update(k, y - self.design.y_nom[k])
            self.meas_kind[k] = 'update'
            self.n_updates += 1
        self._emit(k, a[0], t)

    def _emit(self, k: int, a: np.ndarray, t_recv: float) -> None:
        if self.on_estimate is not None:       # lqg: the command goes out first
            self.on_estimate(k, a)
        self.pub_est.publish(c.joint_state(k, self.s.dt, self.labels, position=a))
        self.compute_s.append(steady() - t_recv)
        # the cloud is n_x points: build it only when someone listens (viewers, recorder)
        if self.publish_field and self.pub_field.get_subscription_count() > 0:
            d = self.design
            T_hat = d.T_nom[k] + d.G[k] @ a
            std = self.kf.field_std(precomputed=d.field_std)
            self.pub_field.publish(c.field_cloud(k, self.s.dt, self.x_grid, T_hat, std))
        self._nis()
        if k == self.N:
            self.done = True
        # the applied input of step k may already be here (it never is in a healthy loop)
        if k < self.N and not np.isnan(self.applied[k, 0]):
            self.kf.predict(k, self._du(k))

    def _nis(self) -> None:
        if self._prior is None:
            return
        k, a, P, y = self._prior
        self._prior = None
        C = self.design.C[k]
        innov = y - self.design.y_nom[k] - C @ a[0]
        if P is None:                                   # on schedule: precomputed S_k^-1
            val = float(innov @ self.S_inv[k] @ innov)
        else:
            S = C @ P @ C.T + self.v_var * np.eye(C.shape[0])
            val = float(innov @ np.linalg.solve(S, innov))
        self.nis.append(val)
        self.nis_sum += val
        self.nis_n += 1

    def _on_applied(self, msg) -> None:
        j = self._step_of(msg, 'heat_applied', self.N - 1)
        if j is None:
            return
        u, rej = gate.check_vector(msg.name, msg.effort, self.heaters, 'heat_applied effort')
        if rej is None and not np.isnan(self.applied[j, 0]):
            rej = gate.Rejection(gate.DUPLICATE, f'second heat_applied for step {j}')
        if rej is not None:
            self._reject('heat_applied', rej, j)
            return
        self.applied[j] = u
        if not self.started:
            return
        kf = self.kf
        if kf.k == j and kf.posterior:
            kf.predict(j, self._du(j))            # the usual case: time update right away
        elif j in self.used_du and kf.k == j + 1:
            self._correct_late(j, u)
        elif j in self.used_du:
            self.late_uncorrected += 1

    def _correct_late(self, j: int, u: np.ndarray) -> None:
        """The filter predicted step j with an assumed input; the applied one differs."""
        used = self.used_du.pop(j)
        delta_du = (u - self.design.u_nom[j]) - used
        if not np.any(delta_du):
            return
        delta = self.design.B[j] @ delta_du
        if self.kf.posterior and self.meas_kind.get(j + 1) == 'update':
            C = self.design.C[j + 1]
            L = self.kf.P @ C.T / self.v_var          # Kalman gain = P_{k|k} C' V^-1
            delta = delta - L @ (C @ delta)
        self.kf.a = self.kf.a + delta
        self.late_corrected += 1

    def _on_command(self, msg) -> None:
        j, _ = gate.step_of_stamp(c.time_ns(msg.header.stamp), self.dt_ns)
        if j is None or not 0 <= j < self.N:
            return  # the plant gates commands; here they are only a fallback for late inputs
        u, rej = gate.check_vector(msg.name, msg.effort, self.heaters)
        if rej is None:
            self.note_command(j, u)

    def note_command(self, j: int, u: np.ndarray) -> None:
        """The command of step j (from the LQR in the same process, or heat_command)."""
        self.commanded[j] = u

    # -------------------------------------------------------------- report
    def nis_stats(self) -> dict:
        n_y = self.s.n_y
        recent = float(np.mean(self.nis)) if self.nis else None
        lo, hi = gate.chi2_interval(n_y, len(self.nis), 0.99)
        return {'nis_mean': self.nis_sum / self.nis_n if self.nis_n else None,
                'nis_recent_mean': recent, 'nis_expected': n_y, 'nis_recent_interval_99': [lo, hi],
                'nis_consistent': None if recent is None else bool(lo <= recent <= hi)}

    def health(self) -> c.Health:
        nis = self.nis_stats()
        comp = percentiles(self.compute_s)
        level, message = c.OK, 'ok'
        problems = []
        if self.rej.total:
            problems.append(f'{self.rej.total} rejected messages')
        if nis['nis_consistent'] is False:
            problems.append(f"NIS mean {nis['nis_recent_mean']:.2f} outside "
                            f"[{nis['nis_recent_interval_99'][0]:.2f}, {nis['nis_recent_interval_99'][1]:.2f}]")
        if problems:
            level, message = c.WARN, '; '.join(problems)
        return c.Health(name=self.node.get_fully_qualified_name(), hardware_id='slab_estimator',
                        level=level, message=message, values={
                            'step': self.last_k, 'n_steps': self.N,
                            'updates': self.n_updates, 'skipped_updates': self.n_skipped,
                            'missing_measurements': self.n_gap, 'restarts': self.restarts,
                            'rejected_messages': self.rej.total,
                            'rejected_by_reason': self.rej.as_dict(),
                            'last_rejection': str(self.rej.last or ''),
                            'input_source': self.input_source,
                            'late_inputs_corrected': self.late_corrected,
                            'late_inputs_uncorrected': self.late_uncorrected,
                            **nis, 'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99'],
                            'design_file': self.design_file})

    def summary(self, status: str) -> dict:
        comp = percentiles(self.compute_s)
        return {'node': 'estimator', 'status': status, 'design_file': self.design_file,
                'steps': self.last_k, 'n_steps': self.N, 'updates': self.n_updates,
                'skipped_updates': self.n_skipped, 'missing_measurements': self.n_gap,
                'restarts': self.restarts, 'rejected_messages': self.rej.total,
                'rejected_by_reason': self.rej.as_dict(), 'input_source': self.input_source,
                'late_inputs_corrected': self.late_corrected,
                'late_inputs_uncorrected': self.late_uncorrected, **self.nis_stats(),
                'compute_p50_s': comp['p50'], 'compute_p99_s': comp['p99']}

    def summary_line(self, s: dict) -> str:
        nis = 'n/a' if s['nis_mean'] is None else f"{s['nis_mean']:.2f} (expected {s['nis_expected']})"
        return (f"{s['updates']} updates, {s['skipped_updates']} skipped, {s['missing_measurements']} missing, "
                f"{s['rejected_messages']} rejected, {s['restarts']} restarts, mean NIS {nis}, "
                f"compute p50 {fmt_s(s['compute_p50_s'])} p99 {fmt_s(s['compute_p99_s'])}")

    def publishers(self):
        return [self.pub_est, self.pub_field, self.pub_diag]


def c_decl(node, name, default, description):
    from sep_plant.node_util import declare
    return declare(node, name, default, description)


class _Process:
    """One estimator in its own process."""

    def __init__(self, executor: str):
        self.est = EstimatorNode()
        self.executor = make_executor(executor)
        self.executor.add_node(self.est.node)

    def run(self) -> int:
        rc = spin_episode(self.executor, [self.est])
        self.finish('completed')
        return rc

    def finish(self, status: str, error: str | None = None) -> None:
        self.est.finish(status, error)

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        self.est.destroy_node()


def main(argv: list[str] | None = None) -> int:
    opts, args = parse_front('estimator', 'ROM Kalman filter node (sep_estimator): estimates the '
                          'slab state and field from slab/measurements.', argv, None, PARAMETERS)
    limit_blas_threads(1)
    return run_node(lambda a: _Process(opts.executor), sim_time_default(args), 'estimator')


if __name__ == '__main__':
    sys.exit(main())
