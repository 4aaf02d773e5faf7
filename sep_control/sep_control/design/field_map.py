"""The design's field map, compressed to the directions the ROM state reaches.

The identification's field map G_k = Phi g_k spans every field response of the experiments.
With the LQG running (and without it) the ROM state a_k spreads as X_k (`state_spread`);
directions of Phi that X_k moves by less than `FIELD_MAP_TOL` times the largest spread are
dropped (`compress_field_map`), unless the LQR weighs the field (lqr_weighting: field: the
identification's map is kept, `compressed_lqg`). The filter (it reads the outputs) does not use G, nor does the
LQR weighting the outputs, so those gains do not change; an LQR weighting the field
(lqr_weighting: field) is redesigned on the compressed map (`gains.regained`), so that its gains
and the MPC's weights read the same map. The field std `LQG.field_std` is that of the compressed map.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel, PODFieldMap, psd_factor

from sep_control.design.gains import GainsResult, estimate_covariances, regained
from sep_control.design.svd import svd

#: relative tolerance of the design's field map against the ROM state's spread
#: (`compress_field_map`, `state_spread`). Measured on the four shipped scenarios (200 closed-loop
#: runs each, the same runs with the full and the compressed map): the reconstructed field moved by
#: at most 9.3e-4 of the largest per-node std (8.3e-5 rms), the 2-sigma coverage not at all (4
#: digits), and Phi shrank 59 -> 24 (reference), 220 -> 70 (plate 64^2), 246 -> 86 (block 24^3),
#: 517 -> 158 (Allen-Cahn) columns
FIELD_MAP_TOL = 1e-5


def state_spread(model: LTVModel, K: np.ndarray, kf: KalmanSchedule, V: np.ndarray) -> np.ndarray:
    """X_k = P_k|k + cov(ahat_k) in closed loop + cov(ahat_k) in open loop (N+1, n, n): covers the
    ROM state's covariance with the LQG running (P_k|k + the closed-loop estimate's, which moves
    along B_k through the feedback) and without it (P_k|k + the open-loop estimate's). For a model
    with disturbance states, of z = [a; d]: the field map G_z = [G_k, 0] reads its a-block only."""
    return (kf.P_post + estimate_covariances(model, K, kf, V, closed_loop=True)
            + estimate_covariances(model, K, kf, V, closed_loop=False))


def compress_field_map(G: PODFieldMap, X: np.ndarray, tol: float) -> PODFieldMap:
    """G_k = Phi g_k on fewer directions: the SVD U S V' of [g_0 L_0 ... g_N L_N], X_k = L_k L_k'
    (X (N+1, n, n): the state spread, `state_spread`), keeps U_r, the directions with
    S > tol S_1: Phi' = Phi U_r (still orthonormal), g_k' = U_r' g_k.

    What is dropped moves the field by less than tol times its largest spread, both the
    reconstructed mean and the std."""
    gL = G.g @ psd_factor(X)                                   # (N+1, r_f, n)
    U, S, _ = svd(np.concatenate(list(gL), axis=1))
    r = int(np.count_nonzero(S > tol * S[0])) if S.size and S[0] > 0 else 0
    Ur = U[:, :max(r, 1)] if G.rank else U[:, :0]
    return PODFieldMap(np.ascontiguousarray(G.Phi @ Ur), np.ascontiguousarray(np.matmul(Ur.T, G.g)))


def compressed_lqg(gains: GainsResult, tol: float = FIELD_MAP_TOL, name: str = "rom_lqg") -> LQG:
    """The field-map stage of the design: the LQG of `gains` on its model with the POD field map
    compressed at `tol` against the state spread these gains give (`state_spread`,
    `compress_field_map`), and `LQG.field_std` computed for that map. A map that is not a POD
    one (the oracle's) is kept as it is. With disturbance states the ROM's map is compressed
    against the a-block of the spread of z (d does not move the field). Under the field weighting
    (lqr_weighting: field) the identification's map is kept: the LQR weighs the field through it,
    and a map compressed against the filter's spread (rank 1 where the spread is) would drop the
    field directions the cost reads (measured on controlgym's envs, docs/benchmarks.md)."""
    rom = gains.model if gains.rom is None else gains.rom
    field_weighted = gains.problem is not None and gains.problem.lqr_weighting == "field"
    if isinstance(rom.G, PODFieldMap) and not field_weighted:
        X = state_spread(gains.model, gains.K, gains.kf, gains.V)[:, :rom.n, :rom.n]
        rom = replace(rom, G=compress_field_map(rom.G, X, tol))
        gains = regained(gains, rom)
    return gains.lqg(name, rom)
