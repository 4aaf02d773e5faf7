"""The offline subcommands of `sep`, called in-process through sep_control.cli.main.main(argv)."""
import json

import numpy as np
import pytest

from sep_control.cli.main import main as sep
from sep_estimator.design_file import load_design
from sep_plant.scenario import load_scenario
from core_helpers import TINY_YAML


def design_cli_main(argv):
    return sep(["design", *argv])


def evaluate_cli_main(argv):
    return sep(["evaluate", *argv])

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
    rc = design_cli_main(["--scenario", str(scen), "--out", str(out), "--json", str(d / "summary.json")] + FAST)
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
    rc = design_cli_main(["--scenario", str(scen), "--out", str(tmp_path / "x.npz"), "--no-belief"] + FAST)
    assert rc == 0
    out = capsys.readouterr().out
    assert "design written to" in out and "Markov relative error" in out
    assert (tmp_path / "x.npz").is_file()


def test_design_flags_reach_the_settings(tiny, tmp_path):
    scen, _, _ = tiny
    out = tmp_path / "rom.npz"
    rc = design_cli_main(["--scenario", str(scen), "--out", str(out), "--no-belief", "--no-coarse-proposals",
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
    code, err = exit_code_and_stderr(capsys, design_cli_main, ["--scenario", str(p), "--out", str(out), "--quiet"])
    assert code not in (0, None)
    assert needle in err and "Traceback" not in err
    assert not out.exists()


def test_design_missing_scenario_file(tmp_path, capsys):
    code, err = exit_code_and_stderr(capsys, design_cli_main,
                                     ["--scenario", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o.npz")])
    assert code not in (0, None) and "nope.yaml" in err and "not found" in err


def test_design_binary_scenario_file(tmp_path, capsys):
    """A design file passed as --scenario by mistake: a clean error, not a traceback."""
    p = tmp_path / "design.npz"
    p.write_bytes(b"PK\x03\x04\x14\x00\x00\x00\x08\x00\xff\xfe\x00\x81")
    code, err = exit_code_and_stderr(capsys, design_cli_main, ["--scenario", str(p), "--out", str(tmp_path / "o.npz")])
    assert code not in (0, None) and "design.npz" in err


def test_design_bad_settings(tiny, tmp_path, capsys):
    scen, _, _ = tiny
    code, err = exit_code_and_stderr(capsys, design_cli_main,
                                     ["--scenario", str(scen), "--out", str(tmp_path / "o.npz"), "--ensemble", "3"])
    assert code not in (0, None) and "ensemble" in err


def test_evaluate_json_and_figures(tiny, tmp_path, capsys):
    _, design, _ = tiny
    js, figs = tmp_path / "metrics" / "m.json", tmp_path / "figs"
    rc = evaluate_cli_main(["--design", str(design), "--runs", "20", "--json", str(js), "--figures", str(figs),
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
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(bad), "--runs", "5", "--quiet"])
    assert code not in (0, None)
    assert "corrupt.npz" in err and "corrupt" in err and "Traceback" not in err


def test_evaluate_garbage_design_file(tmp_path, capsys):
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(np.random.default_rng(0).bytes(2000))
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(bad), "--quiet"])
    assert code not in (0, None) and "garbage.npz" in err


def test_evaluate_missing_design_file(tmp_path, capsys):
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(tmp_path / "none.npz")])
    assert code not in (0, None) and "not found" in err
    assert f"`sep design --scenario SCENARIO --out {tmp_path / 'none.npz'}`" in err     # 0.8.0: `design --out`


def test_evaluate_bad_runs(tiny, capsys):
    _, design, _ = tiny
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(design), "--runs", "0"])
    assert code not in (0, None) and "--runs" in err


