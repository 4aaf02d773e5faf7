"""Experiment plan 0.9's ways to spend fewer run-steps: strided impulses (`impulse_stride`), the
settle stop of the nominal optimizer, the optimizer's models of the inputs only, and the
pre-work estimate of plan 0.9's run-steps."""
from __future__ import annotations

import numpy as np
import pytest

from rd_plant import ReactionDiffusionPlant
from sep_control.design.impulse import (experiment_run_steps, impulse_experiments, interpolate_starts,
                                        strided_starts)
from sep_control.design.jacobians import SensitivityJacobian
from sep_control.design.optimizer import Optimizer, OptimizerOptions
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.plan import design_plan
from sep_control.design.runsteps import RunStepMeter, metered
from sep_control.design.tvera import identify, markov_relative_error
from sep_plant.problem import Problem
from sep_plant.scenario import reference


def test_strided_starts_hold_the_first_and_last_step():
    assert strided_starts(7, 2).tolist() == [0, 2, 4, 6]
    assert strided_starts(8, 3).tolist() == [0, 3, 6, 7]
    assert strided_starts(5, 1).tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="impulse stride"):
        strided_starts(5, 0)


def test_interpolation_between_start_steps_is_exact_for_a_linear_trend():
    j = np.arange(11, dtype=float)
    Z = (3.0 + 0.5 * j)[:, None, None] * np.ones((1, 2, 3))
    starts = strided_starts(11, 3)                   # 0, 3, 6, 9, 10
    holes = Z.copy()
    holes[np.setdiff1d(np.arange(11), starts)] = 0.0  # what the strided experiments leave
    np.testing.assert_allclose(interpolate_starts(holes, starts), Z, rtol=1e-14)


def test_strided_experiments_impulse_every_stride_th_step_and_count_their_runs():
    plant = reference().with_plant(n_x=20).plant
    N, lags, delta = 21, 6, 1e-3
    U = 0.2 + 0.05 * np.sin(np.arange(N) / 4.0)[:, None] * np.ones((1, plant.n_u))
    full = impulse_experiments(plant, U, lags, 3, delta, scheme="forward", chunks=2)
    for stride in (2, 3, 4):                         # lags a multiple of the stride or not
        meter = RunStepMeter()
        data = impulse_experiments(metered(plant, meter), U, lags, 3, delta, scheme="forward", chunks=2,
                                   stride=stride)
        starts = strided_starts(N, stride)
        # the experiments of the start steps only, each run stepped `lags` times, and the nominal
        assert meter.total == experiment_run_steps(len(starts), plant.n_u, lags, "forward") + N + lags
        assert data.experiments == len(starts) * plant.n_u
        # at the start steps the experiments' own Markov parameters (the batch differs: round-off)
        np.testing.assert_allclose(data.Y[starts], full.Y[starts], rtol=1e-6, atol=1e-9 * np.abs(full.Y).max())
        # between them interpolated: close on a smooth nominal, not equal
        err = np.linalg.norm(data.Y - full.Y) / np.linalg.norm(full.Y)
        assert 0 < err < 2e-2 * stride**2
        np.testing.assert_allclose(data.Yf, full.Yf, atol=5e-2 * stride**2 * np.abs(full.Yf).max())


def test_a_strided_identification_records_its_stride_and_fits_its_markov_parameters():
    plant = reference().with_plant(n_x=20).plant
    U = np.full((30, plant.n_u), 0.2)
    ident = identify(plant, U, 4, 4, 8, scheme="forward", stride=2)
    assert ident.stride == 2 and ident.data.experiments == len(strided_starts(30, 2)) * plant.n_u
    every = identify(plant, U, 4, 4, 8, scheme="forward")
    # the model fits the true Markov parameters about as well as the one from every start step
    # (p = q = 4 limits both: 2.6e-2 here)
    own = markov_relative_error(every.model, every.data.Y)
    assert markov_relative_error(ident.model, every.data.Y) < 1.05 * own


