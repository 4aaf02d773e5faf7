"""FMU plants (sep_plant.plants.fmu) against the native rod: the example rod FMU is built from
C source at test time (examples/fmu_rod/build_fmu.py, the system C compiler) and must step
like tests/fmu_rod.py's RodPlant, which has the same physics and the same fixed-step RK4:

* Model Exchange stepped by sep and Co-Simulation stepped by the FMU equal the native rod;
* both conform (check_plant), batches equal runs one by one, opaque states restart;
* every unsuitable FMU is refused with a message naming the FMU and the problem;
* scenarios resolve the FMU next to the scenario file and compare FMUs by SHA-256;
* a plant pickles with its FMU's bytes and rebuilds where the file is absent;
* a short design with the ME rod agrees with the native rod's.

Without a C compiler every test here skips, saying so (CI has gcc).
"""
from __future__ import annotations

import pickle
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

import fmu_rod
from fmu_rod import RodPlant
from sep_plant.conformance import check_plant
from sep_plant.plants import PlantConfigError, make_plant
from sep_plant.scenario import ScenarioError, load_scenario

fmu_rod.skip_without_toolchain()

HEATERS = ["heater_1", "heater_2", "heater_3"]
ME = {"inputs": HEATERS, "field": "T", "substeps": 4, "field_coordinates": "(i + 0.5) / n"}
CS = {"inputs": HEATERS, "field": "T", "interface": "co_simulation", "field_coordinates": "(i + 0.5) / n"}
#: relative agreement of an FMU plant with the native rod (same arithmetic; measured: bitwise
#: for FMI 2.0, 2e-16 for FMI 3.0)
RTOL = 1e-12
#: (FMU, keys) of every kind of FMU plant: FMI 2.0 and 3.0, Model Exchange and Co-Simulation
KINDS = [("rod", ME), ("rod", CS), ("rod3", ME), ("rod3", CS)]
KIND_IDS = ["fmi2-me", "fmi2-cs", "fmi3-me", "fmi3-cs"]


@pytest.fixture(scope="session")
def fmus(tmp_path_factory) -> dict[str, Path]:
    """The test FMUs: the rod (both interfaces), variants for the refusals, another rod."""
    d = tmp_path_factory.mktemp("fmus")
    return {
        "rod": fmu_rod.session_fmu(tmp_path_factory),
        "rod3": fmu_rod.build(d / "rod3.fmu", fmi_version=3),
        "rod40": fmu_rod.session_fmu(tmp_path_factory, "rod40", nodes=40),
        "cs_nostate": fmu_rod.build(d / "cs_nostate.fmu", interfaces=("co_simulation",), state=False),
        "cs_nostate3": fmu_rod.build(d / "cs_nostate3.fmu", interfaces=("co_simulation",), state=False,
                                     fmi_version=3),
        "me_events": fmu_rod.build(d / "me_events.fmu", interfaces=("model_exchange",), event_indicators=2),
    }


def fmu(path: Path, **keys):
    return make_plant("fmu", {"path": str(path), **keys})


def run(plant, X, U, W=None):
    out = [X]
    for k in range(U.shape[1]):
        out.append(plant.step(out[-1], U[:, k], None if W is None else W[:, k]))
    return out


def inputs(M: int, T: int, seed: int = 1):
    rng = np.random.default_rng(seed)
    return 0.3 + 0.1 * rng.standard_normal((M, T, 3)), 0.05 * rng.standard_normal((M, T, 3))


# ------------------------------------------------------------------ physics
@pytest.mark.parametrize("name,keys", KINDS, ids=KIND_IDS)
def test_fmu_plant_steps_like_the_native_rod(fmus, name, keys):
    plant, native = fmu(fmus[name], **keys), RodPlant()
    assert (plant.n_u, plant.n_y, plant.n_field, plant.dt) == (3, 3, 50, 0.25)
    assert plant.input_names == native.input_names and plant.output_names == native.output_names
    assert np.allclose(plant.field_coordinates(), native.field_coordinates(), rtol=0, atol=1e-15)
    U, W = inputs(4, 120)
    a, b = run(plant, plant.initial_state(4), U, W), run(native, native.initial_state(4), U, W)
    scale = np.max(np.abs(b[-1] - b[0]))
    assert scale > 20.0                                       # the rod heats up: a real test
    for Xa, Xb in zip(a, b):
        assert np.max(np.abs(plant.field(Xa) - Xb)) <= RTOL * scale
        assert np.max(np.abs(plant.observe(Xa) - native.observe(Xb))) <= RTOL * scale