def test_scenario_design_section_sets_defaults_and_flags_override(tmp_path, capsys):
    """A scenario's `design:` section gives the design tool its defaults; options override them;
    an unknown setting is named."""
    scen = tmp_path / "s.yaml"
    scen.write_text(TINY_YAML + "design:\n  n_r: 6\n  belief: false\n  p: 5\n  q: 5\n  ensemble: 20\n")
    out = tmp_path / "d.npz"
    assert design_cli_main(["--scenario", str(scen), "--out", str(out), "--quiet"]) == 0
    st = load_design(out).meta["settings"]
    assert (st["n_r"], st["belief"], st["p"]) == (6, False, 5)
    assert design_cli_main(["--scenario", str(scen), "--out", str(out), "--quiet", "--n-r", "8"]) == 0
    assert load_design(out).meta["settings"]["n_r"] == 8
    scen.write_text(TINY_YAML + "design:\n  n_rr: 6\n")
    code, err = exit_code_and_stderr(capsys, design_cli_main, ["--scenario", str(scen), "--out", str(out)])
    assert code == 2 and "n_rr" in err


# ------------------------------------------------------------------ one vocabulary
FAST_SETTINGS = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1)


def test_errors_name_the_subcommand(tiny, capsys):
    _, design, _ = tiny
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(design), "--runs", "0"])
    assert code == 2 and "sep evaluate: error: --runs must be >= 1, got 0" in err
    code, err = exit_code_and_stderr(capsys, sep, ["design", "--out", "x.npz", "--bogus"])     # argparse's
    assert code == 2 and "sep design: error: unrecognized arguments: --bogus" in err


def test_design_enkf_seed_and_its_old_spelling(tiny, tmp_path, capsys):
    """--enkf-seed sets the EnKF seed; the old design --seed still does, with one warning line."""
    scen, _, _ = tiny
    for flags, seed, warned in ((["--enkf-seed", "5"], 5, False), (["--seed", "6"], 6, True)):
        out = tmp_path / f"s{seed}.npz"
        assert design_cli_main(["--scenario", str(scen), "--out", str(out)] + flags + FAST) == 0
        assert load_design(out).meta["settings"]["enkf_seed"] == seed
        err = capsys.readouterr().err
        assert ("sep design: warning: --seed is deprecated; use --enkf-seed" in err) is warned, err


