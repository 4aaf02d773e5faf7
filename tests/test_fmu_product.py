"""FMU plants through the offline product: `sep design` -> design file -> `sep evaluate`.

* The Model Exchange rod designs like the native rod (tests/fmu_rod.py: the same physics and
  arithmetic) through `sep design`: the nominal cost to 1e-6 relative; its ROM-LQG costs what
  the full-order oracle costs.
* The Co-Simulation rod (opaque states): a design with the mean-only nominal and no belief
  statistics (design-file meta belief "absent"), equal to the Model Exchange rod's `--no-belief`
  design; `sep evaluate` skips the oracle and says why; figures without a belief.
* Another FMU under the design's path is refused by `sep evaluate` (exit 2) and makes `sep demo`
  redesign; the same FMU is reused, also for the opaque plant.
* `sep plants` lists fmu without building one (its path is required).

The FMUs are built from C source once per session (tests/fmu_rod.py); without a C compiler
every test here skips, saying so (CI has gcc).
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import fmu_rod
from sep_control.cli.main import main as sep
from sep_estimator.design_file import SINGLE, load_design
from sep_plant.scenario import load_scenario

fmu_rod.skip_without_toolchain()

NATIVE_PLANT = "plant:\n  type: 'fmu_rod:RodPlant'\n  t_right: 120.0\n  dt: 0.5\n  substeps: 8\n"
FAST = ["--p", "8", "--q", "8", "--n-r", "12", "--ensemble", "20", "--belief-iter", "1", "--quiet"]


def rod_scenarios(folder, fmu) -> dict[str, object]:
    """me.yaml, cs.yaml (the FMU next to them) and native.yaml in `folder`."""
    shutil.copy(fmu, folder / "rod.fmu")
    files = {"me": fmu_rod.rod_plant_yaml("model_exchange") + "  substeps: 8\n" + fmu_rod.ROD_PROBLEM,
             "cs": fmu_rod.rod_plant_yaml("co_simulation") + fmu_rod.ROD_PROBLEM,
             "native": NATIVE_PLANT + fmu_rod.ROD_PROBLEM}
    for name, text in files.items():
        (folder / f"{name}.yaml").write_text(text)
    return {name: folder / f"{name}.yaml" for name in files}


@pytest.fixture(scope="module")
def rods(tmp_path_factory):
    """The scenarios and their designs by `sep design`: me, me_nobelief, cs, native."""
    d = tmp_path_factory.mktemp("fmu_product")
    scen = rod_scenarios(d, fmu_rod.session_fmu(tmp_path_factory))
    runs = {"me": ("me", []), "me_nobelief": ("me", ["--no-belief"]), "cs": ("cs", []), "native": ("native", [])}
    designs = {}
    for name, (which, extra) in runs.items():
        designs[name] = d / f"{name}.npz"
        assert sep(["design", "--scenario", str(scen[which]), "--out", str(designs[name])] + FAST + extra) == 0
    return d, scen, designs


def evaluate_json(capsys, design, *args) -> tuple[dict, str]:
    js = design.with_name(design.stem + ".metrics.json")
    assert sep(["evaluate", "--design", str(design), "--json", str(js), "--quiet", *args]) == 0
    return {r["name"]: r for r in json.loads(js.read_text())}, capsys.readouterr().out


def test_model_exchange_rod_designs_like_the_native_rod(rods, capsys):
    """`sep design` on the ME rod and on the native rod: the same nominal (cost to 1e-6), the
    same belief; `sep evaluate`: ROM-LQG / oracle ~ 1."""
    _, _, designs = rods
    fmu, native = load_design(designs["me"]), load_design(designs["native"])
    assert fmu.meta["belief"] == "ensemble" and not fmu.info.state_is_opaque
    a, b = fmu.meta["optimizer"]["nominal_cost"], native.meta["optimizer"]["nominal_cost"]
    assert a == pytest.approx(b, rel=1e-6)
    np.testing.assert_allclose(fmu.nominal.u, native.nominal.u, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(fmu.nominal.belief_mean, native.nominal.belief_mean, rtol=1e-6)
    assert fmu.meta["validation"]["max_dev_in_band_window"] < fmu.problem.band
    rows, out = evaluate_json(capsys, designs["me"], "--runs", "100", "--controllers", "open_loop", "rom_lqg",
                              "oracle_lqg")
    assert "ROM-LQG / oracle mean cost" in out
    assert rows["rom_lqg"]["cost_mean"] == pytest.approx(rows["oracle_lqg"]["cost_mean"], rel=0.02)
    assert rows["rom_lqg"]["cost_mean"] < rows["open_loop"]["cost_mean"]


def test_co_simulation_rod_design_has_no_belief_and_no_oracle(rods, capsys):
    """Opaque states: the mean-only nominal (the ME rod's --no-belief design, to round-off), the
    file has no belief statistics; evaluate skips the oracle, saying why, and draws the nominal."""
    d, _, designs = rods
    cs, me = load_design(designs["cs"]), load_design(designs["me_nobelief"])
    assert cs.info.state_is_opaque and cs.info.n_x > 3 + 3 + 50
    assert cs.meta["belief"] == "absent" and cs.meta["settings"]["belief"] is False
    assert cs.nominal.belief_mean is None and cs.nominal.belief_std is None
    with np.load(designs["cs"], allow_pickle=False) as z:
        assert not set(SINGLE) & set(z.files)
    assert me.meta["belief"] == "ensemble" and me.meta["settings"]["belief"] is False
    # the FMU steps its own RK4 exactly as sep steps the ME rod: the same design
    for a, b in ((cs.nominal.u, me.nominal.u), (cs.nominal.field, me.nominal.field), (cs.lqg.K, me.lqg.K),
                 (cs.lqg.field_std, me.lqg.field_std), (cs.hankel_sv, me.hankel_sv)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12 * np.abs(b).max())
    rows, out = evaluate_json(capsys, designs["cs"], "--runs", "60", "--figures", str(d / "cs_figures"))
    assert "oracle_lqg skipped: the plant's states are opaque" in out
    assert set(rows) == {"open_loop", "rom_lqg"}
    assert rows["rom_lqg"]["cost_mean"] < rows["open_loop"]["cost_mean"]
    assert (d / "cs_figures" / "nominal_belief_and_control.png").stat().st_size > 0
    with pytest.raises(SystemExit) as exc:        # the oracle alone: nothing left to run
        sep(["evaluate", "--design", str(designs["cs"]), "--runs", "2", "--controllers", "oracle_lqg", "--quiet"])
    captured = capsys.readouterr()
    assert exc.value.code == 2 and "states are opaque" in captured.out and "no controller left" in captured.err


def test_another_fmu_is_refused_and_demo_redesigns(rods, tmp_path, tmp_path_factory, capsys):
    from sep_control.cli.demo import reusable_design
    from sep_control.design.settings import DesignSettings

    _, scen, designs = rods
    for name, which in (("me", "me"), ("cs", "cs")):
        (tmp_path / name).mkdir()
        folder = tmp_path / name
        paths = rod_scenarios(folder, fmu_rod.session_fmu(tmp_path_factory))
        shutil.copy(designs[name], folder / "design.npz")
        settings = DesignSettings.for_scenario(load_scenario(paths[which]), p=8, q=8, n_r=12, ensemble=20,
                                               belief_iter=1)
        # the same FMU in another folder: the design is reused (also with the opaque plant's belief off)
        assert reusable_design(folder / "design.npz", load_scenario(paths[which]), settings) is not None
        assert "reusing design file" in capsys.readouterr().out
    # another FMU under the scenario's file name: demo redesigns, saying what differs
    other = fmu_rod.session_fmu(tmp_path_factory, "rod40", nodes=40)
    folder = tmp_path / "me"
    shutil.copy(other, folder / "rod.fmu")
    changed = load_scenario(folder / "me.yaml")
    settings = DesignSettings.for_scenario(changed, p=8, q=8, n_r=12, ensemble=20, belief_iter=1)
    assert reusable_design(folder / "design.npz", changed, settings) is None
    out = capsys.readouterr().out
    assert "redesigning" in out and "plant file fmu: sha256" in out
    # the design names its FMU by absolute path and SHA-256: another file there is refused
    original = load_design(folder / "design.npz").scenario.plant_config["path"]
    saved = original + ".saved"
    shutil.move(original, saved)
    try:
        shutil.copy(other, original)
        with pytest.raises(SystemExit) as exc:
            sep(["evaluate", "--design", str(folder / "design.npz"), "--runs", "2", "--quiet"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "sep evaluate: error:" in err and "another FMU" in err, err
        assert "Traceback" not in err
    finally:
        shutil.move(saved, original)


def test_plants_lists_fmu_without_building_one(capsys):
    assert sep(["plants"]) == 0
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert "sep_plant.plants.fmu.plant:FMUPlant" in rows["fmu"] and "built-in" in rows["fmu"]
