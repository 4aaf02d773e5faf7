"""Uncertain initial states (sep_plant.initial): spread 0 changes nothing, a spread gives each
run its own seeded draw in the Monte Carlo and the plant episode, and the design's filter prior
accounts for it."""
from __future__ import annotations

import numpy as np
import pytest

from sep_plant.initial import initial_seed, initial_states, sample_initial_states
from sep_plant.plants import make_plant


@pytest.mark.parametrize("type_name,config", [("slab", {}), ("plate", {"nodes": [8, 6]}),
                                              ("block", {"nodes": [4, 4, 4]}), ("allen_cahn", {"nodes": [10, 10]})])
def test_spread_zero_is_the_known_state_and_no_key(type_name, config):
    p = make_plant(type_name, config)
    assert "initial_spread" not in p.config()
    X = initial_states(p, 1, range(5))
    np.testing.assert_array_equal(X, p.initial_state(5))
    assert sample_initial_states(p, 8) is None


def test_spread_gives_each_run_its_own_seeded_draw():
    p = make_plant("slab", {"n_x": 20, "initial_spread": 2.0})
    assert p.config()["initial_spread"] == 2.0
    X = initial_states(p, 3, [0, 1, 2])
    offsets = X[:, 0] - p.initial_state(1)[0, 0]
    np.testing.assert_allclose(X - p.initial_state(3), np.repeat(offsets[:, None], 20, axis=1))
    assert len(set(np.round(offsets, 12))) == 3 and np.std(offsets) > 0.1
    np.testing.assert_array_equal(initial_states(p, 3, [2])[0], X[2])       # a run's draw, whatever the chunk
    assert initial_seed(3, 2) != initial_seed(3, 1) and initial_seed(3, 2) != initial_seed(4, 2)


def test_monte_carlo_and_episode_start_from_the_runs_draw():
    """The Monte Carlo's runs and a plant episode of the same (seed, run) start from the same draw;
    the design adds the initial deviation to the filter's prior."""
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.evaluation.montecarlo import simulate
    from sep_plant.plant_episode import PlantEpisode
    from sep_plant.problem import Problem

    plant = make_plant("slab", {"n_x": 20, "initial_spread": 3.0})
    problem = Problem(n_steps=40, band_window=(24, 40), lqr_k_switch=20)
    d = run_design(plant, problem, DesignSettings(n_r=8, p=6, q=6, ensemble=20, belief_iter=1),
                   show_progress=False, log=lambda m: None)
    assert d.meta["initial_prior"]["k0"] >= 1 and d.meta["initial_prior"]["trace"] > 0
    res = simulate(plant, d, "rom_lqg", 7, range(3, 5))
    X0 = initial_states(plant, 7, [3, 4])
    np.testing.assert_array_equal(res.F[:, 0], X0)
    ep = PlantEpisode(plant, problem, seed=7, run=4, keep_trajectory=True)
    assert ep.seed == 7 and ep.run_index == 4
