"""Many process-noise channels: impulses on a few random combinations of them, not on each.

A plant whose process noise does not enter through the inputs (`noise_on_inputs` False) has
n_w noise channels, and TV-ERA identifies the ROM's noise input B_w,k (n_r, n_w) from impulses
on them beside the inputs' (`sep_control.design.impulse`): 2 N n_w more experiments and Hankel
matrices of (p n_y) x q (n_u + n_w) per step. With noise on every node (n_w = n_x, hundreds)
that is a Hankel SVD thousands of columns wide per step. The design needs B_w only through the
ROM's process-noise covariance

    Q_k = B_w,k W B_w,k'    (n_r x n_r),   W = diag(w_std^2),

so above `SKETCH_FROM` channels the impulses go on r_w = `SKETCH_PROBES` combinations per
start step j instead (a randomized trace/covariance sketch):

    Omega_j  (n_e, r_w)  orthonormal columns, Haar-random, seeded by (SKETCH_SEED, j), on the
                         n_e channels with w_std > 0;
    d_{j,i} = W^{1/2} omega_{j,i} / s_{j,i},  s_{j,i} = |W^{1/2} omega_{j,i}|  (unit probes);
    B~_j = B_w,j D_j      (n_r, r_w)    identified like an input's B (Hankel width q (n_u + r_w));
    B^_j = B~_j diag(c s_j) Omega_j' W^{-1/2}   (n_r, n_w),   c = sqrt(n_e / r_w),

so that B^_j W B^_j' = c^2 B_w,j W^{1/2} Omega_j Omega_j' W^{1/2} B_w,j', whose expectation
over Omega_j is Q_j (E[Omega Omega'] = (r_w / n_e) I): an unbiased estimate of the covariance,
with fresh combinations at every start step, so that the filter, which sums Q_j over many
steps, averages their errors. Strided impulses (`impulse_stride` s > 1) keep each start step's
combinations for the s - 1 steps after it (`hold`): the steps between are not impulsed, and their
noise columns are the held start step's responses (`sep_control.design.impulse.hold_starts`), so
the lift uses the combinations those responses were measured on (a linear interpolation between
two start steps would mix responses to two different Omega_j). The ROM keeps B^ (n_w columns): the Kalman filter, the design
file and the online nodes see the plant's own noise channels, W unchanged. The sketch's
sampling error is reported as the relative standard error of tr Q^_j from its r_w probes
(`trace_std_error`). Plants with at most SKETCH_FROM channels (every shipped scenario) are
identified channel by channel as before, bit for bit.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: noise channels above which the channels are sketched (controlgym's 64-node envs with noise on
#: every node stay exact: a sketch saves less than half of their experiments there)
SKETCH_FROM = 64
#: random combinations per start step (measured effect: docs/benchmarks.md)
SKETCH_PROBES = 32
#: seed of the combinations (start step j uses SeedSequence(SKETCH_SEED, spawn_key=(j,)); held: the
#: key of j - j mod hold)
SKETCH_SEED = 20260433


@dataclass(frozen=True)
class NoiseSketch:
    """The probes of `r_w` random combinations of the noise channels whose stds are `w_std`."""

    w_std: tuple[float, ...]
    rank: int
    hold: int = 1          # start step j uses the combinations of j - j mod hold (strided impulses)

    @property
    def n_w(self) -> int:
        return len(self.w_std)

    def _omega(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(Omega_j (n_e, r_w), the channels with w_std > 0)."""
        std = np.asarray(self.w_std)
        live = np.flatnonzero(std > 0)
        rng = np.random.default_rng(np.random.SeedSequence(SKETCH_SEED, spawn_key=(int(j) - int(j) % self.hold,)))
        G = rng.standard_normal((live.size, self.rank))
        Q, R = np.linalg.qr(G)
        return Q * np.sign(np.diag(R))[None, :], live     # Haar: the sign fix of QR

    def parts(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(D_j (n_w, r_w) unit probes, L_j (r_w, n_w) with B^_j = B~_j L_j) of start step j."""
        std = np.asarray(self.w_std)
        omega, live = self._omega(j)
        Wh = std[live, None] * omega                      # W^{1/2} Omega on the live channels
        s = np.linalg.norm(Wh, axis=0)
        D = np.zeros((self.n_w, self.rank))
        D[live] = Wh / s[None, :]
        L = np.zeros((self.rank, self.n_w))
        c = np.sqrt(live.size / self.rank)
        L[:, live] = (c * s)[:, None] * omega.T / std[None, live]
        return D, L

    def directions(self, j: int) -> np.ndarray:
        """D_j: the unit noise vectors of start step j's r_w probes (n_w, r_w)."""
        return self.parts(j)[0]

    def lift(self, Bs: np.ndarray, start: int = 0) -> np.ndarray:
        """B^ (N, n_r, n_w) from the sketched B~ (N, n_r, r_w) of start steps start..start+N-1."""
        out = np.zeros(Bs.shape[:2] + (self.n_w,))
        for i in range(Bs.shape[0]):
            out[i] = Bs[i] @ self.parts(start + i)[1]
        return out

    def sketched(self, Bw: np.ndarray, start: int = 0) -> np.ndarray:
        """B^ (N, n_r, n_w) back on the probes, B~_j = B^_j D_j (L_j D_j)^{-1} (L_j D_j = c I): exactly
        B~ for a lifted B^ (`lift`), to compare a model with its experiments (N, n_r, r_w)."""
        out = np.zeros(Bw.shape[:2] + (self.rank,))
        for i in range(Bw.shape[0]):
            D, L = self.parts(start + i)
            out[i] = Bw[i] @ D @ np.linalg.inv(L @ D)
        return out


def sketch_for(n_w: int, w_std, probes: int | None = None, hold: int = 1) -> NoiseSketch | None:
    """The sketch of `n_w` noise channels of stds `w_std` (scalar or n_w; None: 1), or None when
    they are identified one by one: n_w <= SKETCH_FROM, `probes` 0, or no fewer probes than
    channels with noise. `hold`: the impulse stride (each start step's combinations held over it)."""
    r = SKETCH_PROBES if probes is None else int(probes)
    std = np.broadcast_to(np.asarray(1.0 if w_std is None else w_std, dtype=float), (n_w,))
    if r <= 0 or n_w <= SKETCH_FROM or r >= int(np.count_nonzero(std > 0)):
        return None
    return NoiseSketch(tuple(float(v) for v in std), r, int(hold))


def identified_noise_channels(plant, w_std) -> int:
    """The noise channels a design's experiments step beside the inputs: none when the noise is
    on the inputs, the sketch's r_w above SKETCH_FROM channels, else every one (n_w)."""
    from sep_plant.protocol import noise_channels

    n_w = 0 if getattr(plant, "noise_on_inputs", True) else int(noise_channels(plant))
    sketch = sketch_for(n_w, w_std) if n_w else None
    return n_w if sketch is None else sketch.rank


def trace_std_error(Bs: np.ndarray, sketch: NoiseSketch, start: int = 0) -> float:
    """The median over start steps of the relative standard error of tr Q^_j from its r_w probes:
    std(t) / (mean(t) sqrt(r_w)), t_i = (c s_i)^2 |b~_i|^2 the probes' shares of the trace."""
    errs = []
    for i in range(Bs.shape[0]):
        D, L = sketch.parts(start + i)
        scale2 = np.einsum("in,n,in->i", L, np.asarray(sketch.w_std) ** 2, L)     # (c s_i)^2
        t = scale2 * np.sum(Bs[i] ** 2, axis=0)
        if t.mean() > 0:
            errs.append(float(t.std(ddof=1) / (t.mean() * np.sqrt(sketch.rank))))
    return float(np.median(errs)) if errs else 0.0
