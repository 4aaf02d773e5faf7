"""docs/reference/design-file.md gives the exact online recursion from the design file's arrays.
This test implements that page in plain numpy (np.load of the .npz, json of its meta; nothing of
sep's filter, controller, model or design-file reader) and checks that it reproduces the offline
Monte Carlo's ROM-LQG inputs to 1e-9, for designs without disturbance states, with input and with
output disturbance states, with noise-kind ones and the combinations input+noise, noise+output
(stacked states) and the field weighting on a slab whose noise has channels of its own (the page's recursion does not change with the weighting: it is in K), and
with input limits that bind; and for a recipe (a time-varying target, format version 6) with
rate limits that bind (the page's rate clip after the box clip). Only the plant and the noise (what
the page's reader supplies: the real plant and its sensors) come from sep."""
import dataclasses
import json

import numpy as np
import pytest
import yaml

from core_helpers import TINY_YAML, one_blas_thread  # noqa: F401
from sep_control.design.pipeline import run_design
from sep_control.design.settings import DesignSettings
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.design_file import load_design, save_design
from sep_plant.noise import noise_sequences
from sep_plant.protocol import PlantInfo
from sep_plant.scenario import Scenario

RUNS = 6
#: the disturbance kinds checked; the combinations on the slab with noise channels of its own
KINDS = ["none", "input", "output", "noise", "input+noise", "noise+output"]


def read(path):
    """Every member of the file as plain arrays, the compressed trajectories expanded
    (the page's "Reading the file")."""
    with np.load(path, allow_pickle=False) as z:
        raw = {k: z[k] for k in z.files}
    meta = json.loads(raw.pop("meta").tobytes().decode())
    for name in [k[:-len("__coef")] for k in raw if k.endswith("__coef")]:
        raw[name] = raw.pop(name + "__coef") @ raw.pop(name + "__basis").T
    return meta, raw


def limits(meta, n_u):
    """u_min, u_max, du_max from the file's scenario (a number, a list, or "inf"/"-inf"; du_max
    absent: no rate limit)."""
    def vec(v):
        return np.broadcast_to(np.asarray([float(x) for x in v] if isinstance(v, list) else float(v)), (n_u,))
    s = meta["scenario"]
    return vec(s["u_min"]), vec(s["u_max"]), vec(s.get("du_max", "inf"))


def augmented(meta, a):
    """A_z, B_z, C_z of the page's "The model the filter runs on"."""
    A, B, C = a["A"], a["B"], a["C"]
    N, n_r, n_u = B.shape
    kind = meta.get("disturbance", {}).get("kind", "none")
    if kind == "none":
        return A, B, C
    M = a["dist_map"]
    n_d = M.shape[1]
    Az = np.zeros((N, n_r + n_d, n_r + n_d))
    Az[:, :n_r, :n_r] = A
    Az[:, n_r:, n_r:] = np.eye(n_d)
    Cz = np.concatenate([C, np.zeros(C.shape[:2] + (n_d,))], axis=2)
    rows = {"input": n_u, "noise": a["Bw"].shape[2] if "Bw" in a else n_u, "output": C.shape[1]}
    r, c = 0, n_r                        # a combination: its parts' blocks of the map, in order
    for part, m in zip(kind.split("+"), meta["disturbance"].get("part_dims", [n_d])):
        block = M[r:r + rows[part], c - n_r:c - n_r + m]
        if part == "input":
            Az[:, :n_r, c:c + m] = B @ block
        elif part == "noise":
            Az[:, :n_r, c:c + m] = a["Bw"] @ block
        else:
            Cz[:, :, c:c + m] = block
        r, c = r + rows[part], c + m
    Bz = np.concatenate([B, np.zeros((N, n_d, n_u))], axis=1)
    return Az, Bz, Cz


def closed_loop(path, plant, seed, runs):
    """The page's online recursion for `runs` runs of the Monte Carlo with `seed`: returns the
    applied inputs (runs, N, n_u) and the reconstructed field (runs, N+1, n_field)."""
    meta, a = read(path)
    Az, Bz, Cz = augmented(meta, a)
    K, L = a["K"], a["L"]
    u_nom, y_nom, f_nom = a["u_nom"], a["y_nom"], a["field_nom"]
    Phi, g = a["field_basis"], a["field_coef"]
    N, n_u = u_nom.shape
    n_r = a["A"].shape[1]
    lo, hi, du = limits(meta, n_u)
    # the noise of run i of the Monte Carlo with this seed (the plant node's seed/run parameters)
    w, v = noise_sequences(Scenario.from_dict(meta["scenario"], canonical=False).problem,
                           PlantInfo.from_dict(meta["plant_info"]), seed, runs)
    U = np.empty((runs, N, n_u))
    F_hat = np.empty((runs, N + 1, Phi.shape[0]))
    for i in range(runs):
        x = plant.initial_state(1)
        z = np.zeros(K.shape[2])                                       # z_{0|-1} = 0
        for k in range(N + 1):
            y = plant.observe(x)[0] + v[i, k]                          # the measurement of step k
            z = z + L[k] @ ((y - y_nom[k]) - Cz[k] @ z)                 # update: z_{k|k}
            F_hat[i, k] = f_nom[k] + Phi @ (g[k] @ z[:n_r])            # field estimate
            if k == N:
                break
            u = np.clip(u_nom[k] + K[k] @ z, lo, hi)                   # command of step k
            if k > 0:
                u = np.clip(u, U[i, k - 1] - du, U[i, k - 1] + du)     # rate limit after the box
            U[i, k] = u
            x = plant.step(x, u[None], w[i, k][None])                 # the plant applies u (+ w)
            z = Az[k] @ z + Bz[k] @ (u - u_nom[k])                     # predict: z_{k+1|k}
    return U, F_hat


