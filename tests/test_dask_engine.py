"""Experiment batches on a Dask LocalCluster: the same answers as in-process, and the faults.

One LocalCluster of two worker processes serves the module (it takes a few seconds to start);
the worker-loss test kills one of its workers, so it runs last.
"""
import json
import socket
import time

import numpy as np
import pytest

from core_helpers import flat
from dask_plants import KillsWorkerOnce, RaisesOnWorker
from sep_control.cli.main import main as sep
from sep_control.design import tvera
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.compute.engine import EngineError, InProcess, TaskError, open_engine, parse_dask
from sep_control.evaluation.montecarlo import simulate

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)
FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1)


@pytest.fixture(scope="module")
def cluster():
    eng = open_engine("local:2")
    assert eng.workers == 2
    yield eng
    eng.close()


@pytest.fixture(scope="module")
def small_design():
    sc = flat(**SMALL)
    return sc, run_design(sc.plant, sc.problem, DesignSettings.for_scenario(sc, **FAST), show_progress=False,
                          log=lambda m: None)


def close(a, b, rel=1e-12):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape
    scale = max(float(np.abs(b).max(initial=0.0)), 1e-300)
    assert float(np.abs(a - b).max(initial=0.0)) <= rel * scale


def test_design_on_a_cluster_equals_in_process(cluster, small_design):
    sc, here = small_design
    there = run_design(sc.plant, sc.problem, DesignSettings.for_scenario(sc, **FAST), show_progress=False,
                       log=lambda m: None, engine=cluster)
    close(there.nominal.u, here.nominal.u)
    close(there.lqg.K, here.lqg.K)
    close(there.lqg.field_std, here.lqg.field_std)
    close(there.rom.A, here.rom.A)
    close(there.rom.C, here.rom.C)
    for k in (1, 20, 40):
        close(there.rom.G.matrix(k), here.rom.G.matrix(k))
    close(there.hankel_sv, here.hankel_sv)


def test_design_cli_dask_local2_writes_the_same_arrays(tmp_path, capsys):
    """The acceptance command: `design --dask local:2 --out a.npz` == `design --out b.npz`."""
    scen = tmp_path / "small.yaml"
    scen.write_text("".join(f"{k}: {v}\n" for k, v in SMALL.items()))
    fast = ["--p", "5", "--q", "5", "--n-r", "10", "--ensemble", "20", "--belief-iter", "1", "--quiet"]
    assert sep(["design", "--scenario", str(scen), "--out", str(tmp_path / "a.npz"), "--dask", "local:2"] + fast) == 0
    assert "dashboard" in capsys.readouterr().err
    assert sep(["design", "--scenario", str(scen), "--out", str(tmp_path / "b.npz")] + fast) == 0
    a, b = np.load(tmp_path / "a.npz", allow_pickle=False), np.load(tmp_path / "b.npz", allow_pickle=False)
    assert sorted(a.files) == sorted(b.files)
    floats = [k for k in a.files if a[k].dtype.kind == "f"]
    assert len(floats) >= 10
    for k in floats:
        close(a[k], b[k])


def test_monte_carlo_on_a_cluster_equals_in_process(cluster, small_design):
    sc, d = small_design
    for controller in ("open_loop", "rom_lqg"):
        here = simulate(sc.plant, d, controller, 3, 50, keep_estimates=2, keep_trajectories=3)
        there = simulate(sc.plant, d, controller, 3, 50, keep_estimates=2, keep_trajectories=3, engine=cluster)
        # per run the same numbers up to the round-off of batch-size-dependent BLAS blocking
        close(there.U, here.U)
        close(there.F, here.F)
        close(there.F_mean, here.F_mean)
        for key, val in here.summary.items():
            assert there.summary[key] == pytest.approx(val, rel=1e-12, abs=1e-12), key


def test_plant_error_on_a_worker_names_the_plant_and_the_experiments(cluster):
    plant = RaisesOnWorker(n_x=8)
    U = np.full((30, 2), 0.2)
    t0 = time.perf_counter()
    with pytest.raises(TaskError) as exc:
        tvera.impulse_experiments(plant, U, 6, 3, 1e-3, chunks=4, engine=cluster)
    msg = str(exc.value)
    assert "RaisesOnWorker" in msg and "TV-ERA impulse experiments, chunk" in msg and "start steps" in msg
    assert "solver diverged" in msg
    assert time.perf_counter() - t0 < 120      # failed, not hung
    # the cluster is still usable afterwards
    assert cluster.map(abs, [-1, -2]) == [1, 2]


