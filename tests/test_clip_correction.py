"""The clip correction (sep_control.design.saturation, pipeline._with_clip_correction).

* the ROM Monte Carlo's gradient (one reverse pass) is the derivative of its cost, with box
  limits and with rate limits;
* the ROM Monte Carlo predicts the plant's closed-loop cost under the limits' clipping;
* a design with the correction moves the nominal inside the limits, records what the ROM
  predicted, and the plant's closed loop then costs less than without it; without input limits
  the correction does nothing (the design equals the one without it, array for array);
* the plans' defaults (off for 0.8, on for 0.9), the `--clip-correction` option and the pre-work
  plan's count of the extra pass.
"""
import dataclasses

import numpy as np
import pytest

from core_helpers import coarse_scenario, flat
from sep_control.cli.design import _on_off
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.plan import design_plan
from sep_control.design.saturation import ClosedLoopRom, RomClosedLoop, rate_violation
from sep_control.evaluation.montecarlo import simulate

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)
# heaters that only heat: the nominal holds some of them at 0, where half the feedback is cut off
LIMITS = dict(u_min=0.0, u_max=0.6)
# plan 0.8's experiments: the same designs with and without the correction (off unless asked)
FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1, experiment_plan="0.8")


def _design(sc, **kw):
    return run_design(sc.plant, sc.problem, DesignSettings(**FAST, **kw), show_progress=False,
                      log=lambda m: None)


@pytest.fixture(scope="module")
def limited():
    sc = coarse_scenario(30, 80, **LIMITS)
    return sc, _design(sc), _design(sc, clip_correction=True)


def _closed_loop(sc, d) -> ClosedLoopRom:
    return ClosedLoopRom.of(d.lqg, d.nominal.u, d.nominal.field, d.objective, sc.problem)


def _plant_cost(sc, d, runs=400) -> float:
    return simulate(sc.plant, d, "rom_lqg", 3, runs, keep_estimates=0, keep_trajectories=0).metrics()["cost_mean"]


@pytest.mark.parametrize("rate", [None, 0.05])
def test_the_reverse_pass_is_the_derivative_of_the_monte_carlo_cost(limited, rate):
    sc, d, _ = limited
    cl = _closed_loop(sc, d)
    if rate is not None:
        cl = dataclasses.replace(cl, du_max=np.full(cl.lo.shape, rate))
    mc = RomClosedLoop(cl, samples=32, seed=4)
    rng = np.random.default_rng(0)
    delta = 0.02 * rng.standard_normal(cl.u_nom.shape)
    J, g = mc.cost_and_gradient(delta)
    assert J == pytest.approx(mc.cost(delta), rel=1e-12)
    for _ in range(3):
        p = rng.standard_normal(delta.shape)
        h = 1e-7
        fd = (mc.cost(delta + h * p) - mc.cost(delta - h * p)) / (2 * h)
        assert np.sum(g * p) == pytest.approx(fd, rel=1e-4, abs=1e-9)


def test_the_rom_monte_carlo_predicts_the_plants_clipped_cost(limited):
    sc, d, _ = limited
    mc = RomClosedLoop(_closed_loop(sc, d), samples=400, seed=1)
    zero = np.zeros_like(d.nominal.u)
    clipped, free = mc.cost(zero), mc.cost(zero, limits=False)
    plant = _plant_cost(sc, d)
    assert clipped > 1.05 * free, "the limits should clip the feedback in this case"
    assert clipped == pytest.approx(plant, rel=0.05)


