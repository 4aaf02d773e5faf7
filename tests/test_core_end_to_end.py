"""End to end: design on a coarse grid meets the band; the reference design meets the reference anchors of docs/method.md."""
import numpy as np
import pytest

from core_helpers import cached_design, cached_oracle, coarse_scenario
from core_helpers import one_blas_thread  # noqa: F401  (fixture)
from sep_control.evaluation.metrics import in_band, nominal_cost
from sep_control.evaluation.montecarlo import simulate
from sep_control.design.tvera import markov_relative_error
from sep_plant.protocol import nominal_states
from sep_plant.scenario import reference as reference_scenario

pytestmark = pytest.mark.usefixtures("one_blas_thread")


def monte_carlo(design, oracle, runs, seed=1):
    plant = design.scenario.plant
    return {name: simulate(plant, design, name, seed, runs, oracle=oracle, keep_estimates=2).metrics()
            for name in ("open_loop", "rom_lqg", "oracle_lqg")}


# ----------------------------------------------------------------- coarse grid
# n_x = 30, N = 80 (dt = 0.78125 s, same 62.5 s horizon, band from 37.5 s, LQR switch at 30 s),
# noise rescaled to the same continuous-time intensity (see core_helpers.coarse_scenario).
COARSE = coarse_scenario(30, 80)


@pytest.fixture(scope="module")
def coarse():
    return cached_design(COARSE), cached_oracle(COARSE)


def test_coarse_scenario_is_what_the_comment_says():
    p, plant = COARSE.problem, COARSE.plant
    assert (plant.n_x, p.n_steps, p.window, p.k_switch) == (30, 80, (48, 80), 38)
    assert p.window[0] * plant.dt == pytest.approx(37.5) and p.n_steps * plant.dt == pytest.approx(62.5)
    assert p.w_std == pytest.approx(0.3 * np.sqrt(0.25 / plant.dt)) and p.v_std == pytest.approx(np.sqrt(0.25 / plant.dt))


def test_coarse_design_nominal_and_rom(coarse):
    d, _ = coarse
    plant, k0, nom = d.scenario.plant, d.objective.window[0], d.nominal
    # the stored nominal is the simulator's noise-free trajectory of the stored inputs
    T = nominal_states(plant, nom.u)
    np.testing.assert_allclose(nom.field, T, rtol=1e-12)
    np.testing.assert_allclose(nom.y, T[:, plant.sensor_nodes()], rtol=1e-12)
    # nominal: whole field inside the band over the band window, in fact well inside
    dev = np.max(np.abs(nom.field[k0:] - 150.0))
    assert dev < 0.5 < d.objective.band
    assert d.meta["optimizer"]["nominal_cost"] == pytest.approx(float(nominal_cost(T, nom.u, d.objective)), rel=1e-12)
    # ROM: Markov parameters match the experiments (the default plan 0.9's strided impulses put
    # their interpolation's error in: 2.9e-7; plan 0.8's every start step 4e-9); order grows by n_u from k = 0
    assert d.meta["validation"]["markov_rel_error"] < 1e-6
    assert list(d.rom.dims[:4]) == [0, 5, 10, 15] and d.rom.dims.max() <= 20
    # the identified model knows which field nodes the sensors read (C_k rows = G_k rows, in the
    # directions the state takes: the design's field map is compressed to those)
    from sep_estimator.ltv import sensed_nodes
    assert sensed_nodes(d.rom, P=d.lqg.kf.P_prior[-1]) == list(plant.sensor_nodes())
    # belief: the EnKF along the nominal observations follows the nominal, with a spread
    assert np.max(np.abs(nom.belief_mean[k0:] - 150.0)) < d.objective.band
    assert np.all(nom.belief_std[0] == 0) and np.all(nom.belief_std[1:].max(axis=1) > 0)


def test_coarse_design_monte_carlo_meets_the_band(coarse):
    d, orc = coarse
    m = monte_carlo(d, orc, 200)
    assert m["rom_lqg"]["in_band"] >= 0.99
    assert m["oracle_lqg"]["in_band"] >= 0.99
    assert m["open_loop"]["in_band"] < 0.75
    assert abs(m["rom_lqg"]["cost_mean"] / m["oracle_lqg"]["cost_mean"] - 1) < 0.01
    assert m["rom_lqg"]["cost_mean"] < 0.5 * m["open_loop"]["cost_mean"]
    # the filter is consistent: ~95 % of the field errors inside 2 sigma
    assert 0.92 < m["rom_lqg"]["coverage_2sigma"] < 0.98
    for name, row in m.items():
        assert row["n_runs"] == 200


