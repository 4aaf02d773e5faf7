"""Combinations of disturbance kinds (sep_estimator.disturbance: input+noise, noise+output,
input+output): d = [d_1; d_2], each part acting as its single kind does.

* the augmented model's blocks are the single kinds' blocks side by side (the same builders);
* the second part's directions leave the first part's output image out, so the stacked step gain
  has full column rank n_d (detectable together), n_d <= n_y;
* the budget split (default and given) and its refusals, in the settings and the CLI (exit 2);
* on a plant whose noise is on the inputs the noise part is the input kind;
* design file: a combination round trip (part_dims), refused in a version 4 file; lockstep of
  the Monte Carlo with the file's filter (the same closed loop from the file).
"""
import dataclasses

import numpy as np
import pytest
import yaml

from core_helpers import TINY_YAML, ltv_system, one_blas_thread, rewrite_design_file  # noqa: F401
from sep_control.bags.figures import disturbance_axis_label
from sep_control.design.gains import design_lqg
from sep_control.design.pipeline import run_design
from sep_control.design.settings import DesignSettings
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.design_file import DesignFileError, load_design, save_design
from sep_estimator.disturbance import (COMBINED, DisturbanceError, augment, choose, direction_labels,
                                       model_part_views, split_dims, step_gain)
from sep_estimator.ltv import DenseFieldMap, LTVModel
from sep_plant.scenario import Scenario

WINDOW = (10, 30)


def random_rom(seed=0, N=30, n=5, n_u=3, n_y=4, n_w=2, with_bw=True):
    rng = np.random.default_rng(seed)
    A, B, C, F = ltv_system(rng, N, n, n_u, n_y, 6)
    Bw = rng.standard_normal((N, n, n_w)) if with_bw else None
    return LTVModel(A=A, B=B, C=C, G=DenseFieldMap(F), dims=np.full(N + 1, n), Bw=Bw)


@pytest.mark.parametrize("kind", COMBINED)
def test_the_augmented_blocks_are_the_parts_blocks_side_by_side(kind):
    rom = random_rom()
    dist = choose(rom, kind, 1.0, WINDOW)
    z = augment(rom, dist)
    n, n1 = rom.n, dist.part_dims[0]
    assert dist.n_d == sum(dist.part_dims) <= rom.n_y and dist.part_dims == (2, 2)
    views = model_part_views(rom, dist)
    assert [v.kind for v in views] == kind.split("+")
    for v, cols in zip(views, (slice(n, n + n1), slice(n + n1, None))):
        single = augment(rom, v)                          # the single kind's augmented model
        np.testing.assert_array_equal(z.A[:, :n, cols], single.A[:, :n, n:])
        np.testing.assert_array_equal(z.C[:, :, cols], single.C[:, :, n:])
        np.testing.assert_array_equal(z.P0[cols, cols], single.P0[n:, n:])
    np.testing.assert_array_equal(z.A[:, n:, n:], np.broadcast_to(np.eye(dist.n_d), (rom.n_steps, 4, 4)))
    np.testing.assert_array_equal(z.B[:, n:], 0.0)


@pytest.mark.parametrize("kind", COMBINED)
def test_the_parts_are_detectable_together(kind):
    """The second part's directions are chosen with the first's output image projected out: its
    projected image (I - Q_1 Q_1') Gamma_2 E_2 has the recorded singular values (an output part:
    F orthogonal to Q_1); [Gamma_1 E_1, Gamma_2 E_2] has rank n_d (and the record says so)."""
    rom = random_rom(1)
    dist = choose(rom, kind, 1.0, WINDOW)
    images = [v.map if v.kind == "output" else step_gain(rom, WINDOW, kind=v.kind) @ v.map
              for v in model_part_views(rom, dist)]
    Q1 = np.linalg.qr(images[0])[0]
    second = model_part_views(rom, dist)[1]
    projected = images[1] - Q1 @ (Q1.T @ images[1])
    np.testing.assert_allclose(np.linalg.svd(projected, compute_uv=False),
                               second.directions["singular_values"][:second.n_d], rtol=1e-10)
    if second.kind == "output":
        np.testing.assert_allclose(Q1.T @ second.map, 0.0, atol=1e-12)
    assert np.linalg.matrix_rank(np.hstack(images)) == dist.n_d
    assert dist.directions["detectable"] is True and dist.directions["rank_gamma_E"] == dist.n_d
    for v in model_part_views(rom, dist):                # each part's directions orthonormal
        np.testing.assert_allclose(v.map.T @ v.map, np.eye(v.n_d), atol=1e-12)
    labels = direction_labels(dist, ["u0", "u1", "u2"], ["y0", "y1", "y2", "y3"])
    assert [s.split()[0] for s in labels] == ["d_0", "d_1", "d_2", "d_3"]


