"""Gauss-Newton with the TV-ERA (ROM) Jacobian reaches the sensitivity-Jacobian optimum."""
import numpy as np
import pytest

from core_helpers import flat
from sep_control.design.belief import objective_of
from sep_control.design.jacobians import RomJacobian, SensitivityJacobian
from sep_control.design.linearization import NormalEquations, sensitivity_normal_equations
from sep_control.design.optimizer import Optimizer, OptimizerOptions
from sep_control.design.tvera import RomSettings, identify
from sep_plant.protocol import nominal_states as nominal_rollout

SC = flat(n_x=24, n_steps=60, k_band=36, lqr_k_switch=29)
P, S = SC.plant, SC.problem
OBJ = objective_of(P, S)
N_U = P.n_u
ROM = {"p": 8, "q": 8, "n_r": 16}


def run(strategy, U0=None, **options):
    """One `Optimizer` run on the module's plant and problem, no progress bar."""
    return Optimizer(P, S, OptimizerOptions(show_progress=False, **options), strategy).run(U0)


def rom_jacobian(**kw) -> RomJacobian:
    """The ROM Jacobian with the module's TV-ERA settings (a new one per run: it holds state)."""
    return RomJacobian(RomSettings(**ROM), **kw)


def rom_normal_equations(plant, U, obj, residual_field, p=15, q=15, n_r=20, sv_tol=1e-10, impulse=0.01):
    """J'J and J'r of the ROM Jacobian, formed densely (the optimizer solves the same
    Gauss-Newton step through `RomLinearization` without forming them).

    The field sensitivities df_k/du_j are taken from the identified ROM, G_k A_{k-1} ... A_{j+1} B_j:
        M_k = [A_{k-1} M_{k-1}, B_{k-1}]   (n_r x k n_u: the state response to every past input)
        J'J += M_k' (w_k G_k' G_k) M_k,   J'r += M_k' w_k G_k' (f_k - f*),   w_k = q_k / n_f.
    """
    N, n_u = U.shape
    n = N * n_u
    ident = identify(plant, U, p, q, n_r, sv_tol, impulse)
    model = ident.model
    res = residual_field - obj.target
    w = obj.q / res.shape[1]
    JtJ = np.zeros((n, n))
    Jtr = np.zeros(n)
    M = np.zeros((model.n, n))
    for k in range(1, N + 1):
        m = n_u * k
        M[:, :m - n_u] = model.A[k - 1] @ M[:, :m - n_u]
        M[:, m - n_u:m] = model.B[k - 1]
        Mk = M[:, :m]
        JtJ[:m, :m] += Mk.T @ ((w[k] * model.G.gram(k)) @ Mk)
        Jtr[:m] += Mk.T @ (w[k] * model.G.project(k, res[k]))
    JtJ[np.diag_indices(n)] += obj.r_u
    Jtr += obj.r_u * U.ravel()
    return NormalEquations(JtJ, Jtr, ident.data.experiments, ident.data.experiments * (p + q))


def test_rom_normal_equations_match_the_sensitivity_ones():
    sim = P
    U = np.full((S.n_steps, N_U), 0.2) + 0.02 * np.random.default_rng(1).standard_normal((S.n_steps, N_U))
    X = nominal_rollout(sim, U)
    a = sensitivity_normal_equations(sim, U, X, OBJ, eps=1e-5)
    b = rom_normal_equations(sim, U, OBJ, X, **ROM)
    # the one-sided eps = 1e-5 differences carry an O(eps) bias; the ROM's are central differences
    assert np.linalg.norm(b.Jtr - a.Jtr) / np.linalg.norm(a.Jtr) < 1e-4
    assert np.linalg.norm(b.JtJ - a.JtJ) / np.linalg.norm(a.JtJ) < 1e-4
    # 2 N n_u runs of p+q steps (central differences) instead of N n_u runs of N/2 steps on average
    assert b.experiments == 2 * S.n_steps * N_U
    assert b.run_steps == b.experiments * (ROM["p"] + ROM["q"])
    assert a.run_steps == N_U * S.n_steps * (S.n_steps + 1) // 2


def test_rom_gauss_newton_converges_to_the_same_optimum():
    sim = P
    ref = run(SensitivityJacobian())
    rom = run(rom_jacobian())
    assert rom.iterations <= ref.iterations + 1
    assert rom.cost == pytest.approx(ref.cost, rel=1e-6)
    np.testing.assert_allclose(rom.U, ref.U, atol=1e-4 * np.abs(ref.U).max())


