"""`lqg`: estimator and LQR in one process on one executor (the low-latency default).

The two nodes are the same classes the `estimator` and `lqr` executables run (node names
``estimator`` and ``lqr``, namespace ``sep``), composed on a single-threaded executor.  The
estimator hands its estimate to the LQR by a direct call in the measurement callback, so the
command is published before anything else happens (state_estimate and field_estimate
are still published, after the command, for viewers and bags); the LQR tells the estimator
the command it sent (used if the plant's applied_input of that step comes late).

Both are managed (lifecycle) nodes (/sep/estimator and /sep/lqr): with autostart:=false
configure the estimator before the LQR (the LQR uses the estimator's design).

Parameters are those of both nodes (see `estimator --help` and `lqr --help`); ``-p`` on the
command line applies to both, a params file can address each node (share/sep_control/config/lqg.yaml).
"""
from __future__ import annotations

import sys

from sep_plant.ros.base import write_summary_json
from sep_plant.ros.process import NodeProcess, node_main
from sep_estimator.ros.estimator_node import PARAMETERS as EST_PARAMETERS
from sep_estimator.ros.estimator_node import EstimatorNode

from sep_control.ros.lqr_node import CONTROLLER_PARAMETERS, LqrNode

#: the estimator's parameters, then the control law's (the lqr's estimate_timeout_s does not apply)
PARAMETERS = (EST_PARAMETERS.replace('sep_estimator)/share/sep_estimator/config/estimator.yaml',
                                     'sep_control)/share/sep_control/config/lqg.yaml') + CONTROLLER_PARAMETERS
              + "\n  (the LQR's estimate_timeout_s does not apply: the estimate is computed in-process;"
              "\n  set next_design_file on /sep/estimator: the LQR uses the estimator's design)")


class LqgProcess(NodeProcess):
    """The estimator and the LQR on one executor, with one summary file for both."""

    def __init__(self, executor: str = 'events'):
        est = EstimatorNode(subscribe_command=False)
        lqr = LqrNode(peer=est, standalone=False)
        est.on_estimate = lqr.on_estimate
        lqr.on_command = est.note_command
        est.followers.append(lqr)          # a new episode (and a swapped design) reaches the LQR through the estimator
        self.est, self.lqr = est, lqr
        # one summary file for the process (a -p summary_file:=X applies to both nodes)
        self.summary_file = est.summary_file or lqr.summary_file
        est.summary_file = lqr.summary_file = ''
        super().__init__([est, lqr], executor)    # autostart: the estimator is configured first

    def finish(self, status: str, error: str | None = None) -> None:
        if self.finished:
            return
        self.finished = True
        # a node cleaned up before has written its summary then (status 'cleaned_up'): that one
        summ = {'node': 'lqg', 'status': status,
                'estimator': self.est.finish(status, error) or self.est.last_summary,
                'lqr': self.lqr.finish(status, error) or self.lqr.last_summary}
        if error:
            summ['error'] = error
        if self.summary_file:
            write_summary_json(self.summary_file, summ)


def main(argv: list[str] | None = None) -> int:
    return node_main('lqg', 'Estimator + LQR in one process (sep_control): the low-latency '
                     'controller of the sep closed loop.', argv, PARAMETERS,
                     lambda opts: LqgProcess(opts.executor))


if __name__ == '__main__':
    sys.exit(main())
