"""The streamed field basis (sep_control.design.basis) and the POD field map (sep_estimator.ltv):
snapshots in, an orthonormal basis and coefficients out, the field map G_k = Phi g_k behaving
exactly like the dense one it replaces."""
import numpy as np
import pytest

from sep_control.design.basis import METHODS, IncrementalBasis, truncate
from sep_estimator.disturbance_model import PaddedFieldMap
from sep_estimator.ltv import (AUTO_FLOAT32_BYTES, DenseFieldMap, Float32Reconstruction, IdentityFieldMap, PODFieldMap,
                               in_precision, resolve_precision)


def low_rank(rng, n, m, rank, decay=1.0):
    U = np.linalg.qr(rng.standard_normal((n, rank)))[0]
    return U @ np.diag(decay ** np.arange(rank)) @ rng.standard_normal((rank, m))


def stream(X, block, tol=1e-12, method="gram"):
    """Add the columns of X in blocks; return the basis and the (r, m) coefficients."""
    b = IncrementalBasis(X.shape[0], tol, method=method)
    parts = [(i, b.add(X[:, i:i + block].T)) for i in range(0, X.shape[1], block)]
    C = np.zeros((b.rank, X.shape[1]))
    for i, c in parts:
        C[:c.shape[1], i:i + c.shape[0]] = c.T
    return b, C


@pytest.mark.parametrize("method", METHODS)
def test_streamed_basis_reproduces_the_snapshots_and_finds_their_rank(method):
    rng = np.random.default_rng(0)
    X = low_rank(rng, 400, 300, 17)
    b, C = stream(X, 23, method=method)
    assert b.rank == 17
    np.testing.assert_allclose(b.phi.T @ b.phi, np.eye(17), atol=1e-13)
    np.testing.assert_allclose(b.phi @ C, X, atol=1e-12 * np.abs(X).max())


@pytest.mark.parametrize("method", METHODS)
def test_what_is_dropped_is_below_the_tolerance(method):
    rng = np.random.default_rng(1)
    X = low_rank(rng, 300, 200, 40, decay=0.5)           # singular values 1, 0.5, 0.25, ...
    for tol in (1e-4, 1e-8):
        b, C = stream(X, 10, tol, method)
        err = np.linalg.norm(b.phi @ C - X, axis=0).max() / np.linalg.norm(X, axis=0).max()
        assert err < 30 * tol and b.rank < 40
        np.testing.assert_allclose(b.phi.T @ b.phi, np.eye(b.rank), atol=1e-12)
    # truncation to the span the coefficients use
    b, C = stream(X, 10, 1e-14, method)
    Phi, C2 = truncate(b.phi, C, 1e-6)
    assert Phi.shape[1] < b.rank
    assert np.linalg.norm(Phi @ C2 - X) <= 1e-5 * np.linalg.norm(X)


def test_pod_field_map_equals_the_dense_one():
    rng = np.random.default_rng(2)
    Phi = np.linalg.qr(rng.standard_normal((50, 8)))[0]
    g = rng.standard_normal((6, 8, 4))
    pod = PODFieldMap(Phi, g)
    dense = DenseFieldMap(np.einsum("fr,krn->kfn", Phi, g))
    a = rng.standard_normal((3, 4))
    L = rng.standard_normal((6, 4, 4))
    P = L @ L.transpose(0, 2, 1)
    v = rng.standard_normal((2, 50))
    for k in range(6):
        np.testing.assert_allclose(pod.apply(k, a), dense.apply(k, a), atol=1e-12)
        np.testing.assert_allclose(pod.matrix(k), dense.matrix(k), atol=1e-12)
        np.testing.assert_allclose(pod.std(k, P[k]), dense.std(k, P[k]), rtol=1e-10)
        np.testing.assert_allclose(pod.gram(k), dense.gram(k), atol=1e-12)
        np.testing.assert_allclose(pod.project(k, v), dense.project(k, v), atol=1e-12)
    np.testing.assert_allclose(pod.std_all(P), dense.std_all(P), rtol=1e-10)
    # every step's G_k' v_k at once (one pass over Phi) is the step-by-step projection
    V = rng.standard_normal((6, 50))
    steps = np.stack([dense.project(k, V[k]) for k in range(6)])
    np.testing.assert_allclose(pod.project_all(V), steps, atol=1e-12)
    np.testing.assert_allclose(dense.project_all(V), steps, atol=1e-12)
    padded = PaddedFieldMap(pod, 2)
    np.testing.assert_allclose(padded.project_all(V), np.stack([padded.project(k, V[k]) for k in range(6)]),
                               atol=1e-12)
    np.testing.assert_array_equal(IdentityFieldMap(50).project_all(V), V)


