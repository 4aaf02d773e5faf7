"""The design file: the one place that knows its format (docs/reference/design-file.md).

A design file is a numpy `.npz` archive read with ``allow_pickle=False`` (no code execution on
load). Member ``meta`` holds a UTF-8 JSON document (format version, the scenario — plant type,
plant keys and problem —, the plant's description, design settings, validation numbers,
provenance, and the source record of everything the design was made from with its SHA-256,
``source`` and ``source_digest``: `sep_estimator.design_source`); every other member is a float64/int64 array listed below with its expected
shape (the two belief statistics float32, see below). Loading checks the format version, every member's presence, dtype, shape and
finiteness, and the zip CRCs, and raises `DesignFileError` with a message that says what is
wrong. Loading never imports the plant's code: the file is self-contained data.

Arrays (N steps, n_r ROM order, n_d disturbance states, n_z = n_r + n_d, n_field field nodes;
index conventions of `sep_estimator.ltv`):

    u_nom (N, n_u)  y_nom (N+1, n_y)  field_nom, belief_mean, belief_std (N+1, n_field)
    target (n_field,) (version 6: (N+1, n_field) for a time-varying target)  field_xyz (n_field, 3)  rom_dims (N+1,) int
    A (N, n_r, n_r)  B (N, n_r, n_u)  C (N+1, n_y, n_r)                  the ROM
    field_basis (n_field, r_f)  field_coef (N+1, r_f, n_r)   the field map G_k = field_basis field_coef_k
    (or G (N+1, n_field, n_r) dense, as version 1 stored it)
    Bw (N, n_r, n_w)   only for plants whose noise does not enter through the inputs
    rom_P0 (n_r, n_r)  only for a ROM with initial-condition states (an uncertain initial state,
                       `sep_control.design.initial_prior`): the prior P_0 = blockdiag(0, cov(c))
    K (N, n_u, n_z)  L (N+1, n_z, n_y)  P_post (N+1, n_z, n_z)  field_std (N+1, n_field)
    hankel_sv (N+1, n_sv)
    dist_map (n_u, n_d) E, (n_w, n_d) E_w or (n_y, n_d) F (a combination: its parts' blocks),
                       dist_std0 (n_d,), dist_walk_std (n_d,)
                       only with disturbance states (`sep_estimator.disturbance`)

Version 5 adds the disturbance kind "noise" (dist_map (n_w, n_d): directions of the process
noise's channels) and the combinations "input+noise", "noise+output", "input+output" (dist_map
block-diagonal over the parts' channels stacked in that order, (n_u + n_w, n_d), (n_w + n_y, n_d)
or (n_u + n_y, n_d); meta["disturbance"]["part_dims"] = [n_d1, n_d2]) and the LQR weighting keys of the problem (lqr_weighting, lqr_field_nodes,
lqr_field_time; the field weighting's gains are on the stored field map) and the ROM's prior
rom_P0 (initial-condition states); files of versions 1-4
read with the output weighting (their problem has no such key) and kinds none/input/output.
Version 4 adds the disturbance states: meta["disturbance"] = {"kind": "none" | "input" |
"output", "n_d", "directions" (how chosen, singular values), "std0_rule"}; A, B, C, rom_dims
and meta["n_r"] stay the ROM's, the gains and the filter's schedule are on z = [a; d]. Files of
versions 1-3 have none (kind "none", n_z = n_r).

Trajectories over the field (field_nom, field_std) of more than `COMPRESS_ABOVE` numbers are
stored as a truncated SVD, `<name>__basis` (n_field, r) and `<name>__coef` (N+1, r), to
`TRAJECTORY_TOL` relative (smooth fields: r of a few dozen, so a large grid's file grows as
n_field r, not N n_field); they are expanded on load. The EnKF belief statistics (belief_mean,
belief_std: estimates from M members, sampling error ~1/sqrt(M), 7 % of the std at M = 200) are
noise to an SVD (full rank) and are stored as float32 (round-off 6e-8 relative), read as
float64; version 2 files (sep 0.2-0.3) hold them as float64, compressed or not, and are read too.
``meta["belief"]`` says whether they are there: "ensemble" (the EnKF belief) or "absent" (a plant
whose states are opaque, `PlantInfo.state_is_opaque`: the design's nominal is the mean-only one,
no EnKF ran, and the file has no belief_mean/belief_std); files before version 4 hold the
ensemble belief.

Version 1 files (sep 0.1, the slab only) are read too: their scenario is the flat slab format
and their field is the state (``T_nom``).

The objects a file holds, `Design` and `Nominal`, are in `sep_estimator.design`.
"""
from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from sep_plant.problem import Objective, Problem
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario, ScenarioError, json_default, same_value

