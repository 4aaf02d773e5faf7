"""End to end: a lockstep episode (plant + lqg processes) recorded by `record`, analysed offline.

Acceptance (issue 4): the bag's metrics equal the live run's (the plant's own trajectory file
through `metrics.summarize`) and the field trajectory from the bag equals the offline Monte
Carlo run with the same seed/run (`montecarlo.simulate(design, 'rom_lqg', seed, [run])`).
Small scenario for speed; isolated DDS domain (conftest.py); processes always cleaned up.
"""
from __future__ import annotations

import numpy as np
import pytest

from recorded_lockstep import run_recorded_episode

pytestmark = pytest.mark.ros

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=19)
SEED, RUN = 7, 2


@pytest.fixture(scope="module")
def small_design(tmp_path_factory):
    from sep_control.design.pipeline import run_design
    from sep_estimator.design_file import save_design
    from sep_plant.scenario import load_scenario

    d = tmp_path_factory.mktemp("e2e_design")
    (d / "small.yaml").write_text("".join(f"{k}: {v}\n" for k, v in SMALL.items()))
    s = load_scenario(d / "small.yaml")
    design = run_design(s.plant, s.problem, show_progress=False, log=lambda *a, **k: None)
    path = save_design(d / "design.npz", design)
    return path, d / "small.yaml"


def test_lockstep_episode_bag_equals_live_run_and_offline(tmp_path, small_design, procs):
    from sep_control.evaluation import metrics as M
    from sep_control.evaluation import montecarlo
    from sep_control.bags.analysis import analyze
    from sep_estimator.design_file import load_design

    design_path, scen = small_design
    run_recorded_episode(tmp_path, design_path, scen, SEED, RUN, procs)

    design = load_design(design_path)
    rep = analyze(tmp_path / "bag", design)
    ep = rep.episode
    assert ep.complete and not ep.missing, (ep.missing, ep.notes)
    live = np.load(tmp_path / "traj.npz", allow_pickle=False)
    # the bag holds exactly what the plant simulated and applied
    np.testing.assert_array_equal(ep.F, live["F"])
    np.testing.assert_array_equal(ep.u, live["U"])
    np.testing.assert_array_equal(ep.y, live["Y"])
    # metrics equal the live run's to printing precision (here: exactly)
    ref = M.summarize(live["F"][None], live["U"][None], design.nominal.field, design.objective)
    for k, v in ref.items():
        assert M._fmt(rep.metrics[k]) == M._fmt(v), k
        assert rep.metrics[k] == pytest.approx(v, rel=1e-12, abs=1e-12), k
    assert rep.metrics["deadline_misses"] == 0 and rep.metrics["rejected_messages"] == 0
    assert rep.metrics["latency_p50_s"] is not None and 0 < rep.metrics["latency_p50_s"] < 1.0
    # the offline Monte Carlo run with the same seed/run: same trajectory, same estimates
    mc = montecarlo.simulate(design.scenario.plant, design, "rom_lqg", SEED, range(RUN, RUN + 1))
    assert np.max(np.abs(ep.F - mc.F[0])) <= 1e-9
    assert np.max(np.abs(ep.F_hat - mc.F_hat[0])) <= 1e-9
    assert rep.metrics["coverage_2sigma"] == pytest.approx(mc.coverage_2sigma, abs=1e-12)
    # the bag opens with rosbags' AnyReader too
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "bag"]) as reader:
        assert {c.topic for c in reader.connections} >= {"/sep/measurements", "/sep/command", "/sep/field"}