def test_float32_reconstruction_agrees_to_single_precision_and_keeps_the_rest_float64():
    """field_precision 'float32': the reconstruction (a g_k') Phi' from a float32 copy of Phi,
    within float32 round-off of the float64 one, returned as float64; std and the rest unchanged."""
    rng = np.random.default_rng(3)
    Phi = np.linalg.qr(rng.standard_normal((3000, 40)))[0]
    pod = PODFieldMap(Phi, rng.standard_normal((5, 40, 6)))
    f32 = in_precision(pod, "float32")
    assert isinstance(f32, Float32Reconstruction) and in_precision(pod, "float64") is pod
    assert in_precision(f32, "float32") is f32
    a = rng.standard_normal((2, 6))
    P = np.eye(6)
    for k in range(5):
        exact, single = pod.apply(k, a), f32.apply(k, a)
        assert single.dtype == np.float64 and single.shape == exact.shape
        err = np.abs(single - exact).max() / np.abs(exact).max()
        assert 0 < err < 1e-6, err        # float32 round-off: present, and small
        np.testing.assert_array_equal(f32.std(k, P), pod.std(k, P))
    dense = DenseFieldMap(np.zeros((5, 7, 6)))
    assert in_precision(dense, "float32") is dense
    with pytest.raises(ValueError, match="auto, float64, float32"):
        in_precision(pod, "float16")


def test_auto_precision_is_float32_only_for_a_field_basis_too_large_for_the_caches():
    """'auto' keeps a small basis in float64 (the reconstruction is then bitwise the default's)
    and reconstructs from a float32 copy of a basis of AUTO_FLOAT32_BYTES or more."""
    rng = np.random.default_rng(5)
    g = rng.standard_normal((3, 16, 4))
    rows = AUTO_FLOAT32_BYTES // (8 * 16)
    small = PODFieldMap(np.linalg.qr(rng.standard_normal((rows - 1, 16)))[0], g)
    large = PODFieldMap(np.linalg.qr(rng.standard_normal((rows, 16)))[0], g)
    assert resolve_precision(small, "auto") == "float64" and in_precision(small, "auto") is small
    assert resolve_precision(large, "auto") == "float32"
    assert isinstance(in_precision(large, "auto"), Float32Reconstruction)
    assert resolve_precision(large, "float64") == "float64" and in_precision(large, "float64") is large
    dense = DenseFieldMap(np.zeros((3, rows, 4)))
    assert resolve_precision(dense, "auto") == "float64" and in_precision(dense, "auto") is dense


def test_identified_field_map_is_compact_and_its_rank_does_not_grow_with_the_grid():
    """The slab's field map lives in a basis of ~60 directions at 400 and at 1600 nodes (memory
    n_field r_f + N r_f n_r), and equals the field map of a near-exact basis (tolerance 1e-13) to
    the basis' tolerance."""
    from core_helpers import flat
    from sep_control.design import tvera

    ranks = []
    for n_x in (400, 1600):
        s = flat(n_x=n_x, n_steps=40, k_band=24, lqr_k_switch=19)
        U = np.full((40, 5), 0.2)
        ident = tvera.identify(s.plant, U, 6, 6, 16)
        G = ident.model.G
        assert isinstance(G, PODFieldMap)
        ranks.append(G.rank)
    assert max(ranks) < 100 and ranks[1] <= ranks[0] + 10
    fine = tvera.identify(s.plant, U, 6, 6, 16, field_tol=1e-13)
    assert fine.model.G.rank > 2 * G.rank
    for k in (1, 10, 40):
        Gf = fine.model.G.matrix(k)
        assert np.abs(G.matrix(k) - Gf).max() <= 1e-6 * np.abs(Gf).max()


