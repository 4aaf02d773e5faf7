"""Model-mismatch evaluation (ROS-free): the oracle on a truth plant, `sep evaluate --truth /
--truth-scenario / --perturb / --robustness`, their refusals (exit 2 naming the bad value), the
sweep's table, JSON and figure."""
import json

import numpy as np
import pytest

from core_helpers import TINY_YAML, one_blas_thread  # noqa: F401
from sep_control.cli.main import main as sep
from sep_control.design.gains import design_lqg, output_weights, tv_lqr
from sep_control.evaluation.robustness import make_truth, oracle_on, parse_sweep, sweep_truths
from sep_control.evaluation.montecarlo import simulate
from sep_control.evaluation.oracle import (Oracle, OracleUnavailable, affine_feedforward, full_order_model, oracle_lqg,
                                           truth_oracle)
from sep_estimator.design_file import load_design
from sep_estimator.ltv import DenseFieldMap, LTVModel
from sep_plant.protocol import nominal_states
from sep_plant.truth import TruthError


def plain_oracle(d, plant):
    """The full-order LQG of `plant` along its own trajectory under ubar, without disturbance
    states: what `truth_oracle` reduces to on the model (its affine terms vanish)."""
    X = nominal_states(plant, d.nominal.u)
    return design_lqg(full_order_model(plant, X, d.nominal.u), d.problem).lqg("oracle_lqg")