def test_unknown_jacobian_refused():
    from sep_control.design.settings import DesignSettings
    from sep_control.design.stages import mean_only_jacobian

    with pytest.raises(ValueError, match="jacobian"):
        DesignSettings(jacobian="adjoint").check()
    with pytest.raises(ValueError, match="jacobian"):
        mean_only_jacobian(DesignSettings(), "adjoint")


def test_rom_step_is_the_dense_gauss_newton_solve_without_the_matrix():
    """RomLinearization solves (J'J + lam diag(J'J)) dU = -J'r by a Riccati pass on the ROM:
    the same step as the dense solve of the same Jacobian, its diagonal and gradient too."""
    from sep_control.design.linearization import RomLinearization

    U = np.full((S.n_steps, N_U), 0.2) + 0.02 * np.random.default_rng(2).standard_normal((S.n_steps, N_U))
    X = nominal_rollout(P, U)
    ne = rom_normal_equations(P, U, OBJ, X, **ROM)
    lin = RomLinearization(identify(P, U, **ROM), OBJ, X, U)
    for lam in (0.0, 1e-3, 1.0):
        dense = -np.linalg.solve(ne.JtJ + lam * np.diag(np.diag(ne.JtJ)), ne.Jtr).reshape(U.shape)
        np.testing.assert_allclose(lin.step(lam), dense, rtol=0, atol=1e-9 * np.abs(dense).max())
    np.testing.assert_allclose(lin.D.ravel(), np.diag(ne.JtJ), rtol=1e-10)
    np.testing.assert_allclose(lin.gradient().ravel(), 2 * ne.Jtr, rtol=0, atol=1e-10 * np.abs(ne.Jtr).max())


def test_the_design_reuses_the_optimizers_last_identification():
    """With the ROM Jacobian the mean-only optimizer ends identified at its optimum; the
    belief-space refinement takes that model as a chord; the design identifies once more, at
    the final input (or reuses the model when the input did not move)."""
    from sep_control.design.linearization import SAME_INPUT_RTOL
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.design.stages import PROPOSAL_ROM
    from sep_control.design.tvera import SCHEMES

    st = DesignSettings(jacobian="rom", p=8, q=8, n_r=16, belief=False, relinearize_rtol=SAME_INPUT_RTOL,
                        experiment_plan="0.8")
    d = run_design(P, S, st, show_progress=False, log=lambda m: None)
    lins = d.meta["optimizer"]["linearizations"]
    # far from the optimum coarse proposal models (forward: one run per impulse), near it the
    # design's own (central: two), identified at every iterate (relinearize_rtol 1e-6)
    assert lins[0] == "rom (proposal)" and lins[-1] == "rom" and "rom (kept)" not in lins
    runs = {"rom (proposal)": SCHEMES[PROPOSAL_ROM["scheme"]], "rom": SCHEMES[st.impulse_scheme]}
    assert d.meta["optimizer"]["experiments"] == sum(runs[k] for k in lins) * S.n_steps * N_U
    assert len(lins) == d.meta["optimizer"]["iterations"] + 1
    assert d.meta["timings"]["identify_s"] < 0.05          # reused, not identified again
    assert d.meta["validation"]["markov_rel_error"] < 1e-5       # (n_r = 16, p = q = 8)
    assert d.meta["optimizer"]["identification_reused"]
    assert d.meta["settings"]["enkf_seed"] == d.meta["provenance"]["seed"] == 0 and "seed" not in d.meta["settings"]


