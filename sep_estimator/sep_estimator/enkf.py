"""Ensemble Kalman Filter (stochastic, perturbed observations) over a black-box model.

Forecast  x_i <- f(x_i, u + w_i),            w_i ~ N(0, W) on the input channels
Analysis  x_i <- x_i + K (y + v_i - h(x_i)),  v_i ~ N(0, V),
          K = P_xy P_yy^{-1} with P_xy, P_yy the ensemble (cross-)covariances (+ V).

The ensemble is one batch (M, n_x): a forecast is one batched simulator call, so the
cost is that of M runs stepped together.

With ``antithetic=True`` (M even) members i and i + M/2 receive opposite noise draws
(w and -w, v and -v). The ensemble then stays symmetric about its mean to first order,
so the mean carries no first-order sampling noise: what remains is the nonlinear
(second-order) effect of the spread. This matters when the belief mean is optimized
over U, where sampling noise would otherwise be fitted as if it were signal.

On a device the ensemble stays there for the whole run (`upload`, `download`: the copies of
the caller's array module, e.g. `sep_plant.device`): the forecast steps it there, the analysis
forms the anomalies and P_xy = A_x' A_y / (M-1) there, and only the small parts cross: H X and
P_yy (M n_y and n_y^2 numbers) down, the gain's weights solve(P_yy, innovations) (M n_y) up,
the field's mean and std (2 n_f) down per step. The random numbers are drawn on the host, so
a device run filters with the same draws. With numpy the operations are those of 0.8.0.
Pure numpy (or a numpy-compatible module): no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

StepFn = Callable[..., np.ndarray]                          # (M, n_x), (M, n_u)[, (M, n_w)] -> (M, n_x)
ObserveFn = Callable[[np.ndarray], np.ndarray]              # (M, n_x) -> (M, n_y)
FieldFn = Callable[[np.ndarray], np.ndarray]                # (M, n_x) -> (M, n_field)


@dataclass
class EnKFResult:
    mean: np.ndarray   # (N+1, n_f) analysis means of the field (k = 0 is the initial ensemble)
    std: np.ndarray    # (N+1, n_f) per-node standard deviations (n_f = n_x without a field map)


class EnsembleKalmanFilter:
    """Stochastic EnKF with a given random generator (reproducible)."""

    def __init__(self, step: StepFn, observe: ObserveFn, w_std: np.ndarray | float,
                 v_std: np.ndarray | float, rng: np.random.Generator, antithetic: bool = False,
                 field: FieldFn | None = None, noise_on_inputs: bool = True,
                 upload: Callable[[np.ndarray], object] | None = None,
                 download: Callable[[object], np.ndarray] | None = None):
        """`step(X, u + w)` when the noise enters the inputs, else `step(X, u, w)` with w of
        len(w_std) channels; `field` maps members to the field whose mean/std `run` reports.
        `upload`/`download`: a host array to the ensemble's array module and back (None:
        numpy, no copies); `step`, `observe` and `field` then take and return that module's arrays."""
        self.step, self.observe, self.rng = step, observe, rng
        self.antithetic = antithetic
        self.field = field
        self.noise_on_inputs = noise_on_inputs
        self.w_std = np.asarray(w_std, dtype=float)
        self.v_std = np.asarray(v_std, dtype=float)
        self.upload = upload or (lambda a: a)
        self.download = download or (lambda a: a)

    def _draw(self, M: int, n: int) -> np.ndarray:
        if not self.antithetic:
            return self.rng.standard_normal((M, n))
        if M % 2:
            raise ValueError(f"antithetic sampling needs an even ensemble size, got {M}")
        z = self.rng.standard_normal((M // 2, n))
        return np.vstack([z, -z])

    def forecast(self, X: np.ndarray, u: np.ndarray) -> np.ndarray:
        M, n_u = X.shape[0], np.shape(u)[-1]
        if self.noise_on_inputs:
            w = self._draw(M, n_u) * self.w_std
            return self.step(X, np.broadcast_to(u, (M, n_u)) + w)
        w = self._draw(M, self.w_std.size) * self.w_std
        return self.step(X, np.broadcast_to(u, (M, n_u)), w)

    def analysis(self, X: np.ndarray, y: np.ndarray) -> np.ndarray:
        M = X.shape[0]
        HX = self.observe(X)
        n_y = HX.shape[1]
        Ax = X - X.mean(axis=0)
        Ay = HX - HX.mean(axis=0)
        V = np.diag(np.broadcast_to(self.v_std, (n_y,)) ** 2)
        P_xy = Ax.T @ Ay / (M - 1)
        P_yy = self.download(Ay.T @ Ay / (M - 1)) + V
        v = self._draw(M, n_y) * self.v_std
        innov = y + v - self.download(HX)                    # (M, n_y)
        # K innov_i for all members: P_xy P_yy^{-1} innov_i
        return X + self.upload(np.linalg.solve(P_yy, innov.T).T) @ P_xy.T

    def run(self, X0: np.ndarray, U: np.ndarray, Y: np.ndarray) -> EnKFResult:
        """Filter along inputs U (N, n_u) and observations Y (N+1, n_y) (y_0 unused: x_0 is the prior)."""
        N = U.shape[0]
        X = self.upload(np.array(X0, dtype=float))
        F = X if self.field is None else self.field(X)
        mean = np.empty((N + 1, F.shape[1]))
        std = np.empty_like(mean)
        mean[0], std[0] = self.download(F.mean(axis=0)), self.download(F.std(axis=0, ddof=1))
        for k in range(N):
            X = self.analysis(self.forecast(X, U[k]), Y[k + 1])
            F = X if self.field is None else self.field(X)
            mean[k + 1], std[k + 1] = self.download(F.mean(axis=0)), self.download(F.std(axis=0, ddof=1))
        if not (np.isfinite(mean).all() and np.isfinite(std).all()):
            raise FloatingPointError("the EnKF's ensemble became non-finite")
        return EnKFResult(mean, std)
