"""Disturbance states of the ROM filter (sep_estimator.disturbance): offset-free tracking.

* the augmented filter is the textbook Kalman filter on z = [a; d], written here from the
  equations (input and output kind, prior P_0 = blockdiag(0, diag(sigma_0^2)), random walk);
* the augmented LQR is the Riccati recursion on z: its a-block is the ROM's gain bit for bit,
  K_d ~ -E (input kind), K_d = 0 (output kind);
* a known constant input bias (PerturbedPlant input_offset) is estimated to the filter's own
  accuracy and removed; a sensor bias (output kind) is removed from the estimate;
* the design's choice (directions, detectability, prior std) and the refusals (n_d > n_y,
  negative std, unknown kind) with exit 2 naming the key;
* design files: version 4 round trip, its members checked, versions 1-3 read as kind none.
"""
from dataclasses import replace

import numpy as np
import pytest

from core_helpers import (TINY_YAML, cached_design, coarse_scenario, ltv_system, one_blas_thread,  # noqa: F401
                          rewrite_design_file)
from sep_control.control.controllers import make_controller
from sep_control.control.mpc import RomMPC
from sep_control.design.gains import augmented_lqr, design_lqg, lqr_gains, output_weights, tv_lqr
from sep_control.design.pipeline import DesignSettings
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.design_file import VERSION, DesignFileError, arrays_of, load_design, save_design
from sep_estimator.disturbance import (Disturbance, DisturbanceError, augment, choose, cross_input, direction_labels,
                                       input_directions, noise_covariance, step_gain)
from sep_estimator.ltv import LQG, DenseFieldMap, LTVModel
from sep_estimator.tvkf import KalmanFilter, kalman_gains, open_loop_covariance
from sep_plant.noise import noise_sequences
from sep_plant.perturb import PerturbedPlant

SETTINGS = dict(p=5, q=5, n_r=10, ensemble=20, belief=False)


@pytest.fixture(scope="module")
def design():
    """The coarse slab design with the default disturbance states (input, n_d = n_y = 5)."""
    return cached_design(coarse_scenario(20, 40), **SETTINGS)


def with_disturbance(d, kind, **kw):
    """`d` with the gains redesigned for disturbance states `kind` (same ROM and nominal)."""
    dist = choose(d.rom, kind, d.problem.band, d.problem.window, **kw) if kind != "none" else None
    return replace(d, lqg=design_lqg(d.rom, d.problem, dist).lqg())


def closed_loop(d, plant, runs=200, seed=1):
    """rom_lqg on `plant` for `runs` runs (the Monte Carlo's noise): the final filter states
    z_N (runs, n_z) and the final plant states."""
    p, nom, lqg = d.problem, d.nominal, d.lqg
    w, v = noise_sequences(p, d.info, seed, list(range(runs)))
    kf, law = KalmanFilter(lqg, batch=runs), make_controller("rom_lqg", lqg, p, nom.u)
    x = plant.initial_state(runs)
    for k in range(p.n_steps + 1):
        z = kf.update(k, plant.observe(x) + v[:, k] - nom.y[k])
        if k == p.n_steps:
            return z, x
        u = law.command(k, z)
        x = plant.step(x, u, w[:, k])
        kf.predict(k, u - nom.u[k])


# ------------------------------------------------------------------ the filter
def random_case(kind, seed=0, N=12, n=4, n_u=3, n_y=2, n_d=2):
    rng = np.random.default_rng(seed)
    A, B, C, F = ltv_system(rng, N, n, n_u, n_y, 6)
    rom = LTVModel(A=A, B=B, C=C, G=DenseFieldMap(F), dims=np.full(N + 1, n))
    rows = n_u if kind == "input" else n_y
    E = np.linalg.qr(rng.standard_normal((rows, n_d)))[0] if kind == "input" else rng.standard_normal((rows, n_d))
    dist = Disturbance(kind, E, np.array([0.5, 0.2]), np.array([0.03, 0.0]))
    return rng, rom, dist


