"""analyze / aggregate / analyze CLI on synthetic contract bags with known metrics."""
from __future__ import annotations

import json
import subprocess
import sys
import os
from pathlib import Path

import numpy as np
import pytest

from bag_synth import LAT_CMD_NS, LAT_EST_NS, fake_design, small_scenario, synthetic_episode, write_bag
from sep_control import metrics as M
from sep_control.analyze import AnalysisError, aggregate, analyze
from sep_control.analyze_cli import main as cli
from sep_estimator.design_file import save_design

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
    s = ep.scenario
    err = ep.T_hat[1:] - ep.T[1:]
    return {
        "cost_mean": float(M.nominal_cost(ep.T, ep.u, s)),
        "in_band": float(M.in_band(ep.T, s)),
        "rms": float(M.rms_in_window(ep.T, s)),
        "mean_dev_37_5": M.mean_deviation(ep.T[None], design.T_nom, M.step_at(s, 37.5)),
        "mean_dev_62_5": M.mean_deviation(ep.T[None], design.T_nom, M.step_at(s, 62.5)),
        "coverage_2sigma": M.coverage_2sigma(err, ep.T_std[1:]),
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
    assert m["complete"] is True and m["steps_recorded"] == eps[0].scenario.n_steps + 1
    assert set(M.JSON_KEYS) <= set(m)
    np.testing.assert_array_equal(rep.err, eps[0].T_hat - eps[0].T)


def test_without_design_skips_nominal(setup):
    d, eps, bags, _ = setup
    m = analyze(bags[1]).metrics
    assert m["mean_dev_37_5"] is None and m["cost_mean"] == float(M.nominal_cost(eps[1].T, eps[1].u, eps[1].scenario))


def test_aggregate_matches_summarize(setup):
    d, eps, bags, dpath = setup
    agg = aggregate(bags, dpath)
    s = eps[0].scenario
    T = np.stack([e.T for e in eps])
    U = np.stack([e.u for e in eps])
    ref = M.summarize(T, U, agg.design.T_nom, s)
    for k, v in ref.items():
        assert agg.metrics[k] == v, k
    err = np.concatenate([(e.T_hat - e.T)[1:].ravel() for e in eps])
    std = np.concatenate([e.T_std[1:].ravel() for e in eps])
    assert agg.metrics["coverage_2sigma"] == M.coverage_2sigma(err, std)
    assert agg.metrics["deadline_misses"] == 12 and agg.metrics["rejected_messages"] == 8
    assert list(agg.rows) == [f"ep{i}" for i in range(4)]


def test_scenario_mismatch_refused_or_flagged(tmp_path, setup):
    d, eps, bags, _ = setup
    other = synthetic_episode(small_scenario(k0=0.02), seed=0)
    dpath = save_design(tmp_path / "other.npz", fake_design(other))
    with pytest.raises(AnalysisError, match=r"another scenario.*k0"):
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
    bag = write_bag(tmp_path / "partial", eps[0], skip=("/slab/field_estimate", "/diagnostics"))
    rc = cli([str(bag), "--design", str(dpath), "--out", str(tmp_path / "r")])
    assert rc == 0
    out = capsys.readouterr().out
    assert "missing topics /slab/field_estimate, /diagnostics" in out
    md = (tmp_path / "r" / "report.md").read_text()
    assert "missing topics /slab/field_estimate, /diagnostics" in md
    assert "Estimation error with 2-sigma bounds: not drawn" in md
    assert (tmp_path / "r" / "field.png").is_file()


def _run_cli(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(REPO / p) for p in ("sep_plant", "sep_estimator", "sep_control")))
    return subprocess.run([sys.executable, "-m", "sep_control.analyze_cli", *map(str, args)], env=env,
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
