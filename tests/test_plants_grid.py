"""The built-in grid plants (plate, block, allen_cahn) and their batched Douglas ADI step.

Coarse grids throughout (12 x 12, 6^3, Allen-Cahn 12 x 12 / 24 x 24): conformance, keys,
equilibria, symmetry, heat balance, batching, the split against the 1-D solution and the
slab, the spatial operator against an independent stencil, the factored step against a dense
solve, and each scheme against a fine-step RK4 reference.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sep_plant.conformance import check_plant
from sep_plant.plants import PlantConfigError, make_plant
from sep_plant.plants import adi
from sep_plant.plants.slab import SlabPlant
from sep_plant.protocol import PlantInfo

SMALL = {"plate": {"nodes": [12, 12]}, "block": {"nodes": [6, 6, 6]}, "allen_cahn": {"nodes": [12, 12]}}
#: a rapid-thermal-processing wafer: kelvin, radiation dominant, conductivity falling with T
RTP = {"nodes": [12, 12], "lengths": [0.2, 0.2], "unit": "K", "k0": 1e-3, "beta": -0.5, "t_ref": 1000.0,
       "t_scale": 500.0, "eta": 0.0, "radiation": 4.9e-11, "t_amb": 300.0, "t_init": 900.0,
       "boundary_temperatures": {}}


def small(name: str, **kw):
    return make_plant(name, {**SMALL[name], **kw})


def run(plant, x, u, steps: int):
    for _ in range(steps):
        x = plant.step(x, u)
    return x


def rk4(plant, x, u, horizon: float, h: float):
    """The semi-discrete system (plant.rhs) integrated by classical RK4 with small steps."""
    return adi.rk4(plant.rhs, x, u, horizon, h)


def p_dim(name: str) -> int:
    return 3 if name == "block" else 2


def lamp_grid(values) -> np.ndarray:
    """Inputs of the default 3 x 3 actuator grid from a 3 x 3 array [x index][y index]."""
    return np.asarray(values, dtype=float).ravel()


# ------------------------------------------------------------------------------ protocol, keys
@pytest.mark.parametrize("name", sorted(SMALL))
def test_conformance_and_registry(name):
    p = small(name)
    check_plant(p, np.full(p.n_u, 0.1), name=name)
    info = PlantInfo.of(p)
    assert info.grid_shape == tuple(SMALL[name]["nodes"]) and info.field_is_state and info.noise_on_inputs
    assert info.n_x == info.n_field == int(np.prod(info.grid_shape))
    assert json.loads(json.dumps(p.config())) == p.config()


def test_conformance_of_the_rtp_wafer():
    check_plant(make_plant("plate", RTP), np.full(9, 0.3))


@pytest.mark.parametrize("name, shape, n_u, n_y, unit", [
    ("plate", (64, 64), 9, 5, "F"), ("block", (24, 24, 24), 9, 5, "F"), ("allen_cahn", (50, 50), 9, 5, "")])
def test_defaults(name, shape, n_u, n_y, unit):
    p = make_plant(name)
    assert (p.grid_shape, p.n_u, p.n_y, p.field_unit) == (shape, n_u, n_y, unit)
    assert list(p.input_names)[0] in ("lamp_0", "actuator_0") and p.output_names[-1] == f"sensor_{n_y - 1}"
    assert type(p)(**p.config()).config() == p.config()


@pytest.mark.parametrize("name", sorted(SMALL))
def test_field_coordinates_are_metres_in_c_order(name):
    p = small(name, lengths=[2.0, 0.5] + ([1.5] if name == "block" else []))
    xyz = p.field_coordinates().reshape(p.grid_shape + (3,))
    for a, ax in enumerate(p.grid.axes):
        along = np.moveaxis(xyz[..., a], a, 0).reshape(ax.n, -1)
        assert np.all(along == ax.nodes()[:, None])                     # varies along its own axis only
        assert 0.0 <= along.min() and along.max() <= ax.length + 1e-12
    if name == "plate":                                                 # x = L held: its node is eliminated
        assert xyz[..., 0].max() == pytest.approx(2.0 * 11 / 12) and xyz[..., 1].max() == pytest.approx(0.5)


@pytest.mark.parametrize("name, key, value, message", [
    ("plate", "nodes", [2, 12], r"nodes\[0\] must be >= 3"),
    ("plate", "nodes", [12, 12, 12], "nodes must be a list of 2"),
    ("block", "lengths", [1.0, 0.0, 1.0], r"lengths\[1\] must be > 0"),
    ("plate", "boundary_temperatures", {"z_min": 100.0}, "boundary_temperatures: unknown face 'z_min'"),
    ("plate", "boundary_temperatures", {"x_min": "hot"}, "boundary_temperatures.x_min must be a number"),
    ("plate", "unit", "R", "unit must be one of"),
    ("plate", "t_init", -500.0, "t_init = -500 F is below absolute zero"),
    ("plate", "beta", 5.0, "K\\(T\\).*not positive at t_amb = 70"),
    ("plate", "lamp_centers", [[0.5]], r"lamp_centers\[0\] must be a list of 2"),
    ("plate", "sensor_positions", [[0.5, 0.5], [0.51, 0.5]], "sensor_positions"),
    ("block", "lamp_sigma", -1.0, "lamp_sigma must be > 0"),
    ("allen_cahn", "dt", 1.0, "dt must be < 1"),
    ("allen_cahn", "initial_center", [0.5, 1.5], r"initial_center\[1\] must be <= 1"),
])
def test_bad_keys_are_refused_naming_the_key(name, key, value, message):
    with pytest.raises(PlantConfigError, match=message):
        small(name, **{key: value})


# ------------------------------------------------------------------------------ the spatial operator
def stencil_rhs(p, T: np.ndarray) -> np.ndarray:
    """div(K(T) grad T) node by node (plain loops), independent of adi.py: flux form with
    K_face = (K_i + K_j)/2, ghost nodes on insulated faces, held faces' values beyond the ends."""
    K = lambda t: p.k0 * (1 + p.beta * (t - p.t_ref) / p.t_scale)    # noqa: E731
    out = np.zeros_like(T)
    for idx in np.ndindex(T.shape):
        for a, ax in enumerate(p.grid.axes):
            total = 0.0
            for side, face in ((-1, adi.FACES[2 * a]), (1, adi.FACES[2 * a + 1])):
                j = list(idx)
                j[a] += side
                if 0 <= j[a] < ax.n:
                    Tn = T[tuple(j)]
                elif face in p.boundary_temperatures:
                    Tn = p.boundary_temperatures[face]
                else:                                                 # ghost node mirrors the neighbour
                    j[a] -= 2 * side
                    Tn = T[tuple(j)]
                total += 0.5 * (K(T[idx]) + K(Tn)) * (Tn - T[idx])
            out[idx] += total / ax.h ** 2
    return out