@pytest.mark.parametrize("kind", ["input", "output"])
def test_augmented_filter_equals_a_hand_written_augmented_kalman_filter(kind):
    rng, rom, dist = random_case(kind)
    N, n, n_u, n_y, n_d = rom.n_steps, rom.n, rom.n_u, rom.n_y, dist.n_d
    W, V = np.diag([0.3, 0.2, 0.1]) ** 2, np.diag([0.5, 0.4]) ** 2
    z = augment(rom, dist)
    sched = kalman_gains(z, noise_covariance(W, dist), V)
    lqg = LQG("rom_lqg", z, np.zeros((N, n_u, n + n_d)), sched, noise_covariance(W, dist), V,
              disturbance=dist, rom=rom)
    kf = KalmanFilter(lqg)
    # the equations, written out: a' = A a + B (du + E d) + B w (input) | y = C a + F d + v (output)
    E = dist.map
    m, P = np.zeros(n + n_d), np.zeros((n + n_d, n + n_d))
    P[n:, n:] = np.diag(dist.std0**2)
    U, Y = rng.standard_normal((N, n_u)), rng.standard_normal((N + 1, n_y))
    for k in range(N + 1):
        Cz = np.hstack([rom.C[k], E if kind == "output" else np.zeros((n_y, n_d))])
        S = Cz @ P @ Cz.T + V
        G = P @ Cz.T @ np.linalg.inv(S)
        m, P = m + G @ (Y[k] - Cz @ m), P - G @ S @ G.T
        np.testing.assert_allclose(kf.update(k, Y[k])[0], m, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(sched.P_post[k], P, rtol=1e-9, atol=1e-12)
        if k == N:
            break
        Az = np.block([[rom.A[k], rom.B[k] @ E if kind == "input" else np.zeros((n, n_d))],
                       [np.zeros((n_d, n)), np.eye(n_d)]])
        Bz = np.vstack([rom.B[k], np.zeros((n_d, n_u))])
        Q = np.zeros_like(P)
        Q[:n, :n], Q[n:, n:] = rom.B[k] @ W @ rom.B[k].T, np.diag(dist.walk_std**2)
        m, P = Az @ m + Bz @ U[k], Az @ P @ Az.T + Q
        kf.predict(k, U[k])
    # a filter restarted mid-episode starts from the open-loop covariance of z_k from P_0
    kf.restart_at(5)
    P = z.initial_covariance()
    for j in range(5):
        P = z.A[j] @ P @ z.A[j].T + z.noise_input[j] @ noise_covariance(W, dist) @ z.noise_input[j].T
    np.testing.assert_allclose(kf.P, P, rtol=1e-12, atol=1e-14)
    assert kf.P[n, n] == pytest.approx(dist.std0[0] ** 2 + 5 * dist.walk_std[0] ** 2)
    np.testing.assert_allclose(open_loop_covariance(z.A, z.noise_input, noise_covariance(W, dist), 0, z.P0), z.P0)
    # the prior covariances of a schedule rebuilt from its posteriors start from P_0 too
    np.testing.assert_allclose(lqg.kf.P_prior, sched.P_prior, rtol=1e-12, atol=1e-15)


def test_augmented_model_blocks_and_field_map():
    _, rom, dist = random_case("input")
    z = augment(rom, dist)
    n = rom.n
    np.testing.assert_array_equal(z.A[:, :n, :n], rom.A)
    np.testing.assert_allclose(z.A[:, :n, n:], rom.B @ dist.map)
    np.testing.assert_array_equal(z.A[:, n:, n:], np.broadcast_to(np.eye(2), (rom.n_steps, 2, 2)))
    np.testing.assert_array_equal(z.B[:, n:], 0.0)
    np.testing.assert_array_equal(z.C[:, :, n:], 0.0)
    a = np.random.default_rng(1).standard_normal((3, n + 2))
    np.testing.assert_array_equal(z.G.apply(4, a), rom.G.apply(4, a[:, :n]))     # G_z = [G, 0]
    assert augment(rom, None) is rom and noise_covariance(np.eye(3), None).shape == (3, 3)


# ------------------------------------------------------------------ the LQR
@pytest.mark.parametrize("kind", ["input", "output"])
def test_augmented_lqr_is_the_riccati_of_the_augmented_model(kind):
    _, rom, dist = random_case(kind)
    N, n, n_u, n_d = rom.n_steps, rom.n, rom.n_u, dist.n_d
    Q = output_weights(rom.C, np.linspace(0.1, 1.0, N + 1))
    R = 0.05 * np.eye(n_u)
    K_a, S_a = tv_lqr(rom.A, rom.B, Q, R)
    K, S = augmented_lqr(rom.A, rom.B, cross_input(rom, dist), K_a, S_a, R)
    z = augment(rom, dist)
    Kz, Sz = tv_lqr(z.A, z.B, np.pad(Q, ((0, 0), (0, n_d), (0, n_d))), R)
    np.testing.assert_array_equal(K[:, :, :n], K_a)            # the ROM's gain, bit for bit
    np.testing.assert_allclose(K, Kz, rtol=1e-9, atol=1e-12 * np.abs(Kz).max())
    np.testing.assert_allclose(S, Sz, rtol=1e-9, atol=1e-12 * np.abs(Sz).max())
    if kind == "output":
        assert np.all(K[:, :, n:] == 0.0)                      # a sensor bias is never acted on


def test_the_design_cancels_an_input_bias_nearly_and_keeps_the_rom_gain(design):
    d = design
    n, E = d.n_r, d.disturbance.map
    plain = design_lqg(d.rom, d.problem)
    np.testing.assert_array_equal(d.lqg.K[:, :, :n], plain.K)
    np.testing.assert_array_equal(d.lqg.rom.A, d.rom.A)
    # K_d ~ -E: the input moves against the estimated bias, by 95-100 % in the band window
    k0, k1 = d.problem.window
    ratio = np.einsum("ui,kuj->kij", -E, d.lqg.K[k0:k1, :, n:])
    diag = np.diagonal(ratio, axis1=1, axis2=2)
    assert np.all(diag > 0.9) and np.all(diag < 1.02), diag.min()
    # the MPC's terminal weight is the augmented cost-to-go: its unconstrained move is K_k z
    _, S, Q, _ = lqr_gains(d.rom, d.problem, d.disturbance)
    assert S.shape == Q.shape == (d.n_steps + 1, n + 5, n + 5) and np.all(Q[:, n:, :] == 0)


# ------------------------------------------------------------- offset-free tracking
def test_a_constant_input_bias_is_estimated_and_removed(design):
    """input_offset b on every run: dhat_N converges to E'b (E spans the inputs here) to within
    3 sigma of P_N (the spread over runs is that sigma), and the mean output offset at the end of
    the window is a small fraction of the plain LQG's."""
    d = design
    sc = d.scenario
    dd = with_disturbance(d, "input", std=0.2)          # a prior wide enough for this bias
    plain = with_disturbance(d, "none")
    b = np.array([0.1, -0.06, 0.04, 0.08, 0.0])
    truth = PerturbedPlant.around(sc.plant, input_offset=b.tolist())
    z, _ = closed_loop(dd, truth)
    n = d.n_r
    sd = np.sqrt(np.diag(dd.lqg.kf.P_post[-1])[n:])
    target = dd.disturbance.map.T @ b
    assert np.all(np.abs(z[:, n:].mean(axis=0) - target) <= 3 * sd), (z[:, n:].mean(axis=0), target, sd)
    assert np.all(z[:, n:].std(axis=0) < 2 * sd)                           # consistent with P
    offset = {name: np.linalg.norm(np.mean(simulate(truth, x, "rom_lqg", 1, 200).Y[:, -1] - d.nominal.y[-1], axis=0))
              for name, x in (("with", dd), ("plain", plain))}
    assert offset["with"] < 0.35 * offset["plain"], offset


def test_output_kind_removes_a_sensor_bias_from_the_estimate(design):
    d = design
    dd = with_disturbance(d, "output", std=2.0)
    plain = with_disturbance(d, "none")
    assert dd.disturbance.n_d == d.info.n_y and np.array_equal(dd.disturbance.map, np.eye(d.info.n_y))
    s = np.array([1.0, -0.5, 0.8, 0.0, -1.2])
    truth = PerturbedPlant.around(d.scenario.plant, sensor_bias=s.tolist())
    n, N = d.n_r, d.n_steps
    sd = np.sqrt(np.diag(dd.lqg.kf.P_post[-1])[n:])
    err = {}
    for name, x in (("with", dd), ("plain", plain)):
        z, xN = closed_loop(x, truth)
        if name == "with":
            assert np.all(np.abs(z[:, n:].mean(axis=0) - s) <= 3 * sd), (z[:, n:].mean(axis=0), sd)
        F_hat = d.nominal.field[N] + x.lqg.model.G.apply(N, z)
        err[name] = np.abs(np.mean(F_hat - truth.field(xN), axis=0)).max()
    assert err["with"] < 0.2 * err["plain"], err


def test_unbiased_plant_pays_little_for_the_disturbance_states(design):
    """Same runs on the model itself: the default disturbance states cost at most 1 % and keep the band."""
    d = design
    plain = with_disturbance(d, "none")
    sc = d.scenario
    a = simulate(sc.plant, d, "rom_lqg", 1, 100, keep_estimates=0, keep_trajectories=0).summary
    b = simulate(sc.plant, plain, "rom_lqg", 1, 100, keep_estimates=0, keep_trajectories=0).summary
    assert a["cost_mean"] <= 1.01 * b["cost_mean"] and a["in_band"] >= b["in_band"], (a["cost_mean"], b["cost_mean"])


# ------------------------------------------------------------------ the MPC
def test_mpc_with_limits_and_disturbance_estimates_never_violates_a_bound():
    sc = coarse_scenario(20, 40, u_min=0.0, u_max=0.6)
    d = cached_design(sc, **SETTINGS)
    assert d.lqg.n_d == 5
    lo, hi = sc.problem.limits(d.info.n_u)
    rng = np.random.default_rng(7)
    mpc = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=6)
    for k in range(0, d.n_steps, 3):
        z = rng.standard_normal((4, d.lqg.model.n))
        z[:, d.n_r:] *= 0.5                                  # large bias estimates: the bounds bind
        U, _ = mpc.command_batch(k, z)
        assert np.all(U >= lo) and np.all(U <= hi)
        Uf, _ = mpc.command_batch(k, z, fail=True)           # the fallback clip(ubar + K z)
        np.testing.assert_allclose(Uf, np.clip(d.nominal.u[k] + z @ d.lqg.K[k].T, lo, hi), rtol=0, atol=1e-14)
    assert mpc.stats.qp > 0
    truth = PerturbedPlant.around(sc.plant, input_offset=0.05)
    r = simulate(truth, d, "rom_mpc", 3, 20, keep_estimates=0, keep_trajectories=0, mpc={"horizon": 6})
    assert r.U.min() >= 0.0 and r.U.max() <= 0.6 and r.summary["mpc_qp_steps"] > 0


