"""The offline command-line tools, called in-process through their main(argv)."""
import json

import numpy as np
import pytest

from sep_control.cli import design as design_cli

from sep_control.cli import evaluate as evaluate_cli
from sep_estimator.design_file import load_design
from sep_plant.scenario import load_scenario

# A tiny but meaningful scenario: 20 nodes, 40 steps over the same 62.5 s (band from 37.5 s).
TINY_YAML = """\
# tiny test scenario (keys that differ from the reference)
n_x: 20
n_steps: 40
dt: 1.5625
k_band: 24
lqr_k_switch: 19
w_std: 0.12
v_std: 0.4
"""
FAST = ["--p", "5", "--q", "5", "--n-r", "10", "--ensemble", "20", "--belief-iter", "1", "--quiet"]
SECTION3_KEYS = ("cost_mean", "cost_std", "in_band", "rms", "mean_dev_start", "mean_dev_end", "n_runs",
                 "coverage_2sigma")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(scenario path, design path) written by `design --scenario tiny.yaml --out ...`."""
    d = tmp_path_factory.mktemp("cli")
    scen = d / "tiny.yaml"
    scen.write_text(TINY_YAML)
    out = d / "designs" / "tiny.npz"
    rc = design_cli.main(["--scenario", str(scen), "--out", str(out), "--json", str(d / "summary.json")] + FAST)
    assert rc == 0
    return scen, out, d


def exit_code_and_stderr(capsys, main, argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code, capsys.readouterr().err


def test_design_writes_a_loadable_file(tiny):
    scen, out, d = tiny
    design = load_design(out, expect_scenario=load_scenario(scen))
    s = design.scenario
    assert (s.plant_config["n_x"], s.problem.n_steps, s.problem.window) == (20, 40, (24, 40))
    assert design.n_r == 10 and design.meta["settings"]["p"] == 5
    assert np.max(np.abs(design.nominal.field[24:] - 150.0)) < s.problem.band
    summary = json.loads((d / "summary.json").read_text())
    assert summary["n_x"] == 20 and summary["markov_rel_error"] < 1e-4     # (truncated: n_r = 10, p = q = 5)
    assert summary["max_dev_in_band_window"] == pytest.approx(np.max(np.abs(design.nominal.field[24:] - 150)))


def test_design_prints_a_summary(tiny, tmp_path, capsys):
    scen, _, _ = tiny
    rc = design_cli.main(["--scenario", str(scen), "--out", str(tmp_path / "x.npz"), "--no-belief"] + FAST)
    assert rc == 0
    out = capsys.readouterr().out
    assert "design written to" in out and "Markov relative error" in out
    assert (tmp_path / "x.npz").is_file()


def test_design_flags_reach_the_settings(tiny, tmp_path):
    scen, _, _ = tiny
    out = tmp_path / "rom.npz"
    rc = design_cli.main(["--scenario", str(scen), "--out", str(out), "--no-belief", "--no-coarse-proposals",
                          "--jacobian", "rom", "--tol", "1e-6"] + FAST)
    assert rc == 0
    meta = load_design(out).meta
    assert meta["settings"]["coarse_proposals"] is False and meta["settings"]["belief"] is False
    assert meta["settings"]["tol"] == 1e-6
    assert "rom (proposal)" not in meta["optimizer"]["linearizations"]


@pytest.mark.parametrize("text,needle", [
    ("n_x: 20\nbogus_key: 1\n", "bogus_key"),
    ("plant: {type: slab, n_x: 20}\nbogus_key: 1\n", "bogus_key"),
    ("plant: {type: furnace}\n", "furnace"),
    ("plant: {type: slab}\nw_std: [0.1, 0.2]\n", "w_std"),
    ("dt: -1\n", "dt"),
    ("sensor_positions: [0.5, 1.7]\n", "sensor_positions"),
    ("n_x: [1, 2\n", "YAML"),
    ("- just\n- a list\n", "mapping"),
])
def test_design_bad_scenario_file(tmp_path, capsys, text, needle):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    out = tmp_path / "never.npz"
    code, err = exit_code_and_stderr(capsys, design_cli.main, ["--scenario", str(p), "--out", str(out), "--quiet"])
    assert code not in (0, None)
    assert needle in err and "Traceback" not in err
    assert not out.exists()


def test_design_missing_scenario_file(tmp_path, capsys):
    code, err = exit_code_and_stderr(capsys, design_cli.main,
                                     ["--scenario", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o.npz")])
    assert code not in (0, None) and "nope.yaml" in err and "not found" in err


def test_design_binary_scenario_file(tmp_path, capsys):
    """A design file passed as --scenario by mistake: a clean error, not a traceback."""
    p = tmp_path / "design.npz"
    p.write_bytes(b"PK\x03\x04\x14\x00\x00\x00\x08\x00\xff\xfe\x00\x81")
    code, err = exit_code_and_stderr(capsys, design_cli.main, ["--scenario", str(p), "--out", str(tmp_path / "o.npz")])
    assert code not in (0, None) and "design.npz" in err


def test_design_bad_settings(tiny, tmp_path, capsys):
    scen, _, _ = tiny
    code, err = exit_code_and_stderr(capsys, design_cli.main,
                                     ["--scenario", str(scen), "--out", str(tmp_path / "o.npz"), "--ensemble", "3"])
    assert code not in (0, None) and "ensemble" in err


def test_evaluate_json_and_figures(tiny, tmp_path, capsys):
    _, design, _ = tiny
    js, figs = tmp_path / "metrics" / "m.json", tmp_path / "figs"
    rc = evaluate_cli.main(["--design", str(design), "--runs", "20", "--json", str(js), "--figures", str(figs),
                            "--quiet"])
    assert rc == 0
    out = capsys.readouterr().out
    for name in ("open_loop", "rom_lqg", "oracle_lqg"):
        assert name in out
    rows = json.loads(js.read_text())
    assert isinstance(rows, list)
    by_name = {r["name"]: r for r in rows}
    assert set(by_name) == {"open_loop", "rom_lqg", "oracle_lqg"}
    for name, r in by_name.items():
        for k in SECTION3_KEYS:
            assert k in r, (name, k)
            assert isinstance(r[k], (int, float)) and np.isfinite(r[k])
        assert r["n_runs"] == 20
        assert 0.0 <= r["in_band"] <= 1.0 and 0.0 <= r["coverage_2sigma"] <= 1.0
        assert r["cost_mean"] > 0 and r["cost_std"] >= 0 and r["rms"] > 0
    assert by_name["rom_lqg"]["cost_mean"] == pytest.approx(by_name["oracle_lqg"]["cost_mean"], rel=0.02)
    assert by_name["rom_lqg"]["cost_mean"] < by_name["open_loop"]["cost_mean"]
    pngs = sorted(figs.glob("*.png"))
    assert {p.name for p in pngs} >= {"nominal_belief_and_control.png", "closed_loop_mean_vs_nominal.png",
                                      "estimation_error_2sigma.png"}
    for p in pngs:
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_evaluate_corrupt_design_file(tiny, tmp_path, capsys):
    _, design, _ = tiny
    raw = design.read_bytes()
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(raw[: len(raw) // 2])
    code, err = exit_code_and_stderr(capsys, evaluate_cli.main, ["--design", str(bad), "--runs", "5", "--quiet"])
    assert code not in (0, None)
    assert "corrupt.npz" in err and "corrupt" in err and "Traceback" not in err


def test_evaluate_garbage_design_file(tmp_path, capsys):
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(np.random.default_rng(0).bytes(2000))
    code, err = exit_code_and_stderr(capsys, evaluate_cli.main, ["--design", str(bad), "--quiet"])
    assert code not in (0, None) and "garbage.npz" in err


def test_evaluate_missing_design_file(tmp_path, capsys):
    code, err = exit_code_and_stderr(capsys, evaluate_cli.main, ["--design", str(tmp_path / "none.npz")])
    assert code not in (0, None) and "not found" in err and "design --out" in err


def test_evaluate_bad_runs(tiny, capsys):
    _, design, _ = tiny
    code, err = exit_code_and_stderr(capsys, evaluate_cli.main, ["--design", str(design), "--runs", "0"])
    assert code not in (0, None) and "--runs" in err


def test_scenario_design_section_sets_defaults_and_flags_override(tmp_path, capsys):
    """A scenario's `design:` section gives the design tool its defaults; options override them;
    an unknown setting is named."""
    scen = tmp_path / "s.yaml"
    scen.write_text(TINY_YAML + "design:\n  n_r: 6\n  belief: false\n  p: 5\n  q: 5\n  ensemble: 20\n")
    out = tmp_path / "d.npz"
    assert design_cli.main(["--scenario", str(scen), "--out", str(out), "--quiet"]) == 0
    st = load_design(out).meta["settings"]
    assert (st["n_r"], st["belief"], st["p"]) == (6, False, 5)
    assert design_cli.main(["--scenario", str(scen), "--out", str(out), "--quiet", "--n-r", "8"]) == 0
    assert load_design(out).meta["settings"]["n_r"] == 8
    scen.write_text(TINY_YAML + "design:\n  n_rr: 6\n")
    code, err = exit_code_and_stderr(capsys, design_cli.main, ["--scenario", str(scen), "--out", str(out)])
    assert code == 2 and "n_rr" in err
