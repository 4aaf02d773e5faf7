"""The truth plant of a model-mismatch evaluation: key overrides, another scenario, the generic
perturbation wrapper, and the refusals (unknown key, other interface, bad perturbation)."""
import dataclasses

import numpy as np
import pytest

from sep_plant.conformance import check_plant
from sep_plant.perturb import PerturbationError, PerturbedPlant
from sep_plant.plants import make_plant
from sep_plant.scenario import Scenario, load_scenario
from sep_plant.protocol import PlantInfo
from sep_plant.truth import TruthError, interface_differences, parse_assignments, truth_plant

SMALL = {"n_x": 30}


def small_model() -> Scenario:
    return Scenario("slab", SMALL).canonical()


def test_assignments_are_yaml_values():
    got = parse_assignments(["t_right=147", "boundary_temperatures={x_max: 147}", "heater_centers=[0.2, 0.8]",
                             "name=abc"])
    assert got == {"t_right": 147, "boundary_temperatures": {"x_max": 147}, "heater_centers": [0.2, 0.8],
                   "name": "abc"}
    for bad in ("t_right", "=3", "x=[1, 2"):
        with pytest.raises(TruthError):
            parse_assignments([bad])


def test_truth_keys_change_the_plant_and_are_named():
    model = small_model()
    t = truth_plant(model, {"t_right": 147})
    assert t.plant.config()["t_right"] == 147.0 and t.differences == ("plant.t_right: 150.0 -> 147.0",)
    x = t.plant.initial_state(1)
    for _ in range(40):
        x = t.plant.step(x, np.full(5, 0.1))
    x0 = model.plant.initial_state(1)
    for _ in range(40):
        x0 = model.plant.step(x0, np.full(5, 0.1))
    assert x[0, -1] < x0[0, -1] - 0.1          # the node next to the colder boundary is colder
    assert truth_plant(model).is_model and truth_plant(model).describe() == "the model itself"


def test_unknown_key_and_other_interface_are_refused():
    model = small_model()
    with pytest.raises(TruthError, match=r"unknown truth key\(s\) \['t_rightt'\].*t_right"):
        truth_plant(model, {"t_rightt": 147})
    with pytest.raises(TruthError, match="n_u 3 .*has 5"):
        truth_plant(model, {"heater_centers": [0.2, 0.5, 0.8]})
    with pytest.raises(TruthError, match="n_field 40"):
        truth_plant(model, {"n_x": 40})
    other = Scenario("plate", {"nodes": [8, 8]}).canonical()
    with pytest.raises(TruthError, match="of type 'plate'"):
        truth_plant(model, scenario=other)


def test_truth_scenario_of_the_same_type(tmp_path):
    f = tmp_path / "truth.yaml"
    f.write_text("plant:\n  type: slab\n  n_x: 30\n  k0: 0.012\n")
    t = truth_plant(small_model(), {"t_right": 148}, scenario=load_scenario(f))
    assert t.plant.config()["k0"] == 0.012 and t.plant.config()["t_right"] == 148
    assert t.differences == ("plant.k0: 0.01 -> 0.012", "plant.t_right: 150.0 -> 148.0")


def test_perturbation_wrapper_conforms_and_acts_on_the_boundary():
    inner = make_plant("slab", SMALL)
    p = PerturbedPlant.around(inner, input_gain=0.8, input_offset=[0.1, 0, 0, 0, 0], sensor_bias=1.0)
    check_plant(p, np.full(5, 0.1))                           # incl. step(x, u, w) == step(x, u + w)
    x = inner.initial_state(2)
    u, w = np.full((2, 5), 0.2), np.random.default_rng(0).standard_normal((2, 5)) * 0.3
    expect = inner.step(x, 0.8 * (u + w) + np.array([0.1, 0, 0, 0, 0]))
    np.testing.assert_array_equal(p.step(x, u, w), expect)
    np.testing.assert_array_equal(p.observe(expect), inner.observe(expect) + 1.0)
    np.testing.assert_array_equal(p.field(expect), inner.field(expect))
    rebuilt = make_plant("sep_plant.perturb:PerturbedPlant", p.config())     # what a Dask worker does
    np.testing.assert_array_equal(rebuilt.step(x, u, w), expect)
    assert p.perturbation() == {"input_gain": [0.8] * 5, "input_offset": [0.1, 0, 0, 0, 0],
                                "sensor_bias": [1.0] * 5}
    assert p.n_u == 5 and p.dt == inner.dt and p.input_names == inner.input_names
    assert p.inner is inner                                   # the object wrapped, not a rebuild of it


def test_a_truth_builds_its_plant_once():
    model = small_model()
    assert model.canonical().plant is model.plant            # the canonical scenario keeps the plant built
    t = truth_plant(model, perturbation={"input_gain": 0.8})
    assert t.plant.inner is t.scenario.plant


def test_interface_names_are_compared_where_their_counts_agree():
    model = PlantInfo.of(make_plant("slab", SMALL))
    truth = dataclasses.replace(model, n_u=3, input_names=("a", "b", "c"),
                                output_names=tuple(f"s{i}" for i in range(model.n_y)))
    problems = interface_differences(model, truth)
    assert [p.split(" ")[0] for p in problems] == ["n_u", "output_names"], problems


def test_perturbation_refusals():
    model = small_model()
    with pytest.raises(TruthError, match=r"unknown perturbation key\(s\) \['gain'\]"):
        truth_plant(model, perturbation={"gain": 0.8})
    with pytest.raises(TruthError, match="input_offset must be a number or a list of 5"):
        truth_plant(model, perturbation={"input_offset": [1, 2]})
    with pytest.raises(PerturbationError, match="sensor_bias must be finite"):
        PerturbedPlant.around(make_plant("slab", SMALL), sensor_bias=float("nan"))
    t = truth_plant(model, {"t_right": 147}, perturbation={"sensor_bias": 1.0})
    assert t.differences[-1] == "sensor_bias: 1" and t.record()["perturbation"] == {"sensor_bias": [1.0] * 5}