def test_the_budget_split_and_its_refusals():
    assert split_dims("noise+output", None, 4, [3, 4]) == (2, 2)
    assert split_dims("noise+output", None, 5, [1, 5]) == (1, 4)        # the first part capped by its channels
    assert split_dims("input+noise", [1, 3], 4, [5, 3]) == (1, 3)
    with pytest.raises(DisturbanceError, match="n_1 \\+ n_2 <= n_y = 4"):
        split_dims("noise+output", [3, 2], 4, [3, 4])
    with pytest.raises(DisturbanceError, match="list of two numbers"):
        split_dims("noise+output", 3, 4, [3, 4])
    with pytest.raises(DisturbanceError, match="the noise part has 2 channels"):
        split_dims("input+noise", [1, 3], 4, [3, 2])
    rom = random_rom(2)
    d = choose(rom, "noise+output", 1.0, WINDOW, dims=[1, 3], std=[0.1, 0.2, 0.3, 0.4])
    assert d.part_dims == (1, 3) and d.std0.tolist() == [0.1, 0.2, 0.3, 0.4]
    with pytest.raises(DisturbanceError, match="n_d = 4 numbers"):
        choose(rom, "noise+output", 1.0, WINDOW, std=[0.1, 0.2])
    st = DesignSettings(disturbance="noise+output", disturbance_dims=[3, 3])
    with pytest.raises(ValueError, match="n_1 \\+ n_2 <= n_y = 5"):
        st.check_plant_dims(5, 5)
    with pytest.raises(ValueError, match="two integers"):
        DesignSettings(disturbance="input+output", disturbance_dims=3).check()


def test_on_noise_through_the_inputs_the_noise_part_is_the_input_kind():
    rom = random_rom(3, with_bw=False)
    assert choose(rom, "input+noise", 1.0, WINDOW).kind == "input"
    d = choose(rom, "noise+output", 1.0, WINDOW, dims=[1, 3])
    assert d.kind == "input+output" and d.directions["asked_kind"] == "noise+output"
    e = choose(rom, "input+output", 1.0, WINDOW, dims=[1, 3])
    np.testing.assert_array_equal(d.map, e.map)


def test_the_figure_label_names_both_parts():
    assert disturbance_axis_label("noise+output") == "forcing (noise channels) / sensor bias"
    assert disturbance_axis_label("input") == "input bias" and disturbance_axis_label(None) == "d_hat"


@pytest.fixture(scope="module")
def forced_design():
    """A noise+output design on the tiny slab whose noise has channels of its own."""
    scn = Scenario.from_dict(yaml.safe_load(TINY_YAML)).with_plant(noise_centers=[0.25, 0.75], noise_sigma=0.2)
    st = DesignSettings(p=5, q=5, n_r=10, ensemble=20, belief=False, disturbance="noise+output")
    return run_design(scn.plant, scn.problem, st, show_progress=False, log=lambda m: None)