from sep_estimator.design import Design, Nominal
from sep_estimator.design_source import design_source, source_digest
from sep_estimator.disturbance import KINDS as DISTURBANCE_KINDS
from sep_estimator.disturbance import part_rows
from sep_estimator.disturbance import Disturbance, DisturbanceError, augment, noise_covariance
from sep_estimator.ltv import LQG, DenseFieldMap, LTVModel, PODFieldMap
from sep_estimator.tvkf import schedule_from_posteriors

FORMAT = "sep-design"
#: 6: the target may be per step, (N+1, n_field) (a recipe or a target expression in t), problem
#: keys recipe and du_max; 5: disturbance kind noise, LQR weighting keys; 4: disturbance states, the belief statistics may be absent (meta["belief"]); 3 (sep 0.4): belief
#: statistics in float32, field map compressed; 2 (sep 0.2-0.3): all float64
VERSION = 6
READS = (1, 2, 3, 4, 5, 6)
#: (N+1) x n_field trajectories larger than this many numbers are stored as a truncated SVD
COMPRESS_ABOVE = 1 << 20
TRAJECTORY_TOL = 1e-11
TRAJECTORIES = ("field_nom", "belief_mean", "belief_std", "field_std")
#: members written as float32 (ensemble statistics) and never SVD-compressed
SINGLE = ("belief_mean", "belief_std")
#: meta["belief"]: the EnKF belief statistics are stored, or absent (opaque-state plants)
BELIEF_KINDS = ("ensemble", "absent")

#: problem keys a node may take from the plant's own scenario at run time: the noise the plant
#: draws (w_std, v_std) and the input limits its node applies (u_min, u_max) belong to the plant
#: (a robustness run varies them). Every other problem key (n_steps, target, band, band_window,
#: q_*, r_u, lqr_*, u_init) shaped the nominal and the gains: a plant with another value runs
#: another problem than the one designed for, and the nodes refuse it (`check_matches`)
RUN_TIME_KEYS = ("w_std", "v_std", "u_min", "u_max")

#: members every version-2/3 file has (Bw only for plants whose noise is not on the inputs; the
#: belief statistics not when meta["belief"] is "absent")
ARRAYS = ("u_nom", "y_nom", "field_nom", "belief_mean", "belief_std", "target", "field_xyz", "rom_dims", "A",
          "B", "C", "field_basis", "field_coef", "K", "L", "P_post", "field_std", "hankel_sv")


class DesignFileError(ValueError):
    """The design file is unreadable, corrupt, of another version, or for another plant."""