@pytest.mark.parametrize("method", METHODS)
def test_a_block_inside_the_span_adds_nothing_and_needs_no_svd(monkeypatch, method):
    """Once the basis holds the responses, a block whose residual's Frobenius norm is below
    tol * scale (a bound on every singular value) is projected only: no SVD, no new direction."""
    import sep_control.design.basis as basis_mod

    rng = np.random.default_rng(5)
    X = low_rank(rng, 300, 40, 6)
    b = IncrementalBasis(300, 1e-10, method=method)
    b.add(X[:, :20].T)
    assert b.rank == 6
    svds = []
    orig = np.linalg.svd
    monkeypatch.setattr(basis_mod.np.linalg, "svd", lambda *a, **k: svds.append(1) or orig(*a, **k))
    C = b.add(X[:, 20:].T)
    assert svds == [] and b.rank == 6
    np.testing.assert_allclose(C @ b.phi.T, X[:, 20:].T, atol=1e-10 * np.abs(X).max())
    b.add(rng.standard_normal((3, 300)))              # new directions: the SVD runs, the basis grows
    assert svds == [1] and b.rank == 9


def test_basis_rejects_wrong_length_and_an_unknown_method():
    with pytest.raises(ValueError, match="length"):
        IncrementalBasis(5).add(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="gram, svd"):
        IncrementalBasis(5, method="qr")


def test_gram_basis_keeps_directions_down_to_the_tolerance_across_sixteen_decades():
    """A block whose singular values run from 1 to 1e-16 (beyond what one Gram matrix resolves,
    about 1e-5.5 of its largest): the rounds find every direction above the tolerance, as the
    SVD does, and the coefficients rebuild the block to it."""
    rng = np.random.default_rng(7)
    n, b = 2000, 40
    modes = np.linalg.qr(rng.standard_normal((n, b)))[0] * np.logspace(0, -16, b)
    D = np.linalg.qr(rng.standard_normal((b, b)))[0] @ modes.T
    for tol in (1e-8, 1e-12):
        g, s = IncrementalBasis(n, tol, method="gram"), IncrementalBasis(n, tol, method="svd")
        Cg, Cs = g.add(D), s.add(D)
        scale = np.linalg.norm(D, axis=1).max()        # the tolerance is relative to the largest snapshot
        assert g.rank == s.rank == int(np.count_nonzero(np.logspace(0, -16, b) > tol * scale))
        np.testing.assert_allclose(g.phi.T @ g.phi, np.eye(g.rank), atol=1e-12)
        assert np.abs(Cg @ g.phi.T - D).max() <= 2 * tol * scale
        # the same projection of the data (the directions at the tolerance's edge are round-off)
        assert np.abs(g.phi @ (g.phi.T @ D.T) - s.phi @ (s.phi.T @ D.T)).max() <= 2 * tol * scale