def test_keeping_the_identification_for_small_steps_reaches_the_same_design():
    """relinearize_rtol (default 1e-2): the optimizer keeps its last identification while the
    input moved less than that (the last Gauss-Newton steps), so it identifies fewer times; the
    optimum is the same to 1e-6 and the design's ROM is still identified at the final input."""
    from sep_control.design.linearization import SAME_INPUT_RTOL, same_input
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.design.tvera import markov_relative_error

    base = dict(jacobian="rom", p=8, q=8, n_r=16, experiment_plan="0.8")    # plan 0.8's RomJacobian
    every = run_design(P, S, DesignSettings(**base, relinearize_rtol=SAME_INPUT_RTOL), show_progress=False,
                       log=lambda m: None)
    kept = run_design(P, S, DesignSettings(**base), show_progress=False, log=lambda m: None)
    assert DesignSettings().relinearize_rtol == 1e-2
    a, b = every.meta["optimizer"], kept.meta["optimizer"]
    assert b["experiments"] < a["experiments"]
    assert b["nominal_cost"] == pytest.approx(a["nominal_cost"], rel=1e-6)
    assert b["mean_only_cost"] == pytest.approx(a["mean_only_cost"], rel=1e-6)
    # the ROM is the final nominal's own: it fits a fresh identification there as well as
    # that identification's own model does
    fresh = identify(P, kept.nominal.u, **ROM)
    err_kept = markov_relative_error(kept.rom, fresh.data.Y)
    assert err_kept < 1e-5 and err_kept <= 1.01 * markov_relative_error(fresh.model, fresh.data.Y) + 1e-12
    # optimize on its own: the result carries its last identification, near (not at) the final U
    res = run(rom_jacobian(relinearize_rtol=1e-2))
    ref = run(rom_jacobian())
    assert res.experiments < ref.experiments and res.cost == pytest.approx(ref.cost, rel=1e-6)
    assert same_input(res.identification.U, res.U, 1e-2) and not same_input(res.identification.U, res.U)


def test_a_kept_model_whose_trials_all_fail_is_replaced_by_one_identified_at_U(monkeypatch):
    """A kept identification proposes steps from where it was made; when none of them lowers the
    true objective, the optimizer identifies at the current input and tries again, instead of
    stopping. Forced here: every model used away from its own input proposes uphill steps."""
    from sep_control.design.linearization import RomLinearization

    ref = run(rom_jacobian())
    orig = RomLinearization.step

    def uphill_when_kept(self, lam, frozen=None):
        d = orig(self, lam, frozen)
        return d if np.array_equal(self.U, self.identification.U) else -d

    monkeypatch.setattr(RomLinearization, "step", uphill_when_kept)
    res = run(rom_jacobian(relinearize_rtol=1e9))
    assert res.iterations >= 3
    assert res.cost == pytest.approx(ref.cost, rel=1e-6)


def test_old_design_files_identified_after_every_step():
    from sep_control.design.linearization import SAME_INPUT_RTOL
    from sep_control.design.settings import DesignSettings

    assert DesignSettings.from_meta({"settings": {"n_r": 20}}).relinearize_rtol == SAME_INPUT_RTOL
    assert DesignSettings.from_meta({"settings": {"relinearize_rtol": 0.05}}).relinearize_rtol == 0.05
    for bad in (0.0, 0.5, float("nan")):
        with pytest.raises(ValueError, match="relinearize_rtol"):
            DesignSettings(relinearize_rtol=bad).check()


def test_the_enkf_seed_was_called_seed():
    """DesignSettings.enkf_seed: a scenario's `design: {seed: ...}` is read as enkf_seed with a
    FutureWarning naming the new key, a design file's recorded `seed` silently; the
    metadata then records enkf_seed, and the provenance the seed's value."""
    import dataclasses

    from sep_control.design.settings import DesignSettings

    old = dataclasses.replace(SC, design={"seed": 7, "n_r": 16})
    with pytest.warns(FutureWarning, match="enkf_seed"):
        st = DesignSettings.for_scenario(old)
    assert st.enkf_seed == 7 and st.n_r == 16 and "seed" not in DesignSettings.__dataclass_fields__
    new = dataclasses.replace(SC, design={"enkf_seed": 7})
    assert DesignSettings.for_scenario(new).enkf_seed == 7
    with pytest.raises(ValueError, match="enkf_seed"):
        DesignSettings.for_scenario(dataclasses.replace(SC, design={"seed": 1, "enkf_seed": 2}))
    assert DesignSettings.from_meta({"settings": {"seed": 5}}).enkf_seed == 5
    assert DesignSettings.from_meta({"settings": {"enkf_seed": 6}}).enkf_seed == 6


def test_auto_picks_the_cheaper_jacobian():
    from sep_control.design.pipeline import DesignSettings

    st = DesignSettings()                                   # p = q = 15
    assert st.jacobian == "auto"
    assert st.resolved_jacobian(250) == "rom" and st.resolved_jacobian(80) == "sensitivity"
    assert st.resolved_jacobian(150) == "rom" and st.resolved_jacobian(149) == "sensitivity"
    assert DesignSettings(jacobian="sensitivity").resolved_jacobian(250) == "sensitivity"


