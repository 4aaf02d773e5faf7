"""The field-weighted LQR/MPC (problem key lqr_weighting: field) and the noise disturbance kind.

* Q_k = G_k' Q_f,k G_k on the design's (compressed) field map: the gains are the TV-LQR of that
  weight written out densely, mean or sum over the nodes; the ROM-MPC's unconstrained first move
  is that law (with disturbance states too), so the online cost per step is today's;
* the problem keys are checked; design files of version 5 keep the weighting and the noise
  kind, version-4 files read with the output weighting;
* the noise kind: z = [a; d], a_{k+1} = A a + B du + B_w E_w d; on a model whose noise enters
  through the inputs it IS the input kind (same map, prior and gains); with channels of its own
  it estimates and removes a distributed constant source the input kind cannot explain;
* the slab's optional keys: source and noise channels of its own (the reference unchanged).
"""
from dataclasses import replace

import numpy as np
import pytest

from core_helpers import coarse_scenario, rewrite_design_file
from sep_control.control.mpc import RomMPC
from sep_control.design.gains import design_lqg, lqr_gains, state_weights, tv_lqr
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.oracle import oracle_lqg
from sep_estimator.design_file import VERSION, DesignFileError, load_design, problem_mismatches, save_design
from sep_estimator.disturbance import augment, choose, cross_input
from sep_plant.plants.slab import SlabPlant
from sep_plant.problem import Problem, ProblemError
from sep_plant.scenario import Scenario
from sep_plant.truth import truth_plant

FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1)
FORCED = dict(n_x=30, noise_centers=[0.2, 0.5, 0.8], noise_sigma=0.15, sensor_positions=[0.2, 0.4, 0.6, 0.8])


def forced_scenario(**problem) -> Scenario:
    """The coarse slab (30 nodes, 80 steps) with three noise channels of its own, four sensors."""
    base = coarse_scenario(30, 80)
    sc = base.with_plant(**{k: v for k, v in FORCED.items() if k != "n_x"})
    return replace(sc, problem=sc.problem.replace(**problem))


@pytest.fixture(scope="module")
def field_design():
    sc = coarse_scenario(20, 40)
    p = sc.problem.replace(lqr_weighting="field")
    return sc, run_design(sc.plant, p, DesignSettings(**FAST), show_progress=False, log=lambda m: None)


@pytest.fixture(scope="module")
def forced():
    sc = forced_scenario(band=1.5, lqr_weighting="field")
    st = DesignSettings(**FAST)
    out = {k: run_design(sc.plant, sc.problem, replace(st, disturbance=k), show_progress=False, log=lambda m: None)
           for k in ("input", "noise")}
    return sc, out


# ------------------------------------------------------------------ the weight
def test_problem_keys_and_weights():
    p = Problem(lqr_weighting="field", lqr_k_switch=10, n_steps=40, band_window=(20, 40))
    w = p.lqr_field_weights(8)
    np.testing.assert_allclose(w[:10], 0.1 / 8)
    np.testing.assert_allclose(w[10:], 1.0 / 8)
    np.testing.assert_allclose(p.replace(lqr_field_nodes="sum").lqr_field_weights(8), 8 * w)
    obj = p.replace(lqr_field_time="objective", lqr_field_nodes="sum").lqr_field_weights(8)
    np.testing.assert_array_equal(obj, p.q_weights())
    for key in ("lqr_weighting", "lqr_field_nodes", "lqr_field_time"):
        with pytest.raises(ProblemError, match=key):
            Problem(**{key: "nodes"})
    assert Problem.from_dict({}).lqr_weighting == "output"
    assert "lqr_weighting" not in Problem().to_dict()              # a default problem's dict is sep 0.8's
    assert Problem.from_dict(p.to_dict()) == p


