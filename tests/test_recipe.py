"""Recipes (time-varying targets, hold segments) and input rate limits (issue 31).

* the target expression takes t (seconds); the parser stays a whitelist;
* recipe segments resolve to steps (a shared step belongs to the earlier segment; gaps weigh
  q_outside and take the next segment's target), bad recipes are refused with a clear message;
* the metrics per hold: in band = in band over every hold; the streamed accumulator equals
  the batch `summarize`, per segment too;
* the rate clip everywhere: `clip_rate`, the nominal optimizer (a feasible nominal), the LQR
  law (after the box clip), the plant episode (counts `rate_clips`), the Monte Carlo's counts;
* the ROM-MPC's rate rows: its inputs never violate the rate limits (the plant clips nothing)
  and the vectorized feasibility test equals a row-by-row one;
* design file version 6 stores the per-step target and reads it back; the shipped scenarios
  still mean what they meant (no recipe, no rate limit, problem dicts unchanged);
* a lockstep recipe episode over topics (plant, lqg, record) equals the offline Monte Carlo run
  to 1e-9, and the bag report shows the per-hold results and the recipe figure.
"""
from pathlib import Path

import numpy as np
import pytest
import yaml

from core_helpers import TINY_YAML, one_blas_thread  # noqa: F401
from recorded_lockstep import run_recorded_episode
from sep_control.control.controllers import LqrLaw
from sep_control.design.pipeline import run_design
from sep_control.design.settings import DesignSettings
from sep_control.evaluation.metrics import MetricsAccumulator, in_band, summarize
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.design_file import VERSION, load_design, save_design
from sep_plant.plant_episode import PlantEpisode
from sep_plant.problem import Objective, Problem, ProblemError
from sep_plant.protocol import clip_rate, rate_clip_sequence, rate_feasible
from sep_plant.scenario import load_scenario

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = REPO / "sep_plant" / "scenarios"
XYZ = np.column_stack([np.linspace(0, 1, 4), np.zeros(4), np.zeros(4)])
RECIPE = [{"start": 0, "end": 3, "target": "70 + 10 * t", "weight": 0.01},
          {"start": 3, "end": 5, "target": 100, "band": 3},
          {"start": 6, "end": 8, "target": [1, 2, 3, 4], "band": 5, "weight": 2}]
#: the tiny slab (N = 40, dt = 1.5625 s) with a recipe and rate limits that bind
TINY_RECIPE = dict(
    recipe=[{"start": 0, "end": 20, "target": "100 + 50 * t / 20", "weight": 0.05},
            {"start": 20, "end": 40, "target": 150, "band": 3},
            {"start": 40, "end": 47, "target": "150 + 10 * (t - 40) / 7", "weight": 0.05},
            {"start": 47, "end": 62.5, "target": 160, "band": 3}],
    band_window=[13, 40], lqr_k_switch=0, lqr_q_early=1.0, u_min=0.0, u_max=0.6, du_max=0.03)
FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1)


def recipe_yaml() -> str:
    """The tiny slab scenario (`TINY_YAML`) with `TINY_RECIPE`'s problem keys, as a scenario file."""
    base = yaml.safe_load(TINY_YAML)
    return yaml.safe_dump({"plant": {"type": "slab", "n_x": base["n_x"], "dt": base["dt"]},
                           "n_steps": base["n_steps"], "w_std": base["w_std"], "v_std": base["v_std"], **TINY_RECIPE})


# ------------------------------------------------------------------ the problem
def test_target_expression_in_t_gives_a_target_per_step():
    p = Problem.from_dict({"n_steps": 20, "target": "100 + 50 * minimum(t / 5, 1) + x"})
    assert p.time_varying and not p.rate_limited
    f = Objective.of(p, XYZ, 0.5).target
    assert f.shape == (21, 4)
    np.testing.assert_allclose(f[:, 0], 100 + 50 * np.minimum(np.arange(21) * 0.5 / 5, 1))
    np.testing.assert_allclose(f[7] - f[7, 0], XYZ[:, 0])
    with pytest.raises(ProblemError, match="time step"):
        Objective.of(p, XYZ)
    with pytest.raises(ProblemError, match="target_steps"):
        p.target_field(XYZ)
    with pytest.raises(ProblemError, match="unknown name 'time'"):
        Problem(target="time + 1")
    with pytest.raises(ProblemError, match="Attribute"):
        Problem(target="t.__class__")