@pytest.mark.parametrize("name", ["rod", "rod3"], ids=["fmi2", "fmi3"])
def test_model_exchange_state_is_the_fmus_continuous_states(fmus, name):
    plant = fmu(fmus[name], **ME)
    assert plant.n_x == 50 and plant.field_is_state and not getattr(plant, "state_is_opaque", False)
    assert plant.field_name == "T" and plant.field_unit == "F" and plant.grid_shape is None
    assert np.array_equal(plant.initial_state(2), np.full((2, 50), 100.0))
    X = plant.step(plant.initial_state(3), np.full(3, 0.5))
    assert plant.field(X) is X                                # the state itself, as the built-ins


def test_co_simulation_state_is_an_opaque_row(fmus):
    plant = fmu(fmus["rod"], **CS)
    assert plant.state_is_opaque and not plant.field_is_state
    X0 = plant.initial_state(2)
    assert X0.dtype == np.float64 and np.all(np.isfinite(X0)) and plant.n_x == X0.shape[1] > 3 + 3 + 50
    assert np.array_equal(plant.field(X0), np.full((2, 50), 100.0))


@pytest.mark.parametrize("name,keys", KINDS, ids=KIND_IDS)
def test_batch_equals_runs_one_by_one(fmus, name, keys):
    plant = fmu(fmus[name], **keys)
    U, W = inputs(5, 8, seed=3)
    X = run(plant, plant.initial_state(5), U, W)[-1]
    u, w = U[:, 0] + 0.2, W[:, 0]
    batch = plant.step(X, u, w)
    single = np.vstack([plant.step(X[i:i + 1], u[i:i + 1], w[i:i + 1]) for i in range(5)])
    assert np.array_equal(plant.observe(batch), plant.observe(single))
    assert np.array_equal(plant.field(batch), plant.field(single))
    shared = plant.step(X, u[0])                              # one input for every run
    assert np.array_equal(plant.field(shared[2:3]), plant.field(plant.step(X[2:3], u[0])))


@pytest.mark.parametrize("name,keys", KINDS, ids=KIND_IDS)
def test_fmu_plants_conform(fmus, name, keys):
    plant = fmu(fmus[name], **keys)
    check_plant(plant, np.full(3, 0.2), name="fmu")
    assert type(plant)(**plant.config()).config() == plant.config()


@pytest.mark.parametrize("name", ["rod", "rod3"], ids=["fmi2", "fmi3"])
def test_model_exchange_equals_co_simulation_bitwise(fmus, name):
    """Same C derivative, same RK4 arithmetic in the same order: identical numbers."""
    me, cs = fmu(fmus[name], **ME), fmu(fmus[name], **CS)
    U, W = inputs(3, 40, seed=5)
    a, b = run(me, me.initial_state(3), U, W)[-1], run(cs, cs.initial_state(3), U, W)[-1]
    assert np.array_equal(me.field(a), cs.field(b)) and np.array_equal(me.observe(a), cs.observe(b))


@pytest.mark.parametrize("name", ["rod", "rod3"], ids=["fmi2", "fmi3"])
def test_opaque_states_restart(fmus, name):
    """Copies of a state row step like the original, now and after a restart later."""
    plant = fmu(fmus[name], **CS)
    U, _ = inputs(1, 30, seed=7)
    X = run(plant, plant.initial_state(1), U)
    snap = X[10].copy()
    again = run(plant, snap, U[:, 10:])[-1]
    assert np.array_equal(plant.field(again), plant.field(X[-1]))
    assert np.array_equal(plant.observe(again), plant.observe(X[-1]))
    twins = plant.step(np.vstack([snap, snap]), U[0, 10])
    assert np.array_equal(plant.field(twins[0:1]), plant.field(twins[1:2]))
    assert np.array_equal(plant.field(twins[0:1]), plant.field(X[11]))


