"""analyze / aggregate / analyze CLI / report on synthetic contract bags with known metrics: the slab,
sep 0.1 slab bags (its scenario payload, its topic names) and a 2-D grid plant (heat-map figures,
the image topic rendered); the progress hook in run-steps."""
from __future__ import annotations

import json
import subprocess
import sys
import os
from pathlib import Path

import numpy as np
import pytest

from bag_synth import (LAT_CMD_NS, LAT_EST_NS, fake_design, grid_episode, legacy_episode, small_scenario,
                       synthetic_episode, write_bag)
from sep_control.evaluation import metrics as M
from sep_control.bags.analysis import AnalysisError, aggregate, analyze
from sep_control.cli.analyze import main as cli
from sep_control.bags.figures import render_image_frame
from sep_control.bags.report import write_report
from sep_control.bags.storage import BagError
from sep_estimator.design_file import save_design
from sep_plant import topics as T

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    d = tmp_path_factory.mktemp("analyze")
    eps = [synthetic_episode(small_scenario(), seed=i) for i in range(4)]
    bags = [write_bag(d / f"ep{i}", e) for i, e in enumerate(eps)]
    design = fake_design(eps[0])
    dpath = save_design(d / "design.npz", design)
    return d, eps, bags, dpath


def expected(ep, design):
    obj = design.objective
    k0, k1 = obj.window
    err = ep.F_hat[1:] - ep.F[1:]
    return {
        "cost_mean": float(M.nominal_cost(ep.F, ep.u, obj)),
        "in_band": float(M.in_band(ep.F, obj)),
        "rms": float(M.rms_in_window(ep.F, obj)),
        "mean_dev_start": M.mean_deviation(ep.F[None], design.nominal.field, k0),
        "mean_dev_end": M.mean_deviation(ep.F[None], design.nominal.field, k1),
        "coverage_2sigma": M.coverage_2sigma(err, ep.F_std[1:]),
    }


def test_single_episode_metrics_exact(setup):
    d, eps, bags, dpath = setup
    rep = analyze(bags[0], dpath)
    m = rep.metrics
    for k, v in expected(eps[0], rep.design).items():
        assert m[k] == v, k
    assert m["n_runs"] == 1 and m["cost_std"] == 0.0
    assert m["latency_p50_s"] == pytest.approx(LAT_CMD_NS * 1e-9, abs=1e-15)
    assert m["latency_p99_s"] == pytest.approx(LAT_CMD_NS * 1e-9, abs=1e-15)
    assert m["latency_estimate_p50_s"] == pytest.approx(LAT_EST_NS * 1e-9, abs=1e-15)
    assert m["deadline_misses"] == 3 and m["rejected_messages"] == 2
    assert m["complete"] is True and m["steps_recorded"] == eps[0].scenario.problem.n_steps + 1
    assert set(M.JSON_KEYS) <= set(m) and m["mean_dev_start"] is not None and m["mean_dev_end"] is not None
    np.testing.assert_array_equal(rep.err, eps[0].F_hat - eps[0].F)


def test_without_design_skips_nominal(setup):
    """Without a design the objective is the bag's scenario's, on the clouds' coordinates."""
    d, eps, bags, _ = setup
    rep = analyze(bags[1])
    m = rep.metrics
    assert m["mean_dev_start"] is None and m["mean_dev_end"] is None
    assert m["cost_mean"] == float(M.nominal_cost(eps[1].F, eps[1].u, eps[1].objective))
    assert m["in_band"] == float(M.in_band(eps[1].F, eps[1].objective))
    assert rep.objective.window == eps[1].scenario.problem.window


def test_aggregate_matches_summarize(setup):
    d, eps, bags, dpath = setup
    agg = aggregate(bags, dpath)
    F = np.stack([e.F for e in eps])
    U = np.stack([e.u for e in eps])
    ref = M.summarize(F, U, agg.design.nominal.field, agg.design.objective)
    assert {"mean_dev_start", "mean_dev_end"} <= set(ref)
    for k, v in ref.items():
        assert agg.metrics[k] == v, k
    err = np.concatenate([(e.F_hat - e.F)[1:].ravel() for e in eps])
    std = np.concatenate([e.F_std[1:].ravel() for e in eps])
    assert agg.metrics["coverage_2sigma"] == M.coverage_2sigma(err, std)
    assert agg.metrics["deadline_misses"] == 12 and agg.metrics["rejected_messages"] == 8
    assert list(agg.rows) == [f"ep{i}" for i in range(4)]