def test_recipe_segments_steps_weights_and_gaps():
    p = Problem.from_dict({"n_steps": 20, "band_window": [5, 20], "recipe": RECIPE})
    assert p.segment_steps(0.5) == [(0, 6), (7, 10), (12, 16)]    # k = 6 (t = 3 s) is segment 0's
    o = Objective.of(p, XYZ, 0.5)
    assert o.holds == ((7, 10, 3.0), (12, 16, 5.0)) and o.window == (7, 16) and o.band == 3.0
    np.testing.assert_allclose(o.q[:7], 0.01)
    np.testing.assert_allclose(o.q[7:11], 1.0)
    np.testing.assert_allclose(o.q[[11, 17, 20]], p.q_outside)     # gaps
    np.testing.assert_allclose(o.q[12:17], 2.0)
    np.testing.assert_allclose(o.target[:7, 2], 70 + 10 * 0.5 * np.arange(7))
    np.testing.assert_allclose(o.target[11], [1, 2, 3, 4])         # a gap: the next segment's target
    np.testing.assert_allclose(o.target[20], [1, 2, 3, 4])         # after the last: the last one's
    # round trip of the scenario dict; the default problem's dict has no recipe/du_max keys
    assert Problem.from_dict(p.to_dict()) == p
    assert "recipe" not in Problem().to_dict() and "du_max" not in Problem().to_dict()


@pytest.mark.parametrize("recipe, message", [
    ([{"start": 0, "end": 1, "target": 1}], "at least one hold"),
    ([{"start": 0, "end": 1, "target": "__import__('os')", "band": 1}], "not allowed"),
    ([{"start": 2, "end": 3, "target": 1, "band": 1}, {"start": 1, "end": 4, "target": 1, "band": 1}], "time order"),
    ([{"start": 0, "end": 1, "target": 1, "band": 1, "hold": 1}], "unknown key"),
    ([{"start": 0, "target": 1, "band": 1}], "missing key 'end'"),
    ([{"start": 0, "end": 1, "target": 1, "band": -1}], "band must be"),
    ([], "non-empty list"),
])
def test_bad_recipes_are_refused(recipe, message):
    with pytest.raises(ProblemError, match=message):
        Problem.from_dict({"recipe": recipe})


def test_recipe_with_the_objectives_schedule_for_the_field_weighting_is_refused():
    rec = [{"start": 0, "end": 1, "target": 1, "band": 1}]
    with pytest.raises(ProblemError, match="lqr_field_time: objective is not available with a recipe"):
        Problem.from_dict({"recipe": rec, "lqr_weighting": "field", "lqr_field_time": "objective"})
    assert Problem.from_dict({"recipe": rec, "lqr_weighting": "field"}).lqr_field_time == "lqr"


def test_recipe_that_does_not_fit_the_horizon_or_the_grid_is_refused():
    p = Problem.from_dict({"n_steps": 10, "recipe": [{"start": 0, "end": 8, "target": 1, "band": 1}]})
    with pytest.raises(ProblemError, match="past the horizon"):
        Objective.of(p, XYZ, 0.5)
    p = Problem.from_dict({"n_steps": 10, "recipe": [{"start": 0, "end": 2, "target": [1, 2], "band": 1}]})
    with pytest.raises(ProblemError, match="has 2 values"):
        p.check_dims(1, 1, 1, XYZ, 0.5)
    with pytest.raises(ProblemError, match="du_max must be > 0"):
        Problem(du_max=0.0)
    with pytest.raises(ProblemError, match="du_max has 2 entries"):
        Problem(du_max=(0.1, 0.2)).check_dims(3, 1, 3, XYZ)