def test_an_altered_opaque_row_is_refused(fmus):
    plant = fmu(fmus["rod"], **CS)
    X = plant.initial_state(2)
    with pytest.raises(ValueError, match="opaque"):
        plant.step(X.mean(axis=0, keepdims=True) + 0.5, np.zeros(3))
    Y = X.copy()
    Y[0, -1] += 1.0                                          # whole numbers, wrong bytes
    with pytest.raises(ValueError, match="checksum"):
        plant.step(Y, np.zeros(3))


def test_noise_on_named_inputs(fmus):
    """noise_inputs: [q_left]: w is the inflow heat flux at x = 0, not added to the heaters."""
    plant = fmu(fmus["rod"], **ME, noise_inputs=["q_left"])
    assert not plant.noise_on_inputs and plant.n_w == 1 and plant.n_u == 3
    check_plant(plant, np.full(3, 0.2), name="fmu noise_inputs")
    native = RodPlant()
    X0, u, w = plant.initial_state(2), np.full((2, 3), 0.3), np.array([[2.0], [-1.0]])
    assert np.allclose(plant.step(X0, u, w), native.step(X0, u, q_left=w[:, 0]), rtol=RTOL, atol=0)
    assert np.array_equal(plant.step(X0, u), native.step(X0, u))


def test_defaults_from_the_model_description(fmus):
    plant = fmu(fmus["rod"])                                  # every Real input, every output
    assert plant.input_names == ("heater_1", "heater_2", "heater_3", "q_left")
    assert plant.output_names == ("sensor_1", "sensor_2", "sensor_3")
    assert plant.interface == "model_exchange" and plant.dt == 0.25 and plant.substeps == 1
    assert plant.field_is_state and plant.field_name == "value"
    assert np.array_equal(plant.field_coordinates()[:, 0], np.arange(50.0))
    cs = fmu(fmus["rod"], interface="co_simulation", outputs=["sensor_2"])
    assert cs.n_field == 1 and np.array_equal(cs.field(cs.initial_state(1)), cs.observe(cs.initial_state(1)))


def test_start_values_set_parameters(fmus):
    plant = fmu(fmus["rod"], **ME, start_values={"t_init": 120.0, "k0": 0.003, "sensor_position_1": 0.1})
    native = RodPlant(t_init=120.0, k0=0.003, sensor_positions=(0.1, 0.55, 0.9))
    X0 = plant.initial_state(1)
    assert np.array_equal(X0, native.initial_state(1))
    X1 = plant.step(X0, np.full(3, 0.4))
    assert np.allclose(X1, native.step(X0, np.full(3, 0.4)), rtol=RTOL, atol=0)
    assert np.array_equal(plant.observe(X1), native.observe(X1))


def test_structured_2d_array_gives_the_grid_shape(fmus, tmp_path):
    """An FMI 2.0 array T[i,j] (structured naming) is a 2-D field whose grid_shape is its box."""
    import re

    def to_2d(text: str) -> str:
        def name(m):
            k = int(m.group(2)) - 1
            return f"{m.group(1)}T[{k // 5 + 1},{k % 5 + 1}]"
        return re.sub(r"(name=\"(?:der\()?)T\[(\d+)\]", name, text)

    path = rewrite(fmus["rod"], tmp_path / "grid.fmu", to_2d)
    plant = fmu(path, **{**ME, "field_coordinates": {"origin": [0.0, 0.0], "spacing": [0.1, 0.2]}})
    assert plant.grid_shape == (10, 5) and plant.field_is_state and plant.field_name == "T"
    assert np.allclose(plant.field_coordinates()[7], [0.1, 0.4, 0.0])
    X = plant.step(plant.initial_state(1), np.full(3, 0.3))
    assert np.array_equal(X, RodPlant().step(RodPlant().initial_state(1), np.full(3, 0.3)))