def test_the_correction_lowers_the_plants_closed_loop_cost(limited):
    sc, d, dc = limited
    rec = dc.meta["clip_correction"]
    assert rec["kept"] == "moved" and rec["check_moved"] < rec["check_optimized"]
    assert "clip_correction" not in d.meta
    lo, hi = sc.problem.limits(d.info.n_u)
    assert np.all(dc.nominal.u >= lo - 1e-12) and np.all(dc.nominal.u <= hi + 1e-12)
    assert not np.allclose(dc.nominal.u, d.nominal.u)
    # the optimizer's record is the optimizer's (the moved nominal is not an optimizer result)
    assert dc.meta["optimizer"]["mean_only_cost"] == d.meta["optimizer"]["mean_only_cost"]
    before, after = _plant_cost(sc, d), _plant_cost(sc, dc)
    assert after < before
    # the plant's run-steps of the extra pass are counted
    assert dc.meta["run_steps"]["total"] > d.meta["run_steps"]["total"]


def test_without_limits_the_correction_changes_nothing():
    sc = flat(**SMALL)
    a, b = _design(sc), _design(sc, clip_correction=True)
    assert "clip_correction" not in b.meta
    for x, y in [(a.nominal.u, b.nominal.u), (a.lqg.K, b.lqg.K), (a.lqg.kf.L, b.lqg.kf.L)]:
        np.testing.assert_array_equal(x, y)


def test_the_plans_defaults_the_option_and_the_plan_estimate():
    assert DesignSettings().resolved().clip_correction is True              # the default plan, 0.9
    assert DesignSettings(experiment_plan="0.8").resolved().clip_correction is False
    assert DesignSettings(experiment_plan="0.9").resolved().clip_correction is True
    assert DesignSettings(experiment_plan="0.9", clip_correction=False).resolved().clip_correction is False
    with pytest.raises(ValueError, match="clip_correction"):
        DesignSettings(clip_correction="yes").check()
    assert _on_off("on") is True and _on_off("off") is False
    sc = flat(**SMALL, **LIMITS)
    on = design_plan(sc.plant, sc.problem, DesignSettings(**FAST, clip_correction=True).for_plant(sc.plant))
    off = design_plan(sc.plant, sc.problem, DesignSettings(**FAST).for_plant(sc.plant))
    assert on["clip_correction"] and not off["clip_correction"]
    free = flat(**SMALL)                  # rate limits alone clip the feedback too
    rate_only = DesignSettings(**FAST, clip_correction=True).for_plant(free.plant)
    assert not design_plan(free.plant, free.problem, rate_only)["clip_correction"]
    assert design_plan(free.plant, free.problem.replace(du_max=0.05), rate_only)["clip_correction"]
    assert on["run_steps"]["total"] > off["run_steps"]["total"]


def test_rate_violation_and_its_gradient():
    rng = np.random.default_rng(2)
    U, du = rng.standard_normal((12, 3)), np.array([0.3, 0.5, 1.0])
    V, g = rate_violation(U, du)
    excess = np.maximum(np.abs(np.diff(U, axis=0)) - du, 0.0)
    assert V == pytest.approx(np.sum(excess**2)) and V > 0
    P, h = rng.standard_normal(U.shape), 1e-6
    fd = (rate_violation(U + h * P, du)[0] - rate_violation(U - h * P, du)[0]) / (2 * h)
    assert np.sum(g * P) == pytest.approx(fd, rel=1e-6)
    assert rate_violation(np.zeros((5, 3)), du) == (0.0, pytest.approx(np.zeros((5, 3))))


def test_with_rate_limits_the_moved_nominal_respects_them():
    """The nominal the correction moves obeys |u_k - u_{k-1}| <= du_max, as the optimizer's does
    (the plant then clips none of the open loop's inputs)."""
    sc = coarse_scenario(30, 80, **LIMITS)
    sc = dataclasses.replace(sc, problem=sc.problem.replace(du_max=0.02))
    d = _design(sc, clip_correction=True)
    rec = d.meta["clip_correction"]
    assert rec["kept"] == "moved", rec
    du = np.abs(np.diff(d.nominal.u, axis=0))
    assert du.max() <= 0.02 + 1e-12
    lo, hi = sc.problem.limits(d.info.n_u)
    assert np.all(d.nominal.u >= lo - 1e-12) and np.all(d.nominal.u <= hi + 1e-12)