def test_design_file_round_trip_of_a_combination(forced_design, tmp_path, one_blas_thread):
    d = forced_design
    assert d.disturbance.kind == "noise+output" and d.disturbance.n_d <= d.info.n_y
    path = save_design(tmp_path / "d.npz", d)
    back = load_design(path, expect_scenario=d.scenario)
    assert back.meta["disturbance"]["part_dims"] == list(d.disturbance.part_dims)
    assert back.disturbance.part_dims == d.disturbance.part_dims
    np.testing.assert_array_equal(back.disturbance.map, d.disturbance.map)
    np.testing.assert_array_equal(back.lqg.model.A, d.lqg.model.A)
    np.testing.assert_array_equal(back.lqg.model.C, d.lqg.model.C)
    a = simulate(d.scenario.plant, d, "rom_lqg", 2, 5)
    b = simulate(d.scenario.plant, back, "rom_lqg", 2, 5)
    np.testing.assert_array_equal(a.U, b.U)
    # the design's gains are those of the augmented model of the file (one concept: design_lqg)
    again = design_lqg(back.rom, back.problem, back.disturbance)
    np.testing.assert_allclose(again.K, d.lqg.K, rtol=0, atol=1e-9 * np.abs(d.lqg.K).max())
    with pytest.raises(DesignFileError, match="needs format version 5"):
        load_design(rewrite_design_file(path, tmp_path / "v4.npz", lambda m: {**m, "version": 4}))


def test_design_command_takes_a_combination_and_refuses_a_bad_split(tmp_path, capsys):
    from sep_control.cli.main import main

    scen = tmp_path / "tiny.yaml"
    scen.write_text(TINY_YAML + "design:\n  p: 5\n  q: 5\n  n_r: 8\n  ensemble: 20\n  belief: false\n")
    out = tmp_path / "d.npz"
    with pytest.raises(SystemExit) as exc:
        main(["design", "--scenario", str(scen), "--out", str(out), "--quiet", "--disturbance", "input+output",
              "--disturbance-dims", "3", "3"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "sep design: error:" in err and "disturbance_dims [3, 3]" in err and not out.exists()
    assert main(["design", "--scenario", str(scen), "--out", str(out), "--disturbance", "input+output",
                 "--disturbance-dims", "2", "3"]) == 0
    text = capsys.readouterr()
    assert "disturbance states       input+output, n_d = 5" in text.out
    assert "detectable together yes" in text.err
    d = load_design(out)
    assert d.disturbance.part_dims == (2, 3) and d.meta["settings"]["disturbance_dims"] == [2, 3]
    assert np.all(d.lqg.K[:, :, d.n_r + 2:] == 0.0)          # the sensor-bias part is not acted on
    assert dataclasses.asdict(DesignSettings.from_meta(d.meta))["disturbance"] == "input+output"


def test_the_oracle_runs_the_same_combination(forced_design, one_blas_thread):
    """Like for like: the oracle's augmented full-order model has the same parts (noise directions
    through its full-order noise channels, the same sensor-bias directions) and the same priors."""
    from sep_control.evaluation.oracle import oracle_lqg

    d = forced_design
    dist, plant = d.disturbance, d.scenario.plant
    orc = oracle_lqg(d, plant)
    full, (noise, output) = orc.rom, model_part_views(d.rom, dist)
    n, n1 = full.n, dist.part_dims[0]
    assert orc.disturbance is dist and orc.model.n == n + dist.n_d
    np.testing.assert_allclose(orc.model.A[:, :n, n:n + n1], full.Bw @ noise.map)
    np.testing.assert_array_equal(orc.model.A[:, :n, n + n1:], 0.0)
    np.testing.assert_array_equal(orc.model.C[:, :, n:n + n1], 0.0)
    np.testing.assert_array_equal(orc.model.C[:, :, n + n1:], np.broadcast_to(output.map, orc.model.C[:, :, n + n1:].shape))
    np.testing.assert_array_equal(np.diag(orc.model.P0)[n:], dist.std0**2)
    assert np.isfinite(simulate(plant, d, "oracle_lqg", 1, 3, oracle=orc).summary["cost_mean"])
