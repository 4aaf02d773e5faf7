"""`lqg`: estimator and LQR in one process on one executor (the low-latency default).

The two nodes are the same classes the `estimator` and `lqr` executables run (node names
``estimator`` and ``lqr``, namespace ``slab``), composed on a single-threaded executor.  The
estimator hands its estimate to the LQR by a direct call in the measurement callback, so the
heat command is published before anything else happens (state_estimate and field_estimate
are still published, after the command, for viewers and bags); the LQR tells the estimator
the command it sent (used if the plant's applied_input of that step comes late).

Parameters are those of both nodes (see `estimator --help` and `lqr --help`); ``-p`` on the
command line applies to both, a params file can address each node (share/sep_control/config/lqg.yaml).
"""
from __future__ import annotations

import sys

from sep_plant.ros.base import (limit_blas_threads, make_executor, parse_front, run_node, sim_time_default,
                                 write_json)
from sep_estimator.ros.estimator_node import PARAMETERS as EST_PARAMETERS
from sep_estimator.ros.estimator_node import EstimatorNode
from sep_estimator.ros.designed_node import spin_episode

from sep_control.ros.lqr_node import LqrNode

PARAMETERS = EST_PARAMETERS.replace('sep_estimator)/share/sep_estimator/config/estimator.yaml',
                                    'sep_control)/share/sep_control/config/lqg.yaml') + """
  controller (str, lqr)            lqr | mpc (box-constrained MPC on the ROM: input limits planned for)
  mpc_horizon (int, 20)            mpc: horizon H in steps
  mpc_time_budget_s (float, 0.02)  mpc: a QP slower than this falls back to the clipped LQR command
  (the LQR's estimate_timeout_s does not apply: the estimate is computed in-process)"""


class LqgProcess:
    def __init__(self, executor: str = 'events'):
        self.est = EstimatorNode(subscribe_command=False)
        self.lqr = LqrNode(design=self.est.design, standalone=False)
        if self.lqr.design_file != self.est.design_file:
            self.lqr.log.warning(f'design_file of lqr ({self.lqr.design_file}) differs from the '
                                 f'estimator\'s; using the estimator\'s ({self.est.design_file})')
        self.est.on_estimate = self.lqr.on_estimate
        self.lqr.on_command = self.est.note_command
        self.executor = make_executor(executor)
        self.executor.add_node(self.est.node)
        self.executor.add_node(self.lqr.node)

        # one summary file for the process (a -p summary_file:=X applies to both nodes)
        self.summary_file = self.est.summary_file or self.lqr.summary_file
        self.est.summary_file = self.lqr.summary_file = ''
        self.finished = False

    def run(self) -> int:
        rc = spin_episode(self.executor, [self.est, self.lqr])
        self.finish('completed')
        return rc

    def finish(self, status: str, error: str | None = None) -> None:
        if self.finished:
            return
        self.finished = True
        summ = {'node': 'lqg', 'status': status, 'estimator': self.est.finish(status, error),
                'lqr': self.lqr.finish(status, error)}
        if error:
            summ['error'] = error
        if self.summary_file:
            write_json(self.summary_file, summ)

    def destroy_node(self) -> None:
        self.executor.shutdown(timeout_sec=0.1)
        self.lqr.destroy_node()
        self.est.destroy_node()


def main(argv: list[str] | None = None) -> int:
    opts, args = parse_front('lqg', 'Estimator + LQR in one process (sep_control): the low-latency '
                          'controller of the sep closed loop.', argv, None, PARAMETERS)
    limit_blas_threads(1)
    return run_node(lambda a: LqgProcess(opts.executor), sim_time_default(args), 'lqg')


if __name__ == '__main__':
    sys.exit(main())
