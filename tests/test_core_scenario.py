"""Scenario: YAML loading, validation messages, JSON round trip, mismatches."""
import math
from pathlib import Path

import numpy as np
import pytest

from sep_plant.scenario import PLANT_KEYS, Scenario, ScenarioError, load_scenario, mismatches

REPO = Path(__file__).resolve().parent.parent
REFERENCE_YAML = REPO / "sep_plant" / "scenarios" / "reference.yaml"



def write(tmp_path, text, name="scenario.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_defaults_are_the_reference_scenario():
    s = Scenario()
    assert (s.n_x, s.length, s.k0, s.beta, s.eta, s.t_right, s.t_init) == (100, 1.0, 0.01, 0.5, 0.002, 150.0, 100.0)
    assert s.heater_centers == (0.1, 0.3, 0.5, 0.7, 0.9) and s.sensor_positions == s.heater_centers
    assert (s.dt, s.n_steps, s.w_std, s.v_std, s.k_band, s.lqr_k_switch) == (0.25, 250, 0.3, 1.0, 150, 120)
    assert (s.heater_sigma, s.q_late, s.q_early, s.r_u, s.lqr_r) == (0.02, 1.0, 1e-5, 0.1, 0.01)
    assert s.u_min == -math.inf and s.u_max == math.inf
    assert s.horizon_s == 62.5
    q = s.q_weights()
    assert q.shape == (251,) and q[149] == 1e-5 and q[150] == 1.0
    qy = s.lqr_output_weights()
    assert qy[119] == pytest.approx(0.1 / 5) and qy[120] == pytest.approx(1.0 / 5)


def test_none_is_the_reference():
    assert load_scenario(None) == Scenario()


def test_yaml_with_overrides(tmp_path):
    p = write(tmp_path, "n_x: 50\ndt: 0.5\nn_steps: 125\nk_band: 75\nlqr_k_switch: 60\n"
                        "heater_centers: [0.2, 0.5, 0.8]\nsensor_positions: [0.25, 0.75]\n"
                        "u_min: 0\nu_max: .inf\nw_std: 0.1\n")
    s = load_scenario(p)
    assert s == Scenario(n_x=50, dt=0.5, n_steps=125, k_band=75, lqr_k_switch=60,
                         heater_centers=(0.2, 0.5, 0.8), sensor_positions=(0.25, 0.75),
                         u_min=0.0, u_max=math.inf, w_std=0.1)
    assert isinstance(s.n_x, int) and isinstance(s.dt, float) and isinstance(s.u_min, float)
    assert (s.n_u, s.n_y) == (3, 2)
    # untouched keys keep the reference values
    assert s.k0 == 0.01 and s.t_right == 150.0


def test_yaml_under_a_scenario_key_and_string_infinities(tmp_path):
    p = write(tmp_path, "scenario:\n  n_x: 60\n  u_min: '-inf'\n  u_max: 'inf'\n")
    s = load_scenario(p)
    assert s.n_x == 60 and s.u_min == -math.inf and s.u_max == math.inf


def test_empty_yaml_is_the_reference(tmp_path):
    assert load_scenario(write(tmp_path, "")) == Scenario()


def test_reference_yaml_is_the_default_scenario():
    if not REFERENCE_YAML.exists():
        pytest.skip("sep_plant/scenarios/reference.yaml not shipped yet")
    assert load_scenario(REFERENCE_YAML) == Scenario()


def test_unknown_key_is_named(tmp_path):
    p = write(tmp_path, "n_x: 40\nheater_sigmaa: 0.03\n")
    with pytest.raises(ScenarioError, match="heater_sigmaa"):
        load_scenario(p)


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
    ("k_band: 300", "k_band"),
    ("lqr_k_switch: -1", "lqr_k_switch"),
    ("k0: true", "k0"),
    ("heater_sigma: -0.02", "heater_sigma"),
    ("u_min: 0.5", "u_init"),
])
def test_bad_values_name_the_key(tmp_path, text, key):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(write(tmp_path, text + "\n"))
    assert key in str(exc.value)


def test_two_sensors_on_one_node_refused():
    with pytest.raises(ScenarioError, match="same grid node"):
        Scenario(n_x=10, sensor_positions=(0.50, 0.52))


@pytest.mark.parametrize("text", ["- 1\n- 2\n", "just a string\n", "n_x: [1, 2\n"])
def test_not_a_mapping_or_not_yaml(tmp_path, text):
    with pytest.raises(ScenarioError):
        load_scenario(write(tmp_path, text))


def test_missing_file(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.yaml")


def test_constructor_validates_too():
    with pytest.raises(ScenarioError, match="n_x"):
        Scenario(n_x=2)
    with pytest.raises(ScenarioError, match="u_min"):
        Scenario().replace(u_min=5.0, u_max=1.0)


@pytest.mark.parametrize("s", [
    Scenario(),
    Scenario(u_min=-math.inf, u_max=math.inf),
    Scenario(u_min=-2.0, u_max=math.inf, n_x=40, heater_centers=(0.25, 0.75), sensor_positions=(0.5,)),
    Scenario(u_min=-math.inf, u_max=3.5, dt=0.1, n_steps=300, k_band=200, lqr_k_switch=100),
])
def test_json_round_trip(s):
    text = s.to_json()
    assert "Infinity" not in text and "NaN" not in text      # strict JSON
    back = Scenario.from_json(text)
    assert back == s
    assert back.u_min == s.u_min and back.u_max == s.u_max
    assert mismatches(back, s, tuple(s.to_dict())) == []


def test_mismatches_lists_differing_keys():
    a = Scenario()
    assert mismatches(a, Scenario()) == []
    b = a.replace(n_x=50, dt=0.5, sensor_positions=(0.1, 0.3, 0.5, 0.7, 0.8))
    diff = mismatches(a, b)
    assert len(diff) == 3
    assert [d.split(":")[0] for d in diff] == ["n_x", "dt", "sensor_positions"]
    assert "100" in diff[0] and "50" in diff[0]
    # numerically equal after a float round trip is not a mismatch
    assert mismatches(a, a.replace(dt=0.1 + 0.15)) == []
    # a different number of heaters is a mismatch
    c = a.replace(heater_centers=(0.1, 0.3, 0.5, 0.7))
    assert [d.split(":")[0] for d in mismatches(a, c)] == ["heater_centers"]
    # only plant keys by default; any key on request
    d = a.replace(w_std=0.5)
    assert mismatches(a, d) == []
    assert mismatches(a, d, ("w_std",)) == ["w_std: 0.3 != 0.5"]
    assert "n_x" in PLANT_KEYS and "sensor_positions" in PLANT_KEYS


def test_derived_grid_quantities():
    s = Scenario(n_x=40)
    assert s.h == pytest.approx(0.025)
    x = s.grid()
    assert x[0] == 0.0 and x[-1] == pytest.approx(1.0 - 0.025) and len(x) == 40
    np.testing.assert_array_equal(s.sensor_nodes(), [4, 12, 20, 28, 36])
    assert s.heater_labels() == [f"heater_{j}" for j in range(5)]


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
