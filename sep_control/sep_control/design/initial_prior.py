"""The design's account of an uncertain initial state: the Kalman filter's prior on the ROM.

A plant with an initial-state distribution (`sep_plant.initial`: the optional method
``initial_states(seeds)``) starts each run somewhere around its nominal initial state
``initial_state`` (the design's nominal starts there). The ROM represents that initial deviation
through its free responses: S sampled initial states x_0^(i) are stepped under the nominal input
for L steps (S L plant run-steps), and their output deviations from the nominal are fitted by the
ROM's free response. A TV-ERA ROM has no state at step 0 (its state at step k is spanned by the
responses to inputs before k, n_0 = 0), so the fit is at the first step k_0 where it has one:

    dy^(i) = [y_k0^(i) - ybar_k0; ...; y_L^(i) - ybar_L] ~ O_k0 a^(i),
    O_k0 = [C_k0; C_k0+1 A_k0; ...; C_L A_L-1 ... A_k0],   a^(i) = O_k0^+ dy^(i)   (least squares),

and the filter's prior covariance at step k_0 gains their second moment
Delta = (1/S) sum_i a^(i) a^(i)' (its mean is the nominal's, a = 0): the initial deviation
carried to step k_0, the part of it the ROM's states can represent (`InitialPrior.fit` says how
much of the sampled output deviations that is). The Kalman schedule is recomputed with it
(P_k0|k0-1 += Delta in the ROM block; the disturbance states keep their prior); the LQR gains do
not depend on it.

A plant without the distribution, or whose draws all equal its initial state (a built-in with
``initial_spread`` 0), leaves the design untouched, bit for bit (`with_initial_prior` returns
the LQG it was given). A design file keeps the gains and posteriors this gives; its priors are
recomputed on loading without Delta (they only feed the NIS statistics and restarts).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel
from sep_estimator.tvkf import measurement_update, time_update
from sep_plant.initial import sample_initial_states
from sep_plant.protocol import Plant, outputs, rollout

#: sampled initial states and free-response steps of the fit
SAMPLES = 64
LAGS = 20


@dataclass(frozen=True)
class InitialPrior:
    """The fitted prior and how well the ROM's free responses explain the sampled ones."""

    k0: int                  # the step the prior is added at (the ROM's first step with states)
    delta: np.ndarray        # (n_r, n_r) covariance of the ROM state at k0 from the initial deviation
    fit: float               # 1 - |dy - O a|^2 / |dy|^2 over the samples (steps k0..L)
    run_steps: int           # plant run-steps the free responses took


def observability(rom: LTVModel, k0: int, lags: int) -> np.ndarray:
    """O_k0 ((lags-k0+1) n_y, n): the ROM's outputs at steps k0..lags from a unit a_k0 (no input)."""
    n = rom.n
    rows, Phi = [], np.eye(n)
    for k in range(k0, lags + 1):
        rows.append(rom.C[k] @ Phi)
        if k < lags:
            Phi = rom.A[k] @ Phi
    return np.concatenate(rows, axis=0)


def fit_initial_prior(plant: Plant, rom: LTVModel, U: np.ndarray, y_nom: np.ndarray,
                      samples: int = SAMPLES, lags: int = LAGS, seed: int = 0) -> InitialPrior | None:
    """Delta at k_0 from the free responses of sampled initial states (module docstring).

    Parameters
    ----------
    plant : Plant
        The plant (its optional ``initial_states``).
    rom : LTVModel
        The identified ROM (A_k, C_k, dims).
    U : ndarray, shape (N, n_u)
        The nominal input.
    y_nom : ndarray, shape (N+1, n_y)
        The nominal outputs.
    samples, lags : int
        S sampled initial states, L free-response steps.
    seed : int
        Seed of the draws (runs 0..S-1 of `sep_plant.initial.initial_states`).

    Returns
    -------
    InitialPrior or None
        None when the plant's initial state is not uncertain or the ROM has no state before L.
    """
    X0 = sample_initial_states(plant, samples, seed)
    if X0 is None:
        return None
    L = int(min(lags, U.shape[0]))
    with_states = np.flatnonzero(np.asarray(rom.dims)[: L + 1] > 0)
    if with_states.size == 0:
        return None
    k0 = int(with_states[0])
    Y = outputs(plant, rollout(plant, X0, U[:L]))                       # (S, L+1, n_y)
    dY = (Y[:, k0:] - y_nom[None, k0: L + 1]).reshape(X0.shape[0], -1).T
    O = observability(rom, k0, L)
    a, *_ = np.linalg.lstsq(O, dY, rcond=None)                          # (n, S)
    resid = dY - O @ a
    fit = 1.0 - float(np.sum(resid ** 2) / max(np.sum(dY ** 2), 1e-300))
    return InitialPrior(k0, a @ a.T / X0.shape[0], fit, int(X0.shape[0] * L))


def with_initial_prior(lqg: LQG, prior: InitialPrior | None) -> LQG:
    """The LQG whose Kalman schedule has P_k0|k0-1 += Delta in the ROM block; `lqg` itself when
    `prior` is None."""
    if prior is None:
        return lqg
    m, W, V = lqg.model, lqg.W, lqg.V
    extra = np.zeros((m.n, m.n))
    n_r = prior.delta.shape[0]
    extra[:n_r, :n_r] = prior.delta
    A, Bw, C = m.A, m.noise_input, m.C
    N1 = C.shape[0]
    Ls = np.zeros((N1, m.n, m.n_y))
    P_post, P_prior = np.zeros((N1, m.n, m.n)), np.zeros((N1, m.n, m.n))
    P = m.initial_covariance()
    for k in range(N1):
        if k == prior.k0:
            P = P + extra
        P_prior[k] = P
        Ls[k], P_post[k] = measurement_update(P, C[k], V)
        if k < N1 - 1:
            P = time_update(P_post[k], A[k], Bw[k], W)
    return replace(lqg, kf=KalmanSchedule(Ls, P_post, P_prior), field_std=None)