def test_impulse_stride_is_a_plan_key_and_is_checked():
    assert DesignSettings(experiment_plan="0.8").impulse_stride == 1
    assert DesignSettings().impulse_stride == 2                          # the default plan, 0.9
    assert DesignSettings(experiment_plan="0.9").impulse_stride == 2
    assert DesignSettings(experiment_plan="0.9", impulse_stride=1).impulse_stride == 1
    assert DesignSettings.from_meta({"settings": {}}).impulse_stride == 1      # files before the key
    for bad in (0, True, 1.5):
        with pytest.raises(ValueError, match="impulse_stride"):
            DesignSettings(impulse_stride=bad).check()


def test_field_tol_is_a_plan_key_reaches_the_identifications_and_is_checked():
    assert DesignSettings(experiment_plan="0.8").field_tol == 1e-8       # 0.8.0's tolerance
    assert DesignSettings().field_tol == 1e-6
    assert DesignSettings().rom().field_tol == 1e-6
    assert DesignSettings(experiment_plan="0.8").rom().field_tol == 1e-8
    assert DesignSettings(field_tol=1e-7).rom().field_tol == 1e-7
    assert DesignSettings.from_meta({"settings": {}}).field_tol == 1e-8       # files before the key
    assert DesignSettings.from_meta({"settings": {"experiment_plan": "0.9"}}).field_tol == 1e-8
    assert DesignSettings.from_meta({"settings": {"field_tol": 1e-6}}).field_tol == 1e-6
    for bad in (0.0, 1.0, -1e-6, float("nan")):
        with pytest.raises(ValueError, match="field_tol"):
            DesignSettings(field_tol=bad).check()


def test_a_scenario_writes_number_settings_as_yaml_reads_them(tmp_path):
    """YAML 1.1 reads 1e-6 (no dot) as a string: a scenario file reads it as the number (in every
    section), and a design setting that is no number is refused naming it."""
    from sep_plant.scenario import load_scenario

    path = tmp_path / "s.yaml"
    path.write_text("w_std: 1e-3\ndesign: {field_tol: 1e-6, sv_tol: 1e-9}\n")
    scen = load_scenario(path)
    st = DesignSettings.for_scenario(scen)
    assert st.field_tol == 1e-6 and st.sv_tol == 1e-9
    assert np.all(np.asarray(scen.problem.w_std) == 1e-3)
    path.write_text("design: {field_tol: tiny}\n")
    with pytest.raises(ValueError, match="field_tol must be a number"):
        DesignSettings.for_scenario(load_scenario(path))


def test_a_coarse_proposal_model_is_never_a_full_one():
    """With Hankel blocks of at most PLAN_PQ (p = q = 6) plan 0.9's proposal settings equal the
    design's but for the coarse mark: its models still count as proposals (the optimizer identifies
    a full model before it settles), the full settings' as full ones."""
    from dataclasses import replace as with_

    from core_helpers import flat
    from sep_control.design.stages import PROPOSAL_ROM

    s = flat(n_x=30, n_steps=12, k_band=8, lqr_k_switch=6)
    U = np.full((12, 5), 0.2)
    rom = with_(DesignSettings(p=3, q=3, n_r=4).rom(), inputs_only=True)
    proposal = with_(rom, **PROPOSAL_ROM)
    assert with_(proposal, coarse=False) == rom                   # the same settings but the mark
    coarse, full = proposal.identify(s.plant, U), rom.identify(s.plant, U)
    assert coarse.coarse and not coarse.made_with(rom.scheme, rom.field_tol, rom.p, rom.q, noise=False)
    assert not full.coarse and full.made_with(rom.scheme, rom.field_tol, rom.p, rom.q, noise=False)


def test_settle_stop_takes_the_step_and_ends_the_run():
    scen = reference().with_plant(n_x=20)
    problem = scen.problem.replace(n_steps=24, band_window=None, lqr_k_switch=None)
    runs = {}
    for settle in (0.0, 0.5):
        opts = OptimizerOptions(max_iter=8, settle=settle, show_progress=False)
        runs[settle] = Optimizer(scen.plant, problem, opts, SensitivityJacobian()).run()
    free, settled = runs[0.0], runs[0.5]
    assert settled.stop.startswith("settled")
    h = settled.history
    rel = [(a - b) / a for a, b in zip(h[:-1], h[1:])]
    assert rel[-1] < 0.5 and all(r >= 0.5 for r in rel[:-1])     # stopped at the first small decrease
    assert settled.iterations < free.iterations
    assert h[-1] == settled.cost                                    # the small step was taken