# ------------------------------------------------------------------ the metrics
def test_metrics_per_hold_and_streamed_equal_batch():
    p = Problem.from_dict({"n_steps": 20, "band_window": [5, 20], "recipe": RECIPE})
    o = Objective.of(p, XYZ, 0.5)
    rng = np.random.default_rng(3)
    F = o.target[None] + rng.normal(0, 1.2, (50, 21, 4))
    F[7, 12, 1] += 10.0                                   # run 7 leaves the second hold's band only
    F[9, 8, 0] += 10.0                                    # run 9 leaves the first hold's only
    U = rng.normal(0, 1, (50, 20, 2))
    ok = in_band(F, o)
    dev1 = np.max(np.abs(F[:, 7:11] - o.target[7:11]), axis=(1, 2))
    dev2 = np.max(np.abs(F[:, 12:17] - o.target[12:17]), axis=(1, 2))
    np.testing.assert_array_equal(ok, (dev1 <= 3) & (dev2 <= 5))
    assert not ok[7] and not ok[9]
    out = summarize(F, U, o.target, o)
    seg = out["segments"]
    assert [s["k_start"] for s in seg] == [7, 12] and seg[1]["band"] == 5.0
    assert seg[0]["in_band"] == np.mean(dev1 <= 3) and seg[1]["max_dev"] == dev2.max()
    assert seg[1]["max_dev_p99"] == np.percentile(dev2, 99)
    np.testing.assert_allclose(out["cost_mean"], np.mean(o.cost(F, U)))
    # the cost's field term uses f*_k of each step
    e = np.mean((F[:, 1:] - o.target[1:]) ** 2, axis=-1)
    np.testing.assert_allclose(o.cost(F, U), e @ o.q[1:] + o.r_u * np.sum(U**2, axis=(1, 2)))
    acc = MetricsAccumulator(o, o.target, 50)
    for k in range(21):
        acc.add_field(k, F[:, k])
        if k < 20:
            acc.add_input(k, U[:, k])
    streamed = acc.result()
    for key in ("cost_mean", "cost_std", "in_band", "rms"):
        np.testing.assert_allclose(streamed[key], out[key], rtol=1e-12)
    assert streamed["segments"] == out["segments"]


# ------------------------------------------------------------------ rate limits
def test_clip_rate_and_feasibility():
    prev = np.array([[0.0, 1.0], [0.5, 0.5]])
    u = np.array([[0.3, 0.0], [0.55, 0.5]])
    np.testing.assert_allclose(clip_rate(u, prev, np.array([0.1, 0.2])), [[0.1, 0.8], [0.55, 0.5]])
    assert clip_rate(u, None, 0.1) is u and clip_rate(u, prev, np.inf) is u
    U = rate_clip_sequence(np.array([[0.0], [1.0], [0.0], [0.05]]), 0.3)
    np.testing.assert_allclose(U[:, 0], [0.0, 0.3, 0.0, 0.05])
    assert rate_feasible(U, 0.3) and not rate_feasible(np.array([[0.0], [1.0]]), 0.3)
    np.testing.assert_array_equal(rate_feasible(np.stack([U, U * 4]), 0.3), [True, False])


class _FakeLQG:
    def __init__(self, K):
        self.K = K


def test_lqr_law_rate_clip_after_the_box_clip():
    K = np.tile(np.eye(2)[None], (3, 1, 1))
    law = LqrLaw(_FakeLQG(K), np.zeros((3, 2)), np.array([0.0, 0.0]), np.array([1.0, 1.0]), du_max=np.array([0.1, 0.5]))
    u0 = law.command(0, np.array([[0.8, 2.0], [0.0, 0.0]]))      # step 0: box only
    np.testing.assert_allclose(u0, [[0.8, 1.0], [0.0, 0.0]])
    u1 = law.command(1, np.array([[0.0, -3.0], [0.05, 0.9]]))     # box to [0, 1], then within du of u0
    np.testing.assert_allclose(u1, [[0.7, 0.5], [0.05, 0.5]])
    assert law.rate_clips == 3


