"""The stride check (`sep_control.design.stride_check`): does a strided identification resolve the
ROM's kept states, and a final model from every start step where it does not."""
from __future__ import annotations

import numpy as np

from sep_control.design import stages, stride_check
from sep_control.design.impulse import hold_starts, interpolate_starts, strided_starts
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.stride_check import interpolation_error, resolved_share
from sep_control.design.tvera import identify
from sep_plant.scenario import reference


def test_the_interpolation_error_estimate_is_exact_for_a_quadratic_trend():
    j = np.arange(13, dtype=float)
    Z = (1.0 + 0.3 * j - 0.05 * j**2)[:, None, None] * np.ones((1, 2, 4))
    starts = strided_starts(13, 3)                    # 0, 3, 6, 9, 12
    lin = interpolate_starts(Z, starts)
    np.testing.assert_allclose(interpolation_error(lin, starts), Z - lin, atol=1e-12)
    # a sketch's held channels are left out (their start steps' responses are to other combinations)
    held = np.concatenate([lin[..., :2], hold_starts(Z, starts)[..., 2:]], axis=-1)
    E = interpolation_error(held, starts, held=2)
    np.testing.assert_allclose(E[..., :2], (Z - lin)[..., :2], atol=1e-12)
    assert not np.any(E[..., 2:])
    assert not np.any(interpolation_error(lin, strided_starts(13, 1)))      # every start step: none


def test_a_time_invariant_plant_is_resolved_and_every_start_step_needs_no_check():
    plant = reference().with_plant(n_x=20).plant
    U = np.full((30, plant.n_u), 0.0)                  # from rest, no input: the linearization holds still
    ident = identify(plant, U, 4, 4, 8, scheme="forward", stride=2)
    assert resolved_share(ident) == 1.0
    assert resolved_share(identify(plant, U, 4, 4, 8, scheme="forward")) == 1.0


def test_the_design_identifies_its_final_model_again_where_the_stride_does_not_resolve_it(monkeypatch):
    scen = reference().with_plant(n_x=20)
    st = DesignSettings(experiment_plan="0.9", n_r=8)
    kept = run_design(scen.plant, scen.problem, st, show_progress=False, log=lambda m: None)
    share = kept.meta["validation"]["stride_resolved_share"]
    assert 0.0 <= share <= 1.0 and share >= stride_check.RESOLVED_MIN
    monkeypatch.setattr(stages, "RESOLVED_MIN", 1.01)  # no strided model passes
    lines: list[str] = []
    again = run_design(scen.plant, scen.problem, st, show_progress=False, log=lines.append)
    assert any("identifying again with impulses at every start step" in m for m in lines)
    assert not again.meta["optimizer"]["identification_reused"]
    run = again.meta["run_steps"]
    assert run["identification"] > kept.meta["run_steps"]["identification"]
    # the same nominal; a model from every start step
    np.testing.assert_array_equal(again.nominal.u, kept.nominal.u)
    assert again.meta["validation"]["markov_rel_error"] < kept.meta["validation"]["markov_rel_error"]
