"""The design file: the one place that knows its format (DESIGN.md §5).

A design file is a numpy `.npz` archive read with ``allow_pickle=False`` (no code
execution on load). Member ``meta`` holds a UTF-8 JSON document (format version,
scenario, design settings, validation numbers, provenance); every other member is a
float64/int64 array listed in `ARRAYS` with its expected shape. Loading checks the
format version, every member's presence, dtype, shape and finiteness, and the zip
CRCs, and raises `DesignFileError` with a message that says what is wrong.

Per-step ROM matrices have varying sizes n_k <= n_r near k = 0 (only k n_u past
inputs exist); they are stored zero-padded to n_r with the true sizes in ``rom_dims``.
Zero padding is exact: padded states start at zero and A, B never excite them.

Index conventions (k = 0..N): a_{k+1} = A_k a_k + B_k (du_k + w_k) for k < N;
y_k - ybar_k = C_k a_k + v_k; dT_k = G_k a_k; du_k = K_k ahat_{k|k};
ahat_{k|k} = ahat_{k|k-1} + L_k (y_k - ybar_k - C_k ahat_{k|k-1}).
"""
from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sep_plant.scenario import Scenario, ScenarioError, mismatches

FORMAT = "sep-design"
VERSION = 1


class DesignFileError(ValueError):
    """The design file is unreadable, corrupt, of another version, or for another plant."""


@dataclass
class Design:
    """Everything the online nodes and the evaluation need (shapes with N steps, n_r ROM order)."""

    scenario: Scenario
    u_nom: np.ndarray         # (N, n_u)       nominal inputs ubar_k
    y_nom: np.ndarray         # (N+1, n_y)     nominal noise-free outputs ybar_k
    T_nom: np.ndarray         # (N+1, n_x)     nominal field
    belief_mean: np.ndarray   # (N+1, n_x)     EnKF belief mean along nominal observations
    belief_std: np.ndarray    # (N+1, n_x)     EnKF belief per-node std
    rom_dims: np.ndarray      # (N+1,) int     n_k, ROM order at step k
    A: np.ndarray             # (N, n_r, n_r)
    B: np.ndarray             # (N, n_r, n_u)
    C: np.ndarray             # (N+1, n_y, n_r)
    G: np.ndarray             # (N+1, n_x, n_r) field output map
    K: np.ndarray             # (N, n_u, n_r)  LQR gains
    L: np.ndarray             # (N+1, n_r, n_y) KF gains
    P_post: np.ndarray        # (N+1, n_r, n_r) KF covariance after the update at k
    field_std: np.ndarray     # (N+1, n_x)     std of the reconstructed field after the update at k
    hankel_sv: np.ndarray     # (N+1, n_sv)    Hankel singular values (zero padded)
    meta: dict[str, Any] = field(default_factory=dict)  # settings, validation, provenance

    @property
    def n_r(self) -> int:
        return int(self.A.shape[1])

    @property
    def n_steps(self) -> int:
        return int(self.u_nom.shape[0])


def _shapes(s: Scenario, n_r: int, n_sv: int) -> dict[str, tuple[int, ...]]:
    N, nx, nu, ny = s.n_steps, s.n_x, s.n_u, s.n_y
    return {
        "u_nom": (N, nu), "y_nom": (N + 1, ny), "T_nom": (N + 1, nx),
        "belief_mean": (N + 1, nx), "belief_std": (N + 1, nx), "rom_dims": (N + 1,),
        "A": (N, n_r, n_r), "B": (N, n_r, nu), "C": (N + 1, ny, n_r), "G": (N + 1, nx, n_r),
        "K": (N, nu, n_r), "L": (N + 1, n_r, ny), "P_post": (N + 1, n_r, n_r),
        "field_std": (N + 1, nx), "hankel_sv": (N + 1, n_sv),
    }


ARRAYS = tuple(_shapes(Scenario(), 1, 1))


