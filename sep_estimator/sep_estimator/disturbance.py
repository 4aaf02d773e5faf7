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
The model (`Disturbance`, `augment`): `sep_estimator.disturbance_model`, re-exported here.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from sep_estimator.disturbance_model import *  # noqa: F401,F403  (the model; one API: sep_estimator.disturbance)
from sep_estimator.disturbance_model import ACTING, KINDS, Disturbance, DisturbanceError, channels, parts, stacked
from sep_estimator.ltv import LTVModel

#: input directions kept: singular values of the step gain above this times the largest
DIRECTION_RTOL = 1e-6
#: default prior std: a bias that moves the outputs by STD0_BANDS bands (module docstring)
STD0_BANDS = 0.04
#: default random-walk std of d per step (0: a constant bias, the limit of a slow random walk)
WALK_STD = 0.0


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


from sep_estimator.disturbance_model import __all__ as _model_all  # noqa: E402

__all__ = [*_model_all, "DIRECTION_RTOL", "STD0_BANDS", "WALK_STD", "split_dims", "choose", "input_directions",
           "step_gain", "per_direction"]
