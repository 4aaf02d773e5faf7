"""FMU plants over ROS 2 topics: the example rod FMU (built from C source) through the nodes.

* Model Exchange rod: plant node + lqg in lockstep equal to the offline closed loop to 1e-9
  (the plant node's scenario_file given relative to the working directory, the FMU relative to
  the scenario file); `sep demo` reuses the design, records a bag, and `sep analyze` reads it:
  the bag's field equals the offline run.
* Co-Simulation rod (opaque states, a design without belief statistics): lockstep equal to the
  offline closed loop to 1e-9.
* A design made with another FMU is refused by the controller nodes (exit 2, naming the file).

Without a C compiler every test here skips, saying so (CI has gcc).
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import fmu_rod
from node_harness import Case, launcher, make_case, probe  # noqa: F401
from test_loop_equivalence import check_equivalence, run_episode

pytestmark = pytest.mark.ros
fmu_rod.skip_without_toolchain()

def rod_yaml(interface: str) -> str:
    """The rod of examples/fmu_rod at dt = 0.5 s (8 RK4 substeps), 40 s, with the fast design
    settings in its `design:` section (the demo designs with them, and reuses a design made so)."""
    return (fmu_rod.rod_plant_yaml(interface, "sensor_1, sensor_2") + fmu_rod.ROD_PROBLEM
            + "design: {p: 8, q: 8, n_r: 12, ensemble: 20, belief_iter: 1}\n")


FAST = {"p": 8, "q": 8, "n_r": 12, "ensemble": 20, "belief_iter": 1}
_CASES: dict[str, Case] = {}


def rod_case(tmp_path_factory, name: str) -> Case:
    """The rod's scenario (next to a copy of the FMU) and its design, once per session; the
    scenario file relative to the working directory, as a user may give it."""
    if name not in _CASES:
        root = tmp_path_factory.mktemp(f"fmu_{name}")
        shutil.copy(fmu_rod.session_fmu(tmp_path_factory), root / "rod.fmu")
        interface = "model_exchange\n  substeps: 8" if name == "me" else "co_simulation"
        case = make_case(root, name, yaml_text=rod_yaml(interface), settings=FAST)
        _CASES[name] = Case(case.scenario, Path(os.path.relpath(case.scenario_file)), case.design, case.design_file)
    return _CASES[name]


@pytest.fixture
def me_case(tmp_path_factory) -> Case:
    return rod_case(tmp_path_factory, "me")


@pytest.fixture
def cs_case(tmp_path_factory) -> Case:
    return rod_case(tmp_path_factory, "cs")


def test_model_exchange_rod_lockstep_over_topics_equals_offline(launcher, probe, me_case, tmp_path):
    assert not me_case.scenario_file.is_absolute() and me_case.design.meta["belief"] == "ensemble"
    pr, summary = run_episode(launcher, probe, me_case, tmp_path, three=False, seed=2, run=3)
    assert summary["status"] == "completed" and summary["plant"] == "fmu"
    assert summary["deadline_misses"] == 0 and summary["rejected_messages"] == 0
    check_equivalence(pr, me_case, 2, 3)


def test_co_simulation_rod_lockstep_over_topics_equals_offline(launcher, probe, cs_case, tmp_path):
    d = cs_case.design
    assert d.info.state_is_opaque and d.meta["belief"] == "absent" and d.nominal.belief_mean is None
    pr, summary = run_episode(launcher, probe, cs_case, tmp_path, three=True, seed=1, run=5)
    assert summary["status"] == "completed" and summary["plant"] == "fmu"
    check_equivalence(pr, cs_case, 1, 5)


def test_model_exchange_rod_demo_bag_and_analyze(launcher, me_case, tmp_path):
    """`sep demo` reuses the design (same FMU, problem and settings), records the episode; `sep
    analyze` reads the bag: the field in the bag is the offline run's."""
    from sep_control.bags.analysis import analyze
    from sep_control.cli.main import main as sep
    from sep_control.evaluation.montecarlo import simulate

    out = tmp_path / "demo"
    p = launcher.start("demo", "--out", str(out), "--scenario", str(me_case.scenario_file), "--design",
                       str(me_case.design_file), "--seed", "4", "--run", "1", "--json", str(tmp_path / "m.json"),
                       "--timeout", "150")
    assert p.wait(240) == 0, p.output()
    text = p.output()
    assert "reusing design file" in text and "rom_lqg (topics)" in text, text
    assert (out / "bag" / "metadata.yaml").is_file() and "report:" in text, text
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["n_runs"] == 1 and m["deadline_misses"] == 0 and m["rejected_messages"] == 0
    js = tmp_path / "analyze.json"
    assert sep(["analyze", str(out / "bag"), "--design", str(me_case.design_file), "--out", str(tmp_path / "rep"),
                "--json", str(js), "--quiet"]) == 0
    assert (tmp_path / "rep" / "report.md").is_file() and js.is_file()
    ep = analyze(out / "bag", me_case.design).episode
    assert ep.complete and not ep.missing, (ep.missing, ep.notes)
    ref = simulate(me_case.plant, me_case.design, "rom_lqg", 4, range(1, 2))
    assert np.max(np.abs(ep.F - ref.F[0])) <= 1e-9
    assert np.max(np.abs(ep.F_hat - ref.F_hat[0])) <= 1e-9


def test_controller_nodes_refuse_a_design_made_with_another_fmu(launcher, me_case, tmp_path, tmp_path_factory):
    """The same scenario next to another FMU: the lqg node compares the FMUs by SHA-256 and
    refuses to start (exit 2), naming the file."""
    shutil.copy(fmu_rod.session_fmu(tmp_path_factory, "rod40", nodes=40), tmp_path / "rod.fmu")
    other = tmp_path / "other.yaml"
    other.write_text(Path(me_case.scenario_file).read_text())
    p = launcher.start("lqg", params={"design_file": me_case.design_file, "scenario_file": other})
    assert p.wait(60) == 2, p.output()
    out = p.output()
    assert "designed for another plant" in out and "plant.path: another file" in out and "SHA-256" in out, out