def _shapes(info: PlantInfo, N: int, n_r: int, n_sv: int, with_bw: bool,
            field_rank: int | None, kind: str = "none", n_d: int = 0,
            with_belief: bool = True, per_step_target: bool = False,
            with_p0: bool = False) -> dict[str, tuple[int, ...]]:
    """Expected member shapes; field_rank None: the dense field map G; `kind`, `n_d`: the
    disturbance states; `with_belief`: the EnKF belief statistics are stored; `per_step_target`:
    f* is stored per step (version 6, a time-varying target); `with_p0`: the ROM's prior
    (initial-condition states)."""
    nf, nu, ny = info.n_field, info.n_u, info.n_y
    nz = n_r + n_d
    out = {
        "u_nom": (N, nu), "y_nom": (N + 1, ny), "field_nom": (N + 1, nf),
        **({"belief_mean": (N + 1, nf), "belief_std": (N + 1, nf)} if with_belief else {}),
        "target": (N + 1, nf) if per_step_target else (nf,), "field_xyz": (nf, 3),
        "rom_dims": (N + 1,), "A": (N, n_r, n_r), "B": (N, n_r, nu), "C": (N + 1, ny, n_r),
        "K": (N, nu, nz), "L": (N + 1, nz, ny), "P_post": (N + 1, nz, nz),
        "field_std": (N + 1, nf), "hankel_sv": (N + 1, n_sv),
    }
    if kind != "none":
        out["dist_map"] = (sum(part_rows(kind, nu, info.noise_dim, ny)), n_d)
        out["dist_std0"], out["dist_walk_std"] = (n_d,), (n_d,)
    if field_rank is None:
        out["G"] = (N + 1, nf, n_r)
    else:
        out["field_basis"], out["field_coef"] = (nf, field_rank), (N + 1, field_rank, n_r)
    if with_bw:
        out["Bw"] = (N, n_r, info.noise_dim)
    if with_p0:
        out["rom_P0"] = (n_r, n_r)
    return out


def arrays_of(d: Design) -> dict[str, np.ndarray]:
    """The file's arrays of a design, by member name."""
    m, nom = d.rom, d.nominal
    if isinstance(m.G, PODFieldMap):
        field_map = {"field_basis": m.G.Phi, "field_coef": m.G.g}
    elif isinstance(m.G, DenseFieldMap):
        field_map = {"G": m.G.G}
    else:
        raise ValueError(f"design files store a POD or dense field map; got {type(m.G).__name__}")
    if (nom.belief_mean is None) != (nom.belief_std is None):
        raise ValueError("the nominal's belief_mean and belief_std must both be given or both be None")
    out = {"u_nom": nom.u, "y_nom": nom.y, "field_nom": nom.field, "target": d.objective.target,
           "field_xyz": d.field_xyz, "rom_dims": np.asarray(m.dims, dtype=np.int64), "A": m.A, "B": m.B, "C": m.C,
           **field_map, "K": d.lqg.K, "L": d.lqg.kf.L, "P_post": d.lqg.kf.P_post, "field_std": d.lqg.field_std,
           "hankel_sv": d.hankel_sv}
    if nom.belief_mean is not None:
        out["belief_mean"], out["belief_std"] = nom.belief_mean, nom.belief_std
    if m.Bw is not None:
        out["Bw"] = m.Bw
    if m.P0 is not None:
        out["rom_P0"] = m.P0
    dist = d.disturbance
    if dist is not None:
        out.update(dist_map=dist.map, dist_std0=dist.std0, dist_walk_std=dist.walk_std)
    return out


def disturbance_meta(dist: Disturbance | None) -> dict[str, Any]:
    """meta["disturbance"] of a design: {"kind": "none", "n_d": 0} or `Disturbance.record`."""
    return {"kind": "none", "n_d": 0} if dist is None else dist.record()