@pytest.mark.parametrize("tol", [1e-8, 1e-13, 1e-15])
def test_gram_basis_stays_orthonormal_at_tolerances_near_round_off(tol):
    """Chunk bases whose snapshots span sixteen decades, merged, and blocks streamed in, at
    tolerances down to round-off: no direction is taken from the projections' round-off (the
    Gram rounds stop at sqrt(b) eps |E|), so the basis stays orthonormal and holds the data, with
    about the rank the SVD method finds."""
    rng = np.random.default_rng(11)
    n, r_c = 4000, 110
    shared = np.linalg.qr(rng.standard_normal((n, 3 * r_c)))[0]
    g, v = IncrementalBasis(n, tol, method="gram"), IncrementalBasis(n, tol, method="svd")
    X = []
    for c in range(4):           # overlapping chunks: each its own mix of the shared directions
        cols = rng.choice(3 * r_c, r_c, replace=False)
        phi = np.linalg.qr(shared[:, cols] @ np.linalg.qr(rng.standard_normal((r_c, r_c)))[0])[0]
        coef = rng.standard_normal((r_c, 200)) * np.logspace(0, -15, r_c)[:, None]
        g.merge(phi, coef)
        v.merge(phi, coef)
        X.append(phi @ coef)
    D = (shared[:, :60] @ (rng.standard_normal((60, 40)) * np.logspace(0, -15, 60)[:, None])).T
    g.add(D)
    v.add(D)
    np.testing.assert_allclose(g.phi.T @ g.phi, np.eye(g.rank), atol=1e-12)
    assert abs(g.rank - v.rank) <= max(3, v.rank // 20), (g.rank, v.rank)
    data = np.hstack(X + [D.T])
    scale = np.linalg.norm(data, axis=0).max()
    res = data - g.phi @ (g.phi.T @ data)
    assert np.linalg.norm(res, axis=0).max() <= max(30 * tol, 1e-13) * scale


def test_both_methods_identify_the_same_field_responses():
    """An identification with the Gram basis (experiment plan 0.9) and with 0.8.0's SVD one, fed
    the same blocks (each step's snapshots): the same rank, the same output Markov parameters,
    field responses equal far below the basis' tolerance (1e-8 of the largest response)."""
    from unittest import mock

    from core_helpers import flat
    from sep_control.design import impulse, tvera

    s = flat(n_x=800, n_steps=40, k_band=24, lqr_k_switch=19)
    U = np.full((40, 5), 0.2) + 0.01 * np.random.default_rng(3).standard_normal((40, 5))
    with mock.patch.object(impulse, "MIN_FIELD_ROWS", 1):
        g = tvera.identify(s.plant, U, 6, 6, 16, chunks=4, field_basis="gram").data
    v = tvera.identify(s.plant, U, 6, 6, 16, chunks=4, field_basis="svd").data
    assert abs(g.basis.shape[1] - v.basis.shape[1]) <= 1
    np.testing.assert_array_equal(g.Y, v.Y)
    np.testing.assert_allclose(g.basis.T @ g.basis, np.eye(g.basis.shape[1]), atol=1e-12)
    assert np.abs(g.Yf - v.Yf).max() <= 1e-9 * np.abs(v.Yf).max()


@pytest.mark.parametrize("tol", [1e-8, 1e-6])
def test_blocks_of_several_steps_keep_the_field_responses_within_the_tolerance(tol):
    """The Gram basis takes the snapshots of consecutive steps in blocks of at least
    MIN_FIELD_ROWS rows (here up to 30 a step): against a reference identified to 1e-12, the
    field responses are within the tolerance of the largest, as close as with each step's block
    alone (measured: 5.9e-9 against 9.9e-9 of the largest at 1e-8), with no more directions."""
    from unittest import mock

    from core_helpers import flat
    from sep_control.design import impulse, tvera

    s = flat(n_x=800, n_steps=40, k_band=24, lqr_k_switch=19)
    U = np.full((40, 5), 0.2) + 0.01 * np.random.default_rng(3).standard_normal((40, 5))
    ref = tvera.identify(s.plant, U, 6, 6, 16, chunks=4, field_tol=1e-12).data
    seen = []
    add = impulse.IncrementalBasis.add

    def counted(self, D, *a, **kw):
        if D.shape[1] == 800:                      # the field responses (a merge streams coefficients)
            seen.append(D.shape[0])
        return add(self, D, *a, **kw)

    with mock.patch.object(impulse.IncrementalBasis, "add", counted):
        blocked = tvera.identify(s.plant, U, 6, 6, 16, chunks=4, field_tol=tol).data
    rows = list(seen)
    with mock.patch.object(impulse, "MIN_FIELD_ROWS", 1):
        stepwise = tvera.identify(s.plant, U, 6, 6, 16, chunks=4, field_tol=tol).data
    # a step holds at most 30 snapshots here (5 channels, 6 field lags): every block but each
    # chunk's last gathers several steps
    assert sum(b < impulse.MIN_FIELD_ROWS for b in rows) <= 4 and len(rows) >= 10
    np.testing.assert_array_equal(blocked.Y, ref.Y)
    scale = np.abs(ref.Yf).max()
    err_blocked = np.abs(blocked.Yf - ref.Yf).max() / scale
    err_stepwise = np.abs(stepwise.Yf - ref.Yf).max() / scale
    assert err_blocked <= tol and err_stepwise <= tol
    assert err_blocked <= 1.2 * err_stepwise
    assert blocked.basis.shape[1] <= stepwise.basis.shape[1]


def test_experiments_split_by_a_memory_budget_give_the_same_data():
    """Channel groups, one lockstep pass each, when the batch does not fit the budget."""
    from unittest import mock

    from core_helpers import flat
    from sep_control.design import impulse

    s = flat(n_x=30, n_steps=20, k_band=12, lqr_k_switch=10)
    U = np.full((20, 5), 0.2)
    whole = impulse.impulse_experiments(s.plant, U, 8, 4, 1e-3)
    with mock.patch.object(impulse, "runs_per_batch", return_value=2 * 8 * 2):     # two channels a pass
        split = impulse.impulse_experiments(s.plant, U, 8, 4, 1e-3)
    np.testing.assert_allclose(split.Y, whole.Y, rtol=0, atol=1e-12 * np.abs(whole.Y).max())
    # (the field responses agree to the basis tolerance, 1e-8 of the largest: the order of adding differs)
    np.testing.assert_allclose(split.Yf, whole.Yf, rtol=0, atol=5e-8 * np.abs(whole.Yf).max())


def test_chunk_bases_merge_to_the_one_chunk_basis():
    """Experiments in 4 chunks of start steps give the field basis one chunk gives: each chunk's
    responses are streamed into the merged basis against the largest response overall, so no
    chunk keeps its own small directions (as unit vectors they had doubled the rank), and the
    merged basis reproduces every chunk's field responses to the basis' tolerance."""
    from core_helpers import flat
    from sep_control.design import tvera

    s = flat(n_x=800, n_steps=40, k_band=24, lqr_k_switch=19)
    U = np.full((40, 5), 0.2) + 0.01 * np.random.default_rng(3).standard_normal((40, 5))
    one = tvera.identify(s.plant, U, 6, 6, 16, chunks=1).data
    four = tvera.identify(s.plant, U, 6, 6, 16, chunks=4).data
    assert abs(four.basis.shape[1] - one.basis.shape[1]) <= 2, (four.basis.shape, one.basis.shape)
    np.testing.assert_allclose(four.basis.T @ four.basis, np.eye(four.basis.shape[1]), atol=1e-12)
    Yf1 = np.einsum("fr,jlrc->jlfc", one.basis, one.Yc)
    Yf4 = np.einsum("fr,jlrc->jlfc", four.basis, four.Yc)
    assert np.abs(Yf4 - Yf1).max() <= 1e-7 * np.abs(Yf1).max()


@pytest.mark.parametrize("method", METHODS)
def test_merge_streams_coefficients_like_add(method):
    """`merge(phi, C)` adds the snapshots phi C as `add` adds them block by block, without
    forming them: the same rank, an orthonormal basis, the same projection of the data, and the
    residual of every snapshot below the tolerance."""
    rng = np.random.default_rng(4)
    n, r, m = 500, 40, 640
    phi = np.linalg.qr(rng.standard_normal((n, r)))[0]
    C = rng.standard_normal((r, m)) * np.logspace(0, -12, r)[:, None]
    a, b = IncrementalBasis(n, 1e-8, method=method), IncrementalBasis(n, 1e-8, method=method)
    a.merge(phi, C)
    X = (phi @ C).T
    for i in range(0, m, 64):
        b.add(X[i:i + 64])
    assert a.rank == b.rank
    np.testing.assert_allclose(a.phi.T @ a.phi, np.eye(a.rank), atol=1e-12)
    res = X.T - a.phi @ (a.phi.T @ X.T)
    assert np.sqrt((res ** 2).sum(axis=0)).max() <= 1e-7 * np.sqrt((X ** 2).sum(axis=1)).max()
    # the same span where the data are (directions at the tolerance's edge may differ)
    Pa, Pb = a.phi @ (a.phi.T @ X.T), b.phi @ (b.phi.T @ X.T)
    assert np.abs(Pa - Pb).max() <= 1e-7 * np.abs(X).max()
    # a second chunk that overlaps the first: only its new part extends the basis
    phi2 = np.linalg.qr(np.hstack([phi[:, :20], rng.standard_normal((n, 10))]))[0]
    C2 = rng.standard_normal((30, 320))
    r0 = a.rank
    a.merge(phi2, C2)
    X2 = (phi2 @ C2).T
    for i in range(0, 320, 64):
        b.add(X2[i:i + 64])
    assert a.rank == b.rank and r0 < a.rank <= r0 + 10 + 20
    np.testing.assert_allclose(a.phi.T @ a.phi, np.eye(a.rank), atol=1e-12)
    res2 = X2.T - a.phi @ (a.phi.T @ X2.T)
    assert np.abs(res2).max() <= 1e-7 * np.abs(X2).max()
    with pytest.raises(ValueError, match="merge"):
        a.merge(phi2[:10], C2)


@pytest.mark.parametrize("first", [True, False])
def test_gram_merge_returns_the_chunk_basis_on_the_merged_one(first):
    """What a "gram" merge returns is Phi' phi on the columns Phi has after it (into an empty
    basis too), from the merge's own products: what `impulse._merge_chunks` takes the chunk's
    coefficients over with; "svd" returns None (0.8.0's merge: the caller projects)."""
    rng = np.random.default_rng(6)
    n = 400
    Q0 = np.linalg.qr(rng.standard_normal((n, 50)))[0]
    b = IncrementalBasis(n, 1e-8, method="gram")
    if not first:
        b.add((Q0[:, :15] @ rng.standard_normal((15, 40))).T)
    phi = np.linalg.qr(np.hstack([Q0[:, 10:15], Q0[:, 15:30] + 1e-3 * Q0[:, 35:]]))[0]    # overlaps
    C = rng.standard_normal((20, 300)) * np.logspace(0, -6, 20)[:, None]
    T = b.merge(phi, C)
    assert T.shape == (b.rank, 20)
    np.testing.assert_allclose(T, b.phi.T @ phi, atol=1e-12)
    assert IncrementalBasis(n, 1e-8, method="svd").merge(phi, C) is None


def test_gram_merge_takes_only_the_directions_the_snapshots_use(monkeypatch):
    """A chunk basis of 40 directions whose snapshots use 10 of them: the Gram merge finds those
    10 from the range of the residual snapshots (A U_c S_c) and orthonormalizes no others, and the
    basis holds every snapshot to the tolerance."""
    from sep_control.design import basis as basis_mod

    rng = np.random.default_rng(5)
    n = 600
    Q0 = np.linalg.qr(rng.standard_normal((n, 60)))[0]
    b = IncrementalBasis(n, 1e-8, method="gram")
    b.add((Q0[:, :20] @ rng.standard_normal((20, 50))).T)
    phi = Q0[:, 20:]                                           # 40 directions outside the basis
    C = np.zeros((40, 200))
    C[:10] = rng.standard_normal((10, 200))                    # the snapshots use 10 of them
    seen = []
    orthonormal = basis_mod._orthonormal
    monkeypatch.setattr(basis_mod, "_orthonormal", lambda xp, W, against: seen.append(W.shape[1]) or
                        orthonormal(xp, W, against))
    b.merge(phi, C)
    assert b.rank == 30 and max(seen) == 10, (b.rank, seen)
    np.testing.assert_allclose(b.phi.T @ b.phi, np.eye(b.rank), atol=1e-12)
    X = phi @ C
    assert np.abs(X - b.phi @ (b.phi.T @ X)).max() <= 1e-8 * np.abs(X).max()


def test_compressed_field_map_drops_only_what_the_state_spread_does_not_reach():
    """compress_field_map: with X_k = L_k L_k', every |(G_k - G_k') L_k|_2 <= tol sigma_1 of
    [g_0 L_0 ... g_N L_N]; Phi' stays orthonormal; the directions the spread reaches are kept."""
    from sep_control.design.field_map import compress_field_map

    rng = np.random.default_rng(4)
    n_f, r_f, n, N1 = 400, 30, 6, 9
    Phi = np.linalg.qr(rng.standard_normal((n_f, r_f)))[0]
    g = np.einsum("r,krn->krn", 10.0 ** -np.linspace(0, 9, r_f), rng.standard_normal((N1, r_f, n)))
    M = rng.standard_normal((N1, n, n))
    X = M @ M.transpose(0, 2, 1)
    G = PODFieldMap(Phi, g)
    Lk = [np.linalg.cholesky(x + 1e-12 * np.eye(n)) for x in X]
    sigma_1 = np.linalg.norm(np.concatenate([G.g[k] @ Lk[k] for k in range(N1)], axis=1), 2)
    for tol in (1e-3, 1e-6):
        C = compress_field_map(G, X, tol)
        assert 0 < C.rank < r_f and C.g.shape == (N1, C.rank, n)
        np.testing.assert_allclose(C.Phi.T @ C.Phi, np.eye(C.rank), atol=1e-12)
        for k in range(N1):
            assert np.linalg.norm((G.matrix(k) - C.matrix(k)) @ Lk[k], 2) <= tol * sigma_1 * (1 + 1e-9)
    assert compress_field_map(G, X, 1e-6).rank > compress_field_map(G, X, 1e-3).rank
    # a direction the spread does not reach (X_k = 0 there) goes, however large g is along it
    X0 = X.copy()
    X0[:, :, 0] = X0[:, 0, :] = 0.0
    g1 = np.zeros_like(g)
    g1[:, 0, 0] = 1e3                       # only the unreached state a_0 maps onto Phi[:, 0]
    g1[:, 1, 1:] = 1.0
    C = compress_field_map(PODFieldMap(Phi, g1), X0, 1e-6)
    assert C.rank == 1 and abs(abs(C.Phi[:, 0] @ Phi[:, 1]) - 1) < 1e-12


def test_design_compresses_its_field_map_and_keeps_its_gains():
    """The design's field map is the identification's compressed at field_map_tol; the LQR and
    Kalman gains are those of the uncompressed model, the field std that of the compressed map."""
    from core_helpers import cached_design, coarse_scenario
    from sep_control.design.pipeline import DesignSettings, identify_rom
    from sep_control.design.field_map import FIELD_MAP_TOL
    from sep_control.design.gains import design_lqg
    from sep_estimator.ltv import field_std_schedule

    scen = coarse_scenario(20, 40)
    # plan 0.8: the design's model is identified at its final input (plan 0.9 may reuse the optimizer's)
    settings = dict(p=5, q=5, n_r=10, ensemble=20, belief=False, experiment_plan="0.8")
    d = cached_design(scen, **settings)
    st = DesignSettings(**settings)
    assert st.field_map_tol == FIELD_MAP_TOL
    ident = identify_rom(scen.plant, d.nominal.u, st)
    full = design_lqg(ident.model, d.problem, d.disturbance).lqg()
    assert d.rom.G.rank < ident.model.G.rank
    for name in ("A", "B", "C"):
        np.testing.assert_array_equal(getattr(d.rom, name), getattr(ident.model, name))
    np.testing.assert_array_equal(d.lqg.K, full.K)
    np.testing.assert_array_equal(d.lqg.kf.L, full.kf.L)
    np.testing.assert_allclose(d.lqg.field_std, field_std_schedule(d.lqg.model.G, d.lqg.kf.P_post), rtol=1e-12)
    np.testing.assert_allclose(d.lqg.field_std, full.field_std, rtol=0, atol=1e-3 * full.field_std.max())
    # the stages apart: design_lqg compresses nothing (the gains on the model it was given), and
    # the field-map stage on those gains gives the design's map and field std bit for bit
    from sep_control.design.field_map import compressed_lqg

    gains = design_lqg(ident.model, d.problem, d.disturbance)
    assert gains.rom is ident.model
    lqg = compressed_lqg(gains, st.field_map_tol)
    np.testing.assert_array_equal(lqg.rom.G.Phi, d.rom.G.Phi)
    np.testing.assert_array_equal(lqg.rom.G.g, d.rom.G.g)
    np.testing.assert_array_equal(lqg.field_std, d.lqg.field_std)
    np.testing.assert_array_equal(lqg.kf.P_prior, d.lqg.kf.P_prior)


def test_the_designs_svd_falls_back_to_gesvd_where_gesdd_does_not_converge(monkeypatch):
    """LAPACK's gesdd failed on a finite 140 x 201 residual block of a 201-node plant's field
    basis; the design's SVD then takes gesvd (and still refuses a matrix with NaN or Inf)."""
    from sep_control.design import svd as module

    rng = np.random.default_rng(0)
    a = rng.standard_normal((14, 20)) @ np.diag(np.logspace(0, -18, 20))
    real = np.linalg.svd

    def failing(x, full_matrices=True, **kw):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(module.np.linalg, "svd", failing)
    U, S, Vt = module.svd(a)
    assert U.shape == (14, 14) and Vt.shape == (14, 20)
    np.testing.assert_allclose((U * S) @ Vt, a, atol=1e-12)
    np.testing.assert_allclose(S, real(a, compute_uv=False), rtol=1e-10, atol=1e-14)
    with pytest.raises(np.linalg.LinAlgError):
        module.svd(np.full((3, 3), np.nan))


def test_gram_basis_in_place_residual_and_reserved_columns_give_the_same_basis():
    """`add(D, overwrite=True)` forms the residual in D's memory (one dgemm) and `reserve`
    allocates the columns ahead: the same coefficients and basis as a plain add into a growing
    buffer (to round-off), the reserved buffer never regrown, and the caller's D left alone
    without `overwrite`."""
    rng = np.random.default_rng(12)
    n = 700
    X = low_rank(rng, n, 240, 60, decay=0.8)
    plain, fast = IncrementalBasis(n, 1e-8, method="gram"), IncrementalBasis(n, 1e-8, method="gram", reserve=240)
    buffer = fast._phi
    for i in range(0, 240, 30):
        D = X[:, i:i + 30].T.copy()
        c_plain = plain.add(D)
        np.testing.assert_array_equal(D, X[:, i:i + 30].T)           # not overwritten
        c_fast = fast.add(D, overwrite=True)
        np.testing.assert_allclose(c_fast, c_plain, atol=1e-12 * np.abs(X).max())
        buffer = fast._phi if buffer.shape[1] == 0 else buffer
        assert fast._phi is buffer                                    # reserved: no growth copies
    assert fast.rank == plain.rank and fast._phi.shape[1] == 240
    np.testing.assert_allclose(np.abs(fast.phi.T @ plain.phi), np.eye(fast.rank), atol=1e-9)
    np.testing.assert_allclose(fast.phi.T @ fast.phi, np.eye(fast.rank), atol=1e-12)


def test_gram_merge_into_an_empty_basis_keeps_the_chunk_basis_when_every_direction_counts():
    """The first chunk merged into an empty basis, every one of its directions above the
    tolerance: phi joins as it is (no rotation) and the transfer is the identity; with directions
    the snapshots do not use, those are dropped and the transfer is Phi' phi."""
    rng = np.random.default_rng(13)
    n = 500
    phi = np.linalg.qr(rng.standard_normal((n, 25)))[0]
    full = IncrementalBasis(n, 1e-8, method="gram")
    T = full.merge(phi, rng.standard_normal((25, 100)))
    np.testing.assert_array_equal(full.phi, phi)
    np.testing.assert_array_equal(T, np.eye(25))
    C = np.zeros((25, 100))
    C[:12] = rng.standard_normal((12, 100))
    part = IncrementalBasis(n, 1e-8, method="gram")
    T = part.merge(phi, C)
    assert part.rank == 12
    np.testing.assert_allclose(T, part.phi.T @ phi, atol=1e-12)
    X = phi @ C
    assert np.abs(X - part.phi @ (T @ C)).max() <= 1e-8 * np.abs(X).max()
