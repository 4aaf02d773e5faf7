"""Run-steps per stage: the design counts every plant step (sep_control.design.runsteps), the
plan estimates them before the work, and the 0.8 plan stays the default."""
from __future__ import annotations

import numpy as np

from sep_control.design.impulse import experiment_run_steps, impulse_experiments
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.plan import design_plan, plan_warnings
from sep_control.design.runsteps import RunStepMeter, metered, unmetered
from sep_plant.scenario import reference


def test_metered_plant_counts_rows_and_passes_everything_else():
    plant = reference().with_plant(n_x=20).plant
    meter = RunStepMeter()
    m = metered(plant, meter)
    X = plant.initial_state(7)
    with meter.stage("belief"):
        out = m.step(X, np.zeros((7, plant.n_u)))
    np.testing.assert_array_equal(out, plant.step(X, np.zeros((7, plant.n_u))))
    m.step(X[0], np.zeros(plant.n_u))
    assert meter.counts["belief"] == 7 and meter.counts["nominal"] == 1 and meter.total == 8
    assert m.n_x == plant.n_x and unmetered(m) is plant and metered(m, meter).plant is plant


def test_impulse_experiments_count_equals_the_formula():
    plant = reference().with_plant(n_x=20).plant
    U = np.full((12, plant.n_u), 0.2)
    for scheme in ("central", "forward"):
        meter = RunStepMeter()
        impulse_experiments(metered(plant, meter), U, 6, 3, 1e-3, scheme=scheme, chunks=2)
        rollout = 12 + 6                       # the nominal over N + lags steps
        assert meter.total == experiment_run_steps(12, plant.n_u, 6, scheme) + rollout


def test_design_records_run_steps_per_stage_and_the_plan_estimates_them():
    scen = reference().with_plant(n_x=20)
    plant, problem = scen.plant, scen.problem
    lines: list[str] = []
    st = DesignSettings(p=6, q=6, n_r=8, ensemble=8, max_iter=3, experiment_plan="0.8")
    d = run_design(plant, problem, st, show_progress=False, log=lines.append)
    rs = d.meta["run_steps"]
    assert rs["total"] == sum(v for k, v in rs.items() if k != "total") > 0
    assert rs["nominal"] > 0 and rs["belief"] > 0
    assert any(line.startswith("plan (0.8): about") for line in lines)
    assert any(line.startswith("run-steps: ") for line in lines)
    assert d.meta["settings"]["experiment_plan"] == "0.8" and d.meta["settings"]["impulse_scheme"] == "central"


def test_plan_warns_on_many_noise_channels_naming_them():
    class Noisy:
        n_u, n_y, n_x, n_field, noise_on_inputs, n_w = 2, 3, 300, 300, False, 60

    problem = reference().problem
    st = DesignSettings()
    plan = design_plan(Noisy(), problem, st)
    assert plan["matrices"]["hankel"] == (st.p * 3, st.q * 62)
    warnings = plan_warnings(plan, problem.n_steps)
    assert any("process-noise channels" in w and "noise_on_inputs" in w for w in warnings)
    Noisy.n_w = 300           # above SKETCH_FROM: identified on SKETCH_PROBES combinations, no warning
    from sep_control.design.noise_sketch import SKETCH_PROBES

    plan = design_plan(Noisy(), problem, st)
    assert plan["matrices"]["hankel"] == (st.p * 3, st.q * (2 + SKETCH_PROBES))
    assert plan_warnings(plan, problem.n_steps) == []
    few = design_plan(reference().plant, problem, st)
    assert plan_warnings(few, problem.n_steps) == []


def test_experiment_plans_resolve_their_keys():
    old = DesignSettings(experiment_plan="0.8")
    assert old.impulse_scheme == "central" and old.ensemble == 200
    new = DesignSettings(experiment_plan="0.9")
    assert (new.impulse_scheme, new.ensemble) == ("forward", 50)
    assert DesignSettings().experiment_plan == "0.9"                     # the default plan
    assert DesignSettings(experiment_plan="0.9", ensemble=100).ensemble == 100
    assert DesignSettings.from_meta({"settings": {}}).experiment_plan == "0.8"


def test_spot_check_of_a_model_at_its_own_input_is_its_markov_error():
    from sep_control.design.spotcheck import spot_error
    from sep_control.design.tvera import identify

    plant = reference().with_plant(n_x=20).plant
    U = np.full((30, plant.n_u), 0.2)
    from sep_control.design.tvera import markov_relative_error

    ident = identify(plant, U, 4, 4, 8, impulse=0.01, scheme="forward")
    own = markov_relative_error(ident.model, ident.data.Y)
    at_own = spot_error(plant, ident, U)           # the same experiments: the model's own error there
    assert 0.5 * own < at_own < 2 * own
    assert spot_error(plant, ident, 3.0 * U) > at_own       # another nominal: the model is further off


def test_plan_09_design_counts_fewer_run_steps_and_records_its_plan():
    scen = reference().with_plant(n_x=20)
    kw = dict(p=6, q=6, n_r=8, max_iter=4)
    old = run_design(scen.plant, scen.problem, DesignSettings(experiment_plan="0.8", **kw), show_progress=False,
                     log=lambda m: None)
    lines: list[str] = []
    new = run_design(scen.plant, scen.problem, DesignSettings(experiment_plan="0.9", **kw), show_progress=False,
                     log=lines.append)
    assert new.meta["run_steps"]["total"] < old.meta["run_steps"]["total"]
    assert new.meta["settings"]["experiment_plan"] == "0.9" and new.meta["settings"]["ensemble"] == 50
    assert any("rom (proposal)" in line for line in lines)


def test_plan_counts_the_limit_margin_passes():
    """Each pass of the limit-margin loop repeats the stages: the estimate multiplies them (and
    a margin without input limits adds no pass)."""
    from dataclasses import replace

    scen = reference()
    # plan 0.8: no clip correction (plan 0.9 runs it only without a margin: one pass more)
    st, margin = DesignSettings(experiment_plan="0.8"), DesignSettings(limit_margin=1.0, margin_iterations=2,
                                                                       experiment_plan="0.8")
    free = design_plan(scen.plant, scen.problem, st)
    assert free["passes"] == 1 and design_plan(scen.plant, scen.problem, margin)["passes"] == 1
    limited = replace(scen.problem, u_min=0.0, u_max=0.6)
    one, three = design_plan(scen.plant, limited, st), design_plan(scen.plant, limited, margin)
    assert three["passes"] == 3
    assert three["run_steps"] == {k: 3 * v for k, v in one["run_steps"].items()}
