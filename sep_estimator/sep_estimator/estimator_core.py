"""The estimator's episode logic without ROS: the Kalman filter plus what real message streams
need (as robot_localization's FilterBase keeps it apart from its node).

Per step k the node hands over what it received, already checked for format (names, lengths,
finite values, stamp on the step grid; `sep_plant.gate`):

* `measurement(k, y)`: y_k, or None when the message was malformed (the filter then predicts
  without that update: `skip`). Stale and duplicate steps are refused (`Rejection`) without
  touching the filter; a gap (missing steps) is skipped through; the first measurement of a
  core that joins an episode at k > 0 restarts the filter there (estimate = nominal,
  open-loop covariance).
* `applied(j, u)`: the input the plant applied at step j; the time update runs as soon as it is
  known. If y_{j+1} comes first, the filter predicts with the commanded input of step j
  (`commanded`) if known, else the nominal; when the applied input then arrives within step
  j+1 and differs, the estimate is corrected exactly: the prior moves by B_j (du_applied -
  du_used), and that change passes through the update of step j+1 with the gain
  P_{j+1|j+1} C' V^{-1} (equal to the Kalman gain).
* NIS: the normalized innovation squared dy' S_k^{-1} dy of every update (S_k^{-1}
  precomputed from the schedule while on it), computed in `finish_step` after the node has sent
  the command (off the measurement-to-command path); the mean over the last `nis_window`
  updates with its 99 % interval tells whether the filter is consistent.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from sep_plant import gate

from sep_estimator.ltv import LQG, in_precision, resolve_precision
from sep_estimator.tvkf import KalmanFilter

NIS_WINDOW = 50


class EstimatorCore:
    """One episode of the online filter (batch of one run)."""

    def __init__(self, lqg: LQG, u_nom: np.ndarray, y_nom: np.ndarray, field_nom: np.ndarray,
                 nis_window: int = NIS_WINDOW, field_precision: str = "auto"):
        """`field_precision` of the field reconstruction G_k a_hat ('float64'; 'float32':
        `ltv.Float32Reconstruction`, half the memory traffic on large grids; 'auto': float32
        from a field basis of `ltv.AUTO_FLOAT32_BYTES` on); the one used is `field_precision`."""
        self.lqg = lqg
        self.u_nom, self.y_nom, self.field_nom = u_nom, y_nom, field_nom
        self.N = int(u_nom.shape[0])
        self.n_u, self.n_y = int(u_nom.shape[1]), int(y_nom.shape[1])
        self.kf = KalmanFilter(lqg)
        self.field_precision = resolve_precision(self.kf.G, field_precision)
        self.kf.G = in_precision(self.kf.G, self.field_precision)
        m = lqg.model
        # innovation covariance inverses S_k^-1 = (C_k P_{k|k-1} C_k' + V)^-1 of the schedule (NIS)
        Pp = lqg.kf.P_prior
        self.S_inv = np.linalg.inv(m.C @ Pp @ m.C.transpose(0, 2, 1) + lqg.V)
        self.started = False
        self.last_meas = -1
        self.applied_u = np.full((self.N, self.n_u), np.nan)
        self.commanded_u = np.full((self.N, self.n_u), np.nan)
        self.used_du: dict[int, np.ndarray] = {}   # step -> du used when the applied input was late
        self.meas_kind: dict[int, str] = {}        # step -> 'update' | 'skip' (for late corrections)
        self.n_updates = self.n_skipped = self.n_gap = self.restarts = 0
        self.input_source = {'applied': 0, 'commanded': 0, 'nominal': 0}
        self.late_corrected = self.late_uncorrected = 0
        self.nis: deque[float] = deque(maxlen=nis_window)
        self.nis_sum = 0.0
        self.nis_n = 0
        self._nis_pending: tuple | None = None     # the last update's prior, for `finish_step`

    # ---------------------------------------------------------------- state
    @property
    def expected_step(self) -> int:
        """The step whose measurement the filter expects next."""
        return self.kf.k + 1 if self.kf.posterior else self.kf.k

    @property
    def estimate(self) -> np.ndarray:
        """The current estimate z_hat (n,): the ROM state a_hat, then the disturbance estimates d_hat
        when the design has disturbance states (`sep_estimator.disturbance`)."""
        return self.kf.a[0]

    def predicted(self, k: int) -> np.ndarray:
        """The predicted estimate zhat_{k|k-1} (n,) of step k: the filter has run the time update
        of step k-1 (`applied`) and not yet the measurement update of step k.

        A plant whose measurement of step k arrives only after its command of step k (an
        observation lagged one step, as controlgym's envs return it) is commanded from it:
        ``controller.command(k, core.predicted(k))``, the certainty-equivalent law on the best
        estimate before y_k. At k = 0 before any measurement it is the prior mean (zeros).

        Raises
        ------
        ValueError
            The filter is not at the prior of step k.
        """
        kf = self.kf
        if kf.k != k or kf.posterior:
            where = f"the posterior of step {kf.k}" if kf.posterior else f"the prior of step {kf.k}"
            raise ValueError(f"predicted({k}): the filter is at {where}")
        return kf.a[0].copy()

    def field_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(fbar_k + G_k a_hat, per-node std) at the filter's current step."""
        k = self.kf.k
        return self.field_nom[k] + self.kf.field_deviation()[0], self.kf.field_std()

    # --------------------------------------------------------------- inputs
    def measurement(self, k: int, y: np.ndarray | None) -> tuple[np.ndarray | None, gate.Rejection | None]:
        """Process the measurement of step k (y None: malformed, skip the update).

        Returns (a_hat_k, None), or (None, Rejection) for a stale or duplicate step."""
        if self.started:
            rej = gate.check_step(k, expected=self.expected_step, last=self.last_meas, allow_ahead=True)
            if rej is not None:
                return None, rej
        self.last_meas = k
        self._advance_to(k)
        if y is None:
            a = self.kf.skip(k)
            self.meas_kind[k] = 'skip'
            self.n_skipped += 1
        else:
            prior = (k, self.kf.a[0].copy(), None if self.kf.on_schedule else self.kf.P.copy())
            dy = y - self.y_nom[k]
            a = self.kf.update(k, dy)
            self.meas_kind[k] = 'update'
            self.n_updates += 1
            self._nis_pending = (*prior, dy)
        out = a[0].copy()
        # the applied input of step k may already be here (it never is in a healthy loop)
        if k < self.N and not np.isnan(self.applied_u[k, 0]):
            self.kf.predict(k, self._du(k))
        return out, None

    def finish_step(self) -> None:
        """Book-keeping of the last update that can wait until the command is out: its NIS."""
        if self._nis_pending is not None:
            k, a_prior, P_prior, dy = self._nis_pending
            self._nis_pending = None
            self._nis(k, dy - self.lqg.model.C[k] @ a_prior, P_prior)

    def applied(self, j: int, u: np.ndarray) -> gate.Rejection | None:
        """The input the plant applied at step j (0 <= j < N)."""
        if not np.isnan(self.applied_u[j, 0]):
            return gate.Rejection(gate.DUPLICATE, f'second applied_input for step {j}')
        self.applied_u[j] = u
        if not self.started:
            return None
        kf = self.kf
        if kf.k == j and kf.posterior:
            kf.predict(j, self._du(j))            # the usual case: time update right away
        elif j in self.used_du and kf.k == j + 1:
            self._correct_late(j, u)
        elif j in self.used_du:
            self.late_uncorrected += 1
        return None

    def commanded(self, j: int, u: np.ndarray) -> None:
        """The command of step j (a fallback when the applied input is late)."""
        if 0 <= j < self.N:
            self.commanded_u[j] = u

    # ------------------------------------------------------------ internals
    def _du(self, j: int) -> np.ndarray:
        """Input deviation of step j for the time update: applied, else commanded, else nominal."""
        if not np.isnan(self.applied_u[j, 0]):
            self.input_source['applied'] += 1
            return self.applied_u[j] - self.u_nom[j]
        if not np.isnan(self.commanded_u[j, 0]):
            self.input_source['commanded'] += 1
            du = self.commanded_u[j] - self.u_nom[j]
        else:
            self.input_source['nominal'] += 1
            du = np.zeros(self.n_u)
        self.used_du[j] = du
        return du

    def _advance_to(self, k: int) -> None:
        """Bring the filter to the prior of step k (restart, or skip/predict through a gap)."""
        if not self.started:
            self.started = True
            if k > 0:
                self.kf.restart_at(k)
                self.restarts += 1
            return
        while self.kf.k < k:
            j = self.kf.k
            if not self.kf.posterior:
                self.kf.skip(j)
                self.meas_kind[j] = 'skip'
                self.n_gap += 1
            self.kf.predict(j, self._du(j))

    def _correct_late(self, j: int, u: np.ndarray) -> None:
        """The filter predicted step j with an assumed input; the applied one differs."""
        used = self.used_du.pop(j)
        delta_du = (u - self.u_nom[j]) - used
        if not np.any(delta_du):
            return
        delta = self.lqg.model.B[j] @ delta_du
        if self.kf.posterior and self.meas_kind.get(j + 1) == 'update':
            L = self.kf.gain_after_update()            # P_{k|k} C' V^-1 = the Kalman gain of step k
            delta = delta - L @ (self.lqg.model.C[j + 1] @ delta)
        self.kf.a = self.kf.a + delta
        self.late_corrected += 1

    def _nis(self, k: int, innov: np.ndarray, P_prior: np.ndarray | None) -> None:
        if P_prior is None:                             # on schedule: precomputed S_k^-1
            val = float(innov @ self.S_inv[k] @ innov)
        else:
            val = float(innov @ np.linalg.solve(self.kf.innovation_covariance(k, P_prior), innov))
        self.nis.append(val)
        self.nis_sum += val
        self.nis_n += 1

    # --------------------------------------------------------------- report
    def nis_stats(self) -> dict[str, Any]:
        self.finish_step()
        recent = float(np.mean(self.nis)) if self.nis else None
        lo, hi = gate.chi2_interval(self.n_y, len(self.nis), 0.99)
        return {'nis_mean': self.nis_sum / self.nis_n if self.nis_n else None,
                'nis_recent_mean': recent, 'nis_expected': self.n_y, 'nis_recent_interval_99': [lo, hi],
                'nis_consistent': None if recent is None else bool(lo <= recent <= hi)}

    def counters(self) -> dict[str, Any]:
        return {'updates': self.n_updates, 'skipped_updates': self.n_skipped, 'missing_measurements': self.n_gap,
                'restarts': self.restarts, 'input_source': dict(self.input_source),
                'late_inputs_corrected': self.late_corrected, 'late_inputs_uncorrected': self.late_uncorrected}