def test_plant_episode_enforces_and_counts_rate_clips():
    sc = load_scenario(None).with_plant(n_x=10)
    problem = sc.problem.replace(n_steps=4, band_window=(2, 4), lqr_k_switch=1, u_min=0.0, u_max=1.0, du_max=0.2)
    plant = sc.plant
    ep = PlantEpisode(plant, problem, keep_trajectory=True)
    cmds = iter([np.full(5, 0.9), np.full(5, 0.0), np.full(5, 0.1), np.full(5, 2.0)])

    class Sink:
        def clock(self, k): pass
        def measurement(self, k, y): pass
        def applied(self, k, u): pass
        def field(self, k, f): pass
        def deadline_miss(self, k, period): pass

    def wait(t_end, done):
        if not done():
            from sep_plant import topics
            ep.command(ep.k * topics.dt_ns(plant.dt), list(plant.input_names), list(next(cmds)))
        return done()

    ep.run(wait, Sink())
    np.testing.assert_allclose(ep.U[:, 0], [0.9, 0.7, 0.5, 0.7])
    assert ep.rate_clips == 3 * 5


# ------------------------------------------------------------ designs with a recipe
@pytest.fixture(scope="module")
def recipe_design(tmp_path_factory):
    from threadpoolctl import threadpool_limits

    root = tmp_path_factory.mktemp("recipe")
    (root / "recipe.yaml").write_text(recipe_yaml())
    sc = load_scenario(root / "recipe.yaml")
    with threadpool_limits(1):
        d = run_design(sc.plant, sc.problem, DesignSettings(**FAST), show_progress=False, log=lambda m: None)
    path = root / "recipe.npz"
    save_design(path, d)
    return sc, d, path


def test_the_nominal_is_rate_feasible_and_the_file_round_trips(recipe_design):
    sc, d, path = recipe_design
    du = d.problem.channels("du_max", d.info.n_u)
    assert rate_feasible(d.nominal.u, du)
    assert np.any(np.abs(np.diff(d.nominal.u, axis=0)) >= du - 1e-9), "the rate limit should bind on the nominal"
    back = load_design(path)
    with np.load(path, allow_pickle=False) as z:
        assert z["target"].shape == (d.n_steps + 1, d.info.n_field)
    assert VERSION == 6
    np.testing.assert_array_equal(back.objective.target, d.objective.target)
    assert back.objective.holds == d.objective.holds and back.problem == d.problem
    np.testing.assert_array_equal(back.objective.q, d.objective.q)
    # the design summary gives the nominal's worst deviation per hold
    from sep_control.cli.design import design_summary, format_summary
    from sep_control.evaluation.metrics import segment_max_dev

    per_hold = segment_max_dev(d.nominal.field[None], d.objective)[:, 0]
    np.testing.assert_allclose(d.meta["validation"]["max_dev_per_hold"], per_hold, rtol=1e-12)
    assert "per hold: " + f"{per_hold[0]:.3g} (band 3)" in format_summary(design_summary(back), "x")


def test_monte_carlo_rate_counts_and_mpc_rate_rows(recipe_design, one_blas_thread):
    sc, d, _ = recipe_design
    du = d.problem.channels("du_max", d.info.n_u)
    lqg = simulate(sc.plant, d, "rom_lqg", 1, 16)
    s = lqg.summary
    assert s["rate_clips"] > 0 and s["rate_violations"] == 0 and 0 < s["rate_at_limit"] < 1
    assert np.all(rate_feasible(lqg.U, du, tol=1e-12))
    assert len(s["segments"]) == 2
    mpc = simulate(sc.plant, d, "rom_mpc", 1, 16, mpc={"horizon": 6})
    assert mpc.summary["rate_violations"] == 0, "the plant should never clip the MPC"
    assert np.all(rate_feasible(mpc.U, du, tol=1e-12))
    assert mpc.summary["mpc_qp_steps"] > 0
    lo, hi = d.problem.limits(d.info.n_u)
    assert np.all(mpc.U >= lo) and np.all(mpc.U <= hi)


