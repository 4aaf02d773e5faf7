"""Scenario: plant section + problem keys, YAML loading, the sep 0.1 flat format, validation
messages, JSON round trip, plant mismatches, targets and per-channel values."""
import math
from pathlib import Path

import numpy as np
import pytest

from core_helpers import Slab, flat
from sep_plant.problem import Objective, Problem, ProblemError, evaluate_expression
from sep_plant.scenario import (Scenario, ScenarioError, load_scenario, mismatches, parse_scenario_payload,
                                reference, scenario_payload)

REPO = Path(__file__).resolve().parent.parent
REFERENCE_YAML = REPO / "sep_plant" / "scenarios" / "reference.yaml"
FLAT_V1_YAML = REPO / "tests" / "data" / "reference_flat_v1.yaml"


def write(tmp_path, text, name="scenario.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_defaults_are_the_reference_scenario():
    s = reference()
    p, c = s.problem, s.plant_config
    assert s.plant_type == "slab"
    assert (c["n_x"], c["length"], c["k0"], c["beta"], c["eta"], c["t_right"], c["t_init"]) == \
        (100, 1.0, 0.01, 0.5, 0.002, 150.0, 100.0)
    assert c["heater_centers"] == [0.1, 0.3, 0.5, 0.7, 0.9] and c["sensor_positions"] == c["heater_centers"]
    assert (c["dt"], p.n_steps, p.w_std, p.v_std, p.window, p.k_switch) == (0.25, 250, 0.3, 1.0, (150, 250), 120)
    assert (c["heater_sigma"], p.q_window, p.q_outside, p.r_u, p.lqr_r) == (0.02, 1.0, 1e-5, 0.1, 0.01)
    assert p.u_min == -math.inf and p.u_max == math.inf
    q = p.q_weights()
    assert q.shape == (251,) and q[149] == 1e-5 and q[150] == 1.0 and q[250] == 1.0
    qy = p.lqr_output_weights(5)
    assert qy[119] == pytest.approx(0.1 / 5) and qy[120] == pytest.approx(1.0 / 5)
    # the defaults that depend on N: the last 40 % of the horizon, the LQR switch 12 % before it
    assert Problem(n_steps=100).window == (60, 100) and Problem(n_steps=100).k_switch == 48


def test_none_is_the_reference():
    assert load_scenario(None) == reference() == Scenario().canonical()


def test_reference_yaml_is_the_default_scenario():
    assert load_scenario(REFERENCE_YAML) == reference()


def test_flat_sep01_file_is_the_same_scenario():
    """sep 0.1's flat reference.yaml (users have such files) means the same slab and problem."""
    assert load_scenario(FLAT_V1_YAML) == reference()


def test_flat_yaml_with_overrides(tmp_path):
    p = write(tmp_path, "n_x: 50\ndt: 0.5\nn_steps: 125\nk_band: 75\nlqr_k_switch: 60\n"
                        "heater_centers: [0.2, 0.5, 0.8]\nsensor_positions: [0.25, 0.75]\n"
                        "u_min: 0\nu_max: .inf\nw_std: 0.1\nq_late: 2.0\nt_target: 140\n")
    s = load_scenario(p)
    assert s.plant_type == "slab" and s.plant_config["n_x"] == 50 and s.plant_config["dt"] == 0.5
    assert s.problem.window == (75, 125) and s.problem.k_switch == 60
    assert s.problem.q_window == 2.0 and s.problem.target == 140.0 and s.problem.u_min == 0.0
    plant = s.plant
    assert (plant.n_u, plant.n_y) == (3, 2)
    assert isinstance(plant.n_x, int) and isinstance(plant.dt, float)
    # untouched keys keep the reference values
    assert s.plant_config["k0"] == 0.01 and s.plant_config["t_right"] == 150.0


def test_current_format_yaml(tmp_path):
    p = write(tmp_path, "plant:\n  type: slab\n  n_x: 60\n  dt: 0.5\nn_steps: 100\nband_window: [70, 90]\n"
                        "target: '150 + 2 * x'\nv_std: [1, 2, 1, 2, 1]\n")
    s = load_scenario(p)
    assert s.plant_config["n_x"] == 60 and s.problem.window == (70, 90)
    assert s.problem.k_switch == 70 - 12                # 12 % of N before the window opens
    target = s.problem.target_field(s.plant.field_coordinates())
    np.testing.assert_allclose(target, 150 + 2 * s.plant.grid())
    np.testing.assert_array_equal(s.problem.channels("v_std", 5), [1, 2, 1, 2, 1])
    # the problem's window ends before N: q_k is the outside weight after it
    q = s.problem.q_weights()
    assert q[70] == q[90] == 1.0 and q[91] == q[69] == 1e-5


def test_yaml_under_a_scenario_key_and_string_infinities(tmp_path):
    p = write(tmp_path, "scenario:\n  n_x: 60\n  u_min: '-inf'\n  u_max: 'inf'\n")
    s = load_scenario(p)
    assert s.plant_config["n_x"] == 60 and s.problem.u_min == -math.inf and s.problem.u_max == math.inf


def test_empty_yaml_is_the_reference(tmp_path):
    assert load_scenario(write(tmp_path, "")) == reference()


@pytest.mark.parametrize("text,name", [
    ("n_x: 40\nheater_sigmaa: 0.03\n", "heater_sigmaa"),
    ("plant: {type: slab}\nheater_sigma: 0.03\n", "heater_sigma"),     # a plant key beside the problem
    ("plant: {type: slab, t_target: 140}\n", "t_target"),             # a problem key in the plant
])
def test_unknown_key_is_named(tmp_path, text, name):
    with pytest.raises(ScenarioError, match=name):
        load_scenario(write(tmp_path, text))


@pytest.mark.parametrize("text,key", [
    ("dt: -0.25", "dt"),
    ("dt: 0", "dt"),
    ("dt: .nan", "dt"),
    ("n_x: 3", "n_x"),
    ("n_x: 50.5", "n_x"),
    ("n_x: fifty", "n_x"),
    ("n_steps: 1", "n_steps"),
    ("sensor_positions: [0.1, 1.5]", "sensor_positions"),
    ("sensor_positions: [-0.1]", "sensor_positions"),
    ("sensor_positions: []", "sensor_positions"),
    ("heater_centers: [0.5, 2.0]", "heater_centers"),
    ("heater_centers: 0.5", "heater_centers"),
    ("u_min: 1.0\nu_max: 1.0\nu_init: 1.0", "u_min"),
    ("u_min: 2.0\nu_max: 1.0", "u_min"),
    ("v_std: 0", "v_std"),
    ("w_std: -0.3", "w_std"),
    ("k_band: 300", "band_window"),
    ("lqr_k_switch: -1", "lqr_k_switch"),
    ("k0: true", "k0"),
    ("heater_sigma: -0.02", "heater_sigma"),
    ("u_min: 0.5", "u_init"),
    ("plant: {type: slab}\nband_window: [100, 300]", "band_window"),
    ("plant: {type: slab}\nband_window: 100", "band_window"),
    ("plant: {type: slab}\nw_std: [0.3, 0.3]", "w_std"),
    ("plant: {type: slab}\ntarget: [150, 150]", "target"),
    ("plant: {type: slab}\ntarget: 'sin(q)'", "q"),
    ("plant: {type: slab}\ntarget: 'x.__class__'", "Attribute"),
    ("plant: {type: slab}\ntarget: 'log(x)'", "target"),                 # -inf at x = 0
    ("plant: {type: slab}\nu_min: [0, 0, 0, 0, 0]\nu_max: [1, 1, 0, 1, 1]", "u_min"),
    ("plant: {n_x: 50}", "type"),
    ("plant: {type: furnace}", "furnace"),
    ("plant: {type: 'no_such_module_xyz:Plant'}", "no_such_module_xyz"),
    ("plant: {type: 'numpy:NoSuchPlant'}", "NoSuchPlant"),
    ("plant: {type: slab, n_xx: 50}", "n_xx"),
    ("plant: 5", "plant"),
])
def test_bad_values_name_the_key(tmp_path, text, key):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(write(tmp_path, text + "\n"))
    assert key in str(exc.value)


def test_unknown_plant_type_lists_the_known_ones(tmp_path):
    with pytest.raises(ScenarioError, match="known types are .*slab"):
        load_scenario(write(tmp_path, "plant: {type: furnace}\n"))


def test_a_class_named_by_module_path(tmp_path):
    s = load_scenario(write(tmp_path, "plant: {type: 'sep_plant.plants.slab:SlabPlant', n_x: 40}\n"))
    assert s.plant.n_x == 40 and type(s.plant).__name__ == "SlabPlant"


def test_two_sensors_on_one_node_refused():
    with pytest.raises(ScenarioError, match="same grid node"):
        flat(n_x=10, sensor_positions=(0.50, 0.52))


@pytest.mark.parametrize("text", ["- 1\n- 2\n", "just a string\n", "n_x: [1, 2\n"])
def test_not_a_mapping_or_not_yaml(tmp_path, text):
    with pytest.raises(ScenarioError):
        load_scenario(write(tmp_path, text))


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")


def test_constructors_validate_too():
    with pytest.raises(ValueError, match="n_x"):
        Slab(n_x=2)
    with pytest.raises(ProblemError, match="u_min"):
        Problem().replace(u_min=5.0, u_max=1.0)
    with pytest.raises(ScenarioError, match="n_x"):
        Scenario("slab", {"n_x": 2}).plant


@pytest.mark.parametrize("s", [
    flat(),
    flat(u_min=-math.inf, u_max=math.inf),
    flat(u_min=-2.0, u_max=math.inf, n_x=40, heater_centers=(0.25, 0.75), sensor_positions=(0.5,)),
    flat(u_min=-math.inf, u_max=3.5, dt=0.1, n_steps=300, k_band=200, lqr_k_switch=100),
    reference().replace(target="150 + 3 * tanh((x - 0.5) / 0.1)", w_std=(0.1, 0.2, 0.3, 0.2, 0.1)),
])
def test_json_round_trip(s):
    text = s.to_json()
    assert "Infinity" not in text and "NaN" not in text      # strict JSON
    back = Scenario.from_json(text)
    assert back == s and hash(back) == hash(s)
    assert back.problem.u_min == s.problem.u_min and back.problem.u_max == s.problem.u_max
    assert mismatches(back, s) == []


def test_scenario_payload_carries_the_plant_description():
    s = flat(n_x=40)
    scen, info = parse_scenario_payload(scenario_payload(s, s.info))
    assert scen == s and info == s.info
    # sep 0.1 published the flat scenario alone: still understood (the built-in slab describes it)
    old = '{"n_x": 40, "u_min": "-inf", "u_max": "inf"}'
    scen, info = parse_scenario_payload(old)
    assert scen.plant_config["n_x"] == 40 and info.n_field == 40 and info.field_name == "temperature"


def test_mismatches_lists_differing_plant_keys():
    a = reference()
    assert mismatches(a, flat()) == []
    b = a.with_plant(n_x=50, dt=0.5, sensor_positions=[0.1, 0.3, 0.5, 0.7, 0.8])
    diff = mismatches(a, b)
    assert [d.split(":")[0] for d in diff] == ["plant.dt", "plant.n_x", "plant.sensor_positions"]
    assert "100" in diff[1] and "50" in diff[1]
    # numerically equal after a float round trip is not a mismatch
    assert mismatches(a, a.with_plant(dt=0.1 + 0.15)) == []
    # a different number of heaters is a mismatch
    c = a.with_plant(heater_centers=[0.1, 0.3, 0.5, 0.7])
    assert [d.split(":")[0] for d in mismatches(a, c)] == ["plant.heater_centers"]
    # the horizon must match; problem keys (noise, weights, limits) may differ
    assert mismatches(a, a.replace(w_std=0.5, u_max=4.0)) == []
    assert [d.split(":")[0] for d in mismatches(a, a.replace(n_steps=200, band_window=(100, 200)))] == ["n_steps"]
    # another plant type
    assert mismatches(a, Scenario("sep_plant.plants.slab:SlabPlant", dict(a.plant_config), a.problem)) == \
        ["plant type: 'slab' != 'sep_plant.plants.slab:SlabPlant'"]


def test_derived_grid_quantities():
    s = Slab(n_x=40)
    assert s.h == pytest.approx(0.025)
    x = s.grid()
    assert x[0] == 0.0 and x[-1] == pytest.approx(1.0 - 0.025) and len(x) == 40
    np.testing.assert_array_equal(s.sensor_nodes(), [4, 12, 20, 28, 36])
    assert list(s.input_names) == [f"heater_{j}" for j in range(5)]
    np.testing.assert_array_equal(s.field_coordinates()[:, 0], x)
    assert not s.field_coordinates()[:, 1:].any()


def test_objective_resolves_the_problem_on_the_plant():
    s = reference().replace(target="150 + (x > 0.5)")
    obj = Objective.of(s.problem, s.plant.field_coordinates())
    assert obj.target.shape == (100,) and obj.target[0] == 150.0 and obj.target[-1] == 151.0
    assert obj.window == (150, 250) and obj.band == 3.0 and obj.n_steps == 250


def test_expression_evaluator_refuses_code():
    xs = {"x": np.linspace(0, 1, 5), "y": np.zeros(5), "z": np.zeros(5)}
    np.testing.assert_allclose(evaluate_expression("where(x < 0.5, 1, 2) + pi * 0", xs), [1, 1, 2, 2, 2])
    for text in ("__import__('os')", "open('f')", "x.real", "x[0]", "lambda: 1", "[1, 2]", "'a'"):
        with pytest.raises(ProblemError):
            evaluate_expression(text, xs)


def test_binary_file_is_a_scenario_error(tmp_path):
    """A file that is not UTF-8 text (e.g. a design .npz passed as --scenario by mistake)."""
    p = tmp_path / "design.npz"
    p.write_bytes(b"PK\x03\x04\xff\xfe\x00\x81binary")
    with pytest.raises(ScenarioError, match="design.npz"):
        load_scenario(p)


def test_unknown_keys_of_mixed_types_are_named(tmp_path):
    p = write(tmp_path, "1: 2\nfoo: 3\nn_x: 40\n")
    with pytest.raises(ScenarioError) as exc:
        load_scenario(p)
    assert "foo" in str(exc.value) and "1" in str(exc.value)



@pytest.mark.parametrize("path", sorted((REPO / "sep_plant" / "scenarios").glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_scenarios_load_and_their_plants_conform(path):
    """Every scenario file we ship loads, builds a plant that passes the protocol checks at its
    full size, resolves its problem on that plant (target, window), survives a JSON round trip
    (as in a design file), and its `design:` section gives valid design settings."""
    from sep_control.design.pipeline import DesignSettings
    from sep_plant.conformance import check_plant

    scen = load_scenario(path)
    plant, problem = scen.plant, scen.problem
    check_plant(plant, problem.u_start(plant.n_u)[0], batch=2, steps=2)
    obj = Objective.of(problem, plant.field_coordinates(), plant.dt)
    per_step = (problem.n_steps + 1, plant.n_field)      # a recipe's target (plate_anneal)
    assert obj.target.shape == (per_step if problem.time_varying else (plant.n_field,))
    assert np.isfinite(obj.target).all()
    assert 0 <= obj.window[0] < obj.window[1] == problem.n_steps
    assert Scenario.from_json(scen.to_json(), canonical=True) == scen.canonical()
    st = DesignSettings.for_scenario(scen)
    assert st.n_r == scen.design.get("n_r", DesignSettings().n_r)


@pytest.mark.parametrize("text,changes", [
    ("u_min: 0.0\n", dict(u_min=0.0)),
    ("target: 149.0\n", dict(target=149.0)),
    ("u_min: 0.0\nu_max: 0.6\nw_std: 0.2\n", dict(u_min=0.0, u_max=0.6, w_std=0.2)),
    ("n_steps: 100\n", dict(n_steps=100)),        # the window: the last 40 % (flat files: k_band 150)
    ("design: {n_r: 12}\nr_u: 0.2\n", dict(r_u=0.2)),
])
def test_a_file_of_problem_keys_is_the_reference_plant_with_them(tmp_path, text, changes):
    s = load_scenario(write(tmp_path, text))
    assert s.plant_type == "slab" and s.plant_config == reference().plant_config
    assert s.problem == reference().problem.replace(band_window=None, lqr_k_switch=None, **changes).resolved()
    if "n_steps" in changes:
        assert s.problem.window == (60, 100)


def test_flat_only_keys_select_the_flat_format(tmp_path):
    """k_band, t_target, q_late, q_early or a slab key mean sep 0.1's flat file (its window and
    LQR switch defaults); a current-format key beside them is named with what to do."""
    s = load_scenario(write(tmp_path, "t_target: 149\nn_steps: 200\nk_band: 120\n"))
    assert s.problem.target == 149.0 and s.problem.window == (120, 200) and s.problem.k_switch == 120
    with pytest.raises(ScenarioError) as exc:
        load_scenario(write(tmp_path, "n_x: 40\ntarget: 149.0\n"))
    msg = str(exc.value)
    assert "['target']" in msg and "flat slab format" in msg and "['n_x']" in msg and "plant:" in msg


def test_infinity_strings_are_read_in_one_place(tmp_path):
    from sep_plant import problem, scenario

    assert problem.decode_inf(["-inf", ".inf", " +Inf ", "x", 1.0]) == [-math.inf, math.inf, math.inf, "x", 1.0]
    assert not hasattr(scenario, "_decode_inf") and not hasattr(problem, "_decode")
    s = load_scenario(write(tmp_path, "n_x: 40\nu_min: -.inf\nu_max: [inf, 1, 1, 1, 1]\n"))
    assert s.problem.u_min == -math.inf and s.problem.u_max == (math.inf, 1.0, 1.0, 1.0, 1.0)