@pytest.fixture(scope="module")
def designs(tmp_path_factory):
    out = {}
    base = yaml.safe_load(TINY_YAML)
    scn = Scenario.from_dict({**base, "u_min": 0.0, "u_max": 0.6})     # limits that bind
    own = scn.with_plant(noise_centers=[0.25, 0.75], noise_sigma=0.2)
    own = dataclasses.replace(own, problem=own.problem.replace(lqr_weighting="field"))
    for kind in KINDS:
        st = DesignSettings(p=5, q=5, n_r=10, ensemble=20, belief_iter=1, disturbance=kind)
        sc = own if "noise" in kind else scn
        d = run_design(sc.plant, sc.problem, st, show_progress=False, log=lambda m: None)
        path = tmp_path_factory.mktemp("ref") / f"{kind}.npz"
        save_design(path, d)
        out[kind] = path
    rec = dataclasses.replace(scn, problem=scn.problem.replace(**RECIPE))
    d = run_design(rec.plant, rec.problem, DesignSettings(p=5, q=5, n_r=10, ensemble=20, belief_iter=1,
                                                          disturbance="input"), show_progress=False, log=lambda m: None)
    out["recipe"] = tmp_path_factory.mktemp("ref") / "recipe.npz"
    save_design(out["recipe"], d)
    return out


#: a recipe on the tiny slab (N = 40, dt = 1.5625 s) with rate limits that bind
RECIPE = dict(recipe=({"start": 0, "end": 20, "target": "100 + 50 * t / 20 + 2 * x", "weight": 0.05},
                      {"start": 20, "end": 40, "target": 150, "band": 3},
                      {"start": 40, "end": 47, "target": "150 + 10 * (t - 40) / 7", "weight": 0.05},
                      {"start": 47, "end": 62.5, "target": 160, "band": 3}),
              band_window=(13, 40), lqr_k_switch=0, lqr_q_early=1.0, du_max=0.03)


def test_the_pages_recursion_with_a_recipe_and_rate_limits(designs, one_blas_thread):
    d = load_design(designs["recipe"])
    _, raw = read(designs["recipe"])
    assert raw["target"].shape == (d.n_steps + 1, d.info.n_field)            # f*_k per step (v6)
    plant = d.scenario.plant
    mc = simulate(plant, d, "rom_lqg", 1, RUNS)
    U, F_hat = closed_loop(designs["recipe"], plant, 1, RUNS)
    du = d.problem.channels("du_max", d.info.n_u)
    assert np.any(np.abs(np.diff(mc.U, axis=1)) >= du - 1e-12), "the rate limits should bind"
    assert mc.summary["rate_clips"] > 0 and mc.summary["rate_violations"] == 0
    np.testing.assert_allclose(U, mc.U, rtol=0, atol=1e-9)
    np.testing.assert_allclose(F_hat, mc.F_hat, rtol=0, atol=1e-9 * np.abs(mc.F_hat).max())


@pytest.mark.parametrize("kind", KINDS)
def test_the_pages_recursion_reproduces_the_monte_carlo(designs, kind, one_blas_thread):
    d = load_design(designs[kind])
    plant = d.scenario.plant
    mc = simulate(plant, d, "rom_lqg", 1, RUNS)
    U, F_hat = closed_loop(designs[kind], plant, 1, RUNS)
    lo, hi = d.problem.limits(d.info.n_u)
    assert np.any(mc.U <= lo + 1e-12) or np.any(mc.U >= hi - 1e-12), "the limits should bind"
    np.testing.assert_allclose(U, mc.U, rtol=0, atol=1e-9)
    np.testing.assert_allclose(F_hat, mc.F_hat, rtol=0, atol=1e-9 * np.abs(mc.F_hat).max())
    assert (d.lqg.n_d > 0) == (kind != "none")
    assert d.disturbance is None or d.disturbance.kind == kind