# ------------------------------------------------------------- the design's choice
def test_directions_are_the_step_gains_right_singular_vectors(design):
    d = design
    G = step_gain(d.rom, d.problem.window)
    E, S, note = input_directions(d.rom, d.problem.window)
    np.testing.assert_allclose(np.linalg.svd(G, compute_uv=False), S, rtol=1e-12)
    np.testing.assert_allclose(E.T @ E, np.eye(5), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(G @ E, axis=0), S, rtol=1e-10)
    assert note["detectable"] and note["kept"] == 5
    dist = d.disturbance
    np.testing.assert_allclose(np.abs(dist.map), np.abs(E), atol=1e-12)
    # the prior: 0.04 band / sqrt(S_i S_cl,i), recorded with its rule in the design's meta
    S_cl = np.array(dist.directions["closed_loop_gains"])
    np.testing.assert_allclose(dist.std0, 0.04 * d.problem.band / np.sqrt(S * S_cl), rtol=1e-12)
    assert np.all(dist.walk_std == 0.0)
    meta = d.meta["disturbance"]
    assert meta["kind"] == "input" and meta["n_d"] == 5 and "sqrt(S_i S_cl,i)" in meta["std0_rule"]
    assert meta["directions"]["singular_values"] == pytest.approx(list(S))
    # fewer directions: the largest singular values first
    E3, S3, _ = input_directions(d.rom, d.problem.window, 3)
    np.testing.assert_allclose(np.abs(E3), np.abs(E[:, :3]), atol=1e-10)
    labels = direction_labels(dist, d.info.input_names, d.info.output_names)
    assert len(labels) == 5 and labels[0].startswith("d_0 along ")