def test_predicted_change_is_the_gauss_newton_model_of_both_jacobians():
    """predicted_change(dU) is the quadratic model 2 J'r dU + dU' J'J dU: the ROM's Riccati-free
    forward pass equals the dense form of the same Jacobian, and near a Gauss-Newton step the
    sensitivity model predicts the true change of the cost."""
    from sep_control.design.linearization import RomLinearization, SensitivityLinearization
    from sep_control.evaluation.metrics import nominal_cost

    rng = np.random.default_rng(3)
    U = np.full((S.n_steps, N_U), 0.2) + 0.02 * rng.standard_normal((S.n_steps, N_U))
    X = nominal_rollout(P, U)
    F = P.field(X)
    ne = rom_normal_equations(P, U, OBJ, F, **ROM)
    rom = RomLinearization(identify(P, U, **ROM), OBJ, F, U)
    dense = SensitivityLinearization(ne, U.shape)
    for dU in (rom.step(1e-3), 1e-3 * rng.standard_normal(U.shape)):
        assert rom.predicted_change(dU) == pytest.approx(dense.predicted_change(dU), rel=1e-8)
    sens = SensitivityLinearization(sensitivity_normal_equations(P, U, X, OBJ, eps=1e-6), U.shape)
    dU = 1e-2 * sens.step(1e-3)                   # a short step: the model's error is O(|dU|^3)
    J0 = nominal_cost(F, U, OBJ)
    actual = nominal_cost(P.field(nominal_rollout(P, U + dU)), U + dU, OBJ) - J0
    assert actual < 0 and sens.predicted_change(dU) == pytest.approx(actual, rel=1e-3)


def test_the_belief_refinement_stops_when_the_model_predicts_less_than_tol_without_an_enkf_run(monkeypatch):
    """Belief objective: a trial that the Gauss-Newton model predicts to lower J_b by less than
    tol is not evaluated (an EnKF run); the refinement stops there. The nominal objective
    evaluates every trial (a rollout): an inexact model may predict too little there."""
    from sep_control.design import optimizer as opt_mod

    mean = run(rom_jacobian())
    assert mean.stop == "the step lowered the objective by less than tol (not taken)"
    runs = []
    orig = opt_mod.run_belief
    monkeypatch.setattr(opt_mod, "run_belief", lambda *a, **k: runs.append(1) or orig(*a, **k))
    res = run(rom_jacobian(chord=True, start=mean.identification), mean.U, objective="belief", members=20,
              max_trials=1)
    assert res.stop == "the model predicts a decrease below tol"
    assert len(runs) == res.iterations + 1              # the start and one accepted trial per step
    assert res.belief is not None and res.cost == res.history[-1]


def test_auto_switches_from_sensitivity_to_one_identification_near_the_optimum():
    """'auto' below the crossover: the sensitivity Jacobian while the steps are large, then one
    TV-ERA identification once a step moved U by 1 % or less; that model proposes the last
    steps, serves the belief refinement as its chord, and is the design's ROM when the input
    does not move after it. The optimum is the sensitivity path's to 1e-6."""
    from sep_control.design.jacobians import NEAR_OPTIMUM
    from sep_control.design.pipeline import DesignSettings, run_design

    base = dict(p=8, q=8, n_r=16, belief=False, experiment_plan="0.8")     # plan 0.8's 'auto' rule
    auto = run_design(P, S, DesignSettings(**base), show_progress=False, log=lambda m: None)
    sens = run_design(P, S, DesignSettings(**base, jacobian="sensitivity"), show_progress=False,
                      log=lambda m: None)
    a, s = auto.meta["optimizer"], sens.meta["optimizer"]
    assert a["jacobian"] == "sensitivity" and NEAR_OPTIMUM == 1e-2
    assert a["linearizations"][-1] == "rom" and set(a["linearizations"][:-1]) == {"sensitivity"}
    assert set(s["linearizations"]) == {"sensitivity"}
    assert len(a["linearizations"]) <= len(s["linearizations"])
    assert a["identification_reused"] and auto.meta["timings"]["identify_s"] < 0.05
    assert a["mean_only_cost"] == pytest.approx(s["mean_only_cost"], rel=1e-6)
    assert a["nominal_cost"] == pytest.approx(s["nominal_cost"], rel=1e-6)
    np.testing.assert_allclose(auto.nominal.u, sens.nominal.u, atol=1e-4 * np.abs(sens.nominal.u).max())


