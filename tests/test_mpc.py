"""The box-constrained ROM-MPC (sep_control.control.mpc) and the limit-aware nominal.

* with no active bound the MPC is the TV-LQR law (the unconstrained path and the QP path);
* with active bounds its move is the box-constrained QP's optimum (checked against L-BFGS-B),
  and no input ever leaves the limits (single commands and a Monte Carlo);
* a QP that fails or runs past its budget falls back to the clipped LQR command, counted;
* the limit-aware nominal stays inside the (tightened) bounds, and the closed-loop input spread
  it uses equals the Monte Carlo's;
* over topics, lockstep plant + lqg with controller:=rom_mpc equals the offline `simulate`
  (rom_mpc) within the solver's tolerance (OSQP eps 1e-8 with polishing: 1e-6 asserted).
"""
import json

import numpy as np
import pytest
from scipy.optimize import minimize

from core_helpers import flat
from node_harness import joint_matrix, launcher, make_case, probe  # noqa: F401
from sep_control.design.pipeline import MARGIN_COST_WARN, DesignSettings, run_design, tightened_limits
from sep_control.design.gains import input_spread
from sep_control.evaluation.montecarlo import simulate
from sep_control.control.mpc import RomMPC
from sep_plant.ros import contract as c

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)
LIMITS = dict(u_min=0.0, u_max=0.6)
# plan 0.8: the limit-margin designs below are compared with one without the clip correction
FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1, experiment_plan="0.8")


@pytest.fixture(scope="module")
def free():
    sc = flat(**SMALL)
    return sc, run_design(sc.plant, sc.problem, DesignSettings(**FAST), show_progress=False, log=lambda m: None)


@pytest.fixture(scope="module")
def limited():
    sc = flat(**SMALL, **LIMITS)
    return sc, run_design(sc.plant, sc.problem, DesignSettings(**FAST), show_progress=False, log=lambda m: None)


def test_inactive_bounds_give_the_tv_lqr_law(free):
    sc, d = free
    mpc = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=8)
    rng = np.random.default_rng(0)
    for k in (0, 1, 17, 32, 35, 39):                     # k + H > N at the end: shortened horizon
        a = rng.standard_normal(d.lqg.model.n)
        lqr = d.nominal.u[k] + d.lqg.K[k] @ a
        u, _ = mpc.command(k, a)
        np.testing.assert_allclose(u, lqr, rtol=0, atol=1e-10)
        # the same through OSQP (bounds far away): the condensed QP itself is the LQR's
        lo, hi = np.full(mpc.H * mpc.n_u, -1e3), np.full(mpc.H * mpc.n_u, 1e3)
        Hk = min(mpc.H, mpc.N - k)
        lo[Hk * mpc.n_u:] = hi[Hk * mpc.n_u:] = 0.0
        z, why = mpc._solve(k, a, lo, hi, None)
        assert why == "ok"
        np.testing.assert_allclose(d.nominal.u[k] + z[:mpc.n_u], lqr, rtol=0, atol=1e-6)
    assert mpc.stats.unconstrained == 6 and mpc.stats.fallbacks == 0


def test_active_bounds_give_the_box_qp_optimum_and_never_leave_the_limits(limited):
    sc, d = limited
    mpc = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=6)
    rng = np.random.default_rng(1)
    lo, hi = sc.problem.limits(d.info.n_u)
    solved = 0
    for k in (3, 12, 25, 38):
        a = 3.0 * rng.standard_normal(d.lqg.model.n)
        u, z = mpc.command(k, a)
        assert np.all(u >= lo) and np.all(u <= hi)
        if z is None:
            continue
        zl, zh = mpc.bounds(k)
        P, q = mpc.P[k], mpc.F[k] @ a
        ref = minimize(lambda x: x @ P @ x + 2 * q @ x, np.clip(np.zeros_like(q), zl, zh),
                       jac=lambda x: 2 * (P @ x + q), bounds=list(zip(zl, zh)), method="L-BFGS-B",
                       options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000})
        cost = lambda x: x @ P @ x + 2 * q @ x
        assert cost(z) <= cost(ref.x) + 1e-8 * max(1.0, abs(cost(ref.x)))
        np.testing.assert_allclose(z, ref.x, atol=1e-5)
        solved += 1
    assert solved >= 2 and mpc.stats.qp >= 2
    # a Monte Carlo under MPC: every applied input inside the limits
    r = simulate(sc.plant, d, "rom_mpc", 2, 12, keep_estimates=0, keep_trajectories=0, mpc={"horizon": 6})
    assert r.U.min() >= lo.min() and r.U.max() <= hi.max()
    assert r.summary["mpc_qp_steps"] > 0 and r.summary["mpc_fallbacks"] == 0


def test_failed_or_slow_qp_falls_back_to_the_clipped_lqr(limited):
    sc, d = limited
    lo, hi = sc.problem.limits(d.info.n_u)
    a = 3.0 * np.random.default_rng(2).standard_normal(d.lqg.model.n)
    k = 10
    clipped = np.clip(d.nominal.u[k] + d.lqg.K[k] @ a, lo, hi)
    for kw, reason in ((dict(solver_settings={"max_iter": 1, "polishing": False}), "maximum iterations"),
                       (dict(time_budget_s=1e-9), "budget")):
        mpc = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=6, **kw)
        u, z = mpc.command(k, a)
        assert z is None and mpc.stats.fallbacks == 1
        assert any(reason in why for why in mpc.stats.fallback_reasons), mpc.stats.fallback_reasons
        np.testing.assert_array_equal(u, clipped)
    forced = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=6)
    u, z = forced.command(k, a, fail=True)
    np.testing.assert_array_equal(u, clipped)
    assert forced.stats.as_dict()["mpc_fallback_reasons"] == {"forced": 1}