def test_monte_carlo_common_random_numbers_and_run_subsets(coarse):
    """Runs are reproducible one by one: run i of seed s is the same whatever batch it is in."""
    d, orc = coarse
    plant = d.scenario.plant
    full = simulate(plant, d, "rom_lqg", 5, 12)
    part = simulate(plant, d, "rom_lqg", 5, range(7, 10))
    np.testing.assert_allclose(part.F, full.F[7:10], rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(part.U, full.U[7:10], rtol=1e-12, atol=1e-12)
    # every controller sees the same measurement noise at k = 0 (same plant state there)
    ol = simulate(plant, d, "open_loop", 5, 12)
    np.testing.assert_array_equal(ol.Y[:, 0], full.Y[:, 0])
    np.testing.assert_allclose(ol.U, np.broadcast_to(d.nominal.u, ol.U.shape))
    # in_band metric agrees with a direct check
    assert np.mean(in_band(full.F, d.objective)) == full.metrics()["in_band"]
    with pytest.raises(ValueError, match="controller"):
        simulate(plant, d, "pid", 5, 2)


def test_monte_carlo_respects_input_limits(coarse):
    d, _ = coarse
    from dataclasses import replace

    limited = replace(d, scenario=d.scenario.replace(u_min=0.0, u_max=float(d.nominal.u.max()) + 0.05))
    res = simulate(d.scenario.plant, limited, "rom_lqg", 3, 20)
    assert res.U.min() >= 0.0 and res.U.max() <= limited.problem.u_max
    # per-input limits too
    lo = [0.0, 0.05, 0.0, 0.05, 0.0]
    limited = replace(d, scenario=d.scenario.replace(u_min=lo, u_max=float(d.nominal.u.max()) + 0.05))
    res = simulate(d.scenario.plant, limited, "rom_lqg", 3, 20)
    assert np.all(res.U.min(axis=(0, 1)) >= lo)


# -------------------------------------------------------------- reference design
@pytest.fixture(scope="module")
def reference():
    s = reference_scenario()
    return cached_design(s), cached_oracle(s)


def test_reference_design_meets_the_acceptance_numbers(reference):
    """docs/method.md anchors / issue 2 acceptance at the shipped defaults (n_x = 100, N = 250)."""
    d, orc = reference
    assert d.scenario == reference_scenario()
    dev = np.max(np.abs(d.nominal.field[150:] - 150.0))
    assert dev <= d.objective.band
    assert dev < 0.5                          # the anchor is ~0.2 F
    assert d.rom.dims.max() == 20
    assert d.meta["validation"]["markov_rel_error"] <= 1e-5       # plan 0.9: 1.7e-6 (the stride's interpolation)
    m = monte_carlo(d, orc, 300)
    assert m["rom_lqg"]["in_band"] >= 0.99
    assert abs(m["rom_lqg"]["cost_mean"] / m["oracle_lqg"]["cost_mean"] - 1) < 0.01
    assert m["open_loop"]["in_band"] < 0.6    # "about a third"


@pytest.fixture(scope="module")
def reference_08():
    """The reference design under plan 0.8 (0.8.0's: central impulses at every start step, the
    model identified at the final input): TV-ERA's own accuracy."""
    return cached_design(reference_scenario(), experiment_plan="0.8")


def test_reference_rom_matches_long_impulse_experiments(reference_08):
    """Re-running the identification reproduces the stored ROM and its recorded Markov error,
    and the ROM predicts impulse responses far beyond the identification lags (p + q = 30):
    lags up to 80 steps (20 s), relative error <= 1e-6 (docs/method.md: "far below 1e-6")."""
    from sep_control.design.pipeline import DesignSettings, identify_rom
    from sep_control.design.tvera import impulse_experiments

    d = reference_08
    st = DesignSettings.from_meta(d.meta)
    sim = d.scenario.plant
    ident = identify_rom(sim, d.nominal.u, st)
    real = ident.model
    np.testing.assert_allclose(real.A, d.rom.A, rtol=0, atol=1e-12 * np.abs(d.rom.A).max())
    assert markov_relative_error(real, ident.data.Y) == pytest.approx(d.meta["validation"]["markov_rel_error"],
                                                                      rel=1e-6)
    lags = 80
    long = impulse_experiments(sim, d.nominal.u, lags, 1, ident.delta)
    N = d.n_steps
    valid = (np.arange(N)[:, None] + np.arange(1, lags + 1)[None, :]) <= N
    Yr = real.markov_all(lags)
    assert np.linalg.norm((Yr - long.Y)[valid]) / np.linalg.norm(long.Y[valid]) <= 1e-6