def test_field_coordinates_and_grid_shape(fmus):
    p = fmu(fmus["rod"], **{**ME, "field_coordinates": {"origin": [0.0, 0.0], "spacing": [0.1, 0.2]},
                            "grid_shape": [10, 5]})
    xyz = p.field_coordinates()
    assert p.grid_shape == (10, 5) and np.allclose(xyz[6], [0.1, 0.2, 0.0])
    p = fmu(fmus["rod"], **{**ME, "field_coordinates": ["i / n", "0.5 * i"]})
    assert np.allclose(p.field_coordinates()[3], [3 / 50, 1.5, 0.0])
    p = fmu(fmus["rod"], **{**ME, "field_coordinates": [[0.1 * i, 1.0] for i in range(50)]})
    assert np.allclose(p.field_coordinates()[4], [0.4, 1.0, 0.0])


# ------------------------------------------------------------------ refusals
def refused(path: Path, **keys) -> str:
    with pytest.raises(PlantConfigError) as exc:
        fmu(path, **keys)
    msg = str(exc.value)
    assert str(path) in msg, msg                              # the FMU is named
    return msg


def rewrite(src: Path, dst: Path, edit) -> Path:
    """A copy of FMU `src` with its modelDescription.xml edited by `edit(text) -> text`."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = edit(data.decode()).encode()
            zout.writestr(item, data)
    return dst


def test_refuses_a_missing_file(tmp_path):
    assert "file not found" in refused(tmp_path / "nowhere.fmu")


def test_refuses_a_zip_that_is_not_an_fmu(tmp_path):
    path = tmp_path / "not_an_fmu.fmu"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("readme.txt", "hello")
    assert "no modelDescription.xml" in refused(path)


def test_refuses_a_corrupt_zip(fmus, tmp_path):
    data = fmus["rod"].read_bytes()
    path = tmp_path / "truncated.fmu"
    path.write_bytes(data[: len(data) // 2])
    assert "not a zip archive" in refused(path)
    path = tmp_path / "text.fmu"
    path.write_text("not a zip")
    assert "not a zip archive" in refused(path)


def test_refuses_a_broken_model_description(fmus, tmp_path):
    broken = rewrite(fmus["rod"], tmp_path / "broken.fmu", lambda t: t.replace("</ModelVariables>", ""))
    assert "modelDescription.xml cannot be read" in refused(broken)
    fmi1 = rewrite(fmus["rod"], tmp_path / "fmi1.fmu", lambda t: t.replace('fmiVersion="2.0"', 'fmiVersion="1.0"'))
    assert "FMI version '1.0' is not supported" in refused(fmi1)


def test_refuses_missing_variables_naming_each(fmus):
    msg = refused(fmus["rod"], inputs=["heater_1", "heater_9"], outputs=["sensor_1", "senser_2"], field="U")
    assert "inputs: the FMU has no variable 'heater_9'" in msg
    assert "outputs: the FMU has no variable 'senser_2' (did you mean sensor_2" in msg
    assert "field: the FMU has no variable 'U'" in msg


def test_refuses_unsuitable_variables(fmus):
    msg = refused(fmus["rod"], inputs=["sensor_1"], start_values={"T[3]": 120.0, "k0": "fast"})
    assert "inputs: sensor_1 has causality 'output', expected input" in msg
    assert "start_values: T[3] cannot be set" in msg and "start_values: k0: a Real variable needs a number" in msg


@pytest.mark.parametrize("name", ["cs_nostate", "cs_nostate3"], ids=["fmi2", "fmi3"])
def test_refuses_a_co_simulation_fmu_without_fmu_state(fmus, name):
    msg = refused(fmus[name], inputs=HEATERS)
    assert "cannot get and set its FMU state" in msg and "cannot serialize its FMU state" in msg


def test_refuses_a_model_exchange_fmu_with_event_indicators(fmus):
    msg = refused(fmus["me_events"], inputs=HEATERS)
    assert "2 event indicator(s)" in msg and "co_simulation" in msg


def test_refuses_inputs_that_cannot_be_set_per_stage(fmus, tmp_path):
    once = rewrite(fmus["rod"], tmp_path / "once.fmu", lambda t: t.replace(
        'name="heater_2" valueReference', 'name="heater_2" canHandleMultipleSetPerTimeInstant="false" valueReference'))
    assert "input heater_2 cannot be set several times per time instant" in refused(once, **ME)
    fmu(once, **CS)                                                     # Co-Simulation sets it once per step


def test_a_closed_plant_reopens(fmus):
    plant = fmu(fmus["rod"], **ME)
    X = plant.step(plant.initial_state(1), np.full(3, 0.3))
    plant.close()
    assert np.array_equal(plant.step(plant.initial_state(1), np.full(3, 0.3)), X)


def test_refuses_an_interface_it_does_not_have(fmus):
    assert "interface model_exchange is not provided" in refused(fmus["cs_nostate"], interface="model_exchange")


def test_refuses_substeps_for_co_simulation_and_bad_keys(fmus):
    assert "substeps applies to Model Exchange only" in refused(fmus["rod"], interface="co_simulation", substeps=2)
    with pytest.raises(PlantConfigError, match="interface must be one of"):
        fmu(fmus["rod"], interface="cs")
    with pytest.raises(PlantConfigError, match="inputs must be a non-empty list"):
        fmu(fmus["rod"], inputs="heater_1")
    with pytest.raises(PlantConfigError, match="grid_shape"):
        fmu(fmus["rod"], **ME, grid_shape=[7, 7])


def test_refuses_another_fmu_than_expected(fmus):
    other = fmu(fmus["rod40"], inputs=HEATERS).path_sha256
    assert "another FMU" in refused(fmus["rod"], path_sha256=other)


# ------------------------------------------------------------------ scenarios and shipping
def scenario_text(path: str) -> str:
    return (f"plant:\n  type: fmu\n  path: {path}\n  inputs: [heater_1, heater_2, heater_3]\n  field: T\n"
            "  substeps: 4\nn_steps: 40\ntarget: 110.0\n")


def test_scenario_path_is_relative_to_the_scenario_file(fmus, tmp_path):
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        shutil.copy(fmus["rod"], tmp_path / sub / "rod.fmu")
        (tmp_path / sub / "scenario.yaml").write_text(scenario_text("rod.fmu"))
    a, b = load_scenario(tmp_path / "a" / "scenario.yaml"), load_scenario(tmp_path / "b" / "scenario.yaml")
    assert a.plant_config["path"] == str(tmp_path / "a" / "rod.fmu") and a.plant.n_x == 50
    assert a.plant_config["path"] != b.plant_config["path"]
    assert a.plant_mismatches(b) == []                        # same content: the same plant
    shutil.copy(fmus["rod40"], tmp_path / "b" / "rod.fmu")    # another FMU under the same name
    diff = a.plant_mismatches(load_scenario(tmp_path / "b" / "scenario.yaml"))
    assert len(diff) == 1 and diff[0].startswith("plant.path: another file") and "SHA-256" in diff[0]
    with pytest.raises(ScenarioError, match="file not found"):
        (tmp_path / "c").mkdir()
        (tmp_path / "c" / "scenario.yaml").write_text(scenario_text("rod.fmu"))
        load_scenario(tmp_path / "c" / "scenario.yaml")


def test_example_scenario_loads_and_conforms(fmus, tmp_path):
    """examples/fmu_rod/scenario.yaml next to a built rod.fmu: the plant the README designs."""
    shutil.copy(fmu_rod.EXAMPLE / "scenario.yaml", tmp_path / "scenario.yaml")
    shutil.copy(fmus["rod"], tmp_path / "rod.fmu")
    scen = load_scenario(tmp_path / "scenario.yaml")
    plant = scen.plant
    assert scen.plant_type == "fmu" and plant.interface == "model_exchange" and plant.n_x == 50
    assert plant.field_name == "temperature" and scen.problem.n_steps == 250
    check_plant(plant, np.full(3, 0.3), name="examples/fmu_rod")
    back = type(scen).from_json(scen.to_json())               # plain data, as in a design file
    assert back == scen and back.plant_mismatches(scen) == [] and back.plant.config() == plant.config()


def test_source_files_and_config(fmus):
    from sep_plant.plants import type_name_of

    plant = fmu(fmus["rod"], **ME)
    assert type_name_of(plant) == "fmu"
    assert plant.source_files() == {"fmu": str(fmus["rod"])}
    from sep_plant.plants.fmu.archive import sha256_file

    assert plant.config()["path_sha256"] == sha256_file(fmus["rod"])


@pytest.mark.parametrize("name,keys", KINDS, ids=KIND_IDS)
def test_pickles_with_its_bytes_and_rebuilds_without_the_file(fmus, tmp_path, monkeypatch, name, keys):
    monkeypatch.setenv("SEP_FMU_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "rod.fmu"
    shutil.copy(fmus[name], path)
    plant = fmu(path, **keys)
    blob = pickle.dumps(plant)
    X = plant.step(plant.initial_state(2), np.full(3, 0.3))
    path.unlink()                                             # a worker's disk: no such file
    again = pickle.loads(blob)
    assert again.path != str(path) and again.path_sha256 == plant.path_sha256
    assert np.array_equal(again.field(again.step(again.initial_state(2), np.full(3, 0.3))), plant.field(X))
    built = type(plant).from_bytes(fmus[name].read_bytes(), **plant.config())
    assert built.config() == {**plant.config(), "path": built.path}
    with pytest.raises(PlantConfigError, match="expected"):             # other bytes than the config's FMU
        type(plant).from_bytes(fmus["rod40"].read_bytes(), **plant.config())


def test_a_perturbed_fmu_rebuilds_from_its_shipped_bytes(fmus, tmp_path, monkeypatch):
    """What a cluster worker without the FMU file does (`sep_control.compute.engine.worker_plant`)."""
    from sep_control.compute import engine
    from sep_plant.perturb import PerturbedPlant

    monkeypatch.setenv("SEP_FMU_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "rod.fmu"
    shutil.copy(fmus["rod"], path)
    plant = PerturbedPlant.around(fmu(path, **ME), input_gain=0.8, sensor_bias=0.5)
    files = engine.plant_files(plant)
    spec = engine.plant_spec(plant, files)
    path.unlink()                                             # a worker's disk: no such file
    monkeypatch.setattr(engine, "_WORKER_FILES", {sha: data for sha, data in files.values()})
    worker = engine.worker_plant(spec)
    assert isinstance(worker, PerturbedPlant) and worker.perturbation() == plant.perturbation()
    U, W = inputs(2, 3)
    for got, want in zip(run(worker, worker.initial_state(2), U, W), run(plant, plant.initial_state(2), U, W)):
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(worker.observe(got), plant.observe(want))


# ------------------------------------------------------------------ design
@pytest.mark.slow
def test_short_design_agrees_with_the_native_rod(fmus):
    """run_design on the ME rod and on the native rod: the nominal cost agrees to 1e-6."""
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_plant.problem import Problem

    problem = Problem(n_steps=40, target=115.0, band=3.0, band_window=(25, 40), w_std=0.05, v_std=0.1,
                      u_init=0.3, u_min=0.0, u_max=3.0, r_u=1e-3, lqr_r=1e-3)
    settings = DesignSettings(max_iter=4, belief_iter=1, ensemble=40, n_r=8, p=5, q=5)
    quiet = {"show_progress": False, "log": lambda m: None}
    d_fmu = run_design(fmu(fmus["rod"], **ME), problem, settings, **quiet)
    d_nat = run_design(RodPlant(), problem, settings, **quiet)
    a, b = d_fmu.meta["optimizer"]["nominal_cost"], d_nat.meta["optimizer"]["nominal_cost"]
    assert a == pytest.approx(b, rel=1e-6)
    assert np.allclose(d_fmu.nominal.u, d_nat.nominal.u, rtol=1e-6, atol=1e-9)
    assert d_fmu.meta["optimizer"]["belief_history"] == pytest.approx(d_nat.meta["optimizer"]["belief_history"],
                                                                      rel=1e-6)
    assert np.allclose(d_fmu.nominal.belief_mean, d_nat.nominal.belief_mean, rtol=1e-9, atol=0)


# ------------------------------------------------------------------ conformance of opaque states
class OpaqueToy:
    """broken_plants.ToyPlant with a state row that also carries a serial number, different on
    every step (as a serialized FMU state may carry counters or addresses): equal states need
    not be equal rows, so an opaque plant is compared by its outputs."""

    state_is_opaque = True

    def __init__(self, interact: bool = False):
        from broken_plants import ToyPlant

        self._toy, self.interact, self._serial = ToyPlant(), interact, 0
        for a in ("dt", "n_u", "n_y", "n_field", "input_names", "output_names", "field_name", "field_unit"):
            setattr(self, a, getattr(self._toy, a))
        self.n_x = self._toy.n_x + 1

    def config(self):
        return {"interact": self.interact}

    def initial_state(self, batch):
        return np.zeros((batch, self.n_x))

    def step(self, x, u, w=None):
        self._serial += 1
        out = np.empty_like(x)
        out[:, :-1] = self._toy.step(x[:, :-1], u, w)
        if self.interact:
            out[:, :-1] += 0.01 * out[:, :-1].mean(axis=0)
        out[:, -1] = self._serial
        return out

    def observe(self, x):
        return self._toy.observe(x[:, :-1])

    def field(self, x):
        return x[:, :-1].copy()

    def field_coordinates(self):
        return self._toy.field_coordinates()


def test_opaque_states_are_compared_by_their_outputs():
    check_plant(OpaqueToy(), np.full(2, 0.1), name="OpaqueToy")      # rows differ, outputs agree
    from sep_plant.conformance import conformance_problems

    plain = OpaqueToy()
    plain.state_is_opaque = False                                      # compared by value: refused
    assert any("not deterministic" in p for p in conformance_problems(plain, np.full(2, 0.1)))
    with pytest.raises(Exception, match="stepped one by one"):
        check_plant(OpaqueToy(interact=True), np.full(2, 0.1), name="OpaqueToy")


# ------------------------------------------------------------------ failed FMI calls (review of 0.8.0)
def _spy(b, calls: list, fail: str | None, names=("deserialize", "set_state", "free_state", "set_reals",
                                                  "do_step", "get_reals", "get_state", "state_size",
                                                  "serialize")):
    """Wrap the Co-Simulation calls of binding `b` to record their order; `fail` returns 3 (error)."""
    for name in names:
        real = getattr(b, name)

        def call(*args, _name=name, _real=real):
            calls.append(_name)
            return 3 if _name == fail else _real(*args)
        setattr(b, name, call)


@pytest.mark.parametrize("fail,named", [("deserialize", "deserialize FMU state"), ("get_state", "get FMU state"),
                                        ("do_step", "do step")])
def test_a_failed_fmi_call_stops_the_step_and_is_named_alone(fmus, fail, named):
    """0.8.0 chained the calls with `|`: after a failed deserialize it still set the state with a bad
    handle and stepped, and a failed get-state surfaced as 'state grew' or a five-call message."""
    from sep_plant.plants.fmu.binding import FMICallError
    plant = fmu(fmus["rod"], **CS)
    X = plant.initial_state(2)
    calls: list[str] = []
    _spy(plant._stepper.b, calls, fail)
    with pytest.raises(FMICallError) as err:
        plant.step(X, np.full(3, 0.2))
    msg = str(err.value)
    assert f"{named} (run 0) failed (status 3, error)" in msg, msg
    assert calls[-1] == fail and calls.count(fail) == 1          # nothing called after the failure
    assert " / " not in msg and "grew" not in msg