def test_gains_are_the_tv_lqr_of_the_field_weight_on_the_design_map(field_design):
    sc, d = field_design
    rom, p = d.lqg.rom, d.problem
    assert p.lqr_weighting == "field"
    N, nf = rom.n_steps, rom.G.n_field
    q = p.lqr_field_weights(nf)
    Q = np.stack([q[k] * rom.G.matrix(k).T @ rom.G.matrix(k) for k in range(N + 1)])      # dense G' Q_f G
    np.testing.assert_allclose(state_weights(rom, p), Q, rtol=1e-10, atol=1e-14 * np.abs(Q).max())
    K, _ = tv_lqr(rom.A, rom.B, Q, p.lqr_r * np.eye(rom.n_u))
    Kd = lqr_gains(rom, p, d.disturbance)[0]
    np.testing.assert_allclose(Kd[:, :, :rom.n], K, rtol=1e-8, atol=1e-10 * np.abs(K).max())
    np.testing.assert_array_equal(d.lqg.K, Kd)        # designed on the map the file keeps
    # the sum over the nodes is the mean's weight times n_field: the same gains as q n_field
    Ks = lqr_gains(rom, p.replace(lqr_field_nodes="sum"))[0]
    Km = lqr_gains(rom, p.replace(lqr_q_late=p.lqr_q_late * nf, lqr_q_early=p.lqr_q_early * nf))[0]
    np.testing.assert_allclose(Ks, Km, rtol=1e-9, atol=1e-12 * np.abs(Km).max())
    assert not np.allclose(lqr_gains(rom, p.replace(lqr_weighting="output"))[0], K)


def test_mpc_first_move_is_the_field_weighted_law_at_the_same_qp_size(field_design):
    sc, d = field_design
    mpc = RomMPC(d.lqg, d.problem, d.nominal.u, horizon=8)
    out = RomMPC(replace(d, lqg=design_lqg(d.rom, d.problem.replace(lqr_weighting="output"),
                                           d.disturbance).lqg()).lqg, d.problem.replace(lqr_weighting="output"),
                 d.nominal.u, horizon=8)
    assert mpc.P.shape == out.P.shape and mpc.F.shape == out.F.shape      # the QP keeps its size
    rng = np.random.default_rng(0)
    for k in (0, 7, 20, 35, 39):
        z = rng.standard_normal(d.lqg.model.n)
        u, _ = mpc.command(k, z)
        np.testing.assert_allclose(u, d.nominal.u[k] + d.lqg.K[k] @ z, rtol=0, atol=1e-10)


def test_design_file_keeps_the_weighting_and_older_files_read_as_output(field_design, tmp_path):
    sc, d = field_design
    path = save_design(tmp_path / "f.npz", d)
    back = load_design(path)
    assert back.meta["version"] == VERSION >= 5 and back.problem.lqr_weighting == "field"
    np.testing.assert_array_equal(back.lqg.K, d.lqg.K)
    mpc = RomMPC(back.lqg, back.problem, back.nominal.u, horizon=6)      # the loaded map, the same law
    z = np.random.default_rng(3).standard_normal(back.lqg.model.n)
    np.testing.assert_allclose(mpc.command(12, z)[0], back.nominal.u[12] + back.lqg.K[12] @ z, atol=1e-10)

    def v4(m):
        m = {**m, "version": 4}
        sc_ = {k: v for k, v in m["scenario"].items() if not k.startswith(("lqr_weighting", "lqr_field"))}
        return {**m, "scenario": sc_}
    old = load_design(rewrite_design_file(path, tmp_path / "v4.npz", v4))
    assert old.problem.lqr_weighting == "output"
    assert problem_mismatches(d.problem, old.problem) == ["problem.lqr_weighting: 'field' != 'output'"]
    assert problem_mismatches(old.problem, d.problem) == ["problem.lqr_weighting: 'output' != 'field'"]
    noise4 = rewrite_design_file(path, tmp_path / "n4.npz",
                                 lambda m: {**v4(m), "disturbance": {**m["disturbance"], "kind": "noise"}})
    with pytest.raises(DesignFileError, match="needs format version 5"):
        load_design(noise4)


# -------------------------------------------------------------- the noise kind
def test_noise_kind_on_inputs_is_the_input_kind(field_design):
    sc, d = field_design
    rom, p = d.lqg.rom, d.problem
    assert rom.Bw is None
    K = lqr_gains(rom, p)[0]
    a = choose(rom, "input", p.band, p.window, K=K)
    n = choose(rom, "noise", p.band, p.window, K=K, noise_std=np.full(rom.n_u, 0.3))
    assert n.kind == "input" and n.directions["asked_kind"] == "noise"
    np.testing.assert_array_equal(n.map, a.map)
    np.testing.assert_array_equal(n.std0, a.std0)
    st = replace(DesignSettings(**FAST), disturbance="noise")
    np.testing.assert_array_equal(design_lqg(rom, p, st.disturbance_for(rom, p)).K, design_lqg(rom, p, a).K)