def save_design(path: str | Path, d: Design) -> Path:
    """Write `d` to `path` (.npz, compressed); the file appears atomically."""
    path = Path(path)
    expect = _shapes(d.scenario, d.n_r, d.hankel_sv.shape[1])
    for name, shape in expect.items():
        arr = getattr(d, name)
        if arr.shape != shape:
            raise ValueError(f"design array {name} has shape {arr.shape}, expected {shape}")
    meta = {**d.meta, "format": FORMAT, "version": VERSION, "scenario": json.loads(d.scenario.to_json()),
            "n_r": d.n_r}
    arrays = {name: np.ascontiguousarray(getattr(d, name)) for name in expect}
    arrays["rom_dims"] = arrays["rom_dims"].astype(np.int64)
    arrays["meta"] = np.frombuffer(json.dumps(meta, default=_plain).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    tmp.replace(path)
    return path


def load_design(path: str | Path, expect_scenario: Scenario | None = None) -> Design:
    """Read and check a design file; with `expect_scenario`, refuse one made for another plant."""
    path = Path(path)
    if not path.is_file():
        raise DesignFileError(f"design file not found: {path} (create one with `design --out {path}`)")
    try:
        _check_members(path)
        with np.load(path, allow_pickle=False) as z:
            names = set(z.files)
            if "meta" not in names:
                raise DesignFileError(f"{path}: not a sep design file (no 'meta' member)")
            raw = {name: z[name] for name in names}   # reading each member checks its CRC
    except DesignFileError:
        raise
    except Exception as exc:  # zlib, zipfile, numpy header parsing: all mean "corrupt"
        raise DesignFileError(f"{path}: corrupt or not a design file ({type(exc).__name__}: {exc}); "
                              "re-run `design` to regenerate it") from None
    try:
        meta = json.loads(raw.pop("meta").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DesignFileError(f"{path}: unreadable metadata ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DesignFileError(f"{path}: not a sep design file (format {meta.get('format') if isinstance(meta, dict) else None!r})")
    if meta.get("version") != VERSION:
        raise DesignFileError(f"{path}: design file version {meta.get('version')!r}, this sep reads version "
                              f"{VERSION}; re-run `design` with this version")
    try:
        scenario = Scenario.from_dict(meta.pop("scenario"), f"{path} scenario")
    except (ScenarioError, KeyError, TypeError) as exc:
        raise DesignFileError(f"{path}: bad scenario record: {exc}") from None
    n_r = meta.get("n_r")
    hsv = raw.get("hankel_sv")
    if not isinstance(n_r, int) or n_r < 1 or hsv is None or hsv.ndim != 2:
        raise DesignFileError(f"{path}: bad ROM order or Hankel record")
    expect = _shapes(scenario, n_r, hsv.shape[1])
    missing = sorted(set(expect) - set(raw))
    if missing:
        raise DesignFileError(f"{path}: missing arrays {missing}")
    for name, shape in expect.items():
        arr = raw[name]
        if arr.shape != shape:
            raise DesignFileError(f"{path}: array {name} has shape {arr.shape}, expected {shape} "
                                  f"for this scenario and n_r = {n_r}")
        if name == "rom_dims":
            if arr.dtype.kind not in "iu" or np.any(arr < 0) or np.any(arr > n_r):
                raise DesignFileError(f"{path}: rom_dims must be integers in [0, {n_r}]")
        elif arr.dtype != np.float64 or not np.all(np.isfinite(arr)):
            raise DesignFileError(f"{path}: array {name} is not finite float64")
    design = Design(scenario=scenario, meta=meta, **{name: raw[name] for name in expect})
    if expect_scenario is not None:
        check_matches(design, expect_scenario, str(path))
    return design


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
    """Raise `DesignFileError` naming every plant value where design and plant differ."""
    diff = mismatches(design.scenario, plant)
    if diff:
        raise DesignFileError(f"{where} was designed for another plant: " + "; ".join(diff) +
                              ". Re-run `design` with this plant's scenario, or run the plant with the "
                              "design's scenario")


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON serializable: {type(v).__name__}")