def test_unreachable_scheduler_exits_2(capsys, tmp_path):
    with socket.socket() as s:          # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as exc:
        sep(["design", "--out", str(tmp_path / "x.npz"), "--dask", f"tcp://127.0.0.1:{port}", "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}" in err and "dask scheduler" in err
    assert time.perf_counter() - t0 < 60
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("bad,message", [
    ("banana", "--dask must be local, local:N"),
    ("local:0", "--dask local:N needs N >= 1, got 'local:0'"),
    ("tcp://nohost", "--dask must be local, local:N"),           # no port
    ("local:two", "--dask must be local, local:N"),
])
def test_bad_dask_values_are_refused(bad, message, capsys, tmp_path):
    with pytest.raises(EngineError, match="--dask"):
        parse_dask(bad)
    with pytest.raises(SystemExit) as exc:
        sep(["design", "--out", str(tmp_path / "x.npz"), "--dask", bad, "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"sep design: error: {message}" in err, err
    assert not (tmp_path / "x.npz").exists()


def test_in_process_engine_names_the_failing_task():
    with pytest.raises(TaskError, match="chunk b: ZeroDivisionError"):
        InProcess().map(lambda x: 1 / x, [1, 0], labels=["chunk a", "chunk b"])


# ------------------------------------------------------------------ FMU plants on the cluster
FMU_YAML = """\
plant:
  type: fmu
  path: rod.fmu
  interface: {interface}
  inputs: [heater_1, heater_2, heater_3]
  field: T
  dt: 0.5
  start_values: {{t_right: 120.0, n_substeps: 8}}
n_steps: 40
target: 112.0
band_window: [30, 40]
w_std: 0.05
"""


@pytest.fixture(scope="module")
def fmu_rods(tmp_path_factory):
    """The example rod FMU (built from C source) as Model Exchange and Co-Simulation scenarios."""
    import fmu_rod
    from sep_plant.scenario import load_scenario

    fmu_rod.skip_without_toolchain()
    d = tmp_path_factory.mktemp("dask_fmu")
    (d / "rod.fmu").write_bytes(fmu_rod.session_fmu(tmp_path_factory).read_bytes())
    out = {}
    for name, interface in (("me", "model_exchange\n  substeps: 8"), ("cs", "co_simulation")):
        (d / f"{name}.yaml").write_text(FMU_YAML.format(interface=interface))
        out[name] = load_scenario(d / f"{name}.yaml")
    return out


def test_fmu_plant_on_a_cluster_equals_in_process_with_its_bytes_shipped_once(cluster, fmu_rods):
    """Design (ME rod) and Monte Carlo (ME and CS rods, the same FMU file) on the cluster equal
    in-process; the FMU's bytes go to the workers once for all the maps (scattered once)."""
    me, cs = fmu_rods["me"], fmu_rods["cs"]
    before = cluster.files_scattered
    fast = DesignSettings.for_scenario(me, p=5, q=5, n_r=10, ensemble=20, belief_iter=1)
    quiet = {"show_progress": False, "log": lambda m: None}
    here = run_design(me.plant, me.problem, fast, **quiet)
    there = run_design(me.plant, me.problem, fast, engine=cluster, **quiet)
    close(there.nominal.u, here.nominal.u)
    close(there.lqg.K, here.lqg.K)
    close(there.rom.C, here.rom.C)
    close(there.hankel_sv, here.hankel_sv)
    for sc in (me, cs):
        a = simulate(sc.plant, here, "rom_lqg", 3, 12, keep_trajectories=2)
        b = simulate(sc.plant, here, "rom_lqg", 3, 12, keep_trajectories=2, engine=cluster)
        close(b.U, a.U)
        close(b.F, a.F)
        assert b.summary["cost_mean"] == pytest.approx(a.summary["cost_mean"], rel=1e-12)
    assert cluster.files_scattered - before == 1       # one file, one content: scattered once


def test_worker_builds_an_fmu_plant_from_the_shipped_bytes(fmu_rods, tmp_path, monkeypatch):
    """On a worker without the FMU file, `worker_plant` builds the plant from the bytes the
    engine shipped (`FMUPlant.rebuild`); without them it says what is missing."""
    from sep_control.compute import engine as eng

    monkeypatch.setenv("SEP_FMU_CACHE", str(tmp_path / "cache"))
    plant = fmu_rods["cs"].plant
    files = eng.plant_files(plant)
    spec = eng.plant_spec(plant, files)
    gone = json.loads(spec.config)
    gone["path"] = str(tmp_path / "elsewhere" / "rod.fmu")          # not on this "worker"
    spec = spec._replace(config=json.dumps(gone, sort_keys=True))
    monkeypatch.setattr(eng, "_WORKER_FILES", {})
    with pytest.raises(RuntimeError, match="were not shipped"):
        eng.worker_plant(spec)
    eng._WORKER_FILES.update({sha: data for sha, data in files.values()})
    built = eng.worker_plant(spec)
    assert built.path.startswith(str(tmp_path / "cache")) and built.path_sha256 == plant.path_sha256
    X = plant.initial_state(2)
    assert np.array_equal(built.field(built.step(X, np.full(3, 0.3))), plant.field(plant.step(X, np.full(3, 0.3))))
    eng.worker_plant.cache_clear()


def test_every_worker_killed_the_batch_is_resubmitted_with_the_same_result(cluster, tmp_path):
    """Both workers die (and with them every copy of the scattered inputs, which the scheduler
    cannot recover): the engine scatters them again and resubmits the lost tasks."""
    marker = tmp_path / "killed"
    plant = KillsWorkerOnce(n_x=8, marker=str(marker), kills=2)
    U = np.full((30, 2), 0.2)
    here = tvera.impulse_experiments(plant, U, 6, 3, 1e-3, chunks=6)
    there = tvera.impulse_experiments(plant, U, 6, 3, 1e-3, chunks=6, engine=cluster)
    assert marker.is_file() and (tmp_path / "killed.1").is_file(), "not both workers were killed"
    close(there.Y, here.Y)
    close(there.Yf, here.Yf)


def test_worker_killed_mid_batch_is_rerun_with_the_same_result(cluster, tmp_path):
    """Last in the module: it costs the cluster a worker (the nanny starts a new one)."""
    marker = tmp_path / "killed"
    plant = KillsWorkerOnce(n_x=8, marker=str(marker))
    U = np.full((30, 2), 0.2)
    here = tvera.impulse_experiments(plant, U, 6, 3, 1e-3, chunks=6)
    there = tvera.impulse_experiments(plant, U, 6, 3, 1e-3, chunks=6, engine=cluster)
    assert marker.is_file(), "no worker was killed: the test tested nothing"
    close(there.Y, here.Y)
    close(there.Yf, here.Yf)


def test_evaluate_and_validate_clis_on_a_cluster_match_in_process(tmp_path, capsys):
    """`evaluate --dask local:2` and `validate --dask local:2` print what they print in-process."""
    import json

    scen = tmp_path / "small.yaml"
    scen.write_text("".join(f"{k}: {v}\n" for k, v in SMALL.items()))
    fast = ["--p", "5", "--q", "5", "--n-r", "10", "--ensemble", "20", "--belief-iter", "1", "--quiet"]
    assert sep(["design", "--scenario", str(scen), "--out", str(tmp_path / "d.npz")] + fast) == 0
    out = {}
    for tag, extra in (("here", []), ("there", ["--dask", "local:2"])):
        ev = ["--design", str(tmp_path / "d.npz"), "--runs", "30", "--controllers", "open_loop", "rom_lqg",
              "--quiet", "--json", str(tmp_path / f"{tag}.json")] + extra
        assert sep(["evaluate", *ev]) == 0
        assert sep(["validate", "--design", str(tmp_path / "d.npz"), "--lags", "12",
                                  "--json", str(tmp_path / f"{tag}_val.json")] + extra) == 0
        out[tag] = (json.loads((tmp_path / f"{tag}.json").read_text()),
                    json.loads((tmp_path / f"{tag}_val.json").read_text()))
    assert "dashboard" in capsys.readouterr().out
    (ev_a, va_a), (ev_b, va_b) = out["here"], out["there"]
    rows_a = {r["name"]: r for r in ev_a} if isinstance(ev_a, list) else ev_a
    rows_b = {r["name"]: r for r in ev_b} if isinstance(ev_b, list) else ev_b
    for name in ("open_loop", "rom_lqg"):
        for key in ("cost_mean", "cost_std", "in_band", "rms", "coverage_2sigma"):
            assert rows_b[name][key] == pytest.approx(rows_a[name][key], rel=1e-12, abs=1e-12), (name, key)
    for key in ("markov_rel_error", "output_prediction_rel_error", "field_prediction_rel_error"):
        assert va_b[key] == pytest.approx(va_a[key], rel=1e-9), key
