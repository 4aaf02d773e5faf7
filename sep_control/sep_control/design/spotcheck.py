"""Spot check of a kept TV-ERA model at another nominal input: a few impulse experiments.

Experiment plan 0.9 (`DesignSettings.experiment_plan`) ends the mean-only optimizer on a model
made where its last identification was, which may lie a few percent (in flat directions of the
cost) from the final input. Before the design reuses that model it is checked: impulse
experiments at SPOT_BLOCKS blocks of SPOT_STARTS start steps spread over the horizon, at the
final input, with the model's own scheme, amplitude and lags, against the model's Markov
parameters there,

    e = |Y_model - Y_spot|_F / |Y_spot|_F   over those start steps (j + lag <= N),

(2 to 3 % of a full identification's run-steps). The design reuses the model when e <= SPOT_TOL;
else it identifies again.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_estimator.ltv import LTVModel
from sep_plant.protocol import Plant, nominal_states

from sep_control.design.impulse import extend_nominal, impulse_experiments
from sep_control.design.tvera import Identification, identified_noise_input

#: blocks of start steps and start steps per block of the spot check
SPOT_BLOCKS = 4
SPOT_STARTS = 3
#: the largest spot-check error at which a kept model is reused (measured effect: docs/benchmarks.md)
SPOT_TOL = 2e-3


def spot_starts(N: int, lags: int, q: int) -> list[int]:
    """The first start step of each block: spread over q .. N - SPOT_STARTS (past the ramp-up)."""
    hi = max(q, N - SPOT_STARTS)
    return sorted({int(round(j)) for j in np.linspace(min(q, hi), hi, SPOT_BLOCKS)})


def spot_error(plant: Plant, ident: Identification, U: np.ndarray) -> float:
    """The spot-check error e of `ident`'s model at the nominal input U (module docstring)."""
    N = U.shape[0]
    lags = ident.data.Y.shape[1]
    U_ext = extend_nominal(U, lags)
    X_ext = nominal_states(plant, U_ext)
    m = ident.model
    noise = ident.data.noise      # a sketch's combinations of the noise channels (`noise_sketch`)
    model = m if m.Bw is None else LTVModel(m.A, np.concatenate([m.B, identified_noise_input(m, noise)], axis=2),
                                            m.C, m.G, m.dims)
    Yr = model.markov_all(lags)
    num = den = 0.0
    for j0 in spot_starts(N, lags, ident.q):
        j1 = min(N, j0 + SPOT_STARTS)
        data = impulse_experiments(plant, U[j0:j1], lags, 0, ident.delta, X_ext[j0:j1 + lags],
                                   scheme=ident.scheme, U_ext=U_ext[j0:], noise=noise, start=j0)
        valid = (np.arange(j0, j1)[:, None] + np.arange(1, lags + 1)[None, :]) <= N
        num += float(np.sum((Yr[j0:j1] - data.Y)[valid] ** 2))
        den += float(np.sum(data.Y[valid] ** 2))
    return float(np.sqrt(num / den)) if den > 0 else float("inf")