def test_mpc_vectorized_rate_check_equals_the_inputs_checked_one_by_one(recipe_design):
    from sep_control.control.mpc import RomMPC

    sc, d, _ = recipe_design
    H = 5
    mpc = RomMPC(d.lqg, d.problem, d.nominal.u, horizon=H)
    lo, hi = d.problem.limits(d.info.n_u)
    rng = np.random.default_rng(0)
    checked = 0
    for k in (1, 10, 30, 37):
        A = rng.normal(0, 0.3, (60, mpc.n))
        prev = np.clip(d.nominal.u[k - 1] + rng.normal(0, 0.02, (60, mpc.n_u)), lo, hi)
        Z = mpc.unconstrained(k, A)
        L, U = mpc.rate_bounds(k, prev)
        rows = mpc._rows(Z)
        vec = np.all((rows >= L - 1e-12) & (rows <= U + 1e-12), axis=1)
        Hk = min(H, d.n_steps - k)
        for r in range(60):                                   # the inputs themselves, run by run
            u = d.nominal.u[k:k + Hk] + Z[r].reshape(H, -1)[:Hk]
            steps = np.diff(np.vstack([prev[r], u]), axis=0)
            slack = np.concatenate([(u - lo).ravel(), (hi - u).ravel(), (mpc.du_max - np.abs(steps)).ravel()])
            if np.min(np.abs(slack)) < 1e-9:                  # on a bound to rounding: either answer
                continue
            assert vec[r] == bool(np.all(slack > 0))
            checked += 1
    assert checked > 100


# ----------------------------------------------------------------- old scenarios
@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_scenarios_without_a_recipe_mean_what_they_meant(path):
    sc = load_scenario(path)
    p = sc.problem
    if path.stem == "plate_anneal":
        assert p.recipe is not None and p.rate_limited and p.time_varying
        return
    d = p.to_dict()
    assert "recipe" not in d and "du_max" not in d and not p.time_varying and not p.rate_limited
    o = Objective.of(p, np.asarray(sc.plant.field_coordinates()), sc.plant.dt)
    assert o.holds is None and o.target.ndim == 1 and o.segments == ((o.window[0], o.window[1], o.band),)


# ----------------------------------------------------------- over topics, bag report
@pytest.mark.ros
def test_lockstep_recipe_over_topics_equals_offline_and_the_report_shows_the_holds(tmp_path, recipe_design, procs):
    from sep_control.bags.analysis import analyze
    from sep_control.bags.report import write_report
    from sep_control.evaluation import metrics as M

    sc, _, design_path = recipe_design
    scen = design_path.parent / "recipe.yaml"
    seed, run = 7, 2
    run_recorded_episode(tmp_path, design_path, scen, seed, run, procs, plant_params=("summary_file:=plant.json",))
    design = load_design(design_path)
    ref = simulate(design.scenario.plant, design, "rom_lqg", seed, range(run, run + 1))
    live = np.load(tmp_path / "traj.npz", allow_pickle=False)
    assert np.max(np.abs(live["U"] - ref.U[0])) <= 1e-9
    assert np.max(np.abs(live["F"] - ref.F[0])) <= 1e-9
    assert np.any(np.abs(np.diff(live["U"], axis=0)) >= design.problem.channels("du_max", design.info.n_u) - 1e-12)
    import json
    assert json.loads((tmp_path / "plant.json").read_text())["rate_clips"] == 0     # the law clipped itself
    rep = analyze(tmp_path / "bag", design)
    assert np.max(np.abs(rep.episode.F - ref.F[0])) <= 1e-9
    want = M.summarize(ref.F, ref.U, design.nominal.field, design.objective)["segments"]
    assert len(want) == 2
    for got, w in zip(rep.metrics["segments"], want):
        assert got["k_start"] == w["k_start"] and got["in_band"] == w["in_band"]
        assert got["max_dev"] == pytest.approx(w["max_dev"], abs=1e-9)
    text = write_report(rep, tmp_path / "report").read_text()
    assert "## Hold segments" in text and "recipe, hold segments" in text
    assert f"{want[1]['max_dev']:.4g}" in text
    assert (tmp_path / "report" / "recipe.png").exists()
