"""The disturbance states' model: `Disturbance` (kind, map, priors; a combination's parts) and
the augmented model on z = [a; d] (`augment`, `cross_input`, `output_map`, `noise_covariance`).

The kinds, their equations and how a design chooses them: `sep_estimator.disturbance` (which
re-exports everything here). Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from sep_estimator.ltv import DenseFieldMap, FieldMap, LTVModel, PODFieldMap

#: the disturbance models a design can have (`DesignSettings.disturbance`)
#: the single kinds, in the order a combination stacks its parts
SINGLE = ("input", "noise", "output")
#: combinations of two single kinds (`sep_estimator.disturbance`)
COMBINED = ("input+noise", "noise+output", "input+output")
KINDS = ("none", "input", "output", "noise") + COMBINED
#: kinds whose states act through a channel matrix (B, or the noise channels B_w) along E
ACTING = ("input", "noise")


class DisturbanceError(ValueError):
    """A disturbance setting that cannot be used (the message names the key to fix)."""


@dataclass(frozen=True)
class Disturbance:
    """n_d disturbance states of the ROM filter (`sep_estimator.disturbance`).

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
        return self._padded(self.base.project(k, v))

    def project_all(self, v: np.ndarray) -> np.ndarray:
        return self._padded(self.base.project_all(v))

    def _padded(self, p: np.ndarray) -> np.ndarray:
        """G' v of the base map (..., n) with the disturbance states' zeros appended."""
        return np.concatenate([p, np.zeros(p.shape[:-1] + (self.n_d,))], axis=-1)


def augment(rom: LTVModel, dist: Disturbance | None) -> LTVModel:
    """The model on z = [a; d] (the kinds: `sep_estimator.disturbance`).

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


__all__ = ["KINDS", "SINGLE", "COMBINED", "ACTING", "parts", "part_rows", "part_views", "model_part_views",
           "stacked", "output_map", "channels", "channel_names", "Disturbance", "DisturbanceError", "summary",
           "direction_labels", "augment", "noise_covariance", "padded_field_map", "PaddedFieldMap", "cross_input"]