def test_settle_stop_waits_for_the_nominal_to_be_within_its_band():
    """A small decrease does not end the run while the nominal's field is out of its band: with
    a band no input reaches, the settle stop never fires and the run is the one without it."""
    scen = reference().with_plant(n_x=20)
    problem = scen.problem.replace(n_steps=24, band_window=None, lqr_k_switch=None)
    runs = {}
    for band, settle in ((1e-6, 0.0), (1e-6, 0.5), (1e3, 0.5)):
        opts = OptimizerOptions(max_iter=8, settle=settle, show_progress=False)
        runs[band, settle] = Optimizer(scen.plant, problem.replace(band=band), opts, SensitivityJacobian()).run()
    free, waited, settled = runs[1e-6, 0.0], runs[1e-6, 0.5], runs[1e3, 0.5]
    assert not waited.stop.startswith("settled") and waited.history == free.history
    assert settled.stop.startswith("settled") and settled.iterations < waited.iterations


def _rd_problem(N: int) -> Problem:
    return Problem(n_steps=N, target=0.3, band=0.05, w_std=0.003, v_std=0.02, u_init=0.2, r_u=0.01)


def test_inputs_only_models_skip_the_noise_channels():
    plant = ReactionDiffusionPlant(n_x=41, noise_modes=8, diffusion=0.002)
    U = np.full((20, plant.n_u), 0.2)
    meter = RunStepMeter()
    ident = identify(metered(plant, meter), U, 4, 4, 8, scheme="forward", inputs_only=True)
    assert ident.inputs_only and ident.model.Bw is None and ident.data.Y.shape[-1] == plant.n_u
    assert meter.total == experiment_run_steps(20, plant.n_u, 8, "forward") + 20 + 8
    assert not ident.made_with("forward") and ident.made_with("forward", noise=False)
    # a plant whose noise is on its inputs has nothing to skip: the same model as without the flag
    slab = reference().with_plant(n_x=20).plant
    Us = np.full((20, slab.n_u), 0.2)
    a = identify(slab, Us, 4, 4, 8, inputs_only=True)
    b = identify(slab, Us, 4, 4, 8)
    assert not a.inputs_only and np.array_equal(a.model.A, b.model.A)


def test_plan_09_design_of_a_noisy_plant_identifies_its_noise_channels_once():
    plant = ReactionDiffusionPlant(n_x=41, noise_modes=8, diffusion=0.002)
    st = DesignSettings(experiment_plan="0.9", p=5, q=5, n_r=8, max_iter=4, belief=False)
    lines: list[str] = []
    d = run_design(plant, _rd_problem(30), st, show_progress=False, log=lines.append)
    assert d.lqg.rom.Bw is not None and d.lqg.rom.Bw.shape[2] == 8          # the design's model has B_w
    assert any("one start step in 2" in m for m in lines)                   # the log says what it traded
    assert d.meta["settings"]["impulse_stride"] == 2


@pytest.mark.parametrize("plan", ["0.8", "0.9"])
def test_the_plan_estimate_follows_the_chosen_plan(plan):
    scen = reference().with_plant(n_x=20)
    st = DesignSettings(experiment_plan=plan, n_r=8).for_plant(scen.plant)
    d = run_design(scen.plant, scen.problem, st, show_progress=False, log=lambda m: None)
    estimate = design_plan(scen.plant, scen.problem, st)["run_steps"]["total"]
    spent = d.meta["run_steps"]["total"]
    assert 0.6 * spent < estimate < 1.6 * spent, (estimate, spent)


def test_plan_09_default_spends_under_a_quarter_of_plan_08_on_a_small_reference():
    scen = reference().with_plant(n_x=20)
    spent = {plan: run_design(scen.plant, scen.problem, DesignSettings(experiment_plan=plan, n_r=8),
                              show_progress=False, log=lambda m: None).meta["run_steps"]["total"]
             for plan in ("0.8", "0.9")}
    assert spent["0.9"] < spent["0.8"] / 3
