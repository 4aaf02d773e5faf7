"""The design file: round trip, plant mismatch, and every kind of corrupt file refused cleanly."""
import io
import json
import math
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

import sep_plant

from core_helpers import flat, rewrite_design_file
from sep_estimator.design import Design, Nominal
from sep_estimator.design_file import (ARRAYS, SINGLE, VERSION, DesignFileError, arrays_of, check_matches,
                                       load_design, save_design)
from sep_estimator.ltv import LQG, DenseFieldMap, KalmanSchedule, LTVModel, PODFieldMap
from sep_estimator.tvkf import KalmanFilter
from sep_plant.problem import Objective
from sep_plant.scenario import Scenario

SCENARIO = flat(n_x=8, n_steps=5, k_band=3, lqr_k_switch=2, u_min=-2.0, u_max=math.inf, dt=0.5)
N_STEPS, N_X, N_U, N_Y = 5, 8, 5, 5
N_R, N_SV, N_RF = 3, 4, 4
REPO = Path(__file__).resolve().parent.parent
V1_FILE = REPO / "tests" / "data" / "design_v1_sep01.npz"


def synthetic_design(s: Scenario = SCENARIO, seed: int = 0) -> Design:
    """A Design with random (but well-typed, finite) content of the right shapes."""
    rng = np.random.default_rng(seed)
    N, nx, nu, ny = s.problem.n_steps, s.plant.n_x, s.plant.n_u, s.plant.n_y
    f = lambda *shape: rng.standard_normal(shape)
    P = f(N + 1, N_R, N_R)
    Phi = np.linalg.qr(f(nx, N_RF))[0]                       # orthonormal field basis
    model = LTVModel(A=f(N, N_R, N_R), B=f(N, N_R, nu), C=f(N + 1, ny, N_R), G=PODFieldMap(Phi, f(N + 1, N_RF, N_R)),
                     dims=np.minimum(np.arange(N + 1) * 2, N_R).astype(np.int64))
    P_post = P @ P.transpose(0, 2, 1)
    W, V = s.problem.noise_covariances(nu, ny)
    lqg = LQG("rom_lqg", model, f(N, nu, N_R), KalmanSchedule(f(N + 1, N_R, ny), P_post, P_post), W, V,
              np.abs(f(N + 1, nx)))
    xyz = s.plant.field_coordinates()
    return Design(
        scenario=s, info=s.info, objective=Objective.of(s.problem, xyz), field_xyz=xyz,
        nominal=Nominal(f(N, nu), f(N + 1, ny), 150 + f(N + 1, nx), f(N + 1, nx), np.abs(f(N + 1, nx))),
        lqg=lqg, hankel_sv=np.abs(f(N + 1, N_SV)),
        meta={"settings": {"n_r": N_R, "method": "gn"}, "validation": {"markov_rel_error": np.float64(3e-9)},
              "history": np.array([3.0, 2.0, 1.5]), "provenance": {"seed": 7, "tool": "test"}})


@pytest.fixture
def design_path(tmp_path):
    return save_design(tmp_path / "design.npz", synthetic_design())


def assert_same(a: Design, b: Design):
    """Every array equal; the float32-stored belief statistics to float32 round-off (equal when
    both designs come from files)."""
    xa, xb = arrays_of(a), arrays_of(b)
    assert set(xa) == set(xb)
    for name in xa:
        x, y = xa[name], xb[name]
        assert x.shape == y.shape, name
        if name in SINGLE:
            np.testing.assert_array_equal(x.astype(np.float32), y.astype(np.float32), err_msg=name)
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.scenario == b.scenario and a.info == b.info


# ------------------------------------------------------------------ round trip
def test_round_trip_preserves_every_array_and_meta(tmp_path):
    d = synthetic_design()
    path = save_design(tmp_path / "sub" / "d.npz", d)
    assert path.is_file() and not list(path.parent.glob("*.tmp"))
    back = load_design(path)
    assert_same(d, back)
    for name, arr in arrays_of(back).items():
        assert arr.dtype == (np.int64 if name == "rom_dims" else np.float64)
    assert set(arrays_of(back)) == set(ARRAYS)
    assert back.problem.u_min == -2.0 and back.problem.u_max == math.inf
    assert back.meta["settings"] == {"n_r": N_R, "method": "gn"}
    assert back.meta["validation"] == {"markov_rel_error": 3e-9}
    assert back.meta["history"] == [3.0, 2.0, 1.5]
    assert back.meta["provenance"] == {"seed": 7, "tool": "test"}
    assert back.meta["version"] == VERSION and back.n_r == N_R and back.n_steps == N_STEPS
    # the priors are rebuilt from the posteriors; the objective from the stored target
    np.testing.assert_array_equal(back.objective.target, d.objective.target)
    assert back.objective.window == (3, 5)
    # loading with the matching plant is fine, and the online filter builds from it
    load_design(path, expect_scenario=SCENARIO)
    f = KalmanFilter(back.lqg, batch=2)
    assert f.a.shape == (2, N_R)


