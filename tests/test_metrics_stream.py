"""The streamed Monte Carlo metrics equal the array formulas on the same runs."""
import numpy as np

from sep_control.metrics import MetricsAccumulator, summarize
from sep_plant.scenario import Scenario


def test_accumulator_equals_summarize_on_random_trajectories():
    s = Scenario(n_x=12, n_steps=30, k_band=18, lqr_k_switch=12)
    rng = np.random.default_rng(4)
    M = 40
    spread = np.linspace(0.2, 2.0, M)[:, None, None]                     # some runs leave the band
    T = 150.0 + rng.standard_normal((M, s.n_steps + 1, s.n_x)) * spread
    U = rng.standard_normal((M, s.n_steps, s.n_u))
    T_nom = 150.0 + rng.standard_normal((s.n_steps + 1, s.n_x)) * 0.1
    acc = MetricsAccumulator(s, T_nom, M)
    for k in range(s.n_steps + 1):
        acc.add_state(k, T[:, k])
        if k < s.n_steps:
            acc.add_input(k, U[:, k])
    ref = summarize(T, U, T_nom, s)
    got = acc.result()
    assert 0.0 < ref["in_band"] < 1.0
    for key, val in ref.items():
        assert np.isclose(got[key], val, rtol=1e-12, atol=0), key
    np.testing.assert_allclose(acc.mean_traj, T.mean(axis=0), rtol=0, atol=1e-12)


def test_monte_carlo_keeps_only_requested_trajectories(tmp_path):
    from sep_control.design import DesignSettings, run_design
    from sep_control.montecarlo import simulate

    s = Scenario(n_x=20, n_steps=40, k_band=24, lqr_k_switch=19)
    d = run_design(s, DesignSettings(belief=False, ensemble=20, p=5, q=5, n_r=10), show_progress=False,
                   log=lambda m: None)
    full = simulate(d, "rom_lqg", 2, 16)
    slim = simulate(d, "rom_lqg", 2, 16, keep_trajectories=1, keep_estimates=0)
    assert slim.T.shape == (1, s.n_steps + 1, s.n_x) and slim.T_hat.shape[0] == 0
    np.testing.assert_array_equal(slim.T[0], full.T[0])
    assert slim.summary == full.summary
    ref = summarize(full.T, full.U, d.T_nom, s)
    for key, val in ref.items():
        assert np.isclose(full.summary[key], val, rtol=1e-12), key
