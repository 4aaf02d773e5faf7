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
    assert d.meta["initial_prior"]["n_c"] >= 1 and d.meta["initial_prior"]["trace"] > 0
    res = simulate(plant, d, "rom_lqg", 7, range(3, 5))
    X0 = initial_states(plant, 7, [3, 4])
    np.testing.assert_array_equal(res.F[:, 0], X0)
    ep = PlantEpisode(plant, problem, seed=7, run=4, keep_trajectory=True)
    assert ep.seed == 7 and ep.run_index == 4


def test_design_appends_initial_condition_states_and_the_file_keeps_their_prior(tmp_path):
    """Spread > 0: the ROM gains n_c constant IC states (A = I, B = 0) whose prior block is
    cov(c) of the sampled free responses, the a-block's prior stays 0, the filter starts from
    it, and the design file's round trip keeps P_0 (member rom_P0) and the schedule."""
    from sep_control.design.initial_prior import MAX_IC_STATES, fit_initial_prior
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_estimator.design_file import arrays_of, load_design, save_design
    from sep_plant.problem import Problem

    plant = make_plant("slab", {"n_x": 20, "initial_spread": 3.0})
    problem = Problem(n_steps=40, band_window=(24, 40), lqr_k_switch=20)
    d = run_design(plant, problem, DesignSettings(n_r=8, p=6, q=6, ensemble=20, belief_iter=1),
                   show_progress=False, log=lambda m: None)
    prior = fit_initial_prior(plant, d.nominal.u, d.nominal.y, d.nominal.field)
    n_c = prior.n_c
    assert 1 <= n_c <= MAX_IC_STATES and d.meta["initial_prior"]["n_c"] == n_c
    assert prior.fit > 0.99                  # a uniform offset: its free responses are few modes
    rom, n = d.rom, d.rom.n - n_c
    np.testing.assert_array_equal(rom.A[:, n:, n:], np.broadcast_to(np.eye(n_c), (40, n_c, n_c)))
    np.testing.assert_array_equal(rom.A[:, n:, :n], 0.0)
    np.testing.assert_array_equal(rom.B[:, n:], 0.0)
    np.testing.assert_array_equal(rom.C[:, :, n:], prior.C)
    np.testing.assert_array_equal(rom.P0[:n, :n], 0.0)
    np.testing.assert_array_equal(rom.P0[n:, n:], prior.cov)
    np.testing.assert_array_equal(d.lqg.kf.P_prior[0][:rom.n, :rom.n], rom.P0)
    for k in (0, 10, 40):                    # the (compressed, FIELD_MAP_TOL) map holds the modes' fields
        np.testing.assert_allclose(rom.G.matrix(k)[:, n:], prior.G[k], atol=1e-4 * np.abs(prior.G).max())
    assert "rom_P0" in arrays_of(d)
    back = load_design(save_design(tmp_path / "d.npz", d))
    np.testing.assert_array_equal(back.rom.P0, rom.P0)
    np.testing.assert_allclose(back.lqg.kf.P_prior, d.lqg.kf.P_prior, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(back.lqg.K, d.lqg.K)


def test_initial_condition_states_reproduce_the_free_responses():
    """The IC modes' outputs times each sample's coordinates give its free response's output
    deviation (to the share of the energy they hold)."""
    from sep_control.design.initial_prior import fit_initial_prior
    from sep_plant.protocol import fields, nominal_states, outputs, rollout

    plant = make_plant("allen_cahn", {"nodes": [10, 10], "initial_spread": 0.05})
    rng = np.random.default_rng(1)
    U = 0.1 * rng.standard_normal((15, plant.n_u))
    X = nominal_states(plant, U)
    prior = fit_initial_prior(plant, U, outputs(plant, X), fields(plant, X), samples=16)
    assert prior is not None and prior.run_steps == 16 * 15
    X0 = initial_states(plant, 0, range(16))
    dF = fields(plant, rollout(plant, X0, U)) - fields(plant, X)[None]          # (16, 16, n_field)
    Gc = prior.G.reshape(-1, prior.n_c)
    c, *_ = np.linalg.lstsq(Gc, dF.reshape(16, -1).T, rcond=None)
    rel = np.linalg.norm(Gc @ c - dF.reshape(16, -1).T) / np.linalg.norm(dF)
    assert rel < 0.05
    np.testing.assert_allclose(np.diag(prior.cov), np.sort(np.diag(prior.cov))[::-1])