def test_coarse_proposal_models_reach_the_same_design():
    """rom Jacobian: the identifications far from the optimum use forward impulses and a 1e-6
    field basis (about half the runs); the design's ROM is identified with the full settings at
    the final input. Same optimum to 1e-6 as identifying every model in full."""
    from sep_control.design.linearization import SAME_INPUT_RTOL
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.design.stages import PROPOSAL_ROM
    from sep_control.design.tvera import SCHEMES

    base = dict(jacobian="rom", p=8, q=8, n_r=16, experiment_plan="0.8")    # plan 0.8's RomJacobian
    coarse = run_design(P, S, DesignSettings(**base), show_progress=False, log=lambda m: None)
    full = run_design(P, S, DesignSettings(**base, coarse_proposals=False), show_progress=False,
                      log=lambda m: None)
    c, f = coarse.meta["optimizer"], full.meta["optimizer"]
    assert PROPOSAL_ROM == {"scheme": "forward", "field_tol": 1e-6, "coarse": True}
    assert "rom (proposal)" in c["linearizations"] and "rom (proposal)" not in f["linearizations"]
    assert c["experiments"] < f["experiments"]
    per = {"rom (proposal)": SCHEMES["forward"], "rom": SCHEMES["central"], "rom (kept)": 0}
    assert c["experiments"] == sum(per[k] for k in c["linearizations"]) * S.n_steps * N_U
    assert c["mean_only_cost"] == pytest.approx(f["mean_only_cost"], rel=1e-6)
    assert c["nominal_cost"] == pytest.approx(f["nominal_cost"], rel=1e-6)
    # the design's ROM is a full identification, never a proposal model: here the belief
    # refinement moves U, so it is identified afresh at the final input ...
    assert not c["identification_reused"]
    # ... and where the optimizer's last model is at the final input (no belief refinement, a
    # model made after every step) it is reused, and it is a full one although proposals came first
    reuse = run_design(P, S, DesignSettings(**base, belief=False, relinearize_rtol=SAME_INPUT_RTOL),
                       show_progress=False, log=lambda m: None).meta
    r = reuse["optimizer"]
    assert r["identification_reused"] and "rom (proposal)" in r["linearizations"]
    assert r["linearizations"][-1] == "rom"
    assert reuse["validation"]["markov_rel_error"] == pytest.approx(
        full.meta["validation"]["markov_rel_error"], rel=0.05)
    assert coarse.meta["validation"]["markov_rel_error"] == pytest.approx(
        full.meta["validation"]["markov_rel_error"], rel=0.05)
    assert DesignSettings.from_meta({"settings": {}}).coarse_proposals is False   # older files


def test_a_belief_refinement_that_takes_no_step_runs_the_enkf_once(monkeypatch):
    """When its trial raises J_b (the model holds the spread fixed), the refinement stops after
    one trial, and the design keeps the belief computed at its start (no EnKF run again)."""
    from sep_control.design import optimizer as opt_mod
    from sep_control.design import stages as design_mod
    from sep_control.design.pipeline import DesignSettings, run_design

    runs = []
    orig = opt_mod.run_belief
    monkeypatch.setattr(opt_mod, "run_belief", lambda *a, **k: runs.append(1) or orig(*a, **k))
    monkeypatch.setattr(design_mod, "run_belief", lambda *a, **k: runs.append(1) or orig(*a, **k))
    # J_b = 1 at the start, and every trial raises it
    monkeypatch.setattr(opt_mod, "belief_cost", lambda b, U, obj: 1.0 if len(runs) == 1 else 1.001)
    d = run_design(P, S, DesignSettings(p=8, q=8, n_r=16, experiment_plan="0.8"), show_progress=False,
                   log=lambda m: None)
    assert design_mod.BELIEF_TRIALS == 1
    assert d.meta["optimizer"]["belief_history"] == [1.0]
    assert len(runs) == 2                               # the start, one trial; none afterwards
    assert d.nominal.belief_mean.shape == (S.n_steps + 1, P.n_field)