def test_evaluate_old_controller_names_and_mpc_budget_flag(tiny, tmp_path, capsys):
    """`lqr` means rom_lqg, --mpc-budget means --mpc-time-budget: both accepted with a warning."""
    _, design, _ = tiny
    js = tmp_path / "m.json"
    assert evaluate_cli_main(["--design", str(design), "--runs", "4", "--controllers", "open_loop", "lqr",
                              "--mpc-budget", "0.5", "--json", str(js), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "controller 'lqr' is deprecated; use 'rom_lqg'" in err
    assert "--mpc-budget is deprecated; use --mpc-time-budget" in err
    assert {r["name"] for r in json.loads(js.read_text())} == {"open_loop", "rom_lqg"}
    code, err = exit_code_and_stderr(capsys, evaluate_cli_main, ["--design", str(design), "--controllers", "pid"])
    assert code == 2 and "invalid choice: 'pid'" in err


def test_evaluate_seed_defaults_to_one(tiny):
    from sep_control.cli.main import build_parser
    from sep_plant.noise import DEFAULT_SEED

    _, design, _ = tiny
    assert DEFAULT_SEED == 1
    for argv in (["evaluate", "--design", str(design)], ["demo"]):
        assert build_parser().parse_args(argv).seed == 1


def test_old_entry_points_print_one_deprecation_line(tmp_path, capsys):
    from sep_control.cli import design as design_cli

    with pytest.raises(SystemExit) as exc:
        design_cli.main(["--scenario", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o.npz")])
    err = capsys.readouterr().err.splitlines()
    assert exc.value.code == 2
    assert err[0] == "design: warning: the `design` command is deprecated; use `sep design`"
    assert err[1].startswith("sep design: error: scenario file not found")


def test_demo_takes_the_design_options_and_the_new_names(tiny, capsys):
    """demo: --controller rom_lqg|rom_mpc (lqr, mpc with a warning), --real-time-factor (--rtf with
    a warning), and the design's options (the same table as `sep design`) for its design step."""
    from sep_control.cli.design import settings_from_args
    from sep_control.cli.main import build_parser

    scen, _, _ = tiny
    args = build_parser().parse_args(["demo", "--scenario", str(scen), "--controller", "mpc", "--rtf", "5",
                                      "--n-r", "8", "--enkf-seed", "3", "--no-belief", "--dask", "local:2",
                                      "--threads", "2", "--memory-budget", "1G"])
    err = capsys.readouterr().err
    assert "controller 'mpc' is deprecated; use 'rom_mpc'" in err and "--rtf is deprecated" in err
    assert (args.controller, args.real_time_factor, args.seed, args.run, args.dask, args.threads) == \
        ("rom_mpc", 5.0, 1, 0, "local:2", 2)
    st = settings_from_args(args, load_scenario(scen))
    assert (st.n_r, st.enkf_seed, st.belief, st.memory_budget) == (8, 3, False, 1 << 30)
    assert build_parser().parse_args(["demo"]).controller == "rom_lqg"
    code, err = exit_code_and_stderr(capsys, sep, ["demo", "--controller", "oracle_lqg"])
    assert code == 2 and "invalid choice" in err


def test_demo_reuses_a_design_only_when_made_from_the_same_inputs(tiny, tmp_path, capsys):
    """The design file's source record: the same scenario and settings reuse it; another target
    or another setting is named and means a redesign."""
    from sep_control.cli.demo import reusable_design
    from sep_control.design.pipeline import DesignSettings

    scen, path, _ = tiny
    s = load_scenario(scen)
    settings = DesignSettings.for_scenario(s, **FAST_SETTINGS)
    assert reusable_design(path, s, settings) is not None
    assert "reusing design file" in capsys.readouterr().out
    other = tmp_path / "t151.yaml"
    other.write_text(TINY_YAML + "t_target: 151.0\n")
    assert reusable_design(path, load_scenario(other), settings) is None
    out = capsys.readouterr().out
    assert "made from other inputs" in out and "problem.target: 150.0 != 151.0" in out, out
    assert reusable_design(path, s, DesignSettings.for_scenario(s, **{**FAST_SETTINGS, "n_r": 12})) is None
    assert "settings.n_r: 10 != 12" in capsys.readouterr().out
    # run-time only settings do not count: the memory budget
    assert reusable_design(path, s, DesignSettings.for_scenario(s, **FAST_SETTINGS, memory_budget=1 << 30))


# ------------------------------------------------------------------ sep itself
def test_version_and_help(capsys):
    from sep_control import __version__

    with pytest.raises(SystemExit) as exc:
        sep(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"sep {__version__}"
    with pytest.raises(SystemExit):
        sep(["--help"])
    out = capsys.readouterr().out
    for name in ("design", "evaluate", "validate", "demo", "analyze", "record", "plants", "check-plant"):
        assert f"    {name}" in out, name
    for name in ("design", "evaluate", "validate", "demo", "analyze", "check-plant"):
        with pytest.raises(SystemExit):
            sep([name, "--help"])
        out = capsys.readouterr().out
        assert out.startswith(f"usage: sep {name}") and "\nBasic:\n" in out, (name, out)
        assert name == "check-plant" or "\nAdvanced:\n" in out, (name, out)
    code, err = exit_code_and_stderr(capsys, sep, [])
    assert code == 2 and "SUBCOMMAND" in err


def test_advanced_group_has_the_compute_options(capsys):
    with pytest.raises(SystemExit):
        sep(["design", "--help"])
    out = capsys.readouterr().out
    basic, advanced = out.split("\nBasic:\n")[1].split("\nAdvanced:\n")
    for flag in ("--scenario", "--out", "--n-r", "--enkf-seed", "--no-belief"):
        assert flag in basic and flag not in advanced, flag
    for flag in ("--threads", "--memory-budget", "--dask", "--device", "--chunks", "--p P"):
        assert flag in advanced and flag not in basic, flag
    assert "--seed" not in out.replace("--enkf-seed", "")              # the old spelling is hidden


def test_plants_lists_types_with_their_classes(capsys):
    assert sep(["plants"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in lines}
    assert "sep_plant.plants.slab:SlabPlant" in rows["slab"] and "built-in" in rows["slab"]
    assert {"slab", "plate", "block", "allen_cahn"} <= set(rows)


def test_check_plant_ok_and_problems(tmp_path, capsys):
    assert sep(["check-plant"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("ok: plant slab: n_x = 100, 5 inputs, 5 outputs, 100 field nodes"), out
    bad = tmp_path / "broken.yaml"
    bad.write_text("plant: {type: 'broken_plants:NonFiniteObserve'}\nn_steps: 20\ntarget: 1.0\n")
    code, err = exit_code_and_stderr(capsys, sep, ["check-plant", "--scenario", str(bad)])
    assert code == 2 and err.startswith(f"sep check-plant: error: {bad}: plant broken_plants:NonFiniteObserve")
    assert "does not meet the plant protocol" in err and "Traceback" not in err


def test_offline_subcommands_import_without_rclpy(tmp_path):
    """Every subcommand but record builds and runs its parser with rclpy unimportable."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parent.parent
    code = ("import sys; sys.modules['rclpy'] = None\n"
            "from sep_control.cli.main import build_parser, main\n"
            "build_parser()\n"
            "assert main(['plants']) == 0\n"
            "assert not [m for m in sys.modules if m.startswith(('rclpy.', 'sep_control.ros', 'sep_plant.ros'))]\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(repo / p) for p in ("sep_plant", "sep_estimator",
                                                                                "sep_control")))
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


def test_record_is_the_recorder_nodes_command_line(capsys):
    with pytest.raises(SystemExit) as exc:
        sep(["record", "--help"])
    assert exc.value.code == 0 and "--out BAG_DIR" in capsys.readouterr().out


# ------------------------------------------------------------------ progress bars
class _Stream:
    def __init__(self, tty):
        self.tty = tty

    def isatty(self):
        return self.tty


def test_bars_only_on_a_terminal_and_never_with_quiet():
    from sep_control.compute.progress import RunSteps, bars_wanted

    assert bars_wanted(False, _Stream(True)) and not bars_wanted(True, _Stream(True))
    assert not bars_wanted(False, _Stream(False)) and not bars_wanted(False, object())
    bar = RunSteps(100, "x", enabled=False)
    bar.add(3, 10)
    bar.add(70)
    assert (bar.done, bar.total) == (100, 100)


def test_design_draws_no_bar_when_stderr_is_not_a_terminal(tiny, tmp_path, capsys):
    scen, _, _ = tiny
    fast = [f for f in FAST if f != "--quiet"]
    assert design_cli_main(["--scenario", str(scen), "--out", str(tmp_path / "d.npz"), "--no-belief"] + fast) == 0
    err = capsys.readouterr().err
    assert "design: scenario" in err                      # the log lines are there
    assert "it/s" not in err and "\r" not in err and "%|" not in err, err


class _CountingPlant:
    """The plant, counting the run-steps it is asked for (rows of every batch stepped)."""

    def __init__(self, plant):
        self._plant, self.steps = plant, 0

    def __getattr__(self, name):
        return getattr(self._plant, name)

    def step(self, x, u, w=None):
        self.steps += x.shape[0]
        return self._plant.step(x, u, w)


def test_validate_and_sweep_bars_count_the_plants_run_steps(tiny):
    """The run-steps the bars are sized with are the ones the plant is stepped, and the bars end
    full."""
    from sep_control.compute.progress import RunSteps
    from sep_control.evaluation.sweep import rom_sweep, sweep_run_steps
    from sep_control.evaluation.validation import validate, validation_run_steps

    _, path, _ = tiny
    d = load_design(path)
    plant = _CountingPlant(d.scenario.plant)
    bar = RunSteps(validation_run_steps(plant, d.n_steps, 12), "v", enabled=False)
    validate(plant, d, lags=12, progress=bar)
    assert plant.steps == bar.done == bar.total == 2 * 40 * 5 * 12 + (40 + 12) + 2 * 40
    plant = _CountingPlant(d.scenario.plant)
    bar = RunSteps(sweep_run_steps(plant, d, [4, 6], 3, oracle=False), "s", enabled=False)
    rows = rom_sweep(plant, d, None, [4, 6], 3, seed=1, progress=bar)
    assert plant.steps == bar.done == bar.total
    assert [r["n_r"] for r in rows] == [4, 6] and rows[0]["cost_oracle"] is None


def test_quiet_keeps_the_warnings(capsys):
    from sep_control.cli.common import stderr_log

    quiet, loud = stderr_log(True), stderr_log(False)
    quiet("design: scenario x")
    quiet("warning: about 1e9 run-steps")
    assert capsys.readouterr().err == "warning: about 1e9 run-steps\n"
    loud("design: scenario x")
    assert capsys.readouterr().err == "design: scenario x\n"