def save_design(path: str | Path, d: Design) -> Path:
    """Write `d` to `path` (.npz, compressed) with its source record (`design_source`).

    Parameters
    ----------
    path : str or Path
        The design file to write; its folder is created. The file appears atomically (written
        to ``<path>.tmp``, then renamed).
    d : Design
        The design; ``d.meta`` is stored with the format's own keys (format, version, belief,
        scenario, plant_info, n_r, disturbance, source, source_digest) added; ``source`` and
        ``source_digest`` are also set in ``d.meta``, as a loaded design has them.

    Returns
    -------
    Path
        `path`.

    Raises
    ------
    ValueError
        An array of `d` does not have the shape the format expects for its plant, ROM order and
        disturbance states, its field map is neither POD nor dense, or only one of the belief
        statistics is given.
    OSError
        The file cannot be written.
    """
    path = Path(path)
    arrays = arrays_of(d)
    dist = d.disturbance
    belief = d.nominal.belief_kind
    expect = _shapes(d.info, d.n_steps, d.n_r, d.hankel_sv.shape[1], "Bw" in arrays, _field_rank(arrays),
                     "none" if dist is None else dist.kind, d.lqg.n_d, belief == "ensemble",
                     d.scenario.problem.time_varying, "rom_P0" in arrays)
    for name, shape in expect.items():
        if arrays[name].shape != shape:
            raise ValueError(f"design array {name} has shape {arrays[name].shape}, expected {shape}")
    source = design_source(d)
    d.meta.update(source=source, source_digest=source_digest(source))
    meta = {**d.meta, "format": FORMAT, "version": VERSION, "belief": belief, "scenario": d.scenario.to_dict(),
            "plant_info": d.info.to_dict(), "n_r": d.n_r, "disturbance": disturbance_meta(dist)}
    arrays = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    for name in SINGLE:
        if name in arrays:
            arrays[name] = arrays[name].astype(np.float32)
    for name in TRAJECTORIES:
        if name not in SINGLE and arrays[name].size > COMPRESS_ABOVE:
            arrays.update(_compressed(name, arrays.pop(name)))
    arrays["meta"] = np.frombuffer(json.dumps(meta, default=json_default).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    tmp.replace(path)
    return path


def _compressed(name: str, T: np.ndarray) -> dict[str, np.ndarray]:
    """T (N+1, n) as `name__coef` (N+1, r) @ `name__basis` (n, r)' to TRAJECTORY_TOL relative."""
    U, S, Vt = np.linalg.svd(T, full_matrices=False)
    r = max(1, int(np.count_nonzero(S > TRAJECTORY_TOL * S[0]))) if S[0] > 0 else 1
    return {f"{name}__coef": np.ascontiguousarray(U[:, :r] * S[:r]), f"{name}__basis": np.ascontiguousarray(Vt[:r].T)}


def _expand(path: Path, raw: dict[str, np.ndarray]) -> None:
    """Replace compressed trajectories by their (N+1, n_field) arrays (in place)."""
    for name in TRAJECTORIES:
        coef, basis = raw.pop(f"{name}__coef", None), raw.pop(f"{name}__basis", None)
        if coef is None and basis is None:
            continue
        if coef is None or basis is None or coef.ndim != 2 or basis.ndim != 2 or coef.shape[1] != basis.shape[1] \
                or name in raw:
            raise DesignFileError(f"{path}: compressed {name} is incomplete or inconsistent")
        if coef.dtype != np.float64 or basis.dtype != np.float64 or not (np.all(np.isfinite(coef))
                                                                         and np.all(np.isfinite(basis))):
            raise DesignFileError(f"{path}: array {name} is not finite float64")
        raw[name] = coef @ basis.T


def _widen(path: Path, raw: dict[str, np.ndarray]) -> None:
    """The float32 members (`SINGLE`) as float64, in place (finite float32 or float64 only)."""
    for name in SINGLE:
        arr = raw.get(name)
        if arr is not None and arr.dtype == np.float32:
            if not np.all(np.isfinite(arr)):
                raise DesignFileError(f"{path}: array {name} is not finite")
            raw[name] = arr.astype(np.float64)


def load_design(path: str | Path, expect_scenario: Scenario | None = None) -> Design:
    """Read and check a design file (docs/reference/design-file.md).

    Parameters
    ----------
    path : str or Path
        The design file (.npz), of any version in `READS`; read with ``allow_pickle=False``.
    expect_scenario : Scenario, optional
        The scenario of the plant the design will run on: refuse a design made for another
        plant or problem (`check_matches`; only the `RUN_TIME_KEYS` may differ).

    Returns
    -------
    Design
        The design, arrays as float64 (compressed trajectories expanded), with its ``meta``.

    Raises
    ------
    DesignFileError
        The file is missing, not a design file, corrupt (zip CRC, member headers, pickles), of an
        unreadable version, has a missing, misshapen or non-finite array, or (with
        `expect_scenario`) was made for another plant or problem. The message says what to fix.
    """
    path = Path(path)
    if not path.is_file():
        raise DesignFileError(f"design file not found: {path} (create one with "
                              f"`sep design --scenario SCENARIO --out {path}`)")
    raw = _read_archive(path)
    meta = _read_meta(path, raw)
    version = meta["version"]
    if version == 1:
        scenario, info, raw = _upgrade_v1(path, meta, raw)
    else:
        try:
            scenario = Scenario.from_dict(meta.pop("scenario"), f"{path} scenario", canonical=False)
            info = PlantInfo.from_dict(meta.pop("plant_info"))
        except (ScenarioError, KeyError, TypeError, ValueError) as exc:
            raise DesignFileError(f"{path}: bad scenario or plant record: {exc}") from None
    kind = _check_arrays(path, raw, meta, version, scenario, info)
    design = _assemble(path, scenario, info, meta, raw, kind)
    if expect_scenario is not None:
        check_matches(design, expect_scenario, str(path))
    return design


def _read_archive(path: Path) -> dict[str, np.ndarray]:
    """Every member of the archive (CRCs checked), compressed trajectories expanded, float32
    members widened; `DesignFileError` for anything unreadable."""
    try:
        _check_members(path)
        with np.load(path, allow_pickle=False) as z:
            names = set(z.files)
            if "meta" not in names:
                raise DesignFileError(f"{path}: not a sep design file (no 'meta' member)")
            raw = {name: z[name] for name in names}   # reading each member checks its CRC
        _expand(path, raw)
        _widen(path, raw)
    except DesignFileError:
        raise
    except Exception as exc:  # zlib, zipfile, numpy header parsing: all mean "corrupt"
        raise DesignFileError(f"{path}: corrupt or not a design file ({type(exc).__name__}: {exc}); "
                              "re-run `sep design` to regenerate it") from None
    return raw


def _read_meta(path: Path, raw: dict[str, np.ndarray]) -> dict[str, Any]:
    """The JSON of member ``meta`` (popped from `raw`), checked to be this format in a version
    this sep reads."""
    try:
        meta = json.loads(raw.pop("meta").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DesignFileError(f"{path}: unreadable metadata ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DesignFileError(f"{path}: not a sep design file (format {meta.get('format') if isinstance(meta, dict) else None!r})")
    version = meta.get("version")
    if version not in READS:
        newer = isinstance(version, int) and version > max(READS)
        raise DesignFileError(f"{path}: design file version {version!r}"
                              + (", written by a newer sep" if newer else "") + "; this sep reads versions "
                              f"{', '.join(map(str, READS))}. " + ("Upgrade sep, or re-run " if newer else "Re-run ")
                              + f"`sep design --scenario SCENARIO --out {path}` with this sep to regenerate it")
    return meta


def _check_arrays(path: Path, raw: dict[str, np.ndarray], meta: dict, version: int, scenario: Scenario,
                  info: PlantInfo) -> str:
    """Check every member's presence, shape, dtype and finiteness against the plant and the
    ROM order; returns the disturbance kind (sets meta["disturbance"], meta["belief"])."""
    n_r = meta.get("n_r")
    hsv, u = raw.get("hankel_sv"), raw.get("u_nom")
    if not isinstance(n_r, int) or n_r < 1 or hsv is None or hsv.ndim != 2 or u is None or u.ndim != 2:
        raise DesignFileError(f"{path}: bad ROM order, nominal or Hankel record")
    N = int(u.shape[0])
    if N != scenario.problem.n_steps:
        raise DesignFileError(f"{path}: nominal has {N} steps, its scenario {scenario.problem.n_steps}")
    basis = raw.get("field_basis")
    if basis is not None and basis.ndim != 2:
        raise DesignFileError(f"{path}: field_basis must be a matrix (n_field, r_f)")
    kind, n_d = _disturbance_kind(path, meta, version, info)
    belief = _belief_kind(path, meta, raw)
    if "rom_P0" in raw and version < 5:
        raise DesignFileError(f"{path}: member rom_P0 needs format version 5, the file says {version}")
    expect = _shapes(info, N, n_r, hsv.shape[1], "Bw" in raw, _field_rank(raw), kind, n_d, belief == "ensemble",
                     version >= 6 and scenario.problem.time_varying, "rom_P0" in raw)
    missing = sorted(set(expect) - set(raw))
    if missing:
        raise DesignFileError(f"{path}: missing arrays {missing}")
    for name, shape in expect.items():
        arr = raw[name]
        if arr.shape != shape:
            raise DesignFileError(f"{path}: array {name} has shape {arr.shape}, expected {shape} "
                                  f"for this plant and n_r = {n_r}")
        if name == "rom_dims":
            if arr.dtype.kind not in "iu" or np.any(arr < 0) or np.any(arr > n_r):
                raise DesignFileError(f"{path}: rom_dims must be integers in [0, {n_r}]")
        elif arr.dtype != np.float64 or not np.all(np.isfinite(arr)):
            raise DesignFileError(f"{path}: array {name} is not finite float64")
    return kind


def _belief_kind(path: Path, meta: dict, raw: dict[str, np.ndarray]) -> str:
    """meta["belief"] ("ensemble" when not recorded: files before version 4), checked against the
    members (sets meta["belief"])."""
    belief = meta.setdefault("belief", "ensemble")
    if belief not in BELIEF_KINDS:
        raise DesignFileError(f"{path}: meta belief must be one of {', '.join(BELIEF_KINDS)}, got {belief!r}")
    if belief == "absent" and any(name in raw for name in SINGLE):
        raise DesignFileError(f"{path}: meta belief is 'absent' but the file holds "
                              f"{sorted(name for name in SINGLE if name in raw)}")
    return belief


def _field_rank(arrays: dict) -> int | None:
    """The POD rank r_f of a design's field map, None for a dense G (version 1)."""
    if "G" in arrays and "field_basis" not in arrays:
        return None
    basis = arrays.get("field_basis")
    return int(basis.shape[1]) if basis is not None and basis.ndim == 2 else 0


def _disturbance_kind(path: Path, meta: dict, version: int, info: PlantInfo) -> tuple[str, int]:
    """(kind, n_d) of meta["disturbance"]; ("none", 0) for files before version 4."""
    if version < 4:
        meta.setdefault("disturbance", {"kind": "none", "n_d": 0})
        return "none", 0
    rec = meta.get("disturbance")
    kind = rec.get("kind") if isinstance(rec, dict) else None
    n_d = rec.get("n_d") if isinstance(rec, dict) else None
    if kind not in DISTURBANCE_KINDS:
        raise DesignFileError(f"{path}: meta disturbance kind must be one of {', '.join(DISTURBANCE_KINDS)}, "
                              f"got {kind!r}")
    if kind == "none":
        return kind, 0
    if "noise" in kind or "+" in kind:
        if version < 5:
            raise DesignFileError(f"{path}: meta disturbance kind {kind!r} needs format version 5, the file says "
                                  f"{version}")
    if not isinstance(n_d, int) or isinstance(n_d, bool) or not 1 <= n_d <= info.n_y:
        raise DesignFileError(f"{path}: meta disturbance n_d must be an integer in 1..n_y = {info.n_y}, got {n_d!r}")
    return kind, n_d


def _assemble(path: Path, scenario: Scenario, info: PlantInfo, meta: dict, a: dict[str, np.ndarray],
              kind: str) -> Design:
    p = scenario.problem
    G = DenseFieldMap(a["G"]) if "field_basis" not in a else PODFieldMap(a["field_basis"], a["field_coef"])
    rom = LTVModel(A=a["A"], B=a["B"], C=a["C"], G=G, dims=a["rom_dims"], Bw=a.get("Bw"), P0=a.get("rom_P0"))
    dist = None
    if kind != "none":
        rec = meta["disturbance"]
        try:
            dist = Disturbance(kind, a["dist_map"], a["dist_std0"], a["dist_walk_std"],
                               dict(rec.get("directions") or {}), str(rec.get("std0_rule", "")),
                               tuple(rec.get("part_dims") or ()))
        except DisturbanceError as exc:
            raise DesignFileError(f"{path}: bad disturbance states: {exc}") from None
    model = augment(rom, dist)
    W, V = p.noise_covariances(info.noise_dim, info.n_y)
    W = noise_covariance(W, dist)
    lqg = LQG("rom_lqg", model, a["K"], schedule_from_posteriors(model, a["L"], a["P_post"], W), W, V,
              a["field_std"], disturbance=dist, rom=rom)
    objective = Objective.with_target(p, a["target"], info.dt)
    nominal = Nominal(a["u_nom"], a["y_nom"], a["field_nom"], a.get("belief_mean"), a.get("belief_std"))
    return Design(scenario, info, objective, a["field_xyz"], nominal, lqg, a["hankel_sv"], meta)


def _upgrade_v1(path: Path, meta: dict, raw: dict) -> tuple[Scenario, PlantInfo, dict]:
    """sep 0.1 design files: the slab only, flat scenario, field = state (T_nom)."""
    try:
        scenario = Scenario.from_dict(meta.pop("scenario"), f"{path} scenario")   # slab: built-in
        plant = scenario.plant
    except (ScenarioError, KeyError, TypeError) as exc:
        raise DesignFileError(f"{path}: bad scenario record of a version 1 file: {exc}") from None
    raw = dict(raw)
    if "T_nom" not in raw:
        raise DesignFileError(f"{path}: missing arrays ['T_nom']")
    raw["field_nom"] = raw.pop("T_nom")
    raw["field_xyz"] = plant.field_coordinates()
    raw["target"] = scenario.problem.target_field(raw["field_xyz"])
    meta.setdefault("upgraded_from_version", 1)
    return scenario, PlantInfo.of(plant), raw


def _check_members(path: Path) -> None:
    """Refuse before numpy allocates anything: every member must be an .npy array whose header
    declares no more bytes than the member holds, and no object dtype (pickles)."""
    if not zipfile.is_zipfile(path):
        raise DesignFileError(f"{path}: not a design file (not an .npz archive)")
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                else:
                    shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
            if dtype.hasobject:
                raise DesignFileError(f"{path}: member {info.filename} holds Python objects; refused "
                                      "(design files never contain pickles)")
            need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            if need > info.file_size:
                raise DesignFileError(f"{path}: member {info.filename} declares {need} bytes but holds "
                                      f"{info.file_size}: corrupt file")


def check_matches(design: Design, plant: Scenario, where: str = "design file") -> None:
    """Raise `DesignFileError` naming every value where the plant's scenario differs from the
    design's: the plant type and keys, and every problem key but the `RUN_TIME_KEYS`."""
    diff = design.scenario.plant_mismatches(plant) + problem_mismatches(design.problem, plant.problem)
    if diff:
        raise DesignFileError(f"{where} was designed for another plant or problem: " + "; ".join(diff) +
                              ". Re-run `sep design` with this plant's scenario, or run the plant with the "
                              f"design's scenario (only {', '.join(RUN_TIME_KEYS)} may differ at run time)")


def problem_mismatches(designed: Problem, running: Problem) -> list[str]:
    """"problem.KEY: designed != running" for each resolved problem key but n_steps (a plant
    mismatch, `Scenario.plant_mismatches`) and the `RUN_TIME_KEYS`."""
    a, b = designed.resolved().to_dict(), running.resolved().to_dict()
    for k in set(a) ^ set(b):           # keys a dict omits at their defaults (the LQR weighting's)
        a.setdefault(k, getattr(designed, k))
        b.setdefault(k, getattr(running, k))
    return [f"problem.{k}: {a[k]!r} != {b[k]!r}" for k in sorted(a)
            if k not in RUN_TIME_KEYS and k != "n_steps" and not same_value(a[k], b[k])]