def test_settings_refuse_bad_disturbance_keys():
    with pytest.raises(ValueError, match="disturbance must be one of none, input, output"):
        DesignSettings(disturbance="state").check()
    with pytest.raises(ValueError, match="disturbance_std"):
        DesignSettings(disturbance_std=-0.1).check()
    with pytest.raises(ValueError, match="disturbance_walk_std"):
        DesignSettings(disturbance_walk_std=[0.1, float("nan")]).check()
    with pytest.raises(ValueError, match="disturbance_dims"):
        DesignSettings(disturbance_dims=0).check()
    with pytest.raises(ValueError, match="disturbance_dims = 6 > n_y = 5"):
        DesignSettings(disturbance_dims=6).check_plant_dims(9, 5)
    with pytest.raises(ValueError, match="disturbance_dims = 4 does not fit the input kind"):
        DesignSettings(disturbance_dims=4).check_plant_dims(3, 5)
    with pytest.raises(ValueError, match="disturbance_std has 2 values"):
        DesignSettings(disturbance_std=[0.1, 0.2]).check_plant_dims(9, 5)
    DesignSettings(disturbance_dims=3, disturbance_std=[0.1, 0.2, 0.3]).check_plant_dims(9, 5)
    assert DesignSettings.from_meta({"settings": {"n_r": 4}}).disturbance == "none"     # older files
    with pytest.raises(DisturbanceError, match="disturbance_std"):
        Disturbance("input", np.eye(2), np.array([-1.0, 1.0]), np.zeros(2))
    with pytest.raises(DisturbanceError, match="one of input, output, noise"):
        Disturbance("bias", np.eye(2), np.ones(2), np.zeros(2))