def test_scenario_mismatch_refused_or_flagged(tmp_path, setup):
    d, eps, bags, _ = setup
    other = synthetic_episode(small_scenario(k0=0.02), seed=0)
    dpath = save_design(tmp_path / "other.npz", fake_design(other))
    with pytest.raises(AnalysisError, match=r"another scenario.*plant\.k0"):
        analyze(bags[0], dpath)
    rep = analyze(bags[0], dpath, allow_mismatch=True)
    assert rep.mismatch and "k0" in rep.mismatch[0] and rep.metrics["scenario_mismatch"]
    # bags of two scenarios are not pooled
    b2 = write_bag(tmp_path / "other_bag", other)
    with pytest.raises(AnalysisError, match="another scenario"):
        aggregate([bags[0], b2])


def test_cli_one_bag_report_and_json(setup, tmp_path, capsys):
    d, eps, bags, dpath = setup
    out = tmp_path / "rep"
    rc = cli([str(bags[0]), "--design", str(dpath), "--out", str(out), "--json", str(tmp_path / "m.json")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "cost_mean" in text and f"report: {out / 'report.md'}" in text
    for f in ("report.md", "field.png", "estimation.png", "inputs.png"):
        assert (out / f).stat().st_size > 0
    md = (out / "report.md").read_text()
    assert "![Closed-loop field vs nominal](field.png)" in md and "latency = receive time" in md
    assert "plant `slab`" in md and "k = 24..40" in md and "field_image" not in md
    rows = json.loads((tmp_path / "m.json").read_text())
    assert rows[0]["name"] == "ep0" and rows[0]["deadline_misses"] == 3
    assert rows[0]["cost_mean"] == pytest.approx(expected(eps[0], fake_design(eps[0]))["cost_mean"], rel=1e-15)


def test_cli_many_bags(setup, tmp_path, capsys):
    d, eps, bags, dpath = setup
    rc = cli([*map(str, bags), "--design", str(dpath), "--out", str(tmp_path / "agg"), "--json",
              str(tmp_path / "a.json")])
    assert rc == 0
    assert "all episodes" in capsys.readouterr().out
    rows = json.loads((tmp_path / "a.json").read_text())
    assert [r["name"] for r in rows] == ["ep0", "ep1", "ep2", "ep3", "all episodes"] and rows[-1]["n_runs"] == 4
    assert "| all episodes |" in (tmp_path / "agg" / "report.md").read_text()


def test_cli_missing_topics_reported(setup, tmp_path, capsys):
    d, eps, bags, dpath = setup
    bag = write_bag(tmp_path / "partial", eps[0], skip=("/sep/field_estimate", "/diagnostics"))
    rc = cli([str(bag), "--design", str(dpath), "--out", str(tmp_path / "r")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "missing topics /sep/field_estimate, /diagnostics" in out
    md = (tmp_path / "r" / "report.md").read_text()
    assert "missing topics /sep/field_estimate, /diagnostics" in md
    assert "Estimation error with 2-sigma bounds: not drawn" in md
    assert (tmp_path / "r" / "field.png").is_file()


def _run_cli(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(REPO / p) for p in ("sep_plant", "sep_estimator", "sep_control")))
    return subprocess.run([sys.executable, "-m", "sep_control.cli.analyze", *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=120)


def test_cli_bad_input_exit_codes_without_traceback(setup, tmp_path):
    d, eps, bags, dpath = setup
    cut = tmp_path / "cut"
    cut.mkdir()
    data = next(write_bag(tmp_path / "chunked", eps[0], chunk_per_step=True).glob("*.mcap")).read_bytes()
    (cut / "cut.mcap").write_bytes(data[: len(data) // 2])
    other = save_design(tmp_path / "other.npz", fake_design(synthetic_episode(small_scenario(n_x=24))))
    corrupt = tmp_path / "corrupt"
    corrupt.mkdir()
    (corrupt / "c.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x7f" * 100)
    cases = [
        ((cut,), "truncated"), ((tmp_path / "nope",), "no such bag"), ((corrupt,), "corrupt"),
        ((bags[0], "--design", other), "another scenario"), ((bags[0], "--design", tmp_path / "none.npz"), "not found"),
    ]
    for args, needle in cases:
        p = _run_cli(*args)
        assert p.returncode == 2, (args, p.stdout, p.stderr)
        assert needle in p.stderr and "Traceback" not in p.stderr, p.stderr
    assert str(cut) in _run_cli(cut).stderr
    p = _run_cli(cut, "--allow-truncated", "--out", tmp_path / "cutrep")
    assert p.returncode == 0 and "truncated bag" in p.stdout
    empty = tmp_path / "empty_cut"
    empty.mkdir()
    (empty / "e.mcap").write_bytes(data[:200])
    p = _run_cli(empty, "--allow-truncated")
    assert p.returncode == 2 and "no messages" in p.stderr
    p = _run_cli(bags[0], "--design", other, "--allow-mismatch", "--out", tmp_path / "mm")
    assert p.returncode == 0 and "WARNING" in p.stdout and "n_x" in p.stdout
    assert "SCENARIO MISMATCH" in (tmp_path / "mm" / "report.md").read_text()


def test_old_sep01_bag_analysed(setup, tmp_path):
    """A sep 0.1 bag (flat slab scenario) is analysed like a new one, with a new design file."""
    d, eps, bags, dpath = setup
    old = legacy_episode(small_scenario(), seed=0)      # same episode as eps[0], old scenario payload
    bag = write_bag(tmp_path / "old", old)
    rep = analyze(bag, dpath)
    assert not rep.mismatch and rep.episode.scenario_source == "bag"
    for k, v in expected(old, rep.design).items():
        assert rep.metrics[k] == v, k
    assert rep.metrics == analyze(bags[0], dpath).metrics
    m = analyze(bag).metrics                           # without a design: the flat scenario's objective
    assert m["cost_mean"] == float(M.nominal_cost(old.F, old.u, old.objective)) and m["mean_dev_end"] is None
    out = tmp_path / "rep"
    write_report(rep, out)
    assert (out / "field.png").stat().st_size > 0 and (out / "estimation.png").stat().st_size > 0


@pytest.mark.parametrize("payload", ["current", "sep01"])
def test_both_namings_give_identical_metrics(setup, tmp_path, payload):
    """eps[0] written with sep 0.1's topic names (slab, heat_command, heat_applied; with its flat
    scenario JSON too for payload sep01) has exactly the metrics of the contract-named bag, with
    and without the design, alone and pooled; the report speaks of `command`."""
    d, eps, bags, dpath = setup
    ep = legacy_episode(small_scenario(), seed=0) if payload == "sep01" else eps[0]
    old = write_bag(tmp_path / "ep0", ep, naming="sep01")        # same name as bags[0]: same table rows
    for dsg in (dpath, None):
        new_rep, old_rep = analyze(bags[0], dsg), analyze(old, dsg)
        assert old_rep.metrics == new_rep.metrics, dsg
        assert not old_rep.notes and not old_rep.mismatch and old_rep.episode.scenario_source == "bag"
        np.testing.assert_array_equal(old_rep.err, new_rep.err)
    assert analyze(old, dpath).metrics["cost_mean"] == expected(eps[0], fake_design(eps[0]))["cost_mean"]
    mixed = aggregate([old, *bags[1:]], dpath)
    assert mixed.metrics == aggregate(bags, dpath).metrics
    md = write_report(analyze(old, dpath), tmp_path / "rep", figures=False).read_text()
    assert "receive time of command k" in md and "heat_" not in md


def test_progress_in_run_steps(setup):
    """on_progress(steps_done, steps_total): one bag of N steps is N run-steps; the total is
    known from the design, else after the first bag."""
    d, eps, bags, dpath = setup
    N = eps[0].scenario.problem.n_steps
    calls = []
    analyze(bags[0], dpath, on_progress=lambda done, total: calls.append((done, total)))
    assert calls == [(0, N), (N, N)]
    calls.clear()
    analyze(bags[0], on_progress=lambda done, total: calls.append((done, total)))
    assert calls == [(0, None), (N, N)]
    calls.clear()
    agg = aggregate(bags, dpath, on_progress=lambda done, total: calls.append((done, total)))
    assert calls == [(i * N, 4 * N) for i in range(5)]
    calls.clear()
    assert aggregate(bags, on_progress=lambda done, total: calls.append((done, total))).metrics["n_runs"] == 4
    assert calls == [(0, None)] + [(i * N, 4 * N) for i in range(1, 5)]
    assert aggregate(bags, dpath).metrics == agg.metrics                 # silent by default, same numbers
    from sep_control.cli.analyze import ProgressBar                      # what `sep analyze` draws
    for dsg in (dpath, None):
        with ProgressBar(enabled=False) as bar:
            assert aggregate(bags, dsg, on_progress=bar).metrics["n_runs"] == 4
        assert bar.bar.done == bar.bar.total == 4 * N


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    d = tmp_path_factory.mktemp("grid")
    eps = [grid_episode((6, 5), seed=i) for i in range(3)]
    bags = [write_bag(d / f"g{i}", e) for i, e in enumerate(eps)]
    dpath = save_design(d / "grid_design.npz", fake_design(eps[0]))
    return d, eps, bags, dpath


def test_grid_plant_bag_analysed_with_heat_maps(grid, tmp_path):
    """A 2-D grid plant (6 x 5, field phi): exact metrics, heat-map figures, the image frame."""
    d, eps, bags, dpath = grid
    rep = analyze(bags[0], dpath)
    assert rep.info.grid_shape == (6, 5) and not rep.mismatch and not rep.episode.missing
    for k, v in expected(eps[0], rep.design).items():
        assert rep.metrics[k] == v, k
    assert rep.metrics["latency_p50_s"] == pytest.approx(LAT_CMD_NS * 1e-9, abs=1e-15)
    # without the design: the scenario's expression target on the clouds' coordinates
    m = analyze(bags[0]).metrics
    assert m["cost_mean"] == float(M.nominal_cost(eps[0].F, eps[0].u, eps[0].objective))
    out = tmp_path / "rep"
    md = write_report(rep, out).read_text()
    for f in ("field.png", "estimation.png", "inputs.png", "field_image.png"):
        assert (out / f).stat().st_size > 0, f
    k1 = eps[0].scenario.problem.window[1]
    assert f"field_image at k = {k1}" in md and "grid 6 x 5" in md and "target field" in md
    # the field figure is the 2 x 3 map panel (closed loop, nominal, difference), not lines
    from sep_control.evaluation.drawing import pyplot

    assert pyplot().imread(out / "field.png").shape[1] > 1.2 * pyplot().imread(out / "inputs.png").shape[1]
    agg = aggregate(bags, dpath)
    assert agg.metrics["n_runs"] == 3 and agg.metrics["mean_dev_end"] is not None
    write_report(agg, tmp_path / "agg")
    assert (tmp_path / "agg" / "estimation.png").stat().st_size > 0


def test_grid_3d_report(tmp_path):
    gep = grid_episode((4, 3, 3), seed=4)
    rep = analyze(write_bag(tmp_path / "g3", gep), fake_design(gep))
    write_report(rep, tmp_path / "rep")
    for f in ("field.png", "estimation.png", "inputs.png", "field_image.png"):
        assert (tmp_path / "rep" / f).stat().st_size > 0, f


def test_render_image_frame_is_the_published_image(grid, tmp_path):
    """The frame as a viewer shows the 32FC1 image: row 0 on top, grey from min to max."""
    from sep_control.evaluation.drawing import pyplot

    d, eps, bags, _ = grid
    rep = analyze(bags[1])
    k = 12
    path = render_image_frame(rep, T.FIELD_IMAGE, k, tmp_path / "frame.png", scale=3)
    png = pyplot().imread(path)
    img = T.image_of_field(eps[1].F[k], (6, 5)).astype(np.float64)
    grey = np.round((img - img.min()) / (img.max() - img.min()) * 255) / 255
    assert png.shape[:2] == (18, 15)
    np.testing.assert_allclose(png[::3, ::3, 0], grey, atol=1e-6)
    assert render_image_frame(bags[1], path=tmp_path / "last.png").is_file()   # a bag path: the window's end
    with pytest.raises(BagError, match="no field_image image at step 999"):
        render_image_frame(rep.episode, T.FIELD_IMAGE, 999, tmp_path / "x.png")


def test_the_controller_is_named_from_the_lqr_diagnostics(setup, tmp_path):
    """Bags name their controller (the LQR node reports it on /diagnostics): rom_mpc with its QP
    and fallback counts; a bag without it (sep < 0.3) leaves it None."""
    from bag_synth import diagnostics, episode_messages, write_messages

    d, eps, bags, dpath = setup
    assert analyze(bags[0], dpath).metrics["controller"] is None
    msgs = episode_messages(eps[0])
    t_last = max(t for _, t, _ in msgs)
    N = eps[0].scenario.problem.n_steps
    ns = N * T.dt_ns(eps[0].info.dt)
    msgs.append((T.DIAGNOSTICS, t_last + 1, bytes(diagnostics(ns, {"controller": "mpc", "mpc_qp_steps": 12,
                                                                    "mpc_fallbacks": 1}, N, name="/sep/lqr"))))
    rep = analyze(write_messages(tmp_path / "mpc_bag", msgs), dpath)
    m = rep.metrics
    assert m["controller"] == "rom_mpc" and m["mpc_qp_steps"] == 12 and m["mpc_fallbacks"] == 1
    text = write_report(rep, tmp_path / "report", figures=False).read_text()
    assert "Controller: rom_mpc (12 steps solved a QP, 1 fell back to the clipped LQR)" in text


def _with_disturbance_estimates(ep, offset: float = 0.0):
    """The episode's messages with state_estimate k = [a_hat_k; d_k] named a_0.., d_0, d_1 (the
    estimator's labels for a design with two disturbance states), and the d_k."""
    from bag_synth import LAT_EST_NS, T0_NS, episode_messages, joint_state

    N = ep.scenario.problem.n_steps
    step = T.dt_ns(ep.info.dt)
    d = np.stack([0.01 * np.arange(N + 1) + offset, np.full(N + 1, -0.2)], axis=1)
    msgs = [m for m in episode_messages(ep) if m[0] != T.topic_name(T.STATE_ESTIMATE)]
    for k in range(N + 1):
        a = np.asarray(ep.a_hat[k])
        names = T.state_labels(len(a), 2)
        msgs.append((T.topic_name(T.STATE_ESTIMATE), T0_NS + k * step + LAT_EST_NS,
                     bytes(joint_state(k * step, names, position=np.concatenate([a, d[k]])))))
    return sorted(msgs, key=lambda m: m[1]), d


def test_disturbance_estimates_in_the_analysis_report_and_json(setup, tmp_path):
    """A bag whose state_estimate carries d_0, d_1 (a design with disturbance states): d_hat over
    the episode, d_hat_end in the metrics (the mean over episodes when pooled), the figure and the
    report line; a bag without them has none."""
    from bag_synth import write_messages

    d, eps, bags, dpath = setup
    plain = analyze(bags[0], dpath)
    assert plain.episode.d_hat.shape[1] == 0 and plain.metrics["d_hat_end"] is None
    msgs, dk = _with_disturbance_estimates(eps[0])
    rep = analyze(write_messages(tmp_path / "dist_bag", msgs), dpath)
    np.testing.assert_array_equal(rep.episode.d_hat, dk)
    assert rep.metrics["d_hat_end"] == [float(v) for v in dk[-1]]
    assert rep.metrics["cost_mean"] == plain.metrics["cost_mean"]     # nothing else changes
    text = write_report(rep, tmp_path / "report").read_text()
    assert (tmp_path / "report" / "disturbance.png").is_file() and "![Disturbance estimates](disturbance.png)" in text
    assert "d_hat_end" in text and "Disturbance states: of the estimator's design, n_d = 2" in text
    assert "disturbance.png" not in write_report(plain, tmp_path / "plain_report").read_text()
    msgs2, dk2 = _with_disturbance_estimates(eps[1], offset=1.0)
    agg = aggregate([rep, analyze(write_messages(tmp_path / "dist_bag2", msgs2), dpath)], dpath)
    np.testing.assert_allclose(agg.metrics["d_hat_end"], (dk[-1] + dk2[-1]) / 2, rtol=1e-15)
    out = tmp_path / "m.json"
    assert cli([str(tmp_path / "dist_bag"), "--design", str(dpath), "--json", str(out), "--no-figures",
                "--out", str(tmp_path / "r2"), "--quiet"]) == 0
    row, = json.loads(out.read_text())
    assert row["name"] == "dist_bag" and row["d_hat_end"] == [float(v) for v in dk[-1]]
