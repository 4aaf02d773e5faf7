"""Are strided impulses fine enough for this ROM? A check from the strided data alone (no plant step).

Strided impulses (`impulse_stride` s > 1) impulse every s-th start step and interpolate the Markov
parameters Y_j = [Y_{j+l,j}]_l of the start steps between linearly (`impulse.interpolate_starts`).
Between two impulsed start steps a < j < b the interpolation misses

    E_j = Y_j - Y^lin_j ~ -(j - a)(b - j) / 2 * Y''_a,

with Y'' the second divided difference of the impulsed start steps a, b and the next one (the
previous one for the last interval). On the five scenarios of docs/benchmarks.md this estimate
was within 35 % of the true error measured at every start step. A noise sketch's held columns
(`noise_sketch`) are left out: two start steps' responses to different random combinations show
no time variation to estimate their error from.

By Weyl's inequality each singular value of the Hankel matrix H_k moves by at most ||E_k||_2, the
spectral norm of the same Hankel matrix built from E. The ROM's states whose sigma_i(H_k) <
||E_k||_2 are therefore set by the interpolation rather than by the plant. A ROM most of whose kept
states are of that kind (the 3-D block: 14 of 38 resolved, and its filter's 2-sigma coverage fell
from 0.95 to 0.91) needs impulses at every start step; the scenarios that keep more than half of
theirs (the rod 55 %, Allen-Cahn 52.5 %, the reference, plate and Burgers 75-95 %) lost nothing
measurable to the stride. The threshold is set by these plants, not derived. `resolved_share` gives that share; the design
identifies its final model again at every start step when it is below `RESOLVED_MIN`.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import numpy as np

from sep_control.design.impulse import strided_starts
from sep_control.design.tvera import Identification, _hankel

#: the share of the kept ROM states (median over steps) that the strided data must resolve; below
#: it the final model is identified at every start step
RESOLVED_MIN = 0.5


def interpolation_error(Y: np.ndarray, starts: np.ndarray, held: int | None = None) -> np.ndarray:
    """The estimated error E (shape of Y) of the rows of Y (N, ...) not in `starts` (those rows
    interpolated linearly in j); zero on the start steps, where fewer than 3 start steps are, and
    on the channels from `held` on (a sketch's held columns, `impulse.hold_starts`; None: none)."""
    E = np.zeros_like(Y)
    if len(starts) < 3:
        return E
    for i in range(len(starts) - 1):
        a, b = int(starts[i]), int(starts[i + 1])
        if b - a < 2:
            continue
        t0, t1, t2 = (a, b, int(starts[i + 2])) if i + 2 < len(starts) else (int(starts[i - 1]), a, b)
        d1 = (Y[t1] - Y[t0]) / (t1 - t0)
        second = 2.0 * ((Y[t2] - Y[t1]) / (t2 - t1) - d1) / (t2 - t0)        # Y'' (divided difference)
        for j in range(a + 1, b):
            E[j] = -0.5 * (j - a) * (b - j) * second
    if held is not None:
        E[..., held:] = 0.0
    return E


def resolved_share(ident: Identification, kept: np.ndarray | None = None) -> float:
    """The median over steps k >= q of the share of the kept states (the model's `dims`) whose
    Hankel singular value exceeds ||E_k||_2 (module docstring); 1 for impulses at every start step."""
    if ident.stride <= 1:
        return 1.0
    Y = ident.data.Y
    N, p, q = Y.shape[0], ident.p, ident.q
    starts = strided_starts(N, ident.stride)
    E = interpolation_error(Y, starts, held=ident.data.n_u if ident.data.noise is not None else None)
    kept = np.asarray(ident.model.dims if kept is None else kept)
    shares = []
    for k in range(q, N + 1):
        n = int(kept[k])
        if n == 0:
            continue
        err = float(np.linalg.norm(_hankel(E, k, p, q, 0), 2))
        shares.append(np.count_nonzero(ident.hankel_sv[k, :n] > err) / n)
    return float(np.median(shares)) if shares else 1.0