def test_round_trip_of_a_real_design(tmp_path):
    from core_helpers import cached_design, coarse_scenario

    d = cached_design(coarse_scenario(20, 40), p=5, q=5, n_r=8, ensemble=20)
    back = load_design(save_design(tmp_path / "real.npz", d), expect_scenario=d.scenario)
    assert_same(d, back)
    assert back.meta["validation"]["markov_rel_error"] == d.meta["validation"]["markov_rel_error"]
    assert back.meta["settings"] == d.meta["settings"]


def test_save_refuses_wrong_shapes(tmp_path):
    d = synthetic_design()
    d.lqg.K = d.lqg.K[:, :, :2]
    with pytest.raises(ValueError, match="K"):
        save_design(tmp_path / "bad.npz", d)
    assert not (tmp_path / "bad.npz").exists()


# ------------------------------------------------------------- another plant
@pytest.mark.parametrize("changes,keys", [
    (dict(n_x=9), ["n_x"]),
    (dict(dt=0.25), ["dt"]),
    (dict(sensor_positions=[0.1, 0.3, 0.5, 0.7, 0.85]), ["sensor_positions"]),
    (dict(n_x=10, dt=0.25, t_right=140.0), ["n_x", "dt", "t_right"]),
    (dict(heater_centers=[0.1, 0.5, 0.9]), ["heater_centers"]),
])
def test_design_for_another_plant_refused(design_path, changes, keys):
    other = SCENARIO.with_plant(**changes)
    with pytest.raises(DesignFileError) as exc:
        load_design(design_path, expect_scenario=other)
    msg = str(exc.value)
    assert "another plant" in msg and str(design_path) in msg
    for k in keys:
        assert k in msg
    # the values are shown so that the user can see which side is which
    if "n_x" in changes:
        assert "8" in msg and str(changes["n_x"]) in msg


def test_check_matches_names_the_keys():
    d = synthetic_design()
    check_matches(d, SCENARIO)
    with pytest.raises(DesignFileError, match="n_steps"):
        check_matches(d, SCENARIO.replace(n_steps=6))
    # the noise, weights and limits may differ (the plant node uses its own)
    check_matches(d, SCENARIO.replace(w_std=0.1, u_max=3.0))


# --------------------------------------------------------------- corrupt files
def refused(path, match=None):
    with pytest.raises(DesignFileError) as exc:
        load_design(path)
    if match:
        assert match in str(exc.value), str(exc.value)
    return str(exc.value)


def test_missing_file_and_directory(tmp_path):
    assert "not found" in refused(tmp_path / "none.npz")
    (tmp_path / "dir.npz").mkdir()
    refused(tmp_path / "dir.npz")


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.5, 0.9, 0.99])
def test_truncated_file_refused(design_path, tmp_path, fraction):
    raw = design_path.read_bytes()
    p = tmp_path / "trunc.npz"
    p.write_bytes(raw[: int(len(raw) * fraction)])
    refused(p)


def test_truncated_at_every_length_refused(design_path, tmp_path):
    raw = design_path.read_bytes()
    p = tmp_path / "trunc.npz"
    for n in range(0, len(raw) - 1, 97):
        p.write_bytes(raw[:n])
        refused(p)


def test_flipped_bytes_refused_or_harmless(design_path, tmp_path):
    """Flip bytes all over the file (headers, compressed data, central directory): the loader
    either refuses with DesignFileError or, where the flipped byte is unprotected metadata (a
    timestamp, an attribute), returns exactly the original content. Never another exception."""
    original = load_design(design_path)
    raw = design_path.read_bytes()
    p = tmp_path / "flip.npz"
    positions = sorted(set(range(0, 64)) | set(range(64, len(raw), 11)) | set(range(len(raw) - 200, len(raw))))
    others = {}
    for i in positions:
        b = bytearray(raw)
        b[i] ^= 0xFF
        p.write_bytes(bytes(b))
        try:
            assert_same(load_design(p), original)
        except DesignFileError:
            pass
        except Exception as exc:      # noqa: BLE001 -- collected and reported below
            others.setdefault(f"{type(exc).__module__}.{type(exc).__name__}", i)
    assert not others, f"exceptions other than DesignFileError (type: first byte offset): {others}"


def member_data_offset(raw: bytes, name: str) -> tuple[int, int]:
    """(offset of the compressed data, compressed size) of zip member `name`, from its local header."""
    with zipfile.ZipFile(io.BytesIO(raw)) as zf:
        info = zf.getinfo(name)
    fn_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
    return info.header_offset + 30 + fn_len + extra_len, info.compress_size