FAST = ["--p", "5", "--q", "5", "--n-r", "10", "--ensemble", "20", "--belief-iter", "1", "--quiet"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(design path, Design) of the tiny slab scenario."""
    d = tmp_path_factory.mktemp("mismatch")
    scen = d / "tiny.yaml"
    scen.write_text(TINY_YAML)
    out = d / "tiny.npz"
    assert sep(["design", "--scenario", str(scen), "--out", str(out), *FAST]) == 0
    return out, load_design(out)


def evaluate(argv):
    return sep(["evaluate", *argv])


def refused(capsys, argv) -> str:
    with pytest.raises(SystemExit) as exc:
        evaluate(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


# ----------------------------------------------------------------------- the oracle
def test_affine_feedforward_is_the_optimum_of_the_affine_problem():
    """kappa_k + K_k x_k minimizes sum x'Qx + u'Ru for x+ = A x + B u + r (batch least squares)."""
    rng = np.random.default_rng(3)
    N, n, m = 6, 4, 2
    A = np.stack([0.9 * np.linalg.qr(rng.standard_normal((n, n)))[0] for _ in range(N)])
    B = rng.standard_normal((N, n, m))
    C = rng.standard_normal((N + 1, 3, n))
    r = rng.standard_normal((N, n))
    Q = output_weights(C, np.linspace(0.5, 2.0, N + 1))
    R = 0.3 * np.eye(m)
    model = LTVModel(A=A, B=B, C=C, G=DenseFieldMap(np.zeros((N + 1, 1, n))), dims=np.full(N + 1, n))
    K, S = tv_lqr(A, B, Q, R)
    kappa = affine_feedforward(model, K, S, R, r)
    x0 = rng.standard_normal(n)
    # x_k = Phi_k x0 + sum_j Gam_kj u_j + Psi_k: stack and solve the least-squares problem
    Phi, Gam, Psi = [np.eye(n)], [np.zeros((n, N * m))], [np.zeros(n)]
    for k in range(N):
        Phi.append(A[k] @ Phi[-1])
        g = A[k] @ Gam[-1]
        g[:, k * m:(k + 1) * m] += B[k]
        Gam.append(g)
        Psi.append(A[k] @ Psi[-1] + r[k])
    rows, rhs = [], []
    for k in range(N + 1):
        L = np.linalg.cholesky(Q[k] + 1e-14 * np.eye(n)).T
        rows.append(L @ Gam[k])
        rhs.append(-L @ (Phi[k] @ x0 + Psi[k]))
    Lr = np.linalg.cholesky(R).T
    rows.append(np.kron(np.eye(N), Lr))
    rhs.append(np.zeros(N * m))
    u_opt = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0].reshape(N, m)
    x, u_fb = x0, []
    for k in range(N):
        u_fb.append(kappa[k] + K[k] @ x)
        x = A[k] @ x + B[k] @ u_fb[-1] + r[k]
    np.testing.assert_allclose(np.array(u_fb), u_opt, rtol=1e-8, atol=1e-10)


def test_oracle_on_the_model_is_unchanged(tiny, one_blas_thread):
    _, d = tiny
    plant = d.scenario.plant
    plain = oracle_lqg(d, plant)
    same = oracle_on(d, None, plant)
    model_truth = make_truth(d.scenario, ["t_right=150"])
    assert model_truth.is_model and not isinstance(oracle_on(d, model_truth, plant), Oracle)
    np.testing.assert_array_equal(simulate(plant, d, "oracle_lqg", 1, 50, oracle=same).F,
                                  simulate(plant, d, "oracle_lqg", 1, 50, oracle=plain).F)
    # the affine oracle on the model: every offset is zero and the closed loop that of the plain
    # full-order LQG (it knows the truth: no disturbance states)
    ref = simulate(plant, d, "oracle_lqg", 1, 50, oracle=plain_oracle(d, plant))
    aff = truth_oracle(d, plant, plant)
    for arr in (aff.affine.r, aff.affine.y, aff.affine.field, aff.affine.a0, aff.affine.u_nom - d.nominal.u):
        assert np.max(np.abs(arr)) <= 1e-12
    res = simulate(plant, d, "oracle_lqg", 1, 50, oracle=aff)
    assert np.max(np.abs(res.F - ref.F)) <= 1e-9
    assert res.metrics()["cost_mean"] == pytest.approx(ref.metrics()["cost_mean"], rel=1e-12)


@pytest.mark.parametrize("keys,pert", [(["t_right=147"], None), (None, ["sensor_bias=1.0"])],
                         ids=["boundary", "sensor_bias"])
def test_oracle_on_a_truth_tracks_the_designs_nominal(tiny, one_blas_thread, keys, pert):
    """The affine oracle (the truth along the design's nominal) keeps the field at the design's
    nominal; the truth's own linearization (along its open-loop trajectory) does not."""
    _, d = tiny
    truth = make_truth(d.scenario, keys, pert)
    orc = oracle_on(d, truth, truth.plant)
    assert isinstance(orc, Oracle) and orc.affine is not None
    runs = 200
    aff = simulate(truth.plant, d, "oracle_lqg", 1, runs, oracle=orc).metrics()
    naive = simulate(truth.plant, d, "oracle_lqg", 1, runs, oracle=plain_oracle(d, truth.plant)).metrics()
    rom = simulate(truth.plant, d, "rom_lqg", 1, runs).metrics()
    assert aff["mean_dev_end"] < 0.7 * naive["mean_dev_end"]
    assert aff["cost_mean"] < 0.7 * naive["cost_mean"] and aff["cost_mean"] < rom["cost_mean"]
    assert aff["in_band"] >= max(naive["in_band"], rom["in_band"])
    # the filter knows the truth: its 2-sigma bounds hold as on the model
    assert abs(aff["coverage_2sigma"] - 0.95) < 0.02


def test_oracle_unavailable_for_another_state_dimension(tiny):
    _, d = tiny

    class Bigger:
        n_x = d.info.n_x + 1

    with pytest.raises(OracleUnavailable, match="n_x"):
        truth_oracle(d, Bigger(), d.scenario.plant)


# ------------------------------------------------------------------------ the truth
def test_sweep_parsing_and_truths(tiny):
    _, d = tiny
    s = parse_sweep("t_right=146:150:3")
    assert s.key == "t_right" and s.values == (146.0, 148.0, 150.0) and not s.is_perturbation
    truths = sweep_truths(d.scenario, s, perturb=["input_gain=0.9"])
    assert [t.plant.config()["plant"]["t_right"] for t in truths] == [146.0, 148.0, 150.0]
    assert truths[-1].differences == ("input_gain: 0.9",)
    g = sweep_truths(d.scenario, parse_sweep("input_gain=0.8:1:2"), truth=["t_right=148"])
    assert [t.perturbation.get("input_gain") for t in g] == [[0.8] * 5, None]
    for text, msg in [("t_right=146:150:1", "N must be >= 2"), ("t_right=146:150", "KEY=LO:HI:N"),
                      ("t_right=a:150:3", "LO and HI must be numbers"), ("t_right=1:2:x", "N must be an integer")]:
        with pytest.raises(TruthError, match=msg):
            parse_sweep(text)


def test_refusals_exit_2_naming_the_value(tiny, tmp_path, capsys):
    path, _ = tiny
    base = ["--design", str(path), "--runs", "5", "--quiet"]
    other = tmp_path / "plate.yaml"
    other.write_text("plant:\n  type: plate\n  nodes: [6, 6]\nn_steps: 40\n")
    cases = [
        (["--truth", "t_rightt=147"], r"unknown truth key\(s\) \['t_rightt'\]"),
        (["--truth", "t_right"], "expected KEY=VALUE, got 't_right'"),
        (["--robustness", "t_right=146:150:1"], "--robustness t_right: N must be >= 2"),
        (["--robustness", "t_right:146:150"], "expected KEY=LO:HI:N"),
        (["--robustness", "nope=1:2:3"], "unknown key 'nope'"),
        (["--perturb", "gain=0.8"], r"unknown perturbation key\(s\) \['gain'\]"),
        (["--perturb", "input_offset=[1, 2]"], "input_offset must be a number or a list of 5"),
        (["--perturb", "sensor_bias=abc"], "sensor_bias must be a number"),
        (["--truth", "heater_centers=[0.2, 0.5, 0.8]"], "another interface.*n_u 3"),
        (["--truth-scenario", str(other)], "of type 'plate'"),
        (["--sweep", "--truth", "t_right=147"], "--sweep re-identifies the ROM"),
    ]
    for extra, msg in cases:
        err = refused(capsys, base + extra)
        assert err.startswith("sep evaluate: error: "), err
        assert __import__("re").search(msg, err), (extra, err)


def test_truth_failing_the_plant_protocol_is_refused(tmp_path, capsys):
    scen = tmp_path / "toy.yaml"
    scen.write_text("plant:\n  type: broken_plants:ToyPlant\nn_steps: 12\ntarget: 0.5\nband: 0.5\n"
                    "band_window: [8, 12]\nw_std: 0.01\nv_std: 0.01\n")
    out = tmp_path / "toy.npz"
    assert sep(["design", "--scenario", str(scen), "--out", str(out), "--n-r", "4", "--p", "3", "--q", "3",
                "--no-belief", "--quiet"]) == 0
    err = refused(capsys, ["--design", str(out), "--runs", "3", "--quiet", "--truth", "decay=.nan"])
    assert "truth plant (plant.decay: 0.1 -> nan)" in err and "does not meet the plant protocol" in err


def test_truth_run_names_both_plants(tiny, tmp_path, capsys):
    path, d = tiny
    js = tmp_path / "t.json"
    rc = evaluate(["--design", str(path), "--runs", "30", "--quiet", "--truth", "t_right=148",
                   "--perturb", "input_gain=0.8", "--json", str(js)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "model: the design's plant (slab); truth: plant.t_right: 150.0 -> 148.0; input_gain: 0.8" in out
    rows = json.loads(js.read_text())
    assert [r["name"] for r in rows] == ["open_loop", "rom_lqg", "oracle_lqg"]
    for r in rows:
        assert r["model"]["t_right"] == 150.0 and r["truth"]["plant"]["t_right"] == 148.0
        assert r["truth"]["differences"] == ["plant.t_right: 150.0 -> 148.0", "input_gain: 0.8"]
        assert r["truth"]["perturbation"] == {"input_gain": [0.8] * 5}
    # the same numbers as the Python API on the truth plant, same seeds
    truth = make_truth(d.scenario, ["t_right=148"], ["input_gain=0.8"])
    ref = simulate(truth.plant, d, "rom_lqg", 1, 30).metrics()
    assert rows[1]["cost_mean"] == ref["cost_mean"] and rows[1]["in_band"] == ref["in_band"]


def test_truth_scenario_file(tiny, tmp_path, capsys):
    path, _ = tiny
    f = tmp_path / "truth.yaml"
    f.write_text(TINY_YAML + "k0: 0.012\n")
    assert evaluate(["--design", str(path), "--runs", "10", "--quiet", "--truth-scenario", str(f),
                     "--controllers", "rom_lqg"]) == 0
    assert "truth: plant.k0: 0.01 -> 0.012" in capsys.readouterr().out


def test_robustness_sweep_outputs(tiny, tmp_path, capsys):
    path, _ = tiny
    js, figs = tmp_path / "r.json", tmp_path / "figs"
    rc = evaluate(["--design", str(path), "--runs", "20", "--quiet", "--robustness", "input_gain=0.8:1.0:3",
                   "--controllers", "open_loop", "rom_lqg", "oracle_lqg", "--json", str(js), "--figures", str(figs)])
    assert rc == 0
    out = capsys.readouterr().out
    for v in ("0.8", "0.9", "1"):
        for c in ("open_loop", "rom_lqg", "oracle_lqg"):
            assert f"input_gain={v} {c}" in out
    assert "in_band" in out and "cost_mean" in out and "mean_dev_end" in out
    data = json.loads(js.read_text())
    assert data["sweep"] == {"key": "input_gain", "values": [0.8, 0.9, 1.0]}
    assert data["model"]["type"] == "slab" and data["runs"] == 20 and data["seed"] == 1
    assert [p["value"] for p in data["points"]] == [0.8, 0.9, 1.0]
    assert data["points"][0]["truth"]["differences"] == ["input_gain: 0.8"]
    assert data["points"][2]["truth"]["differences"] == []
    for p in data["points"]:
        assert set(p["controllers"]) == {"open_loop", "rom_lqg", "oracle_lqg"}
        assert 0 <= p["controllers"]["rom_lqg"]["in_band"] <= 1
    # at the model's own value the numbers are the plain evaluation's
    plain = tmp_path / "plain.json"
    assert evaluate(["--design", str(path), "--runs", "20", "--quiet", "--json", str(plain)]) == 0
    base = {r["name"]: r for r in json.loads(plain.read_text())}
    for c in ("open_loop", "rom_lqg", "oracle_lqg"):
        assert data["points"][2]["controllers"][c]["cost_mean"] == base[c]["cost_mean"]
    assert (figs / "robustness.png").stat().st_size > 0


def test_robustness_of_a_mapping_entry_and_an_integer_key(tiny):
    _, d = tiny
    from sep_plant.scenario import Scenario

    plate = Scenario("plate", {"nodes": [6, 6]}).canonical()
    ts = sweep_truths(plate, parse_sweep("boundary_temperatures.x_max=147:148:2"))
    assert [t.plant.config()["boundary_temperatures"]["x_max"] for t in ts] == [147.0, 148.0]
    with pytest.raises(TruthError, match="is not a mapping"):
        sweep_truths(d.scenario, parse_sweep("t_right.x=1:2:2"))
