"""Disturbance states of the ROM filter: offset-free tracking of a plant that differs from the model.

A design is made on a simulator; the plant it runs on differs by persistent offsets (a boundary
or ambient temperature, a heater gain or offset, a sensor bias). The TV-LQG has no integral
action, so such an offset stays as a steady error. The filter therefore estimates n_d constant
(random-walk) disturbances d_k next to the ROM state a_k, z_k = [a_k; d_k] (n_z = n_r + n_d),
and the LQR of the augmented ROM acts on them (docs/method.md):

* ``input``: a bias of the inputs, along n_d orthonormal input directions E (n_u, n_d):
      a_{k+1} = A_k a_k + B_k (du_k + E d_k) + B_w,k w_k,    dy_k = C_k a_k + v_k.
* ``noise``: a constant forcing where the plant's process noise enters, along n_d orthonormal
  directions E_w (n_w, n_d) of its noise channels:
      a_{k+1} = A_k a_k + B_k du_k + B_w,k (E_w d_k) + B_w,k w_k,    dy_k = C_k a_k + v_k.
  An unmodelled source spread over the domain, on a plant whose noise has channels of its own
  (noise_on_inputs false). For a plant whose noise enters through the inputs B_w = B, and the
  noise kind IS the input kind: `choose` makes an input-kind model (recorded as asked for
  'noise'), the same numbers; the two kinds share every function here (`channels`).
* ``output``: a bias of the sensors, F (n_y, n_d) (F = I: one bias per sensor), estimated and
  removed from the measurements, not acted on:
      a_{k+1} = A_k a_k + B_k du_k + B_w,k w_k,              dy_k = C_k a_k + F d_k + v_k.
* combinations ``input+noise``, ``noise+output``, ``input+output``: the parts' states stacked,
  d = [d_1; d_2] (the parts in the order input, noise, output), each part acting as its kind
  does and with its own directions and priors. The map is block-diagonal over the parts'
  channel spaces stacked in that order (rows n_u, n_w or n_y per part, columns n_d1, n_d2:
  `part_views`). Budget (`split_dims`): n_d1 + n_d2 <= n_y; by default the first part takes
  ceil(n_y / 2) (at most its channels) and the second the rest; `disturbance_dims` [n_1, n_2]
  sets the split. Directions (`_combined`): the first part's as for its kind; the second's from
  its step gain with the first part's output image Gamma_1 E_1 projected out,
  (I - Q_1 Q_1') Gamma_2 (for an output part Gamma_2 = I: F spans the sensor-bias directions the
  first part cannot explain), so the stacked step gain [Gamma_1 E_1, Gamma_2 E_2] has full
  column rank (detectable together; recorded as "detectable", "rank_gamma_E").
* all: d_{k+1} = d_k + eta_k, eta_k ~ N(0, diag(sigma_walk^2)); the prior d_0 ~ N(0,
  diag(sigma_0^2)) is not zero, so the filter starts from P_0 = blockdiag(0, diag(sigma_0^2))
  (`LTVModel.P0`), and so does every covariance recursion from k = 0.

Directions of the input kind (`input_directions`): with fewer sensors than inputs not every
input bias is detectable. The ROM's band-window step gain, the outputs' response to a constant
unit input from k = 0 averaged over the band window,

    Gamma = mean_{k in window} C_k M_k,   M_0 = 0,  M_{k+1} = A_k M_k + B_k,

has the SVD U S V'; E holds the right singular vectors of the n_d largest singular values
(n_d = min(n_y, n_u) by default), those above `DIRECTION_RTOL` S_1. The augmented system is
detectable at steady state when Gamma E has full column rank (its singular values are S_1..S_nd).

Prior std (`choose`): sigma_0,i = c band / sqrt(S_i S_cl,i), c = `STD0_BANDS`: a bias that moves
the outputs by c bands on the geometric mean of two step gains along E_i, the open-loop S_i above
(how strongly the outputs show the bias: the estimate's information) and the closed-loop
S_cl,i = |Gamma_cl E_i|, Gamma_cl the same average with M_{k+1} = (A_k + B_k K_k) M_k + B_k
under the ROM's plain LQR K (the offset the LQG without disturbance states leaves). Measured
(docs/robustness.md): the open-loop rule c band / S_i alone gives a direction the plant
integrates (S_i grows with the window's time: the Burgers ring's mean flow) so tight a prior that
a uniform actuator offset is not removed; the closed-loop rule c band / S_cl,i alone gives the
weakly observed directions, where a boundary offset lives, too tight a prior (the reference at
147 F); the geometric mean keeps the unbiased plants' cost within 1 % and removes both. Without
K (`choose(..., K=None)`) the open-loop rule. The output kind: S_i = S_cl,i = 1 (F = I), a sensor
bias of c bands. sigma_walk = `WALK_STD` = 0: a random walk only added cost for the same offset
removal (measured).
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from sep_estimator.ltv import DenseFieldMap, FieldMap, LTVModel, PODFieldMap

#: the disturbance models a design can have (`DesignSettings.disturbance`)
#: the single kinds, in the order a combination stacks its parts
SINGLE = ("input", "noise", "output")
#: combinations of two single kinds (module docstring)
COMBINED = ("input+noise", "noise+output", "input+output")
KINDS = ("none", "input", "output", "noise") + COMBINED
#: kinds whose states act through a channel matrix (B, or the noise channels B_w) along E
ACTING = ("input", "noise")
#: input directions kept: singular values of the step gain above this times the largest
DIRECTION_RTOL = 1e-6
#: default prior std: a bias that moves the outputs by STD0_BANDS bands (module docstring)
STD0_BANDS = 0.04
#: default random-walk std of d per step (0: a constant bias, the limit of a slow random walk)
WALK_STD = 0.0


class DisturbanceError(ValueError):
    """A disturbance setting that cannot be used (the message names the key to fix)."""


@dataclass(frozen=True)
class Disturbance:
    """n_d disturbance states of the ROM filter (module docstring).

    Parameters
    ----------
    kind : {"input", "noise", "output"}
        Input bias (acts through B_k along E), forcing through the noise channels (B_w,k along
        E_w) or sensor bias (adds F d_k to the outputs).
    map : ndarray, shape (n_u, n_d), (n_w, n_d) or (n_y, n_d)
        E (orthonormal input directions), E_w (noise-channel directions) or F (sensor directions).
    std0 : ndarray, shape (n_d,)
        Prior std sigma_0 of d_0 (mean zero).
    walk_std : ndarray, shape (n_d,)
        Random-walk std sigma_walk of d_{k+1} - d_k.
    directions : dict
        How the map was chosen (rule, the step gain's singular values, detectability).
    std0_rule : str
        How sigma_0 was chosen.
    """

    kind: str
    map: np.ndarray
    std0: np.ndarray
    walk_std: np.ndarray
    directions: dict[str, Any] = field(default_factory=dict)
    std0_rule: str = ""
    part_dims: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS[1:]:
            raise DisturbanceError(f"disturbance kind must be one of {', '.join(KINDS[1:])}, got {self.kind!r}")
        E = np.asarray(self.map, dtype=float)
        s0, sw = np.asarray(self.std0, dtype=float), np.asarray(self.walk_std, dtype=float)
        if E.ndim != 2 or E.shape[1] < 1 or s0.shape != (E.shape[1],) or sw.shape != (E.shape[1],):
            raise DisturbanceError(f"disturbance map {E.shape}, std0 {s0.shape} and walk_std {sw.shape} do not "
                                   "fit (map (n, n_d), stds (n_d,))")
        for name, v in (("map", E), ("disturbance_std", s0), ("disturbance_walk_std", sw)):
            if not np.all(np.isfinite(v)):
                raise DisturbanceError(f"{name} must be finite")
        if np.any(s0 < 0) or np.any(sw < 0):
            raise DisturbanceError("disturbance_std and disturbance_walk_std must be >= 0")
        dims = tuple(int(v) for v in self.part_dims) or (E.shape[1],)
        if len(dims) != len(parts(self.kind)) or min(dims) < 1 or sum(dims) != E.shape[1]:
            raise DisturbanceError(f"disturbance part_dims {list(dims)} do not fit the kind {self.kind!r} "
                                   f"with n_d = {E.shape[1]} (one n_d per part, >= 1, summing to n_d)")
        object.__setattr__(self, "map", E)
        object.__setattr__(self, "std0", s0)
        object.__setattr__(self, "walk_std", sw)
        object.__setattr__(self, "part_dims", dims)

    @property
    def n_d(self) -> int:
        return int(self.map.shape[1])

    def record(self) -> dict[str, Any]:
        """meta["disturbance"] of a design file: kind, n_d, directions, std0_rule (and part_dims
        for a combination)."""
        out = {"kind": self.kind, "n_d": self.n_d, "directions": dict(self.directions),
               "std0_rule": self.std0_rule}
        if len(self.part_dims) > 1:
            out["part_dims"] = list(self.part_dims)
        return out


def parts(kind: str) -> tuple[str, ...]:
    """The single kinds of `kind`: ('input', 'noise') of 'input+noise', ('output',) of 'output'."""
    return tuple(kind.split("+"))


def part_rows(kind: str, n_u: int, n_w: int, n_y: int) -> list[int]:
    """The rows of each part's block of a map: n_u (input), n_w (noise), n_y (output)."""
    return [{"input": n_u, "noise": n_w, "output": n_y}[p] for p in parts(kind)]


def part_views(dist: Disturbance, rows: Sequence[int]) -> list[Disturbance]:
    """The single-kind Disturbance of each part of `dist` (its block of the map, its stds), given
    the rows of each part's block (`part_rows`); [dist] for a single kind."""
    if len(dist.part_dims) == 1:
        return [dist]
    if sum(rows) != dist.map.shape[0]:
        raise DisturbanceError(f"{dist.kind} disturbance map has {dist.map.shape[0]} rows, the parts' channels "
                               f"{list(rows)} sum to {sum(rows)}")
    r, c = np.cumsum([0, *rows]), np.cumsum([0, *dist.part_dims])
    return [Disturbance(p, dist.map[r[i]:r[i + 1], c[i]:c[i + 1]], dist.std0[c[i]:c[i + 1]],
                        dist.walk_std[c[i]:c[i + 1]], dist.directions.get("parts", [{}] * 2)[i], dist.std0_rule)
            for i, p in enumerate(parts(dist.kind))]


def model_part_views(rom: LTVModel, dist: Disturbance) -> list[Disturbance]:
    """`part_views` with the rows of `rom` (its inputs, noise channels, outputs)."""
    return part_views(dist, part_rows(dist.kind, rom.n_u, channels(rom, "noise").shape[2], rom.n_y))


def stacked(kind: str, views: Sequence[Disturbance], note: dict[str, Any], rule: str) -> Disturbance:
    """The combination `kind` of single-kind parts: the block-diagonal map, the stds stacked."""
    rows = [v.map.shape[0] for v in views]
    M = np.zeros((sum(rows), sum(v.n_d for v in views)))
    r = c = 0
    for v in views:
        M[r:r + v.map.shape[0], c:c + v.n_d] = v.map
        r, c = r + v.map.shape[0], c + v.n_d
    return Disturbance(kind, M, np.concatenate([v.std0 for v in views]),
                       np.concatenate([v.walk_std for v in views]), note, rule, tuple(v.n_d for v in views))


def split_dims(kind: str, dims: int | Sequence[int] | None, n_y: int,
               n_c: Sequence[int | None]) -> tuple[int, ...]:
    """n_d per part of a combination (module docstring): `dims` as given ([n_1, n_2]), or the
    default, the first part ceil(n_y / 2) and the second the rest, each at most its channels
    n_c (None: unknown, not capped). Raises DisturbanceError naming what to change when the
    parts do not fit n_1 + n_2 <= n_y."""
    if dims is None:
        n1 = (n_y + 1) // 2 if n_c[0] is None else min((n_y + 1) // 2, n_c[0])
        n2 = n_y - n1 if n_c[1] is None else min(n_y - n1, n_c[1])
        dims = (n1, n2)
    elif np.ndim(dims) == 0:
        raise DisturbanceError(f"disturbance_dims for the combination {kind} must be a list of two numbers, one "
                               f"per part ({' then '.join(parts(kind))}), got {dims!r}")
    dims = tuple(int(v) for v in dims)
    if len(dims) != 2 or min(dims) < 1 or sum(dims) > n_y:
        raise DisturbanceError(f"disturbance_dims {list(dims)} does not fit {kind} on {n_y} sensors: give two "
                               f"numbers >= 1 (one per part: {', '.join(parts(kind))}) with n_1 + n_2 <= n_y = "
                               f"{n_y} (at most n_y disturbances are detectable), or use a single kind")
    for p, n, c in zip(parts(kind), dims, n_c):
        if c is not None and n > c:
            raise DisturbanceError(f"disturbance_dims: the {p} part has {c} channels, {n} directions asked")
    return dims


def summary(dist: Disturbance | None) -> str:
    """One phrase for logs and tables: 'none', 'input, n_d = 5', 'output, n_d = 3' (and
    'NOT detectable' when the input directions' check failed)."""
    if dist is None:
        return "none"
    bad = dist.directions.get("detectable") is False
    return f"{dist.kind}, n_d = {dist.n_d}" + (" (NOT detectable)" if bad else "")


def direction_labels(dist: Disturbance, input_names: Sequence[str], output_names: Sequence[str],
                     terms: int = 3, first: int = 0) -> list[str]:
    """A name for each disturbance state: 'd_0 = bias of <output>' (output kind), or its input
    direction by its largest weights, 'd_0 along +0.71 heater_1 +0.71 heater_2' (input kind; at
    most `terms` inputs, '...' when more carry weight; the noise kind names its channels noise_j;
    a combination labels each part so, numbered on). `first`: the number of the first state."""
    if len(dist.part_dims) > 1:
        n_u, n_y = len(input_names), len(output_names)
        n_w = dist.map.shape[0] - n_u * ("input" in parts(dist.kind)) - n_y * ("output" in parts(dist.kind))
        out: list[str] = []
        for v in part_views(dist, part_rows(dist.kind, n_u, n_w, n_y)):
            out += direction_labels(v, input_names, output_names, terms, first + len(out))
        return out
    if dist.kind == "output":
        out = []
        for i in range(dist.n_d):
            col = dist.map[:, i]
            j = int(np.argmax(np.abs(col)))
            single = np.count_nonzero(np.abs(col) > 1e-12) == 1
            out.append(f"d_{first + i} = bias of {output_names[j]}" if single
                       else f"d_{first + i} (sensor bias direction {i})")
        return out
    labels = []
    input_names = channel_names(dist, input_names)
    for i in range(dist.n_d):
        col = dist.map[:, i]
        order = np.argsort(-np.abs(col), kind="stable")
        big = [j for j in order if abs(col[j]) >= 0.1 * np.abs(col).max()]
        text = " ".join(f"{col[j]:+.2f} {input_names[j]}" for j in big[:terms])
        labels.append(f"d_{first + i} along {text}" + (" ..." if len(big) > terms else ""))
    return labels


def channel_names(dist: Disturbance, input_names: Sequence[str]) -> list[str]:
    """The names of the channels the map's rows stand for: the inputs (input kind), noise_0 ..
    noise_{n_w-1} (noise kind)."""
    if dist.kind == "noise":
        return [f"noise_{j}" for j in range(dist.map.shape[0])]
    return list(input_names)


# --------------------------------------------------------------- the augmented model
def padded_field_map(G: FieldMap, n_d: int) -> FieldMap:
    """G_z = [G_k, 0] (n_field, n + n_d): the field does not depend on d. Same kind of map."""
    if isinstance(G, PODFieldMap):
        g = np.concatenate([G.g, np.zeros(G.g.shape[:2] + (n_d,))], axis=2)
        return PODFieldMap(G.Phi, g)
    if isinstance(G, DenseFieldMap):
        return DenseFieldMap(np.concatenate([G.G, np.zeros(G.G.shape[:2] + (n_d,))], axis=2))
    return PaddedFieldMap(G, n_d)


class PaddedFieldMap:
    """G_z = [G_k, 0] of any field map (the oracle's identity map of the full-order state) without
    storing the padded matrices: every operation reads the first n columns."""

    def __init__(self, G: FieldMap, n_d: int):
        self.base, self.n_d = G, int(n_d)
        self.n_field, self.n = int(G.n_field), int(G.n) + self.n_d

    def apply(self, k: int, a: np.ndarray) -> np.ndarray:
        return self.base.apply(k, a[..., :self.base.n])

    def matrix(self, k: int) -> np.ndarray:
        return np.concatenate([self.base.matrix(k), np.zeros((self.n_field, self.n_d))], axis=1)

    def std(self, k: int, P: np.ndarray) -> np.ndarray:
        return self.base.std(k, P[:self.base.n, :self.base.n])

    def std_all(self, P: np.ndarray) -> np.ndarray:
        n = self.base.n
        return np.stack([self.base.std(k, P[k, :n, :n]) for k in range(P.shape[0])])

    def gram(self, k: int) -> np.ndarray:
        out = np.zeros((self.n, self.n))
        out[:self.base.n, :self.base.n] = self.base.gram(k)
        return out

    def project(self, k: int, v: np.ndarray) -> np.ndarray:
        p = self.base.project(k, v)
        return np.concatenate([p, np.zeros(p.shape[:-1] + (self.n_d,))], axis=-1)


def augment(rom: LTVModel, dist: Disturbance | None) -> LTVModel:
    """The model on z = [a; d] (module docstring).

    A_z = [[A, B E], [0, I]] (input), [[A, B_w E_w], [0, I]] (noise) or blockdiag(A, I) (output),
    B_z = [B; 0], C_z = [C, 0] (input, noise) or [C, F] (output), G_z = [G, 0], B_w,z = blockdiag(B_w, I) (the walk's own
    channels, `noise_covariance`), P0 = blockdiag(0, diag(sigma_0^2)).

    Parameters
    ----------
    rom : LTVModel
        The ROM on a (n_r states).
    dist : Disturbance or None
        The disturbance states; its map has n_u rows (input kind), n_w (noise) or n_y (output).

    Returns
    -------
    LTVModel
        The augmented model (n_r + n_d states, dims n_k + n_d); `rom` itself when `dist` is None.

    Raises
    ------
    DisturbanceError
        The disturbance map's rows do not match the ROM's inputs (input) or outputs (output).
    """
    if dist is None:
        return rom
    N, n, n_u, n_d = rom.n_steps, rom.n, rom.n_u, dist.n_d
    nz = n + n_d
    A = np.zeros((N, nz, nz))
    A[:, :n, :n] = rom.A
    A[:, n:, n:] = np.eye(n_d)
    A[:, :n, n:] = cross_input(rom, dist)
    B = np.concatenate([rom.B, np.zeros((N, n_d, n_u))], axis=1)
    C = np.concatenate([rom.C, np.broadcast_to(output_map(rom, dist), rom.C.shape[:2] + (n_d,))], axis=2)
    Bw0 = rom.noise_input
    n_w = Bw0.shape[2]
    Bw = np.zeros((N, nz, n_w + n_d))
    Bw[:, :n, :n_w] = Bw0
    Bw[:, n:, n_w:] = np.eye(n_d)
    P0 = np.zeros((nz, nz)) if rom.P0 is None else np.pad(rom.P0, (0, n_d))
    P0[n:, n:] = np.diag(dist.std0**2)
    return LTVModel(A=A, B=B, C=C, G=padded_field_map(rom.G, n_d), dims=np.asarray(rom.dims) + n_d, Bw=Bw, P0=P0)


def noise_covariance(W: np.ndarray, dist: Disturbance | None) -> np.ndarray:
    """W_z = blockdiag(W, diag(sigma_walk^2)): the process noise of the augmented model."""
    if dist is None:
        return W
    n_w = W.shape[0]
    out = np.zeros((n_w + dist.n_d,) * 2)
    out[:n_w, :n_w] = W
    out[n_w:, n_w:] = np.diag(dist.walk_std**2)
    return out


def channels(rom: LTVModel, kind: str) -> np.ndarray:
    """The channel matrix a kind's states act through (N, n, n_c): B_k (input) or B_w,k (noise;
    B_k for a model whose noise enters through the inputs, where the two kinds coincide)."""
    return rom.noise_input if kind == "noise" else rom.B


def _checked_views(rom: LTVModel, dist: Disturbance) -> list[Disturbance]:
    """The parts of `dist` (`model_part_views`), each map's rows checked against `rom`."""
    views = model_part_views(rom, dist)
    for v in views:
        expect = rom.n_y if v.kind == "output" else channels(rom, v.kind).shape[2]
        if v.map.shape[0] != expect:
            what = {"input": "inputs", "noise": "noise channels", "output": "outputs"}[v.kind]
            raise DisturbanceError(f"{v.kind} disturbance map has {v.map.shape[0]} rows, the ROM has {expect} {what}")
    return views


def cross_input(rom: LTVModel, dist: Disturbance | None) -> np.ndarray:
    """The a-d block of A_z, (N, n_r, n_d): B_k E (input), B_w,k E_w (noise) or 0 (output, none);
    a combination: its parts' blocks side by side."""
    if dist is None:
        return np.zeros((rom.n_steps, rom.n, 0))
    return np.concatenate([channels(rom, v.kind) @ v.map if v.kind in ACTING
                           else np.zeros((rom.n_steps, rom.n, v.n_d)) for v in _checked_views(rom, dist)], axis=2)


def output_map(rom: LTVModel, dist: Disturbance) -> np.ndarray:
    """The d block of C_z, (n_y, n_d): F (output), 0 (input, noise); a combination: its parts'."""
    return np.concatenate([v.map if v.kind == "output" else np.zeros((rom.n_y, v.n_d))
                           for v in _checked_views(rom, dist)], axis=1)


# ----------------------------------------------------------------- choosing d
def step_gain(rom: LTVModel, window: Sequence[int], K: np.ndarray | None = None,
              kind: str = "input") -> np.ndarray:
    """Gamma = mean over k in [k0, k1] of C_k M_k, M_0 = 0, M_{k+1} = A_k M_k + B_k (n_y, n_u):
    the outputs' response to a constant unit input from k = 0, averaged over the band window;
    with the state feedback K (N, n_u, n), the closed loop's: M_{k+1} = (A_k + B_k K_k) M_k + B_k.
    Kind 'noise': through the noise channels, B_w,k for B_k in the last term (n_y, n_w)."""
    k0, k1 = int(window[0]), min(int(window[1]), rom.n_steps)
    Bc = channels(rom, kind)
    M = np.zeros((rom.n, Bc.shape[2]))
    acc = np.zeros((rom.n_y, Bc.shape[2]))
    for k in range(k1 + 1):          # a recursion over steps: nothing to batch
        if k >= k0:
            acc += rom.C[k] @ M
        if k < rom.n_steps:
            A = rom.A[k] if K is None else rom.A[k] + rom.B[k] @ K[k]
            M = A @ M + Bc[k]
    return acc / (k1 - k0 + 1)


def input_directions(rom: LTVModel, window: Sequence[int], n_d: int | None = None,
                     rtol: float = DIRECTION_RTOL, kind: str = "input", exclude: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """E (n_u, n_d'), the singular values S_1..S_nd' of Gamma E, and the record of the choice.

    The right singular vectors of `step_gain` with the largest singular values, n_d of them
    (default min(n_y, n_u)), less those whose singular value is at most `rtol` S_1 (not
    detectable at steady state). Raises DisturbanceError for n_d outside 1..min(n_y, n_u) or
    when no direction is left. Kind 'noise': the same through the noise channels (n_w for n_u).
    `exclude` (n_y, m), orthonormal: output directions projected out of Gamma first,
    (I - Q Q') Gamma (a combination's second part: at most n_y - m directions)."""
    G = step_gain(rom, window, kind=kind)
    if exclude is not None:
        G = G - exclude @ (exclude.T @ G)
    n_c = G.shape[1]
    n_max = min(rom.n_y - (0 if exclude is None else exclude.shape[1]), n_c)
    n_d = n_max if n_d is None else int(n_d)
    if not 1 <= n_d <= n_max:
        what = "n_w" if kind == "noise" else "n_u"
        raise DisturbanceError(f"disturbance_dims must be in 1..{n_max} (min(n_y, {what}) = min({rom.n_y}, "
                               f"{n_c}): at most n_y {kind} disturbances are detectable), got {n_d}")
    _, S, Vt = np.linalg.svd(G)
    S = S[:n_max]
    keep = int(np.count_nonzero(S[:n_d] > rtol * S[0])) if S[0] > 0 else 0
    if keep == 0:
        raise DisturbanceError(f"the ROM's step gain is zero over the band window: no {kind} disturbance is "
                               "detectable; use disturbance: output or none")
    E = np.ascontiguousarray(Vt[:keep].T)
    rank = int(np.linalg.matrix_rank(G @ E, tol=rtol * S[0]))
    note = {"rule": "right singular vectors of the band-window step gain Gamma = mean_k C_k M_k, largest first"
                    + (" (through the noise channels)" if kind == "noise" else ""),
            "window": [int(window[0]), int(window[1])], "singular_values": [float(s) for s in S],
            "rtol": rtol, "asked": n_d, "kept": keep, "dropped": n_d - keep,
            "detectable": rank == keep, "rank_gamma_E": rank}
    return E, S[:keep], note


def choose(rom: LTVModel, kind: str, band: float, window: Sequence[int], dims: int | None = None,
           std: float | Sequence[float] | None = None, walk_std: float | Sequence[float] = WALK_STD,
           bands: float = STD0_BANDS, K: np.ndarray | None = None,
           noise_std: np.ndarray | None = None) -> Disturbance | None:
    """The design's disturbance model of `kind` on `rom` (None for kind 'none').

    Parameters
    ----------
    rom : LTVModel
        The identified ROM.
    kind : {"none", "input", "output", "noise"}
        The disturbance model ('noise' on a model whose noise enters through the inputs: the
        input kind, recorded as asked for 'noise').
    band : float
        The objective's band (output units), the scale of the prior std.
    window : (k0, k1)
        The band window: where the step gain is averaged.
    dims : int or (int, int), optional
        n_d (default min(n_y, n_u) for input, n_y for output); at most n_y. A combination: n_d
        per part (`split_dims`; default ceil(n_y / 2) for the first, the rest for the second).
    std : float or sequence of float, optional
        sigma_0 for every direction or per direction (overrides the rule).
    walk_std : float or sequence of float
        sigma_walk per step.
    bands : float
        c of the prior-std rule c band / sqrt(S_i S_cl,i) (module docstring).
    K : ndarray, shape (N, n_u, n_r), optional
        The ROM's plain LQR gains, for the closed-loop step gains S_cl,i (None: the open-loop
        rule c band / S_i).
    noise_std : ndarray, shape (n_w,), optional
        The process noise's std per channel (w_std): the noise kind's prior, sigma_0,i =
        |diag(w_std) E_w,i| (`_noise_prior_std`); None: the input kind's rule.

    Returns
    -------
    Disturbance or None
        The disturbance states: map E (input) or F = I (output), prior std sigma_0, walk std,
        and the record of how they were chosen; None for kind 'none'.

    Raises
    ------
    DisturbanceError
        An unknown kind, `dims` out of range, no detectable input direction, or a direction
        with no closed-loop offset and no `std` given.
    """
    if kind not in KINDS:
        raise DisturbanceError(f"disturbance must be one of {', '.join(KINDS)}, got {kind!r}")
    if kind == "none":
        return None
    asked = kind
    if rom.Bw is None and "noise" in kind:      # B_w = B: the noise kind is the input kind
        kind = "+".join(dict.fromkeys(p.replace("noise", "input") for p in parts(kind)))
        if "+" in asked and "+" not in kind and dims is not None:   # input+noise: one input part
            dims = int(np.sum(dims))
    if "+" in kind:
        dist = _combined(rom, kind, band, window, dims, std, walk_std, bands, K, noise_std)
    else:
        dist = _single(rom, kind, band, window, dims, std, walk_std, bands, K, noise_std)
    if asked != kind:
        dist.directions["asked_kind"] = asked
        dist.directions["note"] = "the noise enters through the inputs (B_w = B): the noise kind is the input kind"
    return dist


def _single(rom: LTVModel, kind: str, band: float, window: Sequence[int], dims: int | None,
            std: float | Sequence[float] | None, walk_std: float | Sequence[float], bands: float,
            K: np.ndarray | None, noise_std: np.ndarray | None, exclude: np.ndarray | None = None) -> Disturbance:
    """`choose` for a single kind (the directions with the outputs' subspace `exclude` projected
    out of the step gain, for a combination's second part)."""
    E, S, S_cl, note = _directions(rom, kind, window, dims, K, exclude)
    n_d = E.shape[1]
    if std is None and kind == "noise" and noise_std is not None:
        std0, rule = _noise_prior_std(E, noise_std)
    elif std is None:
        std0, rule = _prior_std(kind, band, bands, S, S_cl, K is not None)
    else:
        std0 = per_direction("disturbance_std", std, n_d)
        rule = "disturbance_std (given)"
    walk = per_direction("disturbance_walk_std", walk_std, n_d)
    return Disturbance(kind, E, std0, walk, note, rule)


def _combined(rom: LTVModel, kind: str, band: float, window: Sequence[int], dims: int | Sequence[int] | None,
              std: float | Sequence[float] | None, walk_std: float | Sequence[float], bands: float,
              K: np.ndarray | None, noise_std: np.ndarray | None) -> Disturbance:
    """`choose` for a combination (module docstring): the parts chosen in order, the second with
    the first's output image projected out, and the stacked step gain checked for rank n_d."""
    n_c = [rom.n_y if p == "output" else channels(rom, p).shape[2] for p in parts(kind)]
    n = split_dims(kind, dims, rom.n_y, n_c)
    per = [None if v is None or np.ndim(v) == 0 else np.asarray(v, dtype=float) for v in (std, walk_std)]
    for name, v in zip(("disturbance_std", "disturbance_walk_std"), per):
        if v is not None and v.shape != (sum(n),):
            raise DisturbanceError(f"{name} must be a number or a list of n_d = {sum(n)} numbers, got {v.tolist()}")
    views: list[Disturbance] = []
    Q = np.zeros((rom.n_y, 0))
    for i, p in enumerate(parts(kind)):
        sl = slice(sum(n[:i]), sum(n[:i + 1]))
        s_i = std if per[0] is None else per[0][sl]
        w_i = walk_std if per[1] is None else per[1][sl]
        v = _single(rom, p, band, window, n[i], s_i, w_i, bands, K, noise_std, Q if i else None)
        views.append(v)
        Q = np.linalg.qr(np.hstack([Q, _image(rom, window, v)]))[0]
    image = np.hstack([_image(rom, window, v) for v in views])
    sv = np.linalg.svd(image, compute_uv=False)
    rank = int(np.count_nonzero(sv > DIRECTION_RTOL * sv[0]))
    note = {"rule": f"{kind}: the parts in order, each with the earlier parts' output images projected out of "
                    "its band-window step gain", "split": list(n), "kept": [v.n_d for v in views],
            "parts": [v.directions for v in views], "singular_values": [float(x) for x in sv],
            "detectable": rank == image.shape[1], "rank_gamma_E": rank}
    return stacked(kind, views, note, "; ".join(f"{v.kind}: {v.std0_rule}" for v in views))


def _image(rom: LTVModel, window: Sequence[int], v: Disturbance) -> np.ndarray:
    """Gamma E of a part (n_y, n_d): its band-window step gain along its directions (F: output)."""
    return v.map if v.kind == "output" else step_gain(rom, window, kind=v.kind) @ v.map


def _directions(rom: LTVModel, kind: str, window: Sequence[int], dims: int | None, K: np.ndarray | None,
                exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """(E or F, the open-loop step gains S_i, the closed-loop ones S_cl,i, the record) of `kind`
    (S_cl = S without K; both 1 for the output kind, F = I). `exclude` (n_y, m), orthonormal:
    output directions projected out of the step gain first (a combination's second part; the
    output kind then has F spanning their complement, n_d <= n_y - m)."""
    if kind in ACTING:
        E, S, note = input_directions(rom, window, dims, kind=kind, exclude=exclude)
        S_cl = S
        if K is not None:
            S_cl = np.linalg.norm(step_gain(rom, window, K, kind) @ E, axis=0)
            note["closed_loop_gains"] = [float(v) for v in S_cl]
        return E, S, S_cl, note
    if exclude is not None:
        U = np.linalg.svd(np.eye(rom.n_y) - exclude @ exclude.T)[0]
        n_d = rom.n_y - exclude.shape[1] if dims is None else int(dims)
        if not 1 <= n_d <= rom.n_y - exclude.shape[1]:
            raise DisturbanceError(f"disturbance_dims: the output part can have 1..{rom.n_y - exclude.shape[1]} "
                                   f"directions (n_y less the first part's), got {n_d}")
        note = {"rule": "F: sensor-bias directions orthogonal to the first part's output image",
                "singular_values": [1.0] * n_d, "detectable": True}
        return U[:, :n_d], np.ones(n_d), np.ones(n_d), note
    n_d = rom.n_y if dims is None else int(dims)
    if n_d != rom.n_y:
        raise DisturbanceError(f"disturbance_dims must be n_y = {rom.n_y} for the output kind (one bias per "
                               f"sensor, F = I), got {n_d}")
    S = np.ones(rom.n_y)
    note = {"rule": "F = I: one bias per sensor", "singular_values": [1.0] * rom.n_y, "detectable": True}
    return np.eye(rom.n_y), S, S, note


def _prior_std(kind: str, band: float, bands: float, S: np.ndarray, S_cl: np.ndarray, closed_loop: bool
               ) -> tuple[np.ndarray, str]:
    """sigma_0,i = c band / sqrt(S_i S_cl,i), c = `bands` (module docstring), and the rule's text."""
    scale = np.sqrt(S * S_cl)
    if not np.all(scale > 0):
        raise DisturbanceError("a disturbance direction leaves no closed-loop offset (S_cl,i = 0); give "
                               "disturbance_std")
    std0 = bands * float(band) / scale
    if kind == "output":
        rule = f"sigma_0 = {bands:g} band (a sensor bias of {bands:g} bands)"
    elif closed_loop:
        rule = (f"sigma_0,i = {bands:g} band / sqrt(S_i S_cl,i) (a bias moving the outputs by {bands:g} bands "
                "on the geometric mean of the open-loop and the plain-LQR closed-loop step gains)")
    else:
        rule = f"sigma_0,i = {bands:g} band / S_i (a bias moving the outputs by {bands:g} bands in open loop)"
    return std0, rule


def _noise_prior_std(E: np.ndarray, noise_std: np.ndarray) -> tuple[np.ndarray, str]:
    """sigma_0,i = |diag(w_std) E_w,i|: a constant forcing as large as one step's process noise
    along direction i (the noise kind's rule; measured on the forced slab, docs/robustness.md: the
    band rule c band / sqrt(S_i S_cl,i), made for biases of a few % of the band, is so tight a
    prior that a forcing of several bands is removed only in part)."""
    w = np.broadcast_to(np.asarray(noise_std, dtype=float), (E.shape[0],))
    return np.linalg.norm(w[:, None] * E, axis=0), "sigma_0,i = |diag(w_std) E_w,i| (a forcing of one step's noise std)"


def per_direction(name: str, value: float | Sequence[float], n_d: int) -> np.ndarray:
    """A setting given for every direction (a number) or per direction (n_d numbers), >= 0."""
    v = np.asarray(value, dtype=float)
    if v.ndim > 1 or (v.ndim == 1 and v.shape[0] != n_d):
        raise DisturbanceError(f"{name} must be a number or a list of n_d = {n_d} numbers, got {value!r}")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise DisturbanceError(f"{name} must be finite and >= 0, got {value!r}")
    return np.broadcast_to(v, (n_d,)).astype(float)


__all__ = ["KINDS", "SINGLE", "COMBINED", "parts", "part_rows", "part_views", "model_part_views", "stacked",
           "split_dims", "output_map", "ACTING", "channels", "channel_names", "Disturbance", "DisturbanceError", "summary", "direction_labels", "augment",
           "noise_covariance", "choose", "input_directions", "step_gain", "padded_field_map", "cross_input",
           "per_direction"]