def central_directory_entry(raw: bytes, name: str) -> int:
    """Offset of the central-directory record of member `name`."""
    pos = raw.find(b"PK\x01\x02")
    while pos >= 0:
        fn_len = struct.unpack("<H", raw[pos + 28:pos + 30])[0]
        if raw[pos + 46:pos + 46 + fn_len] == name.encode():
            return pos
        pos = raw.find(b"PK\x01\x02", pos + 4)
    raise AssertionError(f"{name} not in the central directory")


@pytest.mark.parametrize("member", ["A.npy", "meta.npy", "rom_dims.npy"])
def test_flipped_byte_in_compressed_data_refused(design_path, tmp_path, member):
    """A flip inside the deflate stream of one member: depending on where it lands, an invalid
    deflate stream (zlib.error), a wrong CRC (BadZipFile) or a garbled .npy header. A flip in the
    padding bits after the stream's end-of-block code changes nothing that is read: such a file
    loads, and the member decompresses to the original bytes."""
    raw = design_path.read_bytes()
    start, size = member_data_offset(raw, member)
    with zipfile.ZipFile(design_path) as z:
        original = z.read(member)
    p = tmp_path / "flip.npz"
    n_refused = 0
    for off in (0, 1, size // 3, size // 2, size - 2):
        b = bytearray(raw)
        b[start + off] ^= 0x5A
        p.write_bytes(bytes(b))
        try:
            load_design(p)
        except DesignFileError:
            n_refused += 1
            continue
        assert off >= size - 2, off               # only the stream's last bytes may be padding
        with zipfile.ZipFile(p) as z:
            assert z.read(member) == original
    assert n_refused >= 4


@pytest.mark.parametrize("field,value", [
    (10, 99), (10, 14), (8, 0x01),
    (8, 0x20), (8, 0x40)])
def test_unsupported_zip_features_refused(design_path, tmp_path, field, value):
    """Central-directory compression method (10) or flags (8) that zipfile cannot handle:
    an unknown method, LZMA, encryption, compressed patched data, strong encryption (zipfile raises
    NotImplementedError or RuntimeError for these)."""
    raw = bytearray(design_path.read_bytes())
    pos = central_directory_entry(bytes(raw), "A.npy")
    raw[pos + field:pos + field + 2] = struct.pack("<H", value)
    p = tmp_path / "feature.npz"
    p.write_bytes(bytes(raw))
    refused(p)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("prefix", [b"", b"PK\x03\x04", b"\x93NUMPY\x01\x00", b"\x80\x04"])
def test_random_bytes_refused(tmp_path, seed, prefix):
    p = tmp_path / "random.npz"
    p.write_bytes(prefix + np.random.default_rng(seed).bytes(3000))
    refused(p)


def test_plain_npy_file_refused(tmp_path):
    """A single-array .npy (np.load returns an ndarray, not an archive)."""
    p = tmp_path / "array.npz"
    with open(p, "wb") as fh:
        np.save(fh, np.zeros(5))
    refused(p)


@pytest.mark.parametrize("content", [b"", b"hello, not a design\n", b'{"format": "sep-design"}\n'])
def test_text_or_empty_file_refused(tmp_path, content):
    p = tmp_path / "text.npz"
    p.write_bytes(content)
    refused(p)


def test_zip_that_is_not_an_npz_refused(tmp_path):
    p = tmp_path / "zip.npz"
    with zipfile.ZipFile(p, "w") as zf:
        zf.writestr("readme.txt", "hello")
    refused(p)


class _Payload:
    """Pickling this object creates `marker` when *unpickled* (if the loader ever unpickles)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_pickled_object_arrays_refused_without_executing_code(design_path, tmp_path):
    marker = tmp_path / "pwned"
    evil = np.empty(1, dtype=object)
    evil[0] = _Payload(marker)
    for member in ("A", "meta", "extra_member"):
        p = rewrite_design_file(design_path, tmp_path / f"pickle_{member}.npz", **{member: evil})
        refused(p)
        assert not marker.exists(), "loading executed code from a pickle"
    # a bare pickle file too
    p = tmp_path / "bare.npz"
    import pickle

    p.write_bytes(pickle.dumps(_Payload(marker)))
    refused(p)
    assert not marker.exists()


def test_wrong_version_refused(design_path, tmp_path):
    p = rewrite_design_file(design_path, tmp_path / "v.npz", edit_meta=lambda m: {**m, "version": VERSION + 1})
    assert "version" in refused(p)
    p = rewrite_design_file(design_path, tmp_path / "v0.npz", edit_meta=lambda m: {k: v for k, v in m.items() if k != "version"})
    assert "version" in refused(p)


def test_wrong_format_or_meta_refused(design_path, tmp_path):
    refused(rewrite_design_file(design_path, tmp_path / "f.npz", edit_meta=lambda m: {**m, "format": "other"}))
    refused(rewrite_design_file(design_path, tmp_path / "list.npz", edit_meta=lambda m: [1, 2]))
    refused(_without_meta(design_path, tmp_path / "nometa.npz"), "meta")
    p = tmp_path / "badjson.npz"
    rewrite_design_file(design_path, p)
    with np.load(p, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    members["meta"] = np.frombuffer(b"{not json", dtype=np.uint8)
    np.savez(p, **members)
    refused(p)
    members["meta"] = np.frombuffer(b"\xff\xfe\xfa", dtype=np.uint8)
    np.savez(p, **members)
    refused(p)


def _without_meta(src, dst):
    with np.load(src, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files if k != "meta"}
    np.savez(dst, **members)
    return dst


@pytest.mark.parametrize("change", [
    lambda m: {**m, "scenario": {**m["scenario"], "n_steps": 1}},
    lambda m: {**m, "scenario": {**m["scenario"], "n_steps": 6, "band_window": [3, 6]}},   # != the arrays
    lambda m: {**m, "scenario": {**m["scenario"], "band": -3.0}},
    lambda m: {**m, "scenario": {**m["scenario"], "no_such_key": 1}},
    lambda m: {**m, "scenario": {**m["scenario"], "plant": "slab"}},
    lambda m: {**m, "scenario": [1, 2]},
    lambda m: {k: v for k, v in m.items() if k != "scenario"},
    lambda m: {k: v for k, v in m.items() if k != "plant_info"},
    lambda m: {**m, "plant_info": {**m["plant_info"], "n_field": 9}},
    lambda m: {**m, "plant_info": {**m["plant_info"], "n_u": "five"}},
    lambda m: {**m, "plant_info": [1]},
    lambda m: {**m, "n_r": "three"},
    lambda m: {**m, "n_r": 0},
    lambda m: {**m, "n_r": N_R + 1},
])
def test_bad_scenario_record_or_order_refused(design_path, tmp_path, change):
    refused(rewrite_design_file(design_path, tmp_path / "m.npz", edit_meta=change))


@pytest.mark.parametrize("name", ["A", "K", "P_post", "field_nom", "hankel_sv", "u_nom", "target", "field_xyz"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_array_refused(design_path, tmp_path, name, bad):
    d = load_design(design_path)
    arr = arrays_of(d)[name].copy()
    arr.reshape(-1)[arr.size // 2] = bad
    msg = refused(rewrite_design_file(design_path, tmp_path / "nan.npz", **{name: arr}))
    assert name in msg


@pytest.mark.parametrize("name,shape", [
    ("A", (N_STEPS, N_R, N_R + 1)),
    ("A", (N_STEPS + 1, N_R, N_R)),
    ("C", (N_STEPS + 1, N_Y + 1, N_R)),
    ("field_nom", (N_STEPS + 1, N_X - 1)),
    ("field_xyz", (N_X, 2)),
    ("u_nom", (N_STEPS * N_U,)),
    ("u_nom", (N_STEPS + 1, N_U)),
    ("rom_dims", (N_STEPS,)),
    ("hankel_sv", (N_STEPS + 1,)),
    ("L", ()),
])
def test_wrong_shape_refused(design_path, tmp_path, name, shape):
    arr = np.ones(shape, dtype=np.int64 if name == "rom_dims" else np.float64)
    msg = refused(rewrite_design_file(design_path, tmp_path / "shape.npz", **{name: arr}))
    assert name in msg or "Hankel" in msg or "nominal" in msg


@pytest.mark.parametrize("name", [n for n in ARRAYS])
def test_missing_member_refused(design_path, tmp_path, name):
    refused(rewrite_design_file(design_path, tmp_path / "missing.npz", **{name: None}))


def test_wrong_dtypes_refused(design_path, tmp_path):
    d = arrays_of(load_design(design_path))
    refused(rewrite_design_file(design_path, tmp_path / "a.npz", A=d["A"].astype(np.float32)), "A")
    refused(rewrite_design_file(design_path, tmp_path / "b.npz", K=d["K"].astype(np.int64)), "K")
    refused(rewrite_design_file(design_path, tmp_path / "c.npz", rom_dims=d["rom_dims"].astype(np.float64)), "rom_dims")
    refused(rewrite_design_file(design_path, tmp_path / "d.npz", rom_dims=d["rom_dims"] + N_R), "rom_dims")
    refused(rewrite_design_file(design_path, tmp_path / "e.npz", rom_dims=d["rom_dims"] - 10), "rom_dims")
    refused(rewrite_design_file(design_path, tmp_path / "f.npz", u_nom=d["u_nom"].astype(complex)), "u_nom")


def test_a_rewritten_but_intact_file_still_loads(design_path, tmp_path):
    """(control for the tests above: `rewrite_design_file` itself does not corrupt anything)"""
    p = rewrite_design_file(design_path, tmp_path / "same.npz")
    assert_same(load_design(p), load_design(design_path))


def _npy_bytes(header: str, data: bytes = b"") -> bytes:
    """A hand-made .npy (format 1.0) with an arbitrary header dictionary text."""
    h = header.encode()
    h += b" " * (64 - (10 + len(h) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(h).to_bytes(2, "little") + h + data


@pytest.mark.parametrize("header", [
    "{'descr': '<f8', 'fortran_order': False, 'shape': (1099511627776,), }",   # 8 TiB claimed
    "{'descr': '<f8', 'fortran_order': False, 'shape': (3,",   # unbalanced
    "{'descr': '<f8', 'fortran_order': False, 'shape': (-3,), }",
    "{'descr': '|O', 'fortran_order': False, 'shape': (3,), }",
    "{'descr': __import__('os').getcwd(), 'fortran_order': False, 'shape': (3,), }",
    "{'descr': '<f8', 'fortran_order': False, 'shape': (1000,), }",             # data too short
], ids=["huge-shape", "unbalanced", "negative-shape", "object", "code", "short-data"])
@pytest.mark.parametrize("member", ["meta.npy", "A.npy"])
def test_crafted_npy_headers_refused(design_path, tmp_path, header, member):
    """A small file whose member header lies (a huge shape, a garbled dictionary, code): refused
    with DesignFileError, without trying to allocate what the header claims."""
    with np.load(design_path, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    p = tmp_path / "crafted.npz"
    with zipfile.ZipFile(p, "w") as zf:
        for k, v in members.items():
            buf = io.BytesIO()
            np.save(buf, v)
            zf.writestr(k + ".npy", _npy_bytes(header, b"\0" * 24) if k + ".npy" == member else buf.getvalue())
    refused(p)


def test_a_loaded_design_with_a_new_rom_saves_and_loads(tmp_path):
    """Load a design, replace its ROM by one of another order (what `with_rom` does for the
    n_r sweep), save it again: the file must describe the new ROM, not the loaded meta's n_r."""
    from dataclasses import replace

    d = load_design(save_design(tmp_path / "a.npz", synthetic_design()))
    r = N_R - 1
    m, q = d.rom, d.lqg
    model = LTVModel(m.A[:, :r, :r].copy(), m.B[:, :r].copy(), m.C[:, :, :r].copy(),
                     PODFieldMap(m.G.Phi, m.G.g[:, :, :r].copy()), np.minimum(m.dims, r))
    sched = KalmanSchedule(q.kf.L[:, :r].copy(), q.kf.P_post[:, :r, :r].copy(), q.kf.P_prior[:, :r, :r].copy())
    d2 = replace(d, lqg=LQG("rom_lqg", model, q.K[:, :, :r].copy(), sched, q.W, q.V, q.field_std))
    back = load_design(save_design(tmp_path / "b.npz", d2))
    assert back.n_r == r
    assert_same(back, d2)
    # a loaded design saved unchanged is the same file content again
    assert_same(load_design(save_design(tmp_path / "c.npz", d)), d)


# ------------------------------------------------------------- older versions
def test_version_1_file_of_sep01_is_read(tmp_path):
    """A design file written by sep 0.1 (format version 1, flat slab scenario, T_nom) loads as the
    same design: same arrays under the new names, same scenario, and the same closed loop."""
    from sep_control.evaluation.montecarlo import simulate

    d = load_design(V1_FILE)
    assert d.meta["upgraded_from_version"] == 1 and d.scenario.plant_type == "slab"
    assert d.disturbance is None and d.meta["disturbance"] == {"kind": "none", "n_d": 0}   # before version 4
    assert d.scenario.plant_config["n_x"] == 12 and d.problem.window == (6, 10) and d.problem.k_switch == 4
    with np.load(V1_FILE, allow_pickle=False) as z:
        np.testing.assert_array_equal(d.nominal.field, z["T_nom"])
        np.testing.assert_array_equal(d.rom.G.G, z["G"])          # version 1: the dense field map
        np.testing.assert_array_equal(d.lqg.K, z["K"])
    np.testing.assert_array_equal(d.field_xyz[:, 0], d.scenario.plant.grid())
    # the cost sep 0.1 computed for its rom_lqg, runs 0-4 of seed 1: 13.946957521277634
    r = simulate(d.scenario.plant, d, "rom_lqg", 1, 5)
    assert r.summary["cost_mean"] == pytest.approx(13.946957521277634, rel=1e-12)
    # saved again, it is a version 2 file with the same content
    back = load_design(save_design(tmp_path / "v2.npz", d))
    assert back.meta["version"] == VERSION
    assert_same(back, d)


def test_newer_version_refused_with_how_to_regenerate(design_path, tmp_path):
    msg = refused(rewrite_design_file(design_path, tmp_path / "v9.npz", edit_meta=lambda m: {**m, "version": 9}))
    assert "version 9, written by a newer sep" in msg and "Upgrade sep, or re-run `sep design --scenario" in msg


def test_noise_input_map_round_trip(tmp_path):
    """A plant whose noise is not on the inputs: the ROM's B_w is stored and read back."""
    d = synthetic_design()
    rng = np.random.default_rng(3)
    d.lqg.model.Bw = rng.standard_normal((N_STEPS, N_R, N_U))
    back = load_design(save_design(tmp_path / "bw.npz", d))
    np.testing.assert_array_equal(back.rom.Bw, d.rom.Bw)
    assert "Bw" in arrays_of(back)


def test_large_trajectories_are_stored_compressed(tmp_path, monkeypatch):
    """Field trajectories above COMPRESS_ABOVE numbers go into the file as a truncated SVD and
    come back to TRAJECTORY_TOL; a broken compressed member is refused."""
    import sep_estimator.design_file as df

    monkeypatch.setattr(df, "COMPRESS_ABOVE", 10)
    d = synthetic_design()
    x = np.linspace(0, 1, N_X)
    d.nominal.field = 150 + np.outer(np.linspace(0, 1, N_STEPS + 1), np.sin(3 * x))    # rank 1
    path = save_design(tmp_path / "c.npz", d)
    with np.load(path, allow_pickle=False) as z:
        assert "field_nom" not in z.files and z["field_nom__basis"].shape == (N_X, 2)   # 150 + ramp: rank 2
    back = load_design(path)
    np.testing.assert_allclose(back.nominal.field, d.nominal.field, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.lqg.field_std, d.lqg.field_std, rtol=0, atol=1e-9)
    refused(rewrite_design_file(path, tmp_path / "half.npz", field_nom__coef=None))
    with np.load(path, allow_pickle=False) as z:
        bad = z["field_std__basis"].copy()
    bad[0, 0] = np.nan
    refused(rewrite_design_file(path, tmp_path / "nan.npz", field_std__basis=bad), "field_std")


def test_belief_statistics_are_stored_in_float32_and_read_as_float64(tmp_path, monkeypatch):
    """belief_mean/belief_std (EnKF estimates) go into the file as float32, never SVD-compressed,
    and come back as float64 to float32 round-off; float64 ones (sep <= 0.3 files, compressed or
    not: version 2, sep 0.2-0.3) still load; a non-finite float32 one is refused; any other float32
    member is refused."""
    import sep_estimator.design_file as df

    monkeypatch.setattr(df, "COMPRESS_ABOVE", 10)
    d = synthetic_design()
    path = save_design(tmp_path / "s.npz", d)
    with np.load(path, allow_pickle=False) as z:
        for name in SINGLE:
            assert z[name].dtype == np.float32 and f"{name}__basis" not in z.files
        assert "field_nom__basis" in z.files           # the others still compressed
    back = load_design(path)
    for name in SINGLE:
        x, y = getattr(d.nominal, name), getattr(back.nominal, name)
        assert y.dtype == np.float64
        np.testing.assert_allclose(y, x, rtol=1e-7, atol=1e-30)
    old = rewrite_design_file(path, tmp_path / "old.npz", edit_meta=lambda m: {**m, "version": 2},
                  belief_mean=d.nominal.belief_mean, belief_std=None,
                  belief_std__coef=d.nominal.belief_std[:, :1] * 0 + 1.0,
                  belief_std__basis=np.full((N_X, 1), 0.5))
    back = load_design(old)
    np.testing.assert_array_equal(back.nominal.belief_mean, d.nominal.belief_mean)
    np.testing.assert_array_equal(back.nominal.belief_std, np.full((N_STEPS + 1, N_X), 0.5))
    bad = d.nominal.belief_std.astype(np.float32)
    bad[1, 1] = np.inf
    refused(rewrite_design_file(path, tmp_path / "inf.npz", belief_std=bad), "belief_std")
    refused(rewrite_design_file(path, tmp_path / "f32.npz", target=d.objective.target.astype(np.float32)), "target")


def test_absent_belief_statistics_round_trip(tmp_path):
    """A design without belief statistics (an opaque-state plant: no EnKF) is written with meta
    belief "absent" and no belief members, and reads back with them None; an opaque plant's
    description round-trips."""
    from dataclasses import replace

    d = synthetic_design()
    d = replace(d, info=replace(d.info, state_is_opaque=True),
                nominal=Nominal(d.nominal.u, d.nominal.y, d.nominal.field))
    assert d.nominal.belief_kind == "absent"
    path = save_design(tmp_path / "absent.npz", d)
    with np.load(path, allow_pickle=False) as z:
        assert not set(SINGLE) & set(z.files)
    back = load_design(path)
    assert back.meta["belief"] == "absent" and back.info.state_is_opaque
    assert back.nominal.belief_mean is None and back.nominal.belief_std is None
    assert_same(d, back)
    # the file says "absent" but holds a belief member, or names another kind: refused
    refused(rewrite_design_file(path, tmp_path / "both.npz", belief_mean=np.zeros((N_STEPS + 1, N_X), np.float32)),
            "belief is 'absent' but the file holds")
    refused(rewrite_design_file(path, tmp_path / "kind.npz", edit_meta=lambda m: {**m, "belief": "particles"}), "belief")
    # an ensemble file without its belief members: missing arrays
    ens = save_design(tmp_path / "ens.npz", synthetic_design())
    assert load_design(ens).meta["belief"] == "ensemble"
    refused(rewrite_design_file(ens, tmp_path / "nobelief.npz", belief_mean=None, belief_std=None), "missing arrays")
    with pytest.raises(ValueError, match="both"):
        save_design(tmp_path / "half.npz", replace(d, nominal=Nominal(d.nominal.u, d.nominal.y, d.nominal.field,
                                                                      d.nominal.field)))


def test_version_3_file_holds_the_ensemble_belief_and_no_opaque_flag(design_path, tmp_path):
    """Files before version 4 have no meta belief (the EnKF belief is there) and plant
    descriptions without state_is_opaque (read as False)."""
    def v3(m):
        m = {k: v for k, v in m.items() if k != "belief"}
        m["plant_info"] = {k: v for k, v in m["plant_info"].items() if k != "state_is_opaque"}
        return {**m, "version": 3}

    back = load_design(rewrite_design_file(design_path, tmp_path / "v3.npz", edit_meta=v3))
    assert back.meta["belief"] == "ensemble" and back.nominal.belief_mean is not None
    assert back.info.state_is_opaque is False


# ------------------------------------------------------------- source record
def test_saved_design_records_its_sources_and_their_digest(design_path):
    from sep_estimator.design_source import source_digest

    meta = load_design(design_path).meta
    src = meta["source"]
    assert set(src) == {"format_version", "sep_version", "plant", "plant_code", "plant_files", "problem", "settings"}
    assert src["format_version"] == VERSION and src["plant_files"] == {}
    assert src["sep_version"] == sep_plant.__version__ and src["plant_code"] == {"builtin": True}
    assert src["plant"] == {"type": "slab", **json.loads(json.dumps(SCENARIO.plant_config))}
    assert src["problem"] == SCENARIO.problem.resolved().to_dict()
    assert src["settings"] == {"n_r": N_R, "method": "gn"}
    assert meta["source_digest"] == source_digest(src) and len(meta["source_digest"]) == 64


def test_source_differences_name_each_changed_input(design_path):
    from sep_estimator.design_source import source_differences

    d = load_design(design_path)
    same = {"n_r": N_R, "method": "gn"}
    assert source_differences(d, SCENARIO, same) == []
    # what does not change a design is not recorded: the memory budget
    assert source_differences(d, SCENARIO, {**same, "memory_budget": 1 << 30}) == []
    diff = source_differences(d, SCENARIO.replace(target=151.0, w_std=0.2), {**same, "n_r": 4})
    assert diff == ["problem.target: 150.0 != 151.0", "problem.w_std: 0.3 != 0.2", "settings.n_r: 3 != 4"]
    assert source_differences(d, SCENARIO.with_plant(n_x=9), same) == ["plant.n_x: 8 != 9"]
    assert source_differences(d, SCENARIO, {**same, "jacobian_used": "rom"}) == \
        ["settings.jacobian_used: missing != 'rom'"]


def test_source_record_missing_or_edited(design_path, tmp_path):
    from sep_estimator.design_source import source_differences

    same = {"n_r": N_R, "method": "gn"}
    old = rewrite_design_file(design_path, tmp_path / "old.npz",
                  edit_meta=lambda m: {k: v for k, v in m.items() if k not in ("source", "source_digest")})
    assert "no source record" in source_differences(load_design(old), SCENARIO, same)[0]
    edited = rewrite_design_file(design_path, tmp_path / "edited.npz",
                     edit_meta=lambda m: {**m, "source": {**m["source"], "settings": {"n_r": 99}}})
    assert "does not match its digest" in source_differences(load_design(edited), SCENARIO, same)[0]


def test_the_digest_covers_the_sep_version(design_path, monkeypatch):
    """0.8.0's digest did not cover the code: `sep demo` reused a design made by an older sep."""
    from sep_estimator.design_source import source_differences

    d = load_design(design_path)
    same = {"n_r": N_R, "method": "gn"}
    assert source_differences(d, SCENARIO, same) == []
    monkeypatch.setattr(sep_plant, "__version__", "99.0.0")
    recorded = d.meta["source"]["sep_version"]
    assert source_differences(d, SCENARIO, same) == [f"sep version: {recorded!r} != '99.0.0'"]


def test_the_digest_covers_the_plant_module_given_by_import_path(tmp_path, monkeypatch):
    """A plant given as 'module:Class' is identified by the SHA-256 of its module's source: an edited
    plant module is a different design (0.8.0 reused the design made by the old code)."""
    import hashlib

    from sep_estimator.design_source import plant_code, source_differences

    monkeypatch.syspath_prepend(str(tmp_path))
    module = tmp_path / "my_toy_plant.py"
    module.write_text("from broken_plants import ToyPlant\n\n\nclass Toy(ToyPlant):\n    pass\n")
    s = Scenario.from_dict({"plant": {"type": "my_toy_plant:Toy"}, "n_steps": 5, "band_window": [3, 5],
                            "target": 1.0})
    d = load_design(save_design(tmp_path / "t.npz", synthetic_design(s)))
    code = d.meta["source"]["plant_code"]
    assert code == {"module": "my_toy_plant", "package": "my_toy_plant", "package_version": None,
                    "module_sha256": hashlib.sha256(module.read_bytes()).hexdigest()}
    assert source_differences(d, s, {"n_r": N_R, "method": "gn"}) == []
    old = code["module_sha256"]
    module.write_text(module.read_text() + "# the physics changed\n")
    new = plant_code("my_toy_plant:Toy")["module_sha256"]
    assert source_differences(d, s, {"n_r": N_R, "method": "gn"}) == \
        [f"plant module source sha256: {old[:12]} != {new[:12]}"]


def test_the_digest_covers_a_plant_packages_version():
    """A plant from an installed distribution is identified by that distribution's version too."""
    from importlib.metadata import version

    from sep_estimator.design_source import plant_code

    code = plant_code("numpy.polynomial:Polynomial")       # any class of an installed distribution
    assert code["package"] == "numpy" and code["package_version"] == version("numpy")
    assert len(code["module_sha256"]) == 64


def test_the_digest_does_not_change_the_design_arrays(design_path, tmp_path, monkeypatch):
    """The record is metadata: a design saved by another sep has the same arrays, another digest."""
    d = load_design(design_path)
    monkeypatch.setattr(sep_plant, "__version__", "99.0.0")
    again = load_design(save_design(tmp_path / "again.npz", d))
    assert again.meta["source_digest"] != load_design(design_path).meta["source_digest"]
    assert_same(again, load_design(design_path))


def test_plant_files_are_recorded_by_content(tmp_path):
    """A plant that reads a file (`source_files()`): the file's SHA-256 is part of the record, so
    new content under the same name is a difference."""
    import hashlib

    from sep_estimator.design_source import source_differences

    table = tmp_path / "table.txt"
    table.write_text("0.1\n")
    s = Scenario.from_dict({"plant": {"type": "file_plants:FileToy", "table": str(table)}, "n_steps": 5,
                            "band_window": [3, 5], "target": 1.0})
    path = save_design(tmp_path / "f.npz", synthetic_design(s))
    d = load_design(path)
    assert d.meta["source"]["plant_files"] == {"table.txt": hashlib.sha256(b"0.1\n").hexdigest()}
    assert source_differences(d, s, {"n_r": N_R, "method": "gn"}) == []
    table.write_text("0.2\n")
    diff = source_differences(d, s, {"n_r": N_R, "method": "gn"})
    old, new = hashlib.sha256(b"0.1\n").hexdigest(), hashlib.sha256(b"0.2\n").hexdigest()
    assert diff == [f"plant file table.txt: sha256 {old[:12]} != {new[:12]}"]
    table.unlink()
    assert "unreadable" in source_differences(d, s, {"n_r": N_R, "method": "gn"})[0]


def test_check_matches_refuses_problem_keys_but_the_run_time_ones():
    """Only the plant's noise and input limits may differ at run time (RUN_TIME_KEYS); any
    other problem key is a different problem, named with both values."""
    from sep_estimator.design_file import RUN_TIME_KEYS

    d = synthetic_design()
    assert RUN_TIME_KEYS == ("w_std", "v_std", "u_min", "u_max")
    check_matches(d, SCENARIO.replace(w_std=0.1, v_std=0.5, u_min=-1.0, u_max=3.0))
    for change, text in [(dict(target=151.0), "problem.target: 150.0 != 151.0"),
                         (dict(band=2.0), "problem.band: 3.0 != 2.0"),
                         (dict(band_window=(2, 5)), "problem.band_window: [3, 5] != [2, 5]"),
                         (dict(r_u=0.2), "problem.r_u: 0.1 != 0.2"),
                         (dict(lqr_k_switch=3), "problem.lqr_k_switch: 2 != 3"),
                         (dict(u_init=0.2), "problem.u_init: 0.1 != 0.2")]:
        with pytest.raises(DesignFileError) as exc:
            check_matches(d, SCENARIO.replace(**change))
        assert text in str(exc.value) and "another plant or problem" in str(exc.value), str(exc.value)
