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
    st = DesignSettings(p=6, q=6, n_r=8, ensemble=8, max_iter=3)
    d = run_design(plant, problem, st, show_progress=False, log=lines.append)
    rs = d.meta["run_steps"]
    assert rs["total"] == sum(v for k, v in rs.items() if k != "total") > 0
    assert rs["nominal"] > 0 and rs["belief"] > 0
    assert any(line.startswith("plan (0.8): about") for line in lines)
    assert any(line.startswith("run-steps: ") for line in lines)
    assert d.meta["settings"]["experiment_plan"] == "0.8" and d.meta["settings"]["impulse_scheme"] == "central"


def test_plan_warns_on_many_noise_channels_naming_them():
    class Noisy:
        n_u, n_y, n_x, n_field, noise_on_inputs, n_w = 2, 3, 300, 300, False, 300

    problem = reference().problem
    st = DesignSettings()
    plan = design_plan(Noisy(), problem, st)
    assert plan["matrices"]["hankel"] == (st.p * 3, st.q * 302)
    warnings = plan_warnings(plan, problem.n_steps)
    assert any("process-noise channels" in w and "noise_on_inputs" in w for w in warnings)
    few = design_plan(reference().plant, problem, st)
    assert plan_warnings(few, problem.n_steps) == []


def test_experiment_plans_resolve_their_keys():
    assert DesignSettings().impulse_scheme == "central" and DesignSettings().ensemble == 200
    new = DesignSettings(experiment_plan="0.9")
    assert (new.impulse_scheme, new.ensemble) == ("forward", 50)
    assert DesignSettings(experiment_plan="0.9", ensemble=100).ensemble == 100
    assert DesignSettings.from_meta({"settings": {}}).experiment_plan == "0.8"