@pytest.mark.parametrize("name, held", [
    ("plate", {"x_max": 150.0, "y_min": 120.0}), ("plate", {}), ("block", {"z_min": 150.0, "x_min": 90.0})])
def test_diffusion_matches_an_independent_stencil(name, held):
    p = make_plant(name, {"nodes": [5, 4] + ([3] if name == "block" else []), "boundary_temperatures": held,
                          "eta": 0.0, "sensor_positions": [[0.5] * p_dim(name)]})
    rng = np.random.default_rng(3)
    T = 100.0 + 50.0 * rng.random(p.grid_shape)
    got = p.rhs(T.ravel(), np.zeros(p.n_u)).reshape(p.grid_shape)
    np.testing.assert_allclose(got, stencil_rhs(p, T), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape, held", [((5, 6), {"x_max": 150.0}), ((4, 5, 3), {"z_min": 3.0, "y_max": 1.0})])
@pytest.mark.parametrize("form", ["callable", "array"])
def test_douglas_step_is_the_factored_linear_solve(shape, held, form):
    """(D - dt A_1) D^-1 (D - dt A_2) [D^-1 (D - dt A_3)] Delta = dt F(T_k), dense, every solver;
    K(T) as a callable, or as an array with an extra spatial factor (K(x, T_k))."""
    rng = np.random.default_rng(1)
    T = 1.0 + rng.random((1,) + shape)
    space = 1.0 + 0.5 * rng.random(shape) if form == "array" else 1.0
    K_of = lambda t: 0.3 * (1.0 + 0.5 * t)                             # noqa: E731
    K = K_of if form == "callable" else K_of(T) * space
    faces = {f: adi.Held(v, K_of(v)) for f, v in held.items()}
    grid = adi.axes_for(shape, [1.0] * len(shape), held)
    g, lam, dt = rng.random(T.shape), rng.random(T.shape) - 0.2, 0.3
    n = grid.size
    mats = []
    for a in range(grid.ndim):                                         # A_a column by column (affine: minus A_a 0)
        Ka = np.moveaxis(K_of(T) * space, a + 1, -1)

        def apply_a(X, a=a, Ka=Ka):
            Xl = np.moveaxis(X, a + 1, -1)
            op = adi.AxisOperator(Ka, Xl, grid.h[a], *adi.held_faces(grid, faces)[a])
            return np.moveaxis(op.apply(Xl), -1, a + 1).ravel()
        base = apply_a(np.zeros(T.shape))
        mats.append(np.stack([apply_a(np.eye(n)[i].reshape(T.shape)) - base for i in range(n)], axis=1))
    D = np.diag(1.0 + dt * lam.ravel())
    P = D - dt * mats[0]
    for A in mats[1:]:
        P = P @ np.linalg.solve(D, D - dt * A)
    F = adi.diffusion(grid, T, K, faces).ravel() + g.ravel()
    np.testing.assert_allclose(F - g.ravel(), sum(mats) @ T.ravel() + _held_part(grid, T, K_of(T) * space, faces),
                               rtol=1e-12, atol=1e-12)
    want = T.ravel() + np.linalg.solve(P, dt * F)
    for solver in adi.SOLVERS:
        got = adi.douglas_step(grid, T, K, faces, g, lam, dt, solver)
        np.testing.assert_allclose(got.ravel(), want, rtol=1e-12, atol=1e-12)


def _held_part(grid, T, K, faces) -> np.ndarray:
    """sum_a A_a applied to a zero field: the held faces' inflow terms."""
    out = np.zeros(T.shape)
    for a in range(grid.ndim):
        Z = np.zeros(np.moveaxis(T, a + 1, -1).shape)
        op = adi.AxisOperator(np.moveaxis(K, a + 1, -1), Z, grid.h[a], *adi.held_faces(grid, faces)[a])
        out += np.moveaxis(op.apply(Z), -1, a + 1)
    return out.ravel()


# ------------------------------------------------------------------------------ equilibria
@pytest.mark.parametrize("name, held", [("plate", {}), ("plate", "all"), ("block", {}), ("block", "all")])
def test_uniform_ambient_temperature_stays_put(name, held):
    """T = t_amb everywhere, no input: no conduction, no convective or radiative loss."""
    faces = adi.FACES[:2 * p_dim(name)]
    cfg = {**RTP, "nodes": SMALL[name]["nodes"], "lengths": [0.2] * p_dim(name), "t_init": 300.0,
           "eta": 0.01, "lamp_centers": [[0.5] * p_dim(name)], "sensor_positions": [[0.5] * p_dim(name)],
           "boundary_temperatures": {f: 300.0 for f in faces} if held == "all" else {}}
    p = make_plant(name, cfg)
    x0 = p.initial_state(2)
    np.testing.assert_allclose(run(p, x0, np.zeros(p.n_u), 20), x0, rtol=0, atol=1e-10)


@pytest.mark.parametrize("value", [1.0, -1.0, 0.0])
def test_uniform_phases_are_allen_cahn_fixed_points(value):
    p = small("allen_cahn")
    x0 = np.full((1, p.n_x), value)
    np.testing.assert_array_equal(run(p, x0, np.zeros(p.n_u), 20), x0)


def test_allen_cahn_disc_shrinks_open_loop_and_stays_in_the_phase_bounds():
    """The default problem's open-loop drift: curvature shrinks the disc (R^2 = R0^2 - 2 eps^2 t,
    gone after R0^2 / 2 eps^2 = 19.5 s) and phi stays within [-1, 1] without input."""
    p = make_plant("allen_cahn", {"nodes": [40, 40]})
    x = p.initial_state(1)
    area0 = np.count_nonzero(x > 0)
    x10 = run(p, x, np.zeros(p.n_u), 40)
    assert 0.2 * area0 < np.count_nonzero(x10 > 0) < 0.8 * area0          # ~ (1 - 10/19.5) area0
    x25 = run(p, x10, np.zeros(p.n_u), 60)
    assert np.all(x25 < 0) and np.abs(np.concatenate([x10, x25])).max() <= 1.0 + 1e-12


# ------------------------------------------------------------------------------ symmetry
def test_mirror_symmetric_inputs_give_a_mirror_symmetric_plate():
    p = small("plate", boundary_temperatures={})
    u = lamp_grid([[0.3, 0.1, 0.3], [0.2, 0.6, 0.2], [0.3, 0.1, 0.3]])   # even in x and in y
    T = run(p, p.initial_state(1), u, 20).reshape(p.grid_shape)
    scale = np.abs(T - p.t_init).max()
    assert np.abs(T - T[::-1, :]).max() < 1e-12 * scale
    assert np.abs(T - T[:, ::-1]).max() < 1e-12 * scale


def test_mirror_symmetric_block_and_allen_cahn():
    b = small("block")
    u = lamp_grid([[0.3, 0.1, 0.3], [0.2, 0.6, 0.2], [0.3, 0.1, 0.3]])
    T = run(b, b.initial_state(1), u, 20).reshape(b.grid_shape)
    scale = np.abs(T - b.t_init).max()
    assert np.abs(T - T[::-1]).max() < 1e-12 * scale and np.abs(T - T[:, ::-1]).max() < 1e-12 * scale
    a = make_plant("allen_cahn", {"nodes": [24, 24]})
    phi = run(a, a.initial_state(1), 0.5 * u, 20).reshape(a.grid_shape)
    assert np.abs(phi - phi[::-1]).max() < 1e-12 and np.abs(phi - phi[:, ::-1]).max() < 1e-12


def test_transpose_symmetry_exact_for_commuting_factors_and_small_otherwise():
    """With constant K the x and y factors commute: a transpose-symmetric problem stays exactly
    symmetric. With K(T) the split's O(dt^2) error breaks it slightly; the asymmetry is far below
    the scheme's own time error."""
    u = lamp_grid([[0.3, 0.1, 0.3], [0.1, 0.6, 0.1], [0.3, 0.1, 0.3]])  # symmetric under x <-> y
    lin = small("plate", boundary_temperatures={}, beta=0.0)
    T = run(lin, lin.initial_state(1), u, 20).reshape(lin.grid_shape)
    assert np.abs(T - T.T).max() < 1e-12 * np.abs(T - lin.t_init).max()
    nl = small("plate", boundary_temperatures={})
    T = run(nl, nl.initial_state(1), u, 20).reshape(nl.grid_shape)
    ref = rk4(nl, nl.initial_state(1), u, 20 * nl.dt, 0.02).reshape(nl.grid_shape)
    assert 0 < np.abs(T - T.T).max() < 0.05 * np.abs(T - ref).max()


# ------------------------------------------------------------------------------ heat balance
@pytest.mark.parametrize("name", ["plate", "block"])
@pytest.mark.parametrize("beta", [0.0, 0.5])
def test_insulated_lossless_box_gains_exactly_the_input_energy(name, beta):
    """sum_i w_i T_i cell_volume grows by dt sum_j u_j per step (flux form: also for K(T))."""
    p = small(name, boundary_temperatures={}, eta=0.0, beta=beta)
    w = p.heat_weights()
    rng = np.random.default_rng(2)
    x = p.initial_state(3) + rng.random((3, p.n_x))
    for _ in range(10):
        u = rng.standard_normal((3, p.n_u))
        x_new = p.step(x, u)
        gained = (x_new - x) @ w
        np.testing.assert_allclose(gained, p.dt * u.sum(axis=1), rtol=0, atol=1e-12 * (np.abs(x) @ w).max())
        x = x_new


# ------------------------------------------------------------------------------ batching, solvers
@pytest.mark.parametrize("name", sorted(SMALL))
def test_batch_equals_runs_one_by_one_and_solvers_agree(name):
    p = small(name)
    rng = np.random.default_rng(4)
    X = p.initial_state(5) + 0.5 * rng.standard_normal((5, p.n_x))
    U = 0.2 * rng.standard_normal((5, p.n_u))
    batch = p.step(X, U)
    single = np.vstack([p.step(X[i], U[i])[None] for i in range(5)])
    np.testing.assert_allclose(batch, single, rtol=1e-14, atol=0)
    for solver in adi.SOLVERS:
        p.solver = solver
        np.testing.assert_allclose(p.step(X, U), batch, rtol=1e-13, atol=0)


@pytest.mark.parametrize("name", sorted(SMALL) + ["slab"])
def test_a_batch_stepped_in_cache_sized_blocks_equals_the_batch_in_one_piece(name):
    """Blocks of 2 runs (the last one short) give what one piece gives: bitwise with the same
    line solver (the runs are independent), to round-off with 'auto' (a block's line count may
    pick the other solver); inputs given once for every run and noise are sliced with the runs."""
    p = SlabPlant(n_x=30) if name == "slab" else small(name)
    rng = np.random.default_rng(7)
    X = p.initial_state(7) + 0.5 * rng.standard_normal((7, p.n_x))
    U = 0.2 * rng.standard_normal((7, p.n_u))
    W = 0.1 * rng.standard_normal((7, p.n_u))
    solvers = ["auto"] if name == "slab" else list(adi.SOLVERS)
    for solver in solvers:
        if name != "slab":
            p.solver = solver
        for u, w in ((U, None), (U[:1], None), (U, W)):
            p.block_nodes = 10 ** 9
            whole = p.step(X, u, w)
            p.block_nodes = 2 * p.n_x
            blocked = p.step(X, u, w)
            assert blocked.shape == whole.shape == X.shape
            if solver == "auto" and name != "slab":
                np.testing.assert_allclose(blocked, whole, rtol=1e-13, atol=0)
            else:
                np.testing.assert_array_equal(blocked, whole)

# ------------------------------------------------------------------------------ the split vs 1-D
def backward_euler_1d(n: int, length: float, T: np.ndarray, steps: int, *, k0, beta, t_ref, t_scale,
                      eta, t_amb, t_right, dt) -> np.ndarray:
    """Independent dense 1-D step: insulated at x = 0 (ghost), held at x = L (eliminated), flux
    form with K_face = (K_i + K_j)/2 frozen at T_k, (1 + dt eta - dt A)(T' - T) = dt F(T)."""
    h = length / n
    K = lambda t: k0 * (1 + beta * (t - t_ref) / t_scale)              # noqa: E731
    for _ in range(steps):
        Kn = np.append(K(T), K(t_right))
        c = 0.5 * (Kn[1:] + Kn[:-1]) / h**2                             # faces i+1/2, i = 0..n-1
        A = np.zeros((n, n))
        for i in range(n):
            if i + 1 < n:
                A[i, i + 1] += c[i] * (2.0 if i == 0 else 1.0)
                A[i, i] -= c[i] * (2.0 if i == 0 else 1.0)
            else:
                A[i, i] -= c[i]                                         # towards the held value
            if i > 0:
                A[i, i - 1] += c[i - 1]
                A[i, i] -= c[i - 1]
        bc = np.zeros(n)
        bc[-1] = c[-1] * t_right
        F = A @ T + bc - eta * (T - t_amb)
        T = T + np.linalg.solve((1 + dt * eta) * np.eye(n) - dt * A, dt * F)
    return T


@pytest.mark.parametrize("name", ["plate", "block"])
def test_field_uniform_across_insulated_axes_evolves_like_the_1d_solution(name):
    d = p_dim(name)
    n = 10
    p = make_plant(name, {"nodes": [n] + [5] * (d - 1), "boundary_temperatures": {"x_max": 150.0}})
    x = np.arange(n) / n
    T1 = 100.0 + 30.0 * np.sin(3.0 * x) + 20.0 * x**2                   # varies in x only
    T = np.broadcast_to(T1.reshape((n,) + (1,) * (d - 1)), p.grid_shape).ravel()
    got = run(p, T[None], np.zeros(p.n_u), 12).reshape(p.grid_shape)
    want = backward_euler_1d(n, 1.0, T1, 12, k0=p.k0, beta=p.beta, t_ref=p.t_ref, t_scale=p.t_scale,
                             eta=p.eta, t_amb=p.t_amb, t_right=150.0, dt=p.dt)
    np.testing.assert_allclose(got, np.broadcast_to(want.reshape((n,) + (1,) * (d - 1)), p.grid_shape),
                               rtol=1e-12)


def test_plate_uniform_in_y_is_the_slab():
    """Constant K: the plate extruded from the slab (x = L held, loss to 0 F) steps exactly as
    the reference SlabPlant does (written independently, K T_xx form, dgtsv)."""
    slab = SlabPlant(n_x=16, beta=0.0, gamma=0.0, heater_centers=(0.5,), sensor_positions=(0.5,))
    plate = make_plant("plate", {"nodes": [16, 4], "beta": 0.0, "t_amb": 0.0, "eta": slab.eta})
    rng = np.random.default_rng(5)
    T1 = slab.initial_state(1)[0] + 40.0 * rng.random(16)
    T2 = np.repeat(T1[:, None], 4, axis=1).ravel()
    for _ in range(10):
        T1 = slab.step(T1, np.zeros(1))
        T2 = plate.step(T2, np.zeros(plate.n_u))
        np.testing.assert_allclose(T2.reshape(16, 4), np.repeat(T1[:, None], 4, axis=1), rtol=1e-13)


def test_y_uniform_source_on_the_adi_grid_is_the_1d_step():
    """adi level, with sources and a varying implicit part: 2-D with y-uniform data == 1-D."""
    rng = np.random.default_rng(6)
    K = lambda t: 0.02 * (1.0 + 0.3 * t)                               # noqa: E731
    held = {"x_min": adi.Held(2.0, K(2.0))}
    g2 = adi.axes_for((9, 7), (1.0, 0.5), held)
    g1 = adi.axes_for((9,), (1.0,), held)
    T, g, lam = rng.random((3, 2, 9))
    out1 = adi.douglas_step(g1, T, K, held, g, lam, 0.4)
    wide = lambda a: np.repeat(a[:, :, None], 7, axis=2)               # noqa: E731
    out2 = adi.douglas_step(g2, wide(T), K, held, wide(g), wide(lam), 0.4)
    np.testing.assert_allclose(out2, wide(out1), rtol=1e-13)


# ------------------------------------------------------------------------------ time accuracy
#: scheme, config, input, horizon [s], RK4 step [s], stated tolerance: max error at the default
#: dt relative to the largest change of the field over the horizon (measured: plate 1.2 %, the
#: wafer 1.3 %, both mostly the start of the held edge's 50 F step on the coarse grid; block
#: 0.5 %; Allen-Cahn 0.35 %)
REFERENCE_CASES = [
    ("plate", SMALL["plate"], 0.2, 5.0, 0.02, 0.02),
    ("plate", RTP, 0.3, 5.0, 0.05, 0.02),
    ("block", SMALL["block"], 0.3, 5.0, 0.01, 0.01),
    ("allen_cahn", {"nodes": [24, 24]}, 0.05, 5.0, 0.02, 0.01),
]


@pytest.mark.parametrize("name, cfg, u, horizon, h, tol", REFERENCE_CASES,
                         ids=["plate", "plate_rtp", "block", "allen_cahn"])
def test_scheme_against_a_fine_step_reference(name, cfg, u, horizon, h, tol):
    """The ADI step at dt, dt/2, dt/4 against RK4 of the same semi-discrete system (plant.rhs):
    error below tol of the field's change at dt, and first order (halving dt about halves it;
    Allen-Cahn reaches the asymptotic ratio 2 only below dt/2)."""
    p = make_plant(name, cfg)
    x0 = p.initial_state(1)
    U = np.full(p.n_u, u)
    ref = rk4(p, x0, U, horizon, h)
    change = np.abs(ref - x0).max()
    errs = []
    for dt in (p.dt, p.dt / 2, p.dt / 4):
        q = make_plant(name, {**cfg, "dt": dt})
        errs.append(np.abs(run(q, x0, U, int(round(horizon / dt))) - ref).max())
    assert errs[0] < tol * change
    assert errs[0] > errs[1] and 1.5 < errs[1] / errs[2] < 2.5