def test_noise_kind_acts_through_the_noise_channels(forced):
    sc, designs = forced
    d = designs["noise"]
    dist, rom = d.disturbance, d.lqg.rom
    assert dist.kind == "noise" and rom.Bw is not None and dist.map.shape == (3, dist.n_d)
    assert dist.n_d == min(sc.info.n_y, 3) and dist.directions["detectable"]
    np.testing.assert_allclose(dist.map.T @ dist.map, np.eye(dist.n_d), atol=1e-12)
    np.testing.assert_array_equal(cross_input(rom, dist), rom.Bw @ dist.map)
    z = augment(rom, dist)
    np.testing.assert_array_equal(z.A[:, :rom.n, rom.n:], rom.Bw @ dist.map)
    np.testing.assert_array_equal(z.C[:, :, rom.n:], 0.0)
    # the oracle, like for like: the same directions through its full-order noise channels, and
    # the same field weighting on its own (identity) field map
    orc = oracle_lqg(d, sc.plant)
    assert orc.disturbance is dist and orc.model.n == sc.info.n_x + dist.n_d
    full = orc.rom
    np.testing.assert_allclose(orc.model.A[:, :full.n, full.n:], full.Bw @ dist.map)
    Kf = lqr_gains(full, d.problem, dist)[0]
    np.testing.assert_array_equal(orc.K, Kf)
    q = d.problem.lqr_field_weights(sc.info.n_field)
    np.testing.assert_allclose(state_weights(full, d.problem), q[:, None, None] * np.eye(sc.info.n_x)[None])
    # prior: a forcing of one step's noise std along each direction
    np.testing.assert_allclose(dist.std0, np.linalg.norm(sc.problem.channels("w_std", 3)[:, None] * dist.map, axis=0))


def test_noise_kind_removes_a_distributed_source_better_than_the_input_kind(forced, tmp_path):
    """On the forced truth the noise kind keeps at least the input kind's in band at a lower cost,
    and its estimate of the forcing E_w d_hat points along the uniform source (200 runs)."""
    sc, designs = forced
    truth = truth_plant(sc, {"source": 0.3}, {})
    m = {k: simulate(truth.plant, d, "rom_lqg", 1, 200, keep_estimates=0, keep_trajectories=0).metrics()
         for k, d in designs.items()}
    assert m["noise"]["in_band"] >= m["input"]["in_band"] and m["noise"]["cost_mean"] < m["input"]["cost_mean"]
    back = load_design(save_design(tmp_path / "n.npz", designs["noise"]))
    assert back.disturbance.kind == "noise"
    np.testing.assert_array_equal(back.lqg.K, designs["noise"].lqg.K)


# --------------------------------------------------------------------- the slab
def test_slab_source_and_own_noise_channels():
    ref = SlabPlant()
    assert "source" not in ref.config() and ref.noise_on_inputs
    own = SlabPlant(noise_centers=[0.25, 0.75], noise_sigma=0.2, source=0.5)
    assert not own.noise_on_inputs and own.n_w == 2 and own.config()["source"] == 0.5
    x = np.full((3, own.n_x), 120.0)
    u = np.full((3, own.n_u), 0.2)
    w = np.random.default_rng(0).standard_normal((3, 2))
    lin = SlabPlant(noise_centers=[0.25, 0.75], noise_sigma=0.2)
    # the step is linear in the forcing: source and w enter as dt (s + e(x) w) on the right-hand side
    base = lin.step(x, u)
    h = 1e-3
    dw = (lin.step(x, u, h * w) - base) / h
    src = (SlabPlant(noise_centers=[0.25, 0.75], noise_sigma=0.2, source=h).step(x, u) - base) / h
    assert np.all(src > 0) and np.all(np.abs(dw) > 0)
    np.testing.assert_allclose(own.step(x, u, w), base + 0.5 * src + dw, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(ref.step(x, u, w[:, :1].repeat(5, 1)),
                                  SlabPlant(source=0.0).step(x, u + w[:, :1].repeat(5, 1)))