@pytest.mark.parametrize("args,key", [
    (["--disturbance-dims", "6"], "disturbance_dims"),
    (["--disturbance-std", "-1"], "disturbance_std"),
    (["--disturbance-walk-std", "-0.5"], "disturbance_walk_std"),
    (["--disturbance", "state"], "--disturbance"),
])
def test_design_command_refuses_bad_disturbance_settings(tmp_path, capsys, args, key):
    from sep_control.cli.main import main

    scen = tmp_path / "tiny.yaml"
    scen.write_text(TINY_YAML)
    with pytest.raises(SystemExit) as exc:
        main(["design", "--scenario", str(scen), "--out", str(tmp_path / "d.npz"), "--quiet", *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "sep design: error:" in err and key in err, err
    assert not (tmp_path / "d.npz").exists()


def test_design_command_exits_2_on_a_disturbance_error_inside_the_design(tmp_path, capsys, monkeypatch):
    """A DisturbanceError raised by the design itself (e.g. no input direction detectable once the ROM
    is known) gave a traceback and exit 1 in 0.8.0."""
    from sep_control.cli import design as design_cli
    from sep_control.cli.main import main

    def refuse(*args, **kwargs):
        raise DisturbanceError("the ROM's step gain is zero over the band window: no input disturbance is "
                               "detectable; use disturbance: output or none")

    monkeypatch.setattr(design_cli, "run_design", refuse)
    scen = tmp_path / "tiny.yaml"
    scen.write_text(TINY_YAML)
    with pytest.raises(SystemExit) as exc:
        main(["design", "--scenario", str(scen), "--out", str(tmp_path / "d.npz"), "--quiet", "--disturbance", "input"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "sep design: error: the disturbance model does not fit this plant: the ROM's step gain is zero" in err
    assert "Traceback" not in err and not (tmp_path / "d.npz").exists()


def test_scenario_design_section_refuses_an_unknown_kind(tmp_path, capsys):
    from sep_control.cli.main import main

    scen = tmp_path / "tiny.yaml"
    scen.write_text(TINY_YAML + "design:\n  disturbance: sensor\n")
    with pytest.raises(SystemExit) as exc:
        main(["design", "--scenario", str(scen), "--out", str(tmp_path / "d.npz"), "--quiet"])
    assert exc.value.code == 2 and "disturbance must be one of none, input, output" in capsys.readouterr().err


def test_design_command_writes_the_chosen_disturbance_model(tmp_path, capsys):
    from sep_control.cli.main import main

    scen = tmp_path / "tiny.yaml"
    scen.write_text(TINY_YAML + "design:\n  p: 5\n  q: 5\n  n_r: 8\n  ensemble: 20\n  belief: false\n")
    out = tmp_path / "d.npz"
    assert main(["design", "--scenario", str(scen), "--out", str(out), "--disturbance", "output",
                 "--disturbance-std", "0.3"]) == 0
    text = capsys.readouterr()
    assert "disturbance states       output, n_d = 5" in text.out
    assert "disturbance states: output, n_d = 5; F = I" in text.err
    d = load_design(out)
    assert d.disturbance.kind == "output" and np.all(d.disturbance.std0 == 0.3)
    assert d.meta["settings"]["disturbance"] == "output" and d.meta["disturbance"]["n_d"] == 5
    assert d.lqg.K.shape[2] == d.n_r + 5 and np.all(d.lqg.K[:, :, d.n_r:] == 0.0)


# ------------------------------------------------------------------ design files
def test_version_4_round_trip_with_disturbance_states(design, tmp_path):
    d = design
    back = load_design(save_design(tmp_path / "d.npz", d), expect_scenario=d.scenario)
    dist, got = d.disturbance, back.disturbance
    assert back.meta["version"] == VERSION and back.meta["n_r"] == d.n_r and back.n_r == d.n_r
    assert back.meta["disturbance"] == d.meta["disturbance"] == dist.record()
    np.testing.assert_array_equal(got.map, dist.map)
    np.testing.assert_array_equal(got.std0, dist.std0)
    np.testing.assert_array_equal(got.walk_std, dist.walk_std)
    arrays = arrays_of(back)
    assert arrays["A"].shape[1] == d.n_r and arrays["K"].shape[2] == d.n_r + 5
    for name in ("A", "B", "C", "K", "dist_map"):
        np.testing.assert_array_equal(arrays[name], arrays_of(d)[name])
    np.testing.assert_array_equal(back.lqg.model.A, d.lqg.model.A)
    np.testing.assert_array_equal(back.lqg.model.P0, d.lqg.model.P0)
    np.testing.assert_array_equal(back.lqg.kf.P_prior, d.lqg.kf.P_prior)
    np.testing.assert_array_equal(back.lqg.W, d.lqg.W)
    assert back.rom.n == d.n_r and back.lqg.model.n == d.n_r + 5
    # the same closed loop from the file
    a = simulate(d.scenario.plant, d, "rom_lqg", 2, 5).summary["cost_mean"]
    assert simulate(d.scenario.plant, back, "rom_lqg", 2, 5).summary["cost_mean"] == a


@pytest.mark.parametrize("edit,arrays,match", [
    (None, {"dist_map": None}, "missing arrays \\['dist_map'\\]"),
    (None, {"dist_std0": np.ones(4)}, "dist_std0 has shape"),
    (None, {"dist_walk_std": np.full(5, np.nan)}, "dist_walk_std is not finite"),
    (None, {"dist_std0": -np.ones(5)}, "bad disturbance states"),
    (None, {"dist_map": np.ones((5, 5), dtype=np.float32)}, "dist_map is not finite float64"),
    (lambda m: {**m, "disturbance": {**m["disturbance"], "kind": "state"}}, {}, "disturbance kind"),
    (lambda m: {**m, "disturbance": {**m["disturbance"], "n_d": 6}}, {}, "n_d must be an integer in 1..n_y"),
    (lambda m: {k: v for k, v in m.items() if k != "disturbance"}, {}, "disturbance kind"),
    (lambda m: {**m, "disturbance": {"kind": "none", "n_d": 0}}, {}, "array K has shape"),
])
def test_version_4_members_are_checked(design, tmp_path, edit, arrays, match):
    path = save_design(tmp_path / "d.npz", design)
    with pytest.raises(DesignFileError, match=match):
        load_design(rewrite_design_file(path, tmp_path / "bad.npz", edit, **arrays))


def test_older_versions_read_as_kind_none(design, tmp_path):
    """A version 3 file (no disturbance record, gains on n_r) loads with no disturbance states;
    saved again it is a version 4 file of kind none."""
    plain = with_disturbance(design, "none")
    path = save_design(tmp_path / "plain.npz", plain)
    v3 = rewrite_design_file(path, tmp_path / "v3.npz", lambda m: {k: v for k, v in m.items() if k != "disturbance"}
                  | {"version": 3})
    d = load_design(v3)
    assert d.disturbance is None and d.lqg.n_d == 0 and d.lqg.model is d.rom
    assert d.meta["disturbance"] == {"kind": "none", "n_d": 0}
    np.testing.assert_array_equal(d.lqg.K, plain.lqg.K)
    back = load_design(save_design(tmp_path / "again.npz", d))
    assert back.meta["version"] == VERSION and back.meta["disturbance"]["kind"] == "none"
