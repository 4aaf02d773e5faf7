"""The controller's episode logic without ROS: which step gets which command, once.

The `lqr` node (and the `lqg` process, where the estimator calls it directly) hands over what
it received, already checked for format (`sep_plant.gate`); this core decides:

* `estimate(k, estimate)`: the command of step k from the filter's estimate (`Controller`), unless
  step k already has one (the nominal fallback went out: the estimate is late, counted and
  dropped). An estimate of the last step k = N ends the episode (there is no command of step N).
* `measurement(k)`: a measurement says that step k has begun; the node then arms its watchdog,
  unless step k already has its command.
* `timeout()`: the watchdog fired: the step that began gets the nominal input clip(ubar_k),
  counted as a fallback (at k = N the episode ends without an estimate).

Like the estimator's `sep_estimator.estimator_core.EstimatorCore`, it holds no clock and no
topics: the node times the watchdog, publishes what it returns and logs the events.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_plant.protocol import clip_inputs

from sep_control.control.controllers import Controller


@dataclass
class Decision:
    """What to do for step k: send `u` (None: nothing to send)."""

    k: int
    u: np.ndarray | None = None
    late: bool = False             # the estimate came after the nominal fallback: dropped
    end: bool = False              # the last step (k = N) is done: the episode is over
    fallback: bool = False         # u is the nominal input (no estimate in time)
    law_fallback: bool = False     # the law fell back to a simpler one (the MPC to the clipped LQR)


class ControlLoopCore:
    """One episode of the online controller (one run).

    Parameters
    ----------
    controller : Controller
        The control law (`sep_control.control.controllers.make_controller`).
    u_nom : ndarray, shape (N, n_u)
        The nominal input, sent (clipped) when no estimate comes in time.
    lo, hi : ndarray, shape (n_u,)
        The input limits.
    """

    def __init__(self, controller: Controller, u_nom: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        self.controller = controller
        self.u_nom, self.lo, self.hi = u_nom, lo, hi
        self.N = int(u_nom.shape[0])
        self.sent = np.zeros(self.N + 1, dtype=bool)   # a command (or, for k = N, nothing) done
        self.current = -1                              # newest step announced by a measurement
        self.last_k = -1                               # newest step seen on any input
        self.done = False
        self.n_commands = self.n_fallbacks = self.n_late = 0
        self.fallback_steps: list[int] = []

    def estimate(self, k: int, estimate: np.ndarray) -> Decision:
        """The filter's estimate of step k (0 <= k <= N) arrived."""
        self.last_k = max(self.last_k, k)
        if k >= self.N:
            self.sent[self.N] = self.done = True
            return Decision(k, end=True)
        if self.sent[k]:
            self.n_late += 1
            return Decision(k, late=True)
        stats = self.controller.stats
        before = stats.fallbacks if stats is not None else 0
        u = self.controller.command(k, estimate)
        self.sent[k] = True
        self.n_commands += 1
        return Decision(k, u, law_fallback=stats is not None and stats.fallbacks > before)

    def measurement(self, k: int) -> bool:
        """A measurement stamped k arrived: whether the watchdog is to be (re)armed for step k."""
        if not 0 <= k <= self.N or k <= self.current:
            return False
        self.current = k
        self.last_k = max(self.last_k, k)
        return not self.sent[k]

    def timeout(self) -> Decision | None:
        """No estimate of the step that began came in time; None when that step is served."""
        k = self.current
        if k < 0 or self.sent[k]:
            return None
        self.sent[k] = True
        if k == self.N:
            self.done = True
            return Decision(k, end=True)
        self.n_fallbacks += 1
        self.fallback_steps.append(k)
        return Decision(k, np.array(clip_inputs(self.u_nom[k], self.lo, self.hi)), fallback=True)

    def counters(self) -> dict:
        """Counts for the summary and /diagnostics."""
        return {'commands': self.n_commands, 'fallbacks': self.n_fallbacks, 'late_estimates': self.n_late}