def test_mpc_without_limits_costs_what_lqg_costs(free):
    sc, d = free
    lqg = simulate(sc.plant, d, "rom_lqg", 4, 40).summary
    mpc = simulate(sc.plant, d, "rom_mpc", 4, 40).summary
    assert mpc["cost_mean"] == pytest.approx(lqg["cost_mean"], rel=1e-9)
    assert mpc["mpc_qp_steps"] == 0 and mpc["mpc_unconstrained_steps"] == 40 * 40


def test_limit_aware_nominal_stays_inside_the_tightened_limits(limited, free):
    sc, d = limited
    lo, hi = sc.problem.limits(d.info.n_u)
    assert d.nominal.u.min() >= lo.min() and d.nominal.u.max() <= hi.max()
    assert np.any(np.isclose(d.nominal.u, hi.max())), "the upper limit should be active in this case"
    # the closed-loop input spread the margin uses is the Monte Carlo's (free case: no clipping)
    scf, df = free
    sigma = input_spread(df.lqg)
    r = simulate(scf.plant, df, "rom_lqg", 5, 400, keep_estimates=0, keep_trajectories=0)
    ratio = r.U[:, 5:].std(axis=0) / sigma[5:]
    assert 0.85 < np.median(ratio) < 1.15
    # with a margin: the nominal respects lo + c sigma <= u <= hi - c sigma (of its own LQG)
    st = DesignSettings(**FAST, limit_margin=0.5, margin_iterations=1)
    lines = []
    dm = run_design(sc.plant, sc.problem, st, show_progress=False, log=lines.append)
    assert dm.meta["optimizer"]["limit_margins"][0]["iteration"] == 1
    assert not [m for m in lines if m.startswith("warning: the limit margin")], lines
    LO, HI = tightened_limits(lo, hi, input_spread(d.lqg), 0.5)
    assert np.all(dm.nominal.u >= LO - 1e-12) and np.all(dm.nominal.u <= HI + 1e-12)
    assert np.any(dm.nominal.u < d.nominal.u - 1e-6)     # it moved away from the upper limit


def test_a_margin_that_puts_the_targets_out_of_reach_is_warned_of(limited):
    """Heaters that cannot cool, held c sigma_u above 0 and below u_max: past some c the nominal
    cannot reach its targets, and the design says so (its objective rises many-fold)."""
    sc, d = limited
    lines = []
    dm = run_design(sc.plant, sc.problem, DesignSettings(**FAST, limit_margin=8.0, margin_iterations=1),
                    show_progress=False, log=lines.append)
    before = d.meta["optimizer"]["belief_history"][-1]          # the unmargined design's J_b
    after = dm.meta["optimizer"]["limit_margins"][0]["objective"]
    assert after > MARGIN_COST_WARN * before
    warned = [m for m in lines if m.startswith("warning: the limit margin raised")]
    assert len(warned) == 1 and "--limit-margin" in warned[0], lines


def test_tightened_limits_meet_in_the_middle_when_they_cross():
    LO, HI = tightened_limits(np.zeros(2), np.array([1.0, 0.2]), np.array([[0.1, 0.2]]), 1.0)
    np.testing.assert_allclose(LO, [[0.1, 0.1]])
    np.testing.assert_allclose(HI, [[0.9, 0.1]])




@pytest.mark.ros
def test_lockstep_mpc_over_topics_equals_offline(launcher, probe, tmp_path):
    case = make_case(tmp_path, "limited", settings=FAST, **SMALL, **LIMITS)
    pr = probe().subscribe(c.APPLIED_INPUT, c.DIAGNOSTICS)
    lqg = launcher.start('lqg', params={'design_file': case.design_file, 'wait_for_scenario_s': 20.0,
                                        'summary_file': tmp_path / 'lqg.json', 'controller': 'rom_mpc',
                                        'mpc_horizon': 6})
    plant = launcher.start('plant', params={'scenario_file': case.scenario_file, 'seed': 7, 'run': 3,
                                            'wait_for_subscribers': 1, 'summary_file': tmp_path / 'plant.json',
                                            'trajectory_file': tmp_path / 'traj.npz', 'command_timeout_s': 20.0})
    assert plant.wait(120) == 0, plant.output()
    assert lqg.wait(30) == 0, lqg.output()
    ref = simulate(case.plant, case.design, 'rom_mpc', 7, range(3, 4), mpc={"horizon": 6})
    z = np.load(tmp_path / 'traj.npz', allow_pickle=False)
    assert np.max(np.abs(z['U'] - ref.U[0])) <= 1e-6
    assert np.max(np.abs(z['F'] - ref.F[0])) <= 1e-6
    lo, hi = case.scenario.problem.limits(case.design.info.n_u)
    assert z['U'].min() >= lo.min() and z['U'].max() <= hi.max()
    summ = json.loads((tmp_path / 'lqg.json').read_text())['lqr']
    assert summ['controller'] == 'rom_mpc' and summ['mpc_qp_steps'] > 0 and summ['mpc_fallbacks'] == 0
    assert summ['mpc_horizon'] == 6 and 'rom_mpc: horizon 6' in lqg.output()
